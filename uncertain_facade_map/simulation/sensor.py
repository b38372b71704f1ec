"""The simulated sensor: its scan pattern, drive and error model (:class:`SensorConfig`).

Two scan patterns:

- ``profile``: 360-degree profile scanners whose scan planes are vertical and turned by
  ``scanner_yaws_deg`` from the driving direction (a mobile-mapping system such as the
  RIEGL VMX-250: two scanners in an X seen from above).
- ``spinning``: multi-beam lidars spinning about the vertical axis, one revolution per
  line, with a fixed elevation per beam (``beam_elevations_deg``; a Velodyne VLP-32C has
  32), as on a robot or a self-driving car.

Error model, per return (every term is off at its default, which is the clean simulator):

- range noise: Gaussian, sigma^2 = ``range_noise``^2 + (``range_noise_per_m`` r)^2 +
  (r beta tan(alpha) / sqrt(12))^2, with r the range, alpha the incidence angle (from the
  surface normal, at most 85 degrees) and beta the beam divergence: the last term is the
  spread of ranges inside a footprint of diameter r beta on an inclined surface
  (uniform, hence sqrt(12)).
- per-beam range bias: each laser of the sensor has a constant range offset,
  Gaussian with sigma ``beam_bias`` (calibration residual of multi-beam lidars).
- mixed returns: a footprint straddling a depth edge returns a range between both sides.
  Along the scan direction, a depth edge lies between a shot and the next if the range
  step between them differs by at least ``mixed_gap[0]`` from both the step before and the
  step after (a smooth surface, however oblique, changes range steadily), and is at most
  ``mixed_gap[1]`` (further apart, the two echoes are separate and the first is kept). It
  straddles the edge with probability beta / (angle between shots) (the footprint's share
  of the gap between shots, at most 1), and its range moves a uniform share of the way to
  the next shot's.
- quantisation: ``quantise='float16'`` rounds the coordinates in the vehicle frame (x
  forward, y left, z up, origin on the ground below the vehicle's reference point) to
  float16, as Argoverse 2 stores its sweeps: 7.8 mm steps at 8-16 m, 15.6 mm at 16-32 m.
- registration: campaign k >= 1 is moved by a rigid offset (horizontal and vertical
  translation, Gaussian with sigmas ``registration_sigma[0:2]`` metres, and a yaw about the
  street's middle, sigma ``registration_sigma[2]`` degrees): drives of other days are
  registered to the mapped one (campaign 0, which defines the frame) to a few centimetres.
- clutter outliers (``outlier_share``, ``outlier_gap``), as before.

Properties of the world (bowed walls, plaster, glass) are not here but in the scene
(:mod:`.walls`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..errors import InputError

#: Incidence angles are capped here for the footprint term of the noise, degrees.
MAX_INCIDENCE_DEG = 85.0
PATTERNS = ('profile', 'spinning')
QUANTISATIONS = ('none', 'float16')


@dataclass(frozen=True)
class SensorConfig:
    """Mobile-mapping sensor, drive and error model.

    Attributes:
        scanner_yaws_deg: per scanner; ``profile``: angle of its scan plane's horizontal axis
            from the driving direction, degrees (VMX-250: +45 and -45); ``spinning``:
            azimuth of its first shot from the driving direction, degrees.
        tilt_deg: ``profile`` only: tilt of both scan planes about that axis, degrees.
        mount: per scanner, (forward, left, up) position on the vehicle, metres.
        scan_rate_hz: lines per second per scanner (profiles, or revolutions).
        angular_step_deg: angle between shots of a line (of one beam), degrees.
        elevation_min_deg: ``profile`` only: shots pointing further down than this are not
            fired (they would only hit the road next to the vehicle), degrees.
        range_min: returns closer than this are dropped, metres.
        range_max: range limit, metres.
        range_noise: standard deviation of the range noise at zero range, metres.
        outlier_share: share of building returns replaced by clutter in front of the façade.
        outlier_gap: (min, max) distance of that clutter in front of the surface, metres.
        speed: driving speed, metres per second.
        pattern: ``'profile'`` or ``'spinning'`` (see the module docstring).
        beam_elevations_deg: ``spinning`` only: per scanner, the elevation of each of its
            beams, degrees (negated for a lidar mounted upside down).
        range_noise_per_m: growth of the range noise with range (sigma adds r times this in
            quadrature), metres per metre.
        beam_divergence_mrad: full beam divergence, milliradians: footprint term of the
            noise and mixed returns at edges; 0 for neither.
        beam_bias: standard deviation of the constant range offset of each laser, metres.
        mixed_gap: (min, max) range difference of neighbouring shots that makes a mixed
            return, metres.
        quantise: ``'none'`` or ``'float16'`` (vehicle-frame coordinates, see above).
        registration_sigma: (horizontal m, vertical m, yaw degrees) of the rigid offset of
            each campaign after the first.
    """

    scanner_yaws_deg: tuple[float, ...] = (45.0, -45.0)
    tilt_deg: float = 0.0
    mount: tuple[tuple[float, float, float], ...] = ((-0.6, 0.3, 2.4), (-0.6, -0.3, 2.4))
    scan_rate_hz: float = 50.0
    angular_step_deg: float = 0.2
    elevation_min_deg: float = -20.0
    range_min: float = 1.5
    range_max: float = 60.0
    range_noise: float = 0.02
    outlier_share: float = 0.01
    outlier_gap: tuple[float, float] = (0.3, 2.0)
    speed: float = 5.0
    pattern: str = 'profile'
    beam_elevations_deg: tuple[tuple[float, ...], ...] = ()
    range_noise_per_m: float = 0.0
    beam_divergence_mrad: float = 0.0
    beam_bias: float = 0.0
    mixed_gap: tuple[float, float] = (0.05, 2.0)
    quantise: str = 'none'
    registration_sigma: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        checks = [
            (len(self.scanner_yaws_deg) == len(self.mount) >= 1, 'one mount per scanner yaw, at least one scanner'),
            (self.scan_rate_hz > 0, 'scan_rate_hz must be positive'),
            (0 < self.angular_step_deg <= 45, 'angular_step_deg must be in (0, 45]'),
            (-90 <= self.elevation_min_deg < 90, 'elevation_min_deg must be in [-90, 90)'),
            (0 <= self.range_min < self.range_max, 'need 0 <= range_min < range_max'),
            (self.range_noise >= 0, 'range_noise must be >= 0'),
            (0 <= self.outlier_share < 1, 'outlier_share must be in [0, 1)'),
            (0 < self.outlier_gap[0] <= self.outlier_gap[1], 'outlier_gap must be 0 < min <= max'),
            (self.speed > 0, 'speed must be positive'),
            (self.pattern in PATTERNS, f'pattern must be one of {", ".join(PATTERNS)}'),
            (self.pattern != 'spinning' or (len(self.beam_elevations_deg) == len(self.mount)
                                            and all(len(b) >= 1 for b in self.beam_elevations_deg)),
             'a spinning sensor needs beam_elevations_deg, one non-empty tuple per scanner'),
            (all(-90 < e < 90 for b in self.beam_elevations_deg for e in b), 'beam elevations must be in (-90, 90)'),
            (self.range_noise_per_m >= 0, 'range_noise_per_m must be >= 0'),
            (self.beam_divergence_mrad >= 0, 'beam_divergence_mrad must be >= 0'),
            (self.beam_bias >= 0, 'beam_bias must be >= 0'),
            (0 < self.mixed_gap[0] <= self.mixed_gap[1], 'mixed_gap must be 0 < min <= max'),
            (self.quantise in QUANTISATIONS, f'quantise must be one of {", ".join(QUANTISATIONS)}'),
            (len(self.registration_sigma) == 3 and min(self.registration_sigma) >= 0,
             'registration_sigma must be three values >= 0'),
        ]
        for ok, message in checks:
            if not ok:
                raise InputError(f'sensor: {message}')

    @property
    def clean_noise(self) -> bool:
        """True if the range noise is the plain Gaussian of ``range_noise`` alone."""
        return self.range_noise_per_m == 0 and self.beam_divergence_mrad == 0

    @property
    def mixed_probability(self) -> float:
        """Probability that a shot next to a depth edge straddles it: beta over the angle
        between shots, at most 1."""
        return min(1.0, 1e-3 * self.beam_divergence_mrad / np.deg2rad(self.angular_step_deg))


def range_sigma(sensor: SensorConfig, r: np.ndarray, cos_incidence: np.ndarray) -> np.ndarray:
    """Standard deviation of the range noise of each return (see the module docstring).

    Args:
        sensor: the error model.
        r: (N,) ranges, metres.
        cos_incidence: (N,) cosine of the angle between the ray and the surface normal.

    Returns:
        (N,) sigma, metres.
    """
    cos_a = np.clip(np.abs(cos_incidence), np.cos(np.deg2rad(MAX_INCIDENCE_DEG)), 1.0)
    tan_a = np.sqrt(1.0 - cos_a**2) / cos_a
    footprint = r * 1e-3 * sensor.beam_divergence_mrad * tan_a / np.sqrt(12.0)
    return np.sqrt(sensor.range_noise**2 + (sensor.range_noise_per_m * r) ** 2 + footprint**2)


def mixed_returns(t: np.ndarray, neighbour: np.ndarray, gap: tuple[float, float], probability: float,
                  rng: np.random.Generator, eligible: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Which shots straddle a depth edge, and their mixed range (see the module docstring).

    Args:
        t: (N,) true ranges of the shots, metres (``inf`` for no hit).
        neighbour: (N,) index of the next shot along the scan direction, -1 for none.
        gap: (min, max) of :attr:`SensorConfig.mixed_gap`, metres.
        probability: chance that a shot before an edge straddles it.
        rng: random source (two draws per shot and per mixed shot).
        eligible: (N,) bool, shots that may be mixed (all if None).

    Returns:
        ``(rows, ranges)``: (M,) indices of the mixed shots and (M,) their ranges, metres.
    """
    def after(index: np.ndarray) -> np.ndarray:
        ok = index >= 0
        return np.where(ok, neighbour[np.where(ok, index, 0)], -1)

    def before(index: np.ndarray) -> np.ndarray:
        previous = np.full(len(t), -1)
        previous[neighbour[neighbour >= 0]] = np.flatnonzero(neighbour >= 0)
        ok = index >= 0
        return np.where(ok, previous[np.where(ok, index, 0)], -1)

    def range_of(index: np.ndarray) -> np.ndarray:
        return np.where(index >= 0, t[np.where(index >= 0, index, 0)], np.inf)

    own = np.arange(len(t))
    nxt, nxt2, prv = after(own), after(after(own)), before(own)
    t_next, t_next2, t_prev = range_of(nxt), range_of(nxt2), range_of(prv)
    ok = np.isfinite(t) & np.isfinite(t_next) & np.isfinite(t_next2) & np.isfinite(t_prev)
    with np.errstate(invalid='ignore'):
        step = t_next - t
        # The step to the next shot differs from the steps on both sides of it.
        bend = np.minimum(np.abs(step - (t - t_prev)), np.abs(step - (t_next2 - t_next)))
    edge = ok & (bend >= gap[0]) & (np.abs(step) <= gap[1])
    if eligible is not None:
        edge &= eligible
    rows = np.flatnonzero(edge & (rng.random(len(t)) < probability))
    return rows, t[rows] + rng.random(len(rows)) * step[rows]


def quantise_float16(xyz: np.ndarray, vehicle_xy: np.ndarray, vehicle_yaw: np.ndarray) -> np.ndarray:
    """Round points to float16 in the vehicle frame, as Argoverse 2 stores its sweeps.

    Args:
        xyz: (N, 3) points, metres, map frame.
        vehicle_xy: (N, 2) vehicle position (on the ground) at each point's time, map frame.
        vehicle_yaw: (N,) heading, radians from +x.

    Returns:
        (N, 3) the points after the round trip map -> vehicle frame -> float16 -> map.
    """
    c, s = np.cos(vehicle_yaw), np.sin(vehicle_yaw)
    dx, dy = xyz[:, 0] - vehicle_xy[:, 0], xyz[:, 1] - vehicle_xy[:, 1]
    local = np.stack([c * dx + s * dy, -s * dx + c * dy, xyz[:, 2]], axis=1)
    local = local.astype(np.float16).astype(np.float64)
    return np.stack([vehicle_xy[:, 0] + c * local[:, 0] - s * local[:, 1],
                     vehicle_xy[:, 1] + s * local[:, 0] + c * local[:, 1], local[:, 2]], axis=1)


def with_overrides(sensor: SensorConfig, **overrides: object) -> SensorConfig:
    """Return ``sensor`` with the non-None ``overrides`` applied (validated again)."""
    return replace(sensor, **{k: v for k, v in overrides.items() if v is not None})
