"""The localiser: a MAP estimate of a scan's 6-DoF pose against the uncertain map.

Model. The scan's points ``s_i`` (sensor frame) sit at ``p_i = T s_i`` in the map frame.
The map answers each with a signed distance ``r_i`` to its mean surface (positive outside,
along the outward normal ``n_i``), the surface variance ``v_i`` and the point noise
``eta_i``; the residual's variance is ``sigma_i^2 = v_i + eta_i + sensor_noise^2``. The
cost is

    F(T) = sum_i rho(r_i(T) / sigma_i) + 1/2 e(T)^T Sigma_p^-1 e(T)

with ``rho`` a robust kernel (``kernel``: Geman-McClure by default, Cauchy, Huber or none;
scale ``kernel_scale`` sigmas) and ``e`` the prior's error. Points the map does not answer
(``facade == -1``) weigh nothing.

Pose perturbations. ``delta = (t, w)`` (6,), ROS order: metres along the map's X, Y, Z,
then radians about the map's X, Y, Z axes, applied on the left in the map's axes *at the
sensor's position* ``c``: ``T = C exp(delta) C^-1 T_hat`` with ``C`` the translation by
``c``. So ``t`` is the position error and ``w`` turns the sensor about itself, as a ROS
``PoseWithCovariance`` is read; about the map origin instead (``exp(delta) @ T_hat``) a
0.1 degree error would move a sensor 1 km from the origin by 1.7 m. The solve keeps ``c``
at the prior's position; the returned covariance is moved to the estimate's position (the
adjoint of the translation between the two).

Jacobian. ``dp_i / d delta = [I, -[p_i - c]x]``, so ``dr_i / d delta = n_i^T [I, -[p_i - c]x]
= [n_i, (p_i - c) x n_i]``.

Rounds. A map query is the expensive part, so the map is queried once per round at the
current pose (in batches of ``batch_points``); the round then runs Levenberg-Marquardt on
the *linearised surfaces* ``r_i(T) ~ r_i0 + n_i . (p_i(T) - p_i0)`` (exact for planes; the
rotation is exact) until the step is below the tolerances; the next round queries again at
the new pose. It ends when a round moves the pose less than the tolerances, or less than
``mahalanobis_tolerance`` of its own standard deviations (converged), or after
``max_queries`` rounds. Annealing: in round j the kernel's scale is at least
``anneal_start / 8^j`` metres (zero once below 1 cm), so the first rounds, whose start may
be half a search step off, weigh every answer, and the last ones leave outliers out; a round
with annealing left cannot end the solve. A round whose move turns back on the previous
one's (negative inner product under the Hessian: answers flipping across a depth step) moves
half as far, so such flips die out instead of using up the rounds.

Start. The map answers only within its façade bands (``extraction.band_back`` behind a
wall, ``band_front`` in front), so a prior 3 m off may leave a street's walls unanswered.
Before the first round a grid of horizontal offsets (``search_radius``, ``search_step``) and
yaws (``search_yaw``, ``search_yaw_step``) of the prior is scored with ``search_points`` of
the scan's farther half each, in one batched query: per candidate, the sum over its points
of ``exp(-sd^2 / 2 (step/2)^2)`` (unanswered: 0) minus half the candidate's squared
Mahalanobis distance from the prior. The best starts the solve; the prior factor stays the
prior, so directions the scan cannot see still come from the prior.

Covariance. The inverse of the final Gauss-Newton Hessian ``Sigma_p^-1 + sum_i J_i^T w_i J_i
/ sigma_i^2`` (Cholesky), with the robust weights ``w_i`` of the last iteration. The map's
errors are spatially correlated (a wall's mean surface is off by the same amount over a
patch), which points sharing that error cannot average away; ``correlation_length`` > 0
multiplies each point's surface variance ``v_i`` (not ``eta_i``, the scatter about the
surface, nor the sensor noise: those are the points' own) by the number of used points of
its façade in its cube of that side (:func:`patch_counts`, keyed by the point moved onto the
map's surface), so that ``m`` points sharing one surface error carry ``1 / (v + s^2/m)`` of
information about it, as they should, not ``m / (v + s^2)``. The default, 2 m, is the map's
wall-surface node spacing (``layers.relief_spacing``): the mean surface is a smooth surface
with nodes that far apart, so its errors are alike over about that distance. It is a model
choice, not fitted: see the tests (a world of planes whose errors are alike over 3 m patches:
NEES of the plain Hessian far above its band, inside it with ``correlation_length`` 3 m).
A whole façade may also sit off as a whole (its frame, a registration error of the drive
that mapped it), which no number of its points averages away: with ``facade_offsets`` an
offset ``b_f ~ N(0, v_f)`` shared by a façade's points along their normals, ``v_f`` the
median surface variance answered on them, is marginalised out of the points' information
(:func:`_facade_offsets`, a Schur complement per façade).

Consistency. The used points' weighted mean of ``(r_i / sigma_i)^2`` (``residual_ratio``)
is 1 when the residuals are as large as their variances say; above 1 (a scan distorted by
motion, a map off by more than its variance) the points' information is divided by it, and
above ``max_residual_ratio`` the answer is ``inconsistent``, not converged.

Ambiguity (issue 40). After the solve, the best-scored starts of the search at least a
``search_step`` from every solution so far (``alternatives`` of them) are solved too, and
the solutions are compared on one robust cost over every thinned point, an unanswered point
costing what an outlier does (:meth:`_Problem.common_cost`). An alternative within
``ambiguity_cost`` of the first solution, or cheaper, makes the answer ``ambiguous``: the
first solution is kept (taking the cheaper one turned one of the small scene's 10 test
scans right and another wrong) and the covariance grows by ``d d^T`` for each alternative ``d`` away, so that one
standard deviation reaches it; ``converged`` is then false. ``converged`` is true only for a
solution that settled, is not ambiguous and is consistent (``PoseEstimate.status``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
from scipy.linalg import LinAlgError, cho_factor, cho_solve

from ..errors import InputError
from ..params import LocaliseParams
from . import se3

#: Below this (metres) the annealing scale is zero.
_TAU_MIN = 0.01
#: The annealing scale shrinks this much a round.
_ANNEAL = 8.0
__all__ = ['PoseEstimate', 'localise', 'patch_counts', 'robust_weights', 'subsample', 'point_jacobian']


@dataclass(frozen=True)
class PoseEstimate:
    """The localiser's answer.

    Attributes:
        pose: (4, 4) float64, sensor -> map: ``x_map = pose[:3, :3] @ x_sensor + pose[:3, 3]``.
        covariance: (6, 6) of the solution, ROS order (x, y, z m; rotation about the map's X,
            Y, Z axes, rad), a left perturbation in the map's axes at the sensor's position
            (see the module docstring).
        iterations: Levenberg-Marquardt iterations in all rounds.
        queries: calls of ``query`` (each with at most ``params.batch_points`` points).
        points_used: scan points with a weight > 0 in the last iteration.
        converged: the solution can be trusted: the last round moved the pose less than the
            tolerances, no other start explained the scan nearly as well (not ambiguous) and
            the residuals are consistent with their variances (``status`` says which failed).
        cost: final robust cost (dimensionless; the prior term included).
        seconds: wall time of :func:`localise`, queries included.
        status: ``converged``, or why not: ``ambiguous`` (another solution explains the scan
            within ``localise.ambiguity_cost``; the covariance spans both), ``inconsistent``
            (the residuals' mean square over their variances above
            ``localise.max_residual_ratio``; the covariance is scaled by it) or
            ``not settled`` (the rounds ran out still moving).
        residual_ratio: the used points' weighted mean of ``(r_i / sigma_i)^2``: 1 when the
            residuals are as large as their variances say (dimensionless).
        alternatives: (K, 4, 4) the other solutions within ``localise.ambiguity_cost`` (K = 0:
            none).
    """

    pose: np.ndarray
    covariance: np.ndarray
    iterations: int
    queries: int
    points_used: int
    converged: bool
    cost: float
    seconds: float
    status: str = 'converged'
    residual_ratio: float = 1.0
    alternatives: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))


# ----------------------------------------------------------------------------------------
# Pieces
# ----------------------------------------------------------------------------------------
def subsample(xyz: np.ndarray, voxel: float, max_points: int, seed: int) -> np.ndarray:
    """Indices (M,) of a spatially even, seeded subset of points (N, 3): one random point per
    cubic voxel of side ``voxel`` (0: every point), then at most ``max_points`` of those at
    random. Sorted, so the subset keeps the scan's order."""
    rng = np.random.default_rng(seed)
    n = len(xyz)
    if voxel > 0 and n:
        cells = np.floor(xyz / voxel).astype(np.int64)
        cells -= cells.min(axis=0)
        span = cells.max(axis=0) + 1
        key = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]  # one integer per voxel
        order = rng.permutation(n)  # the first point of a voxel in this order is a random one
        _, first = np.unique(key[order], return_index=True)
        keep = order[first]
    else:
        keep = np.arange(n)
    if len(keep) > max_points:
        keep = rng.choice(keep, max_points, replace=False)
    return np.sort(keep)


def point_jacobian(points: np.ndarray, normals: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(M, 6) Jacobians of the point-to-surface residuals wrt ``delta = (t, w)``:
    ``n_i^T [I, -[p_i - c]x] = [n_i, (p_i - c) x n_i]``.

    Args:
        points: (M, 3) points, map frame, metres.
        normals: (M, 3) unit outward normals, map frame.
        centre: (3,) the perturbation's centre ``c``, map frame.
    """
    return np.hstack([normals, np.cross(points - centre, normals)])


def robust_weights(u: np.ndarray, kernel: str, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """IRLS weights (M,) in (0, 1] and costs ``rho(u)`` (M,) of residuals ``u`` in sigmas.

    cauchy: ``rho = k^2/2 log(1 + (u/k)^2)``, ``w = 1 / (1 + (u/k)^2)``; huber: ``u^2/2``
    up to ``k``, ``k |u| - k^2/2`` beyond, ``w = min(1, k/|u|)``; none: ``u^2/2``, 1.
    """
    if kernel == 'cauchy':
        z = (u / scale) ** 2
        return 1.0 / (1.0 + z), 0.5 * scale**2 * np.log1p(z)
    if kernel == 'geman':
        z = (u / scale) ** 2
        return 1.0 / (1.0 + z) ** 2, 0.5 * u**2 / (1.0 + z)
    if kernel == 'huber':
        a = np.abs(u)
        inside = a <= scale
        return (np.where(inside, 1.0, scale / np.maximum(a, 1e-300)),
                np.where(inside, 0.5 * u**2, scale * a - 0.5 * scale**2))
    return np.ones_like(u), 0.5 * u**2


def patch_counts(points: np.ndarray, facade: np.ndarray, length: float) -> np.ndarray:
    """(M,) how many of the points share each point's façade and cube of side ``length``
    (map frame, metres): the points that see one patch of the map surface, hence one
    surface error. ``length`` 0: ones."""
    if length <= 0 or not len(points):
        return np.ones(len(points))
    keys = np.column_stack([facade.astype(np.int64), np.floor(points / length).astype(np.int64)])
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    return counts[inverse.ravel()].astype(np.float64)


def centred_log(pose: np.ndarray, reference: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """``delta`` with ``pose = C exp(delta) C^-1 reference`` (C: translation by ``centre``)."""
    rel = pose @ se3.inverse(reference)
    # C^-1 rel C: same rotation, translation R c + t - c
    moved = rel.copy()
    moved[:3, 3] = rel[:3, :3] @ centre + rel[:3, 3] - centre
    return se3.se3_log(moved)


def _centred_exp(delta: np.ndarray, pose: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """``C exp(delta) C^-1 pose``."""
    step = se3.se3_exp(delta)
    step[:3, 3] += centre - step[:3, :3] @ centre
    return step @ pose  # re-orthonormalised once at the end of localise()


def _check_inputs(scan: Any, prior_pose: Any, prior_covariance: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    scan = np.asarray(scan, dtype=np.float64)
    if scan.ndim != 2 or scan.shape[1] != 3:
        raise InputError(f'scan: expected (N, 3) points, got shape {scan.shape}')
    finite = np.isfinite(scan).all(axis=1)
    scan = scan[finite]
    if len(scan) < 6:
        raise InputError(f'scan: {len(scan)} finite points; at least 6 are needed to localise')
    prior = np.asarray(prior_pose, dtype=np.float64)
    if prior.shape != (4, 4) or not np.isfinite(prior).all():
        raise InputError(f'prior pose: expected a finite 4x4 matrix, got shape {prior.shape}')
    rot = prior[:3, :3]
    if (not np.allclose(rot.T @ rot, np.eye(3), atol=1e-5) or np.linalg.det(rot) < 0
            or not np.allclose(prior[3], [0, 0, 0, 1])):
        raise InputError('prior pose: the 4x4 matrix is not a rigid motion (rotation block not orthonormal with '
                         'determinant 1, or last row not 0 0 0 1)')
    cov = np.asarray(prior_covariance, dtype=np.float64)
    if cov.shape != (6, 6) or not np.isfinite(cov).all() or not np.allclose(cov, cov.T, rtol=1e-8, atol=1e-12):
        raise InputError(f'prior covariance: expected a finite symmetric 6x6 matrix, got shape {cov.shape}')
    return scan, se3.compose(prior, np.eye(4)), cov


class _Batched:
    """``query`` called in batches of at most ``batch`` points, counting the calls."""

    def __init__(self, query: Callable[[np.ndarray], Any], batch: int) -> None:
        self.query, self.batch, self.calls = query, batch, 0

    def __call__(self, xyz: np.ndarray, constant_variance: float | None) -> tuple[np.ndarray, ...]:
        """(M,) facade, signed distance, variance, noise variance, (M, 3) normals; NaN-free where facade >= 0."""
        parts = []
        for start in range(0, len(xyz), self.batch):
            self.calls += 1
            ans = self.query(np.ascontiguousarray(xyz[start:start + self.batch]))
            try:
                parts.append((np.asarray(ans.facade), np.asarray(ans.signed_distance, dtype=np.float64),
                              np.asarray(ans.variance, dtype=np.float64),
                              np.asarray(ans.noise_variance, dtype=np.float64),
                              np.asarray(ans.normal, dtype=np.float64)))
            except AttributeError as err:
                raise InputError(f'query: the answer lacks {err.name or "a field"} (needs facade, signed_distance, '
                                 'variance, noise_variance and normal)') from err
        facade, sd, var, noise, normal = (np.concatenate(x) for x in zip(*parts))
        if facade.shape != (len(xyz),) or normal.shape != (len(xyz), 3):
            raise InputError(f'query: answered {facade.shape} facades and {normal.shape} normals for {len(xyz)} points')
        ok = ((facade >= 0) & np.isfinite(sd) & np.isfinite(var) & np.isfinite(noise)
              & np.isfinite(normal).all(axis=1))
        if constant_variance is not None:  # the map taken as exact: one value for variance + noise
            var, noise = np.full(len(xyz), float(constant_variance)), np.zeros(len(xyz))
        facade = np.where(ok, facade, -1)
        return (facade, np.where(ok, sd, 0.0), np.where(ok, var, 1.0), np.where(ok, noise, 0.0),
                np.where(ok[:, None], normal, 0.0))


def _search_start(points: np.ndarray, prior: np.ndarray, prior_factor: tuple, centre: np.ndarray, ask: _Batched,
                  params: LocaliseParams, constant_variance: float | None, rng: np.random.Generator
                  ) -> tuple[np.ndarray, np.ndarray]:
    """A grid of horizontal offsets and yaws of the prior, scored (see the module docstring):
    ``(candidates, scores)``, (C, 6) twists ``delta`` of the prior about ``centre`` and (C,),
    best first."""
    r, step = params.search_radius, params.search_step
    k = int(np.floor(r / step))
    grid = np.arange(-k, k + 1) * step
    dx, dy = np.meshgrid(grid, grid, indexing='ij')
    offsets = np.column_stack([dx.ravel(), dy.ravel()])
    offsets = offsets[np.hypot(offsets[:, 0], offsets[:, 1]) <= r + 1e-9]
    k_yaw = int(np.floor(params.search_yaw / params.search_yaw_step + 1e-9))
    yaws = np.deg2rad(np.arange(-k_yaw, k_yaw + 1) * params.search_yaw_step)
    # the farther half of the scan: façades rather than the road and cars next to the sensor, and a turn moves
    # them most (points are in the sensor frame here: the range is their norm)
    far = points[np.linalg.norm(points, axis=1) >= np.median(np.linalg.norm(points, axis=1))]
    pick = far[rng.choice(len(far), min(params.search_points, len(far)), replace=False)]
    candidates = np.array([[ox, oy, 0.0, 0.0, 0.0, yaw] for yaw in yaws for ox, oy in offsets])
    # the candidates' points, vectorised: turned about the centre by the yaw, then moved (a pure yaw's
    # exp moves by J(phi) rho; the grid is what is scored, the best candidate's pose is made from its own twist)
    rel = se3.transform_points(prior, pick) - centre
    turned = np.einsum('yij,mj->ymi', se3.so3_exp(np.column_stack([np.zeros((len(yaws), 2)), yaws])), rel)
    shifts = np.array([se3.so3_left_jacobian(c[3:]) @ c[:3] for c in candidates]).reshape(len(yaws), -1, 3)
    xyz = (centre + turned[:, None, :, :] + shifts[:, :, None, :]).reshape(-1, 3)
    facade, sd, _, _, _ = ask(xyz, constant_variance)
    width = max(step / 2.0, 0.05)
    score = np.where(facade >= 0, np.exp(-0.5 * (sd / width) ** 2), 0.0).reshape(len(candidates), len(pick)).sum(1)
    # the prior's log density breaks near-ties (a street seen end-on): the candidate nearest the prior wins them
    score -= 0.5 * np.einsum('ij,ij->i', candidates, cho_solve(prior_factor, candidates.T).T)
    order = np.argsort(-score, kind='stable')
    return candidates[order], score[order]


# ----------------------------------------------------------------------------------------
# The solve
# ----------------------------------------------------------------------------------------
def localise(scan: np.ndarray, prior_pose: np.ndarray, prior_covariance: np.ndarray,
             query: Callable[[np.ndarray], Any], params: LocaliseParams | None = None, *,
             constant_variance: float | None = None) -> PoseEstimate:
    """Localise a scan against the map: the MAP pose and its covariance (module docstring).

    Args:
        scan: (N, 3) points, metres, sensor frame (non-finite rows are dropped).
        prior_pose: (4, 4) sensor -> map, the prior's mean.
        prior_covariance: (6, 6) the prior's covariance, :attr:`PoseEstimate.covariance`'s
            convention (at the prior's position).
        query: ``query(xyz)`` for (M, 3) float64 map-frame points, M <= ``params.batch_points``,
            returns an object with (M,) ``facade`` (-1: no answer), ``signed_distance`` (m),
            ``variance`` (m^2), ``noise_variance`` (m^2) and (M, 3) ``normal`` (unit, outward,
            map frame): a :class:`~uncertain_facade_map.pipeline.step7_queries.PointQuery`
            (see :func:`~uncertain_facade_map.localisation.map_query` for a map).
        params: the ``localise`` parameters (default: the defaults).
        constant_variance: if given (m^2), every answered point's variance + noise variance
            is this one value (the map taken as exact, a baseline).

    Returns:
        The :class:`PoseEstimate`.

    Raises:
        InputError: a malformed scan, prior pose (not a rigid motion) or prior covariance
            (not symmetric positive definite), a bad ``constant_variance``, or answers
            lacking a field.
    """
    started = time.perf_counter()
    params = LocaliseParams() if params is None else params
    if constant_variance is not None and not (np.isfinite(constant_variance) and constant_variance >= 0):
        raise InputError(f'constant_variance: expected a finite value >= 0 m^2, got {constant_variance!r}')
    scan, prior, prior_cov = _check_inputs(scan, prior_pose, prior_covariance)
    try:
        prior_factor = cho_factor(prior_cov, lower=True)
    except LinAlgError as err:
        raise InputError('prior covariance: not positive definite (every standard deviation must be > 0)') from err
    rng = np.random.default_rng(params.seed)
    points = scan[subsample(scan, params.voxel, params.max_points, params.seed)]
    centre = prior[:3, 3].copy()
    ask = _Batched(query, params.batch_points)
    problem = _Problem(points, prior, prior_factor, centre, ask, params, constant_variance)
    candidates = np.zeros((1, 6))
    if params.search_radius > 0:
        candidates, _ = _search_start(points, prior, prior_factor, centre, ask, params, constant_variance, rng)
    best = problem.solve(_centred_exp(candidates[0], prior, centre))
    # Ambiguity (issue 40): the best-scored starts far from the solution, solved in turn; the
    # solutions are compared on one cost over every thinned point (an unanswered point costs
    # what an outlier does), so that a solution that leaves walls unanswered is no cheaper;
    # one within ambiguity_cost of the first (or cheaper) makes the answer ambiguous.
    others: list[_Solution] = []
    if params.alternatives > 0 and len(candidates) > 1:
        best_cost = problem.common_cost(best.pose)
        tried: list[np.ndarray] = [centred_log(best.pose, prior, centre)]
        for cand in candidates[1:]:
            if len(tried) > params.alternatives:
                break
            if min(np.hypot(*(cand[:2] - t[:2])) for t in tried) < params.search_step:
                continue
            alt = problem.solve(_centred_exp(cand, prior, centre))
            tried.append(centred_log(alt.pose, prior, centre))
            alt_cost = problem.common_cost(alt.pose)
            # Not swapped when cheaper: on the small scene's 10 test scans the cheaper one
            # was right once (2.85 -> 0.53 m) and wrong once (0.01 -> 2.57 m): the scan does
            # not tell, and the answer says so.
            if alt_cost - best_cost < params.ambiguity_cost and np.linalg.norm(
                    centred_log(alt.pose, best.pose, best.pose[:3, 3])[:3]) > 3 * params.translation_tolerance:
                others.append(alt)
    pose = se3.compose(best.pose, np.eye(4))  # re-orthonormalised
    # Consistency: the residuals against their variances; beyond max_residual_ratio the
    # points' information is scaled down by the ratio (a scan distorted by motion, a map
    # off by more than its variance): the covariance grows with what the residuals show.
    ratio = best.residual_ratio
    hessian = best.prior_hessian + best.points_hessian / max(ratio, 1.0)
    try:
        h_factor = cho_factor(hessian, lower=True)
    except LinAlgError as err:  # cannot happen with a positive definite prior; keep the cause
        raise InputError('the final Hessian is not positive definite (a degenerate prior covariance?)') from err
    cov_c = cho_solve(h_factor, np.eye(6))
    # covariance at the centre c, moved to the estimate's position c'
    adjoint = np.eye(6)
    adjoint[:3, 3:] = se3.skew(centre - pose[:3, 3])
    covariance = adjoint @ cov_c @ adjoint.T
    for alt in others:  # the covariance spans each alternative (one standard deviation reaches it)
        d = centred_log(alt.pose, pose, pose[:3, 3])
        covariance = covariance + np.outer(d, d)
    covariance = 0.5 * (covariance + covariance.T)
    status = ('ambiguous' if others else 'inconsistent' if ratio > params.max_residual_ratio
              else 'converged' if best.settled else 'not settled')
    return PoseEstimate(pose=pose, covariance=covariance, iterations=problem.iterations, queries=ask.calls,
                        points_used=int(best.used), converged=status == 'converged', cost=float(best.cost),
                        seconds=time.perf_counter() - started, status=status, residual_ratio=float(ratio),
                        alternatives=np.array([se3.compose(a.pose, np.eye(4)) for a in others]).reshape(-1, 4, 4))


@dataclass(frozen=True)
class _Solution:
    """One solve from one start: the pose, the final Hessian's two parts (the points' and the
    prior's, at the prior's centre), the robust cost, whether the last round settled, the
    points used and the weighted mean square of their residuals in sigmas."""

    pose: np.ndarray
    points_hessian: np.ndarray
    prior_hessian: np.ndarray
    cost: float
    settled: bool
    used: int
    residual_ratio: float


class _Problem:
    """The scan's points, the prior and the map, solved from any start (:meth:`solve`)."""

    def __init__(self, points: np.ndarray, prior: np.ndarray, prior_factor: tuple, centre: np.ndarray,
                 ask: _Batched, params: LocaliseParams, constant_variance: float | None) -> None:
        self.points, self.prior, self.prior_factor, self.centre = points, prior, prior_factor, centre
        self.ask, self.params, self.constant_variance = ask, params, constant_variance
        self.iterations = 0

    def _answers(self, pose: np.ndarray) -> tuple[np.ndarray, ...]:
        """The map's answers at the points placed by ``pose``: (on, p0, r0, sigma2, normal, fac)."""
        params = self.params
        p0 = se3.transform_points(pose, self.points)
        facade, r0, var, noise, normal = self.ask(p0, self.constant_variance)
        on = facade >= 0
        p0, r0, var, noise, normal, fac = p0[on], r0[on], var[on], noise[on], normal[on], facade[on]
        surface = var
        if params.correlation_length > 0 and self.constant_variance is None:
            # the mean surface's error is shared within a patch; the scatter of points about it is not
            var = var * patch_counts(p0 - r0[:, None] * normal, fac, params.correlation_length)  # on the surface
        return on, p0, r0, var + noise + params.sensor_noise**2, normal, fac, surface

    def solve(self, pose: np.ndarray) -> _Solution:
        """The rounds from ``pose`` (module docstring)."""
        params, prior, prior_factor, centre = self.params, self.prior, self.prior_factor, self.centre
        tol_t, tol_r = params.translation_tolerance, np.deg2rad(params.rotation_tolerance)
        settled = False
        previous = None
        for _round in range(params.max_queries):
            on, p0, r0, sigma2, normal, fac, surface = self._answers(pose)
            sigma = np.sqrt(sigma2)
            # annealing: the kernel's scale is at least tau metres, tau shrinking 8x a round (module docstring)
            tau = params.anneal_start / _ANNEAL**_round
            tau = tau if tau >= _TAU_MIN else 0.0
            scale = params.kernel_scale * np.sqrt(1.0 + tau**2 / sigma2)
            start_pose = pose
            hessian, prior_part, cost, pose, n_iter, used, ratio, info = _solve_round(
                self.points[on], p0, r0, normal, sigma, scale, pose, prior, prior_factor, centre, params)
            self.iterations += n_iter
            step = centred_log(pose, start_pose, start_pose[:3, 3])
            if previous is not None and float(step @ hessian @ previous) < 0:
                # the answers flip between two rounds (a depth step crossed back and forth): half the step
                step = 0.5 * step
                pose = _centred_exp(step, start_pose, start_pose[:3, 3])
            previous = step
            moved = centred_log(pose, start_pose, pose[:3, 3])
            small = np.linalg.norm(moved[:3]) < tol_t and np.linalg.norm(moved[3:]) < tol_r
            if tau == 0.0 and (small or float(moved @ hessian @ moved) < params.mahalanobis_tolerance**2):
                settled = True
                break
        points_part = hessian - prior_part
        if params.facade_offsets and self.constant_variance is None:
            points_part = points_part - _facade_offsets(info, fac, surface)
        return _Solution(pose, points_part, prior_part, cost, settled, used, ratio)

    def common_cost(self, pose: np.ndarray) -> float:
        """The robust cost of every thinned point at ``pose`` with the final kernel (no
        annealing), an unanswered point costing the kernel's limit (an outlier's), plus the
        prior's: one scale on which solutions from different starts compare."""
        params = self.params
        on, _, r0, sigma2, _, _, _ = self._answers(pose)
        _, rho = robust_weights(r0 / np.sqrt(sigma2), params.kernel, params.kernel_scale)
        limit = _kernel_limit(params.kernel, params.kernel_scale)
        e = centred_log(pose, self.prior, self.centre)
        return float(rho.sum() + (len(on) - on.sum()) * limit + 0.5 * e @ cho_solve(self.prior_factor, e))


def _facade_offsets(info: tuple[np.ndarray, np.ndarray], facade: np.ndarray, surface: np.ndarray) -> np.ndarray:
    """(6, 6) the information the points lose when each façade's mean surface may be off
    as a whole (issue 40): an offset ``b_f ~ N(0, v_f)`` along the points' normals shared by
    the points of façade ``f``, ``v_f`` the median surface variance answered on them,
    marginalised out (Schur complement): ``sum_f g_f g_f^T / (c_f + 1 / v_f)`` with
    ``g_f = sum_{i in f} J_i^T w_i / sigma_i^2`` and ``c_f = sum_{i in f} w_i / sigma_i^2``.
    No number of points on one façade then pins the pose along its normal better than the
    façade's own variance."""
    jw, cw = info
    out = np.zeros((6, 6))
    for f in np.unique(facade):
        sel = facade == f
        v = float(np.median(surface[sel]))
        if not v > 0:
            continue
        g = jw[sel].sum(axis=0)
        out += np.outer(g, g) / (cw[sel].sum() + 1.0 / v)
    return out


def _kernel_limit(kernel: str, scale: float) -> float:
    """The cost of an unanswered point: the kernel's limit far out (cauchy and huber grow
    without one: the cost at 3 scales), in the units of :func:`robust_weights`."""
    if kernel == 'geman':
        return 0.5 * scale**2
    return float(robust_weights(np.array([3.0 * scale]), kernel, scale)[1][0])


def _costs(points_now, p0, r0, normal, sigma, scale, pose, prior, prior_factor, centre, params):
    """Residuals in sigmas, weights, robust costs and the prior error at ``pose``."""
    r = r0 + np.einsum('ij,ij->i', normal, points_now - p0)
    u = r / sigma
    w, rho = robust_weights(u, params.kernel, scale)
    e = centred_log(pose, prior, centre)
    prior_cost = 0.5 * float(e @ cho_solve(prior_factor, e))
    return r, w, float(rho.sum()) + prior_cost, e


def _solve_round(body, p0, r0, normal, sigma, scale, pose, prior, prior_factor, centre, params):
    """Levenberg-Marquardt on the linearised surfaces of one round.

    Returns:
        The Gauss-Newton Hessian at the end and its prior's part, the cost, the pose, the
        iterations, the points with a weight > 0 and their weighted mean square residual in
        sigmas.
    """
    lam = 1e-4
    tol_t, tol_r = params.translation_tolerance * 0.1, np.deg2rad(params.rotation_tolerance) * 0.1
    now = se3.transform_points(pose, body)
    r, w, cost, e = _costs(now, p0, r0, normal, sigma, scale, pose, prior, prior_factor, centre, params)
    n_iter = 0
    hessian = None
    for _ in range(params.max_iterations):
        n_iter += 1
        jac = point_jacobian(now, normal, centre)
        scaled = jac * np.sqrt(w / sigma**2)[:, None]
        j_prior = se3.se3_left_jacobian_inverse(e)
        info_j = cho_solve(prior_factor, j_prior)  # Sigma_p^-1 J_p
        hessian = scaled.T @ scaled + j_prior.T @ info_j
        grad = jac.T @ (w * r / sigma**2) + info_j.T @ e
        diag = np.diag(hessian).copy()
        accepted = False
        for _try in range(10):
            try:
                step = -cho_solve(cho_factor(hessian + lam * np.diag(diag), lower=True), grad)
            except LinAlgError:
                lam *= 10.0
                continue
            trial = _centred_exp(step, pose, centre)
            trial_now = se3.transform_points(trial, body)
            t_r, t_w, t_cost, t_e = _costs(trial_now, p0, r0, normal, sigma, scale, trial, prior, prior_factor, centre,
                                           params)
            if t_cost <= cost:
                pose, now, r, w, cost, e = trial, trial_now, t_r, t_w, t_cost, t_e
                lam = max(lam / 10.0, 1e-9)
                accepted = True
                break
            lam *= 10.0
        if not accepted or (np.linalg.norm(step[:3]) < tol_t and np.linalg.norm(step[3:]) < tol_r):
            break
    # the Hessian at the final pose, with its weights
    jac = point_jacobian(now, normal, centre)
    scaled = jac * np.sqrt(w / sigma**2)[:, None]
    j_prior = se3.se3_left_jacobian_inverse(e)
    prior_part = j_prior.T @ cho_solve(prior_factor, j_prior)
    hessian = scaled.T @ scaled + prior_part
    ratio = float(np.sum(w * (r / sigma) ** 2) / np.sum(w)) if np.sum(w) > 0 else 1.0
    info = (jac * (w / sigma**2)[:, None], w / sigma**2)  # per point J_i w_i / sigma_i^2 and w_i / sigma_i^2
    return hessian, prior_part, cost, pose, n_iter, int((w > 0).sum()), ratio, info
