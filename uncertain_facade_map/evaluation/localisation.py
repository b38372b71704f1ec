"""Localisation against the map, compared honestly (issue 28, item 3).

Scan-by-scan localisation of drives against a map built from another drive, from initial
poses perturbed as GNSS is in a street canyon, by several *rows* (localisers behind one
interface, :data:`Method`), scored against the true pose:

- **scenarios** (:class:`Scenario`): a simulated scene's campaign 0 mapped with the
  package's map (the building points, as ``uncertain-facade-map build`` takes a cloud with
  a class field), and scans of campaigns 1-4 (:func:`simulated_scenario`); an
  *occlusion-heavy* variant whose mapping drive passes a street lined with tall vans and
  dense trees (:func:`occluded_scene`), the drives localised being the ordinary ones; and
  a real Argoverse 2 sweep against the map of the sweep before it (:func:`real_scenario`).
- **scans** (:class:`ScanCase`): ``scan_seconds`` of a drive's returns (every class:
  ground, cars, trees as well as walls), moved into the sensor frame (scanner 0's mount,
  axes of the vehicle: x forward, y left, z up) at the pose of the window's middle, as a
  scan de-skewed by odometry is; at most ``max_points`` of them, a seeded subset. The true
  pose is the simulator's (the drive's path, not moved by the campaign's registration
  offset: that offset is the campaign's own pose error, which the localiser is to find).
- **priors** (:func:`perturb`): the true pose moved by a horizontal offset of 0.5-3 m in
  a uniformly drawn direction and turned by 1-5 degrees about the vertical (either sign),
  both magnitudes uniform, plus small vertical (``z_sigma``) and roll/pitch
  (``tilt_sigma_deg``) errors; the prior covariance (:func:`prior_covariance`) is
  diagonal with sigma = half the largest offset and turn.
- **metrics** (:func:`pose_error`, :func:`nees`, :func:`summarise`): position error
  (3-D, metres), heading error (yaw of the sensor's x axis, wrapped to (-180, 180]
  degrees), the share of scans within 0.2 m and 1 degree (both), NEES of the output
  covariance against chi-square(6), time per scan.

Poses are 4 x 4 sensor -> map matrices (``x_map = T[:3, :3] @ x_sensor + T[:3, 3]``);
covariances 6 x 6 in ROS order (x, y, z metres; rotation about map X, Y, Z radians) of the
error ``(p - p_hat, log(R R_hat^T))``: position in the map frame, rotation on the left
(:func:`pose_error` computes exactly that vector).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from ..errors import InputError
from ..localisation.queries import map_query

#: The central 95 % band of chi-square with 6 degrees of freedom (per-scan NEES).
NEES_BAND = (float(chi2.ppf(0.025, 6)), float(chi2.ppf(0.975, 6)))
#: Thresholds of a "good" scan: position within (metres) and heading within (degrees).
GOOD_POSITION = 0.2
GOOD_HEADING_DEG = 1.0
#: A "confident miss" (issue 40): more than this off horizontally (metres) and reported converged.
MISS_POSITION = 0.5


# ---------------------------------------------------------------------------------------
# Poses


def pose_matrix(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(4, 4) pose from a (3, 3) rotation and a (3,) translation."""
    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:3, 3] = translation
    return pose


def yaw_pose(x: float, y: float, z: float, yaw: float) -> np.ndarray:
    """(4, 4) pose at (x, y, z) metres turned by ``yaw`` radians about z."""
    return pose_matrix(Rotation.from_euler('z', yaw).as_matrix(), np.array([x, y, z], dtype=np.float64))


def heading(pose: np.ndarray) -> float:
    """Heading of the sensor's x axis in the map's x-y plane, radians from +x."""
    return float(np.arctan2(pose[1, 0], pose[0, 0]))


def wrap_degrees(angle: np.ndarray | float) -> np.ndarray:
    """Angles wrapped to (-180, 180] degrees."""
    a = np.mod(np.asarray(angle, dtype=np.float64) + 180.0, 360.0) - 180.0
    return np.where(a == -180.0, 180.0, a)


def pose_error(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """The error of a (4, 4) pose estimate, (6,): ``(p - p_true, rotvec(R R_true^T))``,
    metres and radians about the map axes (the covariance's convention, ROS order)."""
    dp = estimate[:3, 3] - truth[:3, 3]
    dphi = Rotation.from_matrix(estimate[:3, :3] @ truth[:3, :3].T).as_rotvec()
    return np.concatenate([dp, dphi])


def centred_error(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """The localiser's error vector, (6,): ``delta`` with ``truth = C exp(delta) C^-1 estimate``,
    ``C`` the translation to the estimate's position and ``exp`` that of SE(3) (translation
    first, rotation about the map axes; the convention of ``PoseEstimate.covariance``). To
    first order ``-pose_error(estimate, truth)``."""
    from ..localisation.solver import centred_log

    return centred_log(truth, estimate, estimate[:3, 3])


def nees(error: np.ndarray, covariance: np.ndarray | None) -> float:
    """Normalised estimation error squared ``e^T C^-1 e`` of a (6,) error under a (6, 6)
    covariance (by Cholesky); NaN for no covariance or one that is not positive definite."""
    if covariance is None:
        return float('nan')
    c = np.asarray(covariance, dtype=np.float64)
    if c.shape != (6, 6) or not np.all(np.isfinite(c)):
        return float('nan')
    try:
        lower = np.linalg.cholesky(0.5 * (c + c.T))
    except np.linalg.LinAlgError:
        return float('nan')
    from scipy.linalg import solve_triangular

    y = solve_triangular(lower, np.asarray(error, dtype=np.float64), lower=True)
    return float(y @ y)


# ---------------------------------------------------------------------------------------
# Priors


@dataclass(frozen=True)
class Perturbation:
    """How initial poses are drawn around the truth (GNSS in a street canyon).

    Attributes:
        position: (min, max) horizontal offset, metres (uniform magnitude, uniform direction).
        heading_deg: (min, max) turn about the vertical, degrees (uniform magnitude, either sign).
        z_sigma: standard deviation of the vertical offset, metres.
        tilt_sigma_deg: standard deviation of roll and pitch, degrees.
    """

    position: tuple[float, float] = (0.5, 3.0)
    heading_deg: tuple[float, float] = (1.0, 5.0)
    z_sigma: float = 0.05
    tilt_sigma_deg: float = 0.2

    def __post_init__(self) -> None:
        lo, hi = self.position
        hlo, hhi = self.heading_deg
        if not (0 <= lo <= hi and 0 <= hlo <= hhi and self.z_sigma >= 0 and self.tilt_sigma_deg >= 0):
            raise InputError(f'bad perturbation ranges {self}: need 0 <= min <= max and sigmas >= 0')


def perturb(truth: np.ndarray, rng: np.random.Generator, spec: Perturbation = Perturbation()
            ) -> tuple[np.ndarray, np.ndarray]:
    """An initial pose near the truth.

    Args:
        truth: (4, 4) true sensor -> map pose.
        rng: the random source (one draw of 6 numbers per call, in a fixed order).
        spec: the ranges.

    Returns:
        ``(prior, delta)``: the (4, 4) prior and its (6,) error ``pose_error(prior, truth)``
        (the position offset in the map frame, the rotation vector about the map axes; the
        turn about the vertical is applied last, so the heading error is the drawn turn up
        to the tilt's second-order effect).
    """
    direction = rng.uniform(-np.pi, np.pi)
    radius = rng.uniform(*spec.position)
    turn = np.deg2rad(rng.uniform(*spec.heading_deg)) * rng.choice([-1.0, 1.0])
    dz = rng.normal(0.0, spec.z_sigma)
    tilt = np.deg2rad(rng.normal(0.0, spec.tilt_sigma_deg, size=2))
    rot = Rotation.from_euler('z', turn) * Rotation.from_rotvec([tilt[0], tilt[1], 0.0])
    prior = pose_matrix(rot.as_matrix() @ truth[:3, :3],
                        truth[:3, 3] + np.array([radius * np.cos(direction), radius * np.sin(direction), dz]))
    return prior, pose_error(prior, truth)


def prior_covariance(spec: Perturbation = Perturbation()) -> np.ndarray:
    """(6, 6) diagonal covariance of the priors: sigma = half the largest horizontal offset
    (x, y) and turn (yaw), ``z_sigma`` and ``tilt_sigma_deg`` (ROS order)."""
    s_xy = max(spec.position[1] / 2.0, 1e-3)
    s_yaw = max(np.deg2rad(spec.heading_deg[1]) / 2.0, 1e-5)
    s_z = max(spec.z_sigma, 1e-3)
    s_tilt = max(np.deg2rad(spec.tilt_sigma_deg), 1e-5)
    return np.diag(np.array([s_xy, s_xy, s_z, s_tilt, s_tilt, s_yaw]) ** 2)


# ---------------------------------------------------------------------------------------
# Scenarios


@dataclass(eq=False)
class ScanCase:
    """One scan to localise.

    Attributes:
        label: where it comes from (e.g. ``c1 t=12.5s``).
        points: (N, 3) float64 returns, metres, sensor frame.
        truth: (4, 4) true sensor -> map pose.
        prior: (4, 4) initial pose.
        prior_covariance: (6, 6) its covariance.
        delta: (6,) ``pose_error(prior, truth)``.
    """

    label: str
    points: np.ndarray
    truth: np.ndarray
    prior: np.ndarray
    prior_covariance: np.ndarray
    delta: np.ndarray


@dataclass(eq=False)
class Scenario:
    """A map and the scans to localise against it.

    Attributes:
        name: row label (e.g. ``street_hard``).
        kind: ``clean``, ``hard``, ``occluded`` or ``real``.
        fmap: the map (:class:`~uncertain_facade_map.mapping.facade_map.FacadeMap`).
        map_points: (M, 3) the points the map was built from, metres, map frame (GICP's target).
        cases: the scans.
        notes: what the scenario is, one line each.
        seconds: time to simulate and map, s.
        cloud_points: (K, 3) every return of the mapping drive (ground, cars, trees too),
            one per 0.1 m voxel, metres, map frame (the second GICP row's target).
    """

    name: str
    kind: str
    fmap: Any
    map_points: np.ndarray
    cases: list[ScanCase]
    notes: list[str] = field(default_factory=list)
    seconds: float = 0.0
    cloud_points: np.ndarray | None = None


def thin(xyz: np.ndarray, voxel: float = 0.1) -> np.ndarray:
    """(K, 3) the first of (N, 3) points in every ``voxel`` (metres) cube, in input order."""
    keys = np.floor(xyz / voxel).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return xyz[np.sort(first)]


def _build_map(xyz: np.ndarray, building_id: np.ndarray | None, origins: np.ndarray | None,
               map_origin: np.ndarray) -> Any:
    from ..mapping.facade_map import build_map
    from ..params import MapParams

    return build_map(xyz, building_id, origins, MapParams(), map_origin)


def occluded_scene(scene: Any, seed: int = 0, van_share: float = 0.9, tree_every: float = 8.0) -> Any:
    """The scene as a mapping drive on a busy day sees it: both kerbs lined with tall vans
    (5-7 m long, 2.6-3.4 m high, a slot of 7.5 m taken with probability ``van_share``) and
    trees every ``tree_every`` metres on both pavements, added to the static occluders.

    Assumes a street along x (as the built-in scenes and :func:`~..simulation.scenes.parked_cars`).
    """
    from ..simulation.scene import Car, Scene, Tree

    rng = np.random.default_rng([seed, 2028])
    x0, x1 = float(scene.street.centreline[0, 0]), float(scene.street.centreline[-1, 0])
    kerb = float(scene.street.kerb)
    extra: list[Any] = []
    for side in (1.0, -1.0):
        for x in np.arange(x0 + 5.0, x1 - 5.0, 7.5):
            if rng.random() < van_share:
                width = float(rng.uniform(2.0, 2.3))
                extra.append(Car(float(x + rng.normal(0, 0.4)), side * (kerb + 0.2 + width / 2), float(rng.normal(0, 0.02)),
                                 float(rng.uniform(5.0, 7.0)), width, float(rng.uniform(2.6, 3.4))))
        for x in np.arange(x0 + rng.uniform(1, tree_every), x1, tree_every):
            extra.append(Tree(float(x + rng.normal(0, 0.8)), side * float(rng.uniform(6.6, 7.2)),
                              float(rng.uniform(0.15, 0.3)), float(rng.uniform(2.5, 3.5)),
                              float(rng.uniform(2.2, 3.2)), float(rng.uniform(0.6, 1.0))))
    return Scene(scene.name, scene.seed, scene.buildings, list(scene.static_occluders) + extra, scene.street,
                 map_origin=scene.map_origin, walls=scene.walls)


def simulated_scenario(name: str, campaigns: Sequence[int] = (1, 2, 3, 4), scans_per_drive: int = 2,
                       scan_seconds: float = 1.0, max_points: int = 10_000, seed: int = 0,
                       perturbation: Perturbation = Perturbation(), map_campaign: int = 0,
                       progress: Callable[[str], None] | None = None) -> Scenario:
    """A simulated scenario (see the module docstring).

    Args:
        name: a scene of :func:`~uncertain_facade_map.simulation.scenes.build_scene`, or one
            with ``_occluded`` appended (its mapping drive passes :func:`occluded_scene`).
        campaigns: the drives localised.
        scans_per_drive: scans per drive, their windows evenly spread over the drive (the
            first and last 10 % left out).
        scan_seconds: seconds of returns in a scan.
        max_points: most points per scan (a seeded random subset).
        seed: seed of the subsets and the priors.
        perturbation: how the priors are drawn.
        map_campaign: the drive mapped.
        progress: called with a line of text per step.

    Raises:
        InputError: unknown scene, a campaign equal to the mapped one, bad counts.
    """
    from ..io.inputs import select_building_points
    from ..params import InputConfig
    from ..simulation.campaign import SCENE_SENSORS, SensorConfig, campaign, drive_duration, simulate_campaign
    from ..simulation.export import sensor_scan
    from ..simulation.scenes import build_scene

    if scans_per_drive < 1 or max_points < 10 or not scan_seconds > 0:
        raise InputError(f'need scans_per_drive >= 1, max_points >= 10 and scan_seconds > 0, got '
                         f'{scans_per_drive}, {max_points}, {scan_seconds}')
    if map_campaign in campaigns:
        raise InputError(f'campaign {map_campaign} is the mapped one: localise other campaigns')
    started = time.perf_counter()
    occluded = name.endswith('_occluded')
    base = name[:-len('_occluded')] if occluded else name
    scene = build_scene(base)
    sensor = SCENE_SENSORS.get(base, SensorConfig())
    kind = 'occluded' if occluded else ('hard' if scene.walls is not None else 'clean')
    mapping_scene = occluded_scene(scene, seed) if occluded else scene
    cloud = simulate_campaign(mapping_scene, map_campaign, sensor)
    building = select_building_points(cloud, InputConfig())
    fmap = _build_map(building.xyz, building.building_id, building.sensor_origins, cloud.map_origin)
    if progress:
        progress(f'{name}: mapped campaign {map_campaign}: {len(building):,} building points, {len(fmap.facades)} façades '
                 f'({time.perf_counter() - started:.1f} s)')
    cov = prior_covariance(perturbation)
    cases = []
    for k in campaigns:
        drive = campaign(scene, k)
        duration = drive_duration(scene, drive, sensor)
        span = max(duration * 0.8 - scan_seconds, 0.0)
        starts = duration * 0.1 + (np.arange(scans_per_drive) + 0.5) / scans_per_drive * span
        for j, t0 in enumerate(starts):
            rng = np.random.default_rng([seed, k, j, 28])
            # The campaign's points lie where its (possibly misregistered) poses put them: back
            # into the sensor frame with those poses, they are what the sensor measured.
            xyz, truth, t_mid = sensor_scan(scene, k, sensor, float(t0), scan_seconds, max_points, rng)
            mid = t_mid - drive.start_time
            prior, delta = perturb(truth, rng, perturbation)
            cases.append(ScanCase(f'c{k} t={mid:.1f}s', xyz, truth, prior, cov, delta))
    notes = [f'scene {base} ({kind}), sensor {_sensor_name(sensor)}, map: campaign {map_campaign} '
             f'({len(building):,} building points, {len(fmap.facades)} façades)'
             + (', mapping drive past tall vans on both kerbs and trees every 8 m' if occluded else ''),
             f'scans: campaigns {", ".join(map(str, campaigns))}, {scans_per_drive} per drive, {scan_seconds:g} s '
             f'each, at most {max_points:,} points']
    if progress:
        progress(f'{name}: {len(cases)} scans ({time.perf_counter() - started:.1f} s)')
    return Scenario(name, kind, fmap, building.xyz, cases, notes, time.perf_counter() - started,
                    thin(cloud.xyz))


def _sensor_name(sensor: Any) -> str:
    from ..simulation.presets import SENSOR_PRESETS

    return next((k for k, v in SENSOR_PRESETS.items() if v == sensor), 'custom')


def real_scenario(map_ply: str, scan_ply: str, draws: int = 10, max_points: int = 10_000, seed: int = 0,
                  perturbation: Perturbation = Perturbation()) -> Scenario:
    """A real sweep localised against the map of another sweep of the same place.

    The map: the building points of ``map_ply`` as ``uncertain-facade-map build`` picks them
    in a cloud without classes (the selection of tall vertical planes, with the file's
    sensor origins). The scan: every point of ``scan_ply`` (at most ``max_points``, a seeded
    subset), moved into a frame at the mean sensor origin of the sweep, axes parallel to the
    map's. The truth: that frame, i.e. the identity correction in the shared city frame of
    the two files (Argoverse's ego poses registered both); the two files' map origins must
    agree (else their difference is applied). The same scan is localised from ``draws``
    priors.
    """
    from ..io.clouds import read_cloud
    from ..io.inputs import select_building_points
    from ..params import InputConfig, SelectionConfig

    started = time.perf_counter()
    mapped = read_cloud(map_ply)
    scan = read_cloud(scan_ply)
    building = select_building_points(mapped, InputConfig(), SelectionConfig())
    fmap = _build_map(building.xyz, building.building_id, building.sensor_origins, mapped.map_origin)
    xyz = scan.xyz + (np.asarray(scan.map_origin, float) - np.asarray(mapped.map_origin, float))
    names = scan.points.dtype.names or ()
    if all(f'origin_{c}' in names for c in 'xyz'):
        centre = np.mean(np.stack([scan.points[f'origin_{c}'] for c in 'xyz'], axis=1), axis=0)
        centre = centre + np.asarray(scan.map_origin, float) - np.asarray(mapped.map_origin, float)
    else:
        centre = np.zeros(3)
    truth = pose_matrix(np.eye(3), centre)
    local = xyz - centre
    rng = np.random.default_rng([seed, 29])
    if len(local) > max_points:
        local = local[np.sort(rng.choice(len(local), max_points, replace=False))]
    cov = prior_covariance(perturbation)
    cases = []
    for j in range(draws):
        prior, delta = perturb(truth, rng, perturbation)
        cases.append(ScanCase(f'draw {j}', local, truth, prior, cov, delta))
    notes = [f'map: {map_ply} ({len(building):,} of {len(mapped):,} points selected as building, '
             f'{len(fmap.facades)} façades); scan: {scan_ply} ({len(scan):,} points, {len(local):,} used), '
             f'{draws} priors; truth: the identity in the shared city frame (map origins differ by '
             f'{np.linalg.norm(np.asarray(scan.map_origin, float) - np.asarray(mapped.map_origin, float)):.3f} m)']
    return Scenario('av2_sweep1_vs_0', 'real', fmap, building.xyz, cases, notes, time.perf_counter() - started,
                    thin(mapped.xyz))


# ---------------------------------------------------------------------------------------
# Rows


@dataclass(frozen=True)
class Estimate:
    """A row's answer for one scan.

    Attributes:
        pose: (4, 4) sensor -> map.
        covariance: (6, 6) of the solution (the convention of the module docstring), None
            for a method that gives none.
        seconds: wall time, s.
        converged: the method's own verdict, None if it gives none.
    """

    pose: np.ndarray
    covariance: np.ndarray | None
    seconds: float
    converged: bool | None = None


#: A row: (scan (N, 3) sensor frame, prior (4, 4), prior covariance (6, 6), scenario) -> Estimate.
Method = Callable[[np.ndarray, np.ndarray, np.ndarray, Scenario], Estimate]


def prior_row(scan: np.ndarray, prior: np.ndarray, covariance: np.ndarray, scenario: Scenario) -> Estimate:
    """Row (d): the prior alone."""
    return Estimate(prior.copy(), covariance.copy(), 0.0, None)


def constant_variance(scenario: Scenario, max_points: int = 20_000, seed: int = 0) -> float:
    """One variance for the whole map (row (b)): the median of ``variance + noise_variance``
    of the map's answers at (a seeded subset of at most ``max_points`` of) its own mapped
    points, m^2."""
    rng = np.random.default_rng([seed, 31])
    pts = scenario.map_points
    if len(pts) > max_points:
        pts = pts[rng.choice(len(pts), max_points, replace=False)]
    answer = scenario.fmap.query(pts)
    hit = np.asarray(answer.facade) >= 0
    total = np.asarray(answer.variance)[hit] + np.asarray(answer.noise_variance)[hit]
    return float(np.median(total)) if hit.any() else 0.01


def localiser_row(localise: Callable[..., Any], constant: float | Callable[[Scenario], float] | None = None,
                  params: Any = None, plane_normals: bool = False) -> Method:
    """Rows (a) and (b): ``localise`` (the API of ``uncertain_facade_map.localisation``)
    asking the scenario's map (:func:`~uncertain_facade_map.localisation.map_query`), with its variance (``constant`` None) or
    one constant variance (m^2, or a function of the scenario giving it; computed once per
    scenario)."""
    queries: dict[int, Callable] = {}
    constants: dict[int, float | None] = {}

    def row(scan: np.ndarray, prior: np.ndarray, covariance: np.ndarray, scenario: Scenario) -> Estimate:
        key = id(scenario)
        if key not in queries:
            queries[key] = map_query(scenario.fmap, plane_normals=plane_normals)
            # The first query builds the map's per-point reading (seconds on a street): not a scan's time.
            queries[key](scenario.map_points[:10])
            constants[key] = constant(scenario) if callable(constant) else constant
        started = time.perf_counter()
        kwargs = {} if constants[key] is None else {'constant_variance': constants[key]}
        out = localise(scan, prior, covariance, queries[key], params, **kwargs)
        seconds = time.perf_counter() - started
        return Estimate(np.asarray(out.pose, dtype=np.float64), np.asarray(out.covariance, dtype=np.float64),
                        seconds, bool(out.converged))

    return row


# ---------------------------------------------------------------------------------------
# Running and scoring


@dataclass(frozen=True)
class Outcome:
    """Per scan and row: the (6,) error (:func:`pose_error`), position (m) and heading error
    (degrees, signed, wrapped), NEES, seconds, the method's verdict, the prior's (6,) error,
    and ``sigmas``: the (6,) error in the method's standard deviations, axis by axis
    (:func:`centred_error` over the square root of the covariance's diagonal; NaN without
    one)."""

    scenario: str
    row: str
    label: str
    error: np.ndarray
    position: float
    heading_deg: float
    nees: float
    seconds: float
    converged: bool | None
    prior_error: np.ndarray
    sigmas: np.ndarray = field(default_factory=lambda: np.full(6, np.nan))


def score(estimate: Estimate, case: ScanCase, scenario: str, row: str) -> Outcome:
    """One estimate against its truth."""
    err = pose_error(estimate.pose, case.truth)
    head = float(wrap_degrees(np.rad2deg(heading(estimate.pose) - heading(case.truth))))
    centred = centred_error(estimate.pose, case.truth)
    sigmas = np.full(6, np.nan)
    if estimate.covariance is not None:
        sd = np.sqrt(np.clip(np.diag(np.asarray(estimate.covariance, dtype=np.float64)), 0.0, None))
        sigmas = np.abs(centred) / np.where(sd > 0, sd, np.nan)
    return Outcome(scenario, row, case.label, err, float(np.linalg.norm(err[:3])), head,
                   nees(centred, estimate.covariance), estimate.seconds, estimate.converged, case.delta, sigmas)


def run(scenarios: Sequence[Scenario], rows: dict[str, Method],
        progress: Callable[[str], None] | None = None) -> list[Outcome]:
    """Localise every scan of every scenario by every row; one :class:`Outcome` each.

    The rows take turns scan by scan (so that a busy machine slows them alike). A row that
    raises on a scan is recorded as failed at its prior (error of the prior, NaN NEES,
    ``converged`` False) and the message passed to ``progress``. Outcomes are ordered by
    scenario, row, scan.
    """
    out = []
    for scenario in scenarios:
        started = time.perf_counter()
        by_row: dict[str, list[Outcome]] = {name: [] for name in rows}
        for case in scenario.cases:
            for name, method in rows.items():
                try:
                    est = method(case.points, case.prior, case.prior_covariance, scenario)
                except Exception as exc:  # noqa: BLE001 - a row failing on one scan is a result
                    if progress:
                        progress(f'{scenario.name} {name} {case.label}: failed ({type(exc).__name__}: {exc})')
                    est = Estimate(case.prior.copy(), None, float('nan'), False)
                by_row[name].append(score(est, case, scenario.name, name))
        for name in rows:
            out += by_row[name]
        if progress:
            progress(f'{scenario.name}: {len(scenario.cases)} scans x {len(rows)} rows in '
                     f'{time.perf_counter() - started:.1f} s')
    return out


def summarise(outcomes: Sequence[Outcome]) -> dict[str, float]:
    """Figures of one row on one scenario (or pooled): ``n``, ``position_median``,
    ``position_p95`` (3-D, m), ``horizontal_*`` and ``vertical_*`` (median, p95: the x-y and
    z parts, m), ``heading_median``, ``heading_p95`` (absolute, degrees), ``good_share``
    (within 0.2 m and 1 degree), ``good_share_horizontal`` (the same, horizontally), ``nees_mean``, ``nees_in_band`` (share in
    :data:`NEES_BAND`; NaN without covariances), ``nees_n`` (scans with a NEES),
    ``ms_median``, ``ms_p95``, ``converged_share`` (NaN when the row gives no verdict),
    ``nees_mean_converged`` and ``horizontal_p95_kept`` (over the scans the row did not flag
    as not converged: what a user who drops flagged scans gets),
    ``failures`` (scans off by more than 0.2 m horizontally or 1 degree) and
    ``failures_flagged`` (of those, the ones the row flagged as not converged);
    ``within_3sigma_x``, ``_y``, ``_yaw`` and ``within_3sigma`` (all three): shares of scans
    whose error lies within 3 of the row's standard deviations on that axis (NaN without
    covariances); ``confident_misses``: scans more than :data:`MISS_POSITION` off
    horizontally that the row reported as converged; ``nees_n_converged``."""
    pos = np.array([o.position for o in outcomes])
    err = np.array([o.error for o in outcomes]).reshape(-1, 6)
    horizontal = np.hypot(err[:, 0], err[:, 1])
    vertical = np.abs(err[:, 2])
    head = np.abs(np.array([o.heading_deg for o in outcomes]))
    ne = np.array([o.nees for o in outcomes])
    ms = np.array([o.seconds for o in outcomes]) * 1e3
    verdicts = [o.converged for o in outcomes if o.converged is not None]
    finite = ne[np.isfinite(ne)]
    ms_ok = ms[np.isfinite(ms)]
    flags = np.array([-1 if o.converged is None else int(o.converged) for o in outcomes])
    conv_nees = ne[np.isfinite(ne) & (flags != 0)]
    bad = (horizontal > GOOD_POSITION) | (head > GOOD_HEADING_DEG)
    sig = np.array([o.sigmas for o in outcomes]).reshape(-1, 6)
    has_sigma = np.isfinite(sig).all(axis=1)
    within = sig[has_sigma] <= 3.0

    def share(a: np.ndarray) -> float:
        return float(np.mean(a)) if len(a) else float('nan')

    def q(a: np.ndarray, p: float) -> float:
        return float(np.percentile(a, p)) if len(a) else float('nan')

    return {
        'n': len(outcomes),
        'position_median': q(pos, 50), 'position_p95': q(pos, 95),
        'horizontal_median': q(horizontal, 50), 'horizontal_p95': q(horizontal, 95),
        'vertical_median': q(vertical, 50), 'vertical_p95': q(vertical, 95),
        'heading_median': q(head, 50), 'heading_p95': q(head, 95),
        'good_share': float(np.mean((pos <= GOOD_POSITION) & (head <= GOOD_HEADING_DEG))) if len(pos) else float('nan'),
        'good_share_horizontal': (float(np.mean((horizontal <= GOOD_POSITION) & (head <= GOOD_HEADING_DEG)))
                                  if len(pos) else float('nan')),
        'nees_mean': float(finite.mean()) if len(finite) else float('nan'),
        'nees_in_band': float(np.mean((finite >= NEES_BAND[0]) & (finite <= NEES_BAND[1]))) if len(finite) else float('nan'),
        'nees_n': len(finite),
        'ms_median': q(ms_ok, 50), 'ms_p95': q(ms_ok, 95),
        'converged_share': float(np.mean(verdicts)) if verdicts else float('nan'),
        'nees_mean_converged': float(conv_nees.mean()) if len(conv_nees) else float('nan'),
        'horizontal_p95_kept': q(horizontal[flags != 0], 95),
        'failures': int(np.sum(bad)),
        'failures_flagged': int(np.sum(bad & (flags == 0))),
        'within_3sigma_x': share(within[:, 0]), 'within_3sigma_y': share(within[:, 1]),
        'within_3sigma_yaw': share(within[:, 5]), 'within_3sigma': share(within[:, [0, 1, 5]].all(axis=1)),
        'confident_misses': int(np.sum((horizontal > MISS_POSITION) & (flags == 1))),
        'nees_n_converged': len(conv_nees),
    }


def mean_nees_band(n: int, level: float = 0.95) -> tuple[float, float]:
    """Central ``level`` band of the mean of ``n`` chi-square(6) NEES values."""
    a = (1 - level) / 2
    return float(chi2.ppf(a, 6 * n) / n), float(chi2.ppf(1 - a, 6 * n) / n)


def table(outcomes: Sequence[Outcome]) -> dict[str, dict[str, dict[str, float]]]:
    """``{scenario: {row: summarise(...)}}`` in the order first met."""
    out: dict[str, dict[str, dict[str, float]]] = {}
    for scenario in dict.fromkeys(o.scenario for o in outcomes):
        out[scenario] = {}
        for row in dict.fromkeys(o.row for o in outcomes if o.scenario == scenario):
            out[scenario][row] = summarise([o for o in outcomes if o.scenario == scenario and o.row == row])
    return out


def failed(outcome: Outcome) -> bool:
    """More than :data:`GOOD_POSITION` off horizontally or :data:`GOOD_HEADING_DEG` in heading."""
    return bool(np.hypot(outcome.error[0], outcome.error[1]) > GOOD_POSITION
                or abs(outcome.heading_deg) > GOOD_HEADING_DEG)


def paired(outcomes: Sequence[Outcome], first: str, second: str) -> dict[str, int]:
    """Two rows scan by scan (same scenario and scan): ``scans`` compared, ``first_only``
    (scans only ``first`` got right, i.e. ``second`` failed), ``second_only``, ``both_failed``."""
    a = {(o.scenario, o.label): o for o in outcomes if o.row == first}
    b = {(o.scenario, o.label): o for o in outcomes if o.row == second}
    keys = [k for k in a if k in b]
    fa = np.array([failed(a[k]) for k in keys], dtype=bool)
    fb = np.array([failed(b[k]) for k in keys], dtype=bool)
    return {'scans': len(keys), 'first_only': int(np.sum(~fa & fb)), 'second_only': int(np.sum(fa & ~fb)),
            'both_failed': int(np.sum(fa & fb))}
