"""Chi-squared outlier threshold (paper, Section III.E)."""

import numpy as np
import pytest

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.params import OutlierParams
from uncertain_facade_map.pipeline.step5_outliers import chi2_threshold, flag_outliers


def test_threshold_is_the_chi2_quantile():
    assert chi2_threshold(0.05) == pytest.approx(3.841, abs=1e-3)
    assert chi2_threshold(0.01) == pytest.approx(6.635, abs=1e-3)


def test_false_alarm_rate_on_gaussian_data():
    rng = np.random.default_rng(0)
    z2 = rng.normal(size=200_000) ** 2
    for alpha in (0.01, 0.05):
        assert flag_outliers(z2, alpha).mean() == pytest.approx(alpha, rel=0.05)
    assert not flag_outliers(np.array([np.nan]), 0.05).any()


def test_bad_alpha():
    with pytest.raises(InputError):
        OutlierParams(alpha=1.5)
