"""Chi-squared outlier filtering of GP training points (paper, Section III.E).

"(1) The GP is trained normally with all training data and the mean and variance of each
training point are inferred, (2) the chi-squared test-statistic is calculated using
v_i^2 = (d_i - mu_i)^2 / sigma_i^2, (3) the test-statistics are compared to the chi^2
value given a certain alpha-quantile level and the points with test-statistic values
larger than chi^2 value will be removed as outliers, (4) the GP is trained again with the
filtered training data." The test has one degree of freedom; it may be repeated.

Choice: mu_i and sigma_i^2 are the leave-one-out prediction of point i by its block's GP
(:func:`~uncertain_facade_map.pipeline.step4_gp_blocks.loo_statistic`), noise variance included. A GP
trained with the point itself predicts it close to its own value and would hide an
isolated outlier; leave-one-out costs the same (one pass over the Cholesky factors).
``alpha`` is the significance level: a point is an outlier if
v_i^2 > chi2.ppf(1 - alpha, 1); a larger alpha removes more points, as in the paper.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2


def chi2_threshold(alpha: float) -> float:
    """The (1 - alpha) quantile of chi-squared with one degree of freedom."""
    return float(chi2.ppf(1.0 - alpha, df=1))


def flag_outliers(statistic: np.ndarray, alpha: float) -> np.ndarray:
    """(N,) bool: True where the test statistic v^2 exceeds the chi-squared quantile.

    NaN statistics (points not tested) are never flagged.
    """
    statistic = np.asarray(statistic, dtype=np.float64)
    with np.errstate(invalid='ignore'):
        return statistic > chi2_threshold(alpha)
