"""Occupancy from the uncertain surface (paper, Section IV.C).

"To make the comparison possible, we first transform our abstract surface map to a 3D
occupancy map, where probabilistic least-squares classification is applied and the
occupancy probabilities are obtained through a cumulative Gaussian density function"
(after GPOM and GPmap). The paper leaves the exact form to its reference; the choice here:

A voxel of side ``r`` centred at signed distance ``s`` from the mean surface (positive
outside the building, along the façade normal) is occupied when any of it lies behind the
true surface, i.e. when the surface depth D ~ N(mu, var + noise_var) reaches the voxel's
outer face::

    p_occupied = P(D >= n - r/2) = Phi((r/2 - s) / sqrt(var + noise_var))

so free space in front of the façade tends to 0, voxels holding the surface to about
Phi(r / 2 sigma), and the solid behind it to 1. The noise variance enters because the
map is compared with measured points, which carry it.

:func:`surface_probability` is the other reading, used by the occupancy evaluation
(:mod:`~uncertain_facade_map.evaluation.baselines.facade_gp`): the probability that the voxel *holds the surface*, i.e.
that a measured point of the surface falls inside it, which is the event the evaluation
calls occupied (a voxel holding reference points)::

    p_surface = P(s - h <= D - n <= s + h) = Phi((h - s) / sigma) - Phi((-h - s) / sigma)

with ``h`` the voxel's half extent along the façade normal (``r/2`` for a wall aligned
with the grid, up to ``r sqrt(3)/2`` otherwise: :func:`half_depth`).

**Probabilistic least-squares classification** (:class:`PLSC`, the paper's reading, after
Rasmussen and Williams, *Gaussian Processes for Machine Learning*, Section 6.5): the class
probability is a cumulative Gaussian of an affine function of the latent, with the latent's
predictive variance integrated out (R&W eq. 6.42)::

    p(y = +1 | x) = Phi((alpha mu + beta) / sqrt(1 + alpha^2 sigma^2))

Here the latent is the signed distance s ~ N(s_bar, sigma^2), sigma^2 = var + noise_var,
and the two parameters are written ``alpha = 1 / spread`` and ``beta = scale h / spread``,
so that the two readings above are the special case ``scale = 1, spread = 0``::

    solid:   p = Phi((scale r/2 - s) / sqrt(spread^2 + sigma^2))
    surface: p = Phi((scale h - s) / S) - Phi((-scale h - s) / S),  S = sqrt(spread^2 + sigma^2)

``scale`` widens or narrows the voxel's band that counts as holding the surface, and
``spread`` (metres) is the surface error the map's variance does not account for. Both are
learnt by maximum likelihood (R&W eq. 6.43, there on leave-one-out predictions) on voxels
labelled by the mapped scans themselves, with s and sigma from a map that did not see the
voxels it is asked about (:func:`fit_plsc`; the labelling and the held-out map are
:mod:`~uncertain_facade_map.mapping.calibration`'s).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize, minimize_scalar
from scipy.special import log_ndtr, ndtr

from ..errors import InputError

#: Occupancy of space no façade model covers (unknown, as in OctoMap).
UNKNOWN = 0.5
#: The two readings of an uncertain surface as occupancy in the evaluation: the
#: probability that the voxel holds the surface, or that it lies behind it (solid).
READINGS = ('surface', 'solid')


def occupancy_probability(signed_distance: np.ndarray, variance: np.ndarray, noise_variance: np.ndarray | float,
                          resolution: float) -> np.ndarray:
    """Probability that the voxel centred at each point is occupied.

    Args:
        signed_distance: (N,) distance of the voxel centre to the mean surface along the
            façade normal, metres, positive outside the building; NaN where unknown.
        variance: (N,) surface variance, m^2.
        noise_variance: (N,) or scalar noise variance, m^2.
        resolution: voxel side, metres.

    Returns:
        (N,) probabilities in [0, 1]; :data:`UNKNOWN` where ``signed_distance`` is NaN.
    """
    s = np.asarray(signed_distance, dtype=np.float64)
    sigma = np.sqrt(np.asarray(variance, dtype=np.float64) + noise_variance)
    with np.errstate(invalid='ignore', divide='ignore'):
        p = ndtr((0.5 * resolution - s) / sigma)
    return np.where(np.isfinite(s), p, UNKNOWN)


def half_depth(normal: np.ndarray, resolution: float) -> np.ndarray:
    """Half extent of an axis-aligned voxel along a direction (its support function).

    Args:
        normal: (N, 3) unit normals (or (3,)), map frame.
        resolution: voxel side, metres.

    Returns:
        (N,) (or scalar) ``r/2 (|n_x| + |n_y| + |n_z|)``, metres: ``r/2`` for a normal along
        an axis, ``r/sqrt(2)`` at 45 degrees in a plane.
    """
    return 0.5 * resolution * np.abs(np.asarray(normal, dtype=np.float64)).sum(axis=-1)


def facade_half_depth(facade: np.ndarray, normals: np.ndarray, resolution: float) -> np.ndarray:
    """Half extent of each voxel along the normal of the façade that holds it.

    Args:
        facade: (N,) int index into ``normals`` of each voxel's façade, -1 where none.
        normals: (F, 3) unit outward normal of each façade, map frame.
        resolution: voxel side, metres.

    Returns:
        (N,) :func:`half_depth` of the voxel's façade normal, metres; ``r/2`` where no façade.
    """
    facade = np.asarray(facade)
    h = np.full(len(facade), 0.5 * resolution)
    known = facade >= 0
    if known.any():
        h[known] = half_depth(np.asarray(normals, dtype=np.float64)[facade[known]], resolution)
    return h


def surface_probability(signed_distance: np.ndarray, variance: np.ndarray, noise_variance: np.ndarray | float,
                        half_extent: np.ndarray | float, outside: float = 0.0) -> np.ndarray:
    """Probability that the voxel centred at each point holds the surface (a measured point).

    Args:
        signed_distance: (N,) distance of the voxel centre to the mean surface along the
            façade normal, metres, positive outside the building; NaN where no façade is.
        variance: (N,) surface variance, m^2.
        noise_variance: (N,) or scalar measurement noise variance, m^2.
        half_extent: (N,) or scalar half extent of the voxel along the normal, metres
            (:func:`half_depth`).
        outside: the probability where ``signed_distance`` is NaN (no façade models the
            voxel, so no surface is there: 0 by default).

    Returns:
        (N,) probabilities in [0, 1].
    """
    s = np.asarray(signed_distance, dtype=np.float64)
    sigma = np.sqrt(np.asarray(variance, dtype=np.float64) + noise_variance)
    h = np.asarray(half_extent, dtype=np.float64)
    with np.errstate(invalid='ignore', divide='ignore'):
        p = ndtr((h - s) / sigma) - ndtr((-h - s) / sigma)
    return np.where(np.isfinite(s), np.clip(p, 0.0, 1.0), outside)


@dataclass(frozen=True)
class PLSC:
    """The two parameters of the occupancy's cumulative Gaussian (see the module docstring).

    Attributes:
        scale: dimensionless factor on the voxel's half extent along the normal (1: the
            fixed formula).
        spread: metres, surface error added to the map's sd in quadrature (0: the fixed
            formula).
        n_positive: held-out voxels holding mapped points it was learnt on (0: not learnt).
        n_negative: voxels crossed by mapped rays it was learnt on.
    """

    scale: float = 1.0
    spread: float = 0.0
    n_positive: int = 0
    n_negative: int = 0

    #: Bounds of the fit, searched in log space (as scikit-learn's kernel hyper-parameters).
    SCALE_BOUNDS = (0.05, 20.0)
    SPREAD_BOUNDS = (1e-4, 2.0)

    def __post_init__(self) -> None:
        if not (np.isfinite(self.scale) and self.scale > 0):
            raise InputError(f'PLSC scale must be a positive number, got {self.scale!r}')
        if not (np.isfinite(self.spread) and self.spread >= 0):
            raise InputError(f'PLSC spread must be a number of metres >= 0, got {self.spread!r}')

    @property
    def learnt(self) -> bool:
        """True when fitted to data (else the fixed formula)."""
        return self.n_positive > 0

    def surface(self, signed_distance: np.ndarray, variance: np.ndarray, noise_variance: np.ndarray | float,
                half_extent: np.ndarray | float, outside: float = 0.0) -> np.ndarray:
        """(N,) probability that the voxel holds the surface (arguments of :func:`surface_probability`)."""
        return surface_probability(signed_distance, np.asarray(variance, dtype=np.float64) + self.spread**2,
                                   noise_variance, self.scale * np.asarray(half_extent, dtype=np.float64), outside)

    def solid(self, signed_distance: np.ndarray, variance: np.ndarray, noise_variance: np.ndarray | float,
              resolution: float) -> np.ndarray:
        """(N,) probability that the voxel is occupied (arguments of :func:`occupancy_probability`)."""
        return occupancy_probability(signed_distance, np.asarray(variance, dtype=np.float64) + self.spread**2,
                                     noise_variance, self.scale * resolution)

    def as_dict(self) -> dict[str, float]:
        """The fields by name (for the map file)."""
        return {'scale': self.scale, 'spread': self.spread, 'n_positive': self.n_positive,
                'n_negative': self.n_negative}


#: The fixed formula as a :class:`PLSC` (not learnt).
FIXED = PLSC()


def _log_surface(theta: np.ndarray, s: np.ndarray, sd2: np.ndarray, h: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """log p and log (1 - p) of the surface reading at log parameters ``theta``."""
    scale, spread = np.exp(theta)
    sd = np.sqrt(sd2 + spread**2)
    a = np.abs(s)  # the reading is even in s; |s| keeps both tails in log_ndtr's accurate range
    hi, lo = (scale * h - a) / sd, (-scale * h - a) / sd
    # p = Phi(hi) - Phi(lo) = Phi(hi) (1 - exp(log Phi(lo) - log Phi(hi))), kept in logs.
    lhi, llo = log_ndtr(hi), log_ndtr(lo)
    log_p = lhi + np.log1p(-np.exp(np.minimum(llo - lhi, -1e-300)))
    # 1 - p = Phi(lo) + Phi(-hi).
    log_q = np.logaddexp(llo, log_ndtr(-hi))
    return log_p, log_q


def plsc_log_likelihood(theta: np.ndarray, positive: np.ndarray, weight: np.ndarray, signed_distance: np.ndarray,
                        sd2: np.ndarray, half_extent: np.ndarray) -> float:
    """Weighted log-likelihood of voxel labels under the surface reading (R&W eq. 6.43).

    Args:
        theta: (2,) ``log(scale), log(spread / 1 m)``.
        positive: (N,) bool, True for voxels holding points.
        weight: (N,) weight of each voxel.
        signed_distance: (N,) s of each voxel centre, metres (finite).
        sd2: (N,) var + noise var, m^2.
        half_extent: (N,) the voxel's half extent along its façade normal, metres.
    """
    log_p, log_q = _log_surface(np.asarray(theta, dtype=np.float64), signed_distance, sd2, half_extent)
    return float(np.sum(weight * np.where(positive, log_p, log_q)))


#: Voxels farther than this from the mean surface (metres) are left out of the PLSC fit.
FIT_BAND = 0.5


def fit_plsc(positive: np.ndarray, weight: np.ndarray, signed_distance: np.ndarray, variance: np.ndarray,
             noise_variance: np.ndarray, half_extent: np.ndarray, band: float = FIT_BAND) -> PLSC:
    """Learn :class:`PLSC`'s two parameters by maximum likelihood on labelled voxels.

    Only the voxels within ``band`` of the mean surface count: the cumulative Gaussian
    models the surface's error, and the few hit voxels far from any mean surface (a
    balcony rail, a lamp, a wall no façade holds; 1.4 % of the held-out hit voxels on the
    simulated ``street``) are not such errors. Two parameters cannot set them apart, and
    with them the fit widens the Gaussian for every voxel (scale 2.8, spread 0.12 m on
    ``street`` at 0.1 m, against 2.1 and 0.045 m without them).

    Args:
        positive: (N,) bool, True for voxels holding points, False for voxels rays crossed.
        weight: (N,) float weight of each voxel (> 0).
        signed_distance: (N,) metres; voxels with NaN (no façade) are left out.
        variance: (N,) surface variance, m^2.
        noise_variance: (N,) noise variance, m^2.
        half_extent: (N,) metres (:func:`facade_half_depth`).
        band: metres, see above.

    Returns:
        The fitted parameters, or :data:`FIXED` when fewer than 10 positives or negatives
        have a façade (too little to learn from).
    """
    s = np.asarray(signed_distance, dtype=np.float64)
    sd2 = np.asarray(variance, dtype=np.float64) + np.asarray(noise_variance, dtype=np.float64)
    use = np.isfinite(s) & np.isfinite(sd2) & (np.abs(s) <= band)
    positive = np.asarray(positive, dtype=bool)[use]
    n_pos, n_neg = int(positive.sum()), int((~positive).sum())
    if min(n_pos, n_neg) < 10:
        return FIXED
    args = (positive, np.asarray(weight, dtype=np.float64)[use], s[use], sd2[use],
            np.asarray(half_extent, dtype=np.float64)[use])
    total = float(args[1].sum())
    bounds = [tuple(np.log(PLSC.SCALE_BOUNDS)), tuple(np.log(PLSC.SPREAD_BOUNDS))]
    best = None
    for start in ([0.0, np.log(0.01)], [0.0, np.log(0.1)]):  # two starts: the likelihood need not be convex
        res = minimize(lambda t: -plsc_log_likelihood(t, *args) / total, start, method='L-BFGS-B', bounds=bounds)
        if best is None or res.fun < best.fun:
            best = res
    scale, spread = np.exp(best.x)
    return PLSC(float(scale), float(spread), n_pos, n_neg)


def occupancy_model(learnt: PLSC, choice: str) -> PLSC:
    """The PLSC parameters a query uses: the map's ``learnt`` ones for ``choice`` 'plsc'
    (``query.occupancy``, checked where the configuration is read), the fixed formula's
    for 'fixed'."""
    return FIXED if choice == 'fixed' else learnt


def carve(p: np.ndarray, crossings: np.ndarray, weight: float) -> np.ndarray:
    """Occupancy lowered by the rays that passed through the voxel (the free-space
    extension, beyond the paper): ``logit p' = logit p - weight * crossings``, as an
    occupancy grid's log-odds update takes a miss (OctoMap), with one learnt weight.

    Args:
        p: (N,) occupancy probabilities from the surface.
        crossings: (N,) int number of mapped rays through each voxel (0 for a voxel
            holding a mapped point: a hit outweighs passing rays).
        weight: log-odds taken off per crossing ray (>= 0).

    Returns:
        (N,) probabilities in [0, 1].
    """
    p = np.asarray(p, dtype=np.float64)
    factor = np.exp(-weight * np.asarray(crossings, dtype=np.float64))
    with np.errstate(invalid='ignore', divide='ignore'):
        out = p * factor / (p * factor + (1.0 - p))
    return np.where(p > 0, out, 0.0)


#: Bounds of the carving weight (log-odds per ray).
CARVE_BOUNDS = (0.0, 10.0)


def fit_carving(positive: np.ndarray, weight: np.ndarray, p: np.ndarray, crossings: np.ndarray) -> float:
    """The :func:`carve` weight of maximum likelihood on labelled voxels.

    Args:
        positive: (N,) bool labels (voxel holds points).
        weight: (N,) weight of each voxel.
        p: (N,) occupancy of each voxel before carving.
        crossings: (N,) int rays through each voxel.

    Returns:
        The weight in :data:`CARVE_BOUNDS` (0 when no labelled voxel was crossed).
    """
    crossings = np.asarray(crossings)
    use = crossings > 0  # uncrossed voxels do not depend on the weight
    if not use.any():
        return 0.0
    y, w, p0, k = np.asarray(positive, bool)[use], np.asarray(weight, float)[use], np.asarray(p, float)[use], \
        crossings[use].astype(np.float64)
    eps = 1e-12
    base = np.log(np.clip(p0, eps, 1 - eps)) - np.log1p(-np.clip(p0, eps, 1 - eps))

    def nll(a: float) -> float:
        z = base - a * k
        return float(np.sum(w * np.where(y, np.logaddexp(0.0, -z), np.logaddexp(0.0, z))))

    return float(minimize_scalar(nll, bounds=CARVE_BOUNDS, method='bounded').x)
