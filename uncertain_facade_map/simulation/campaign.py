"""A mobile-mapping campaign: a vehicle with profile scanners driving the street.

The sensor follows a Riegl VMX-250 type system: two 360-degree profile scanners on the
roof whose scan planes are vertical and turned +-45 degrees from the driving direction
(seen from above they form an X), so that each side of the street is scanned once looking
forward and once looking back, and walls across the street are seen too. Every shot is
ray-cast against the scene; the range gets Gaussian noise, and a share of the building
returns is replaced by returns from clutter in front of the façade (signs, poles,
misclassified as building) to act as outliers.

Campaigns of one scene differ in lane, driving direction, parked cars and noise, as
separate drives of the same street on different days would.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from ..errors import InputError
from ..io.cloud import CLASS_BUILDING, Cloud, simulated_dtype
from .scene import Scene
from .scenes import parked_cars

#: Start time of campaign 0, seconds since the UNIX epoch (2023-11-14 22:13:20 UTC).
EPOCH = 1_700_000_000.0
#: Campaign k starts k weeks after campaign 0.
CAMPAIGN_SPACING = 7 * 86_400.0


@dataclass(frozen=True)
class SensorConfig:
    """Mobile-mapping sensor and drive.

    Attributes:
        scanner_yaws_deg: per scanner, angle of its scan plane's horizontal axis from the
            driving direction, degrees (VMX-250: +45 and -45).
        tilt_deg: tilt of both scan planes about that axis, degrees.
        mount: per scanner, (forward, left, up) position on the vehicle, metres.
        scan_rate_hz: profiles per second per scanner.
        angular_step_deg: angle between shots of a profile, degrees.
        elevation_min_deg: shots pointing further down than this are not fired (they would
            only hit the road next to the vehicle), degrees.
        range_min: returns closer than this are dropped, metres.
        range_max: range limit, metres.
        range_noise: standard deviation of the range noise, metres.
        outlier_share: share of building returns replaced by clutter in front of the façade.
        outlier_gap: (min, max) distance of that clutter in front of the surface, metres.
        speed: driving speed, metres per second.
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
        ]
        for ok, message in checks:
            if not ok:
                raise InputError(f'sensor: {message}')


#: Sensor settings of the built-in scenes; ``small`` scans coarser to stay under 50 000 points.
SCENE_SENSORS = {
    'street': SensorConfig(),
    'zurich': SensorConfig(),
    'small': SensorConfig(scan_rate_hz=15.0, angular_step_deg=0.5),
}


@dataclass(frozen=True)
class Campaign:
    """One drive: which lane, which way, and its own random draws.

    Attributes:
        index: campaign number (0 is the one mapped by default).
        lane: lateral offset from the centreline, metres, left of the centreline direction.
        reverse: True to drive the centreline backwards.
        seed: seed of this drive's parked cars and noise.
        start_time: time of the first shot, seconds since the UNIX epoch.
    """

    index: int
    lane: float
    reverse: bool
    seed: int
    start_time: float


def campaign(scene: Scene, index: int) -> Campaign:
    """The ``index``-th campaign of a scene: lanes alternate, every other drive goes back."""
    if index < 0:
        raise InputError(f'campaign index must be >= 0, got {index}')
    lanes = scene.street.lanes
    reverse = index % 2 == 1
    lane = lanes[(index // 2 + (1 if reverse else 0)) % len(lanes)]
    return Campaign(index, float(lane), reverse, int(np.random.SeedSequence([scene.seed, 7, index]).generate_state(1)[0]),
                    EPOCH + index * CAMPAIGN_SPACING)


def _trajectory(scene: Scene, drive: Campaign) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Arc-length parametrised lane polyline: vertices (K, 2), cumulative length (K,), headings (K-1,), length."""
    line = scene.street.centreline[::-1] if drive.reverse else scene.street.centreline
    seg = np.diff(line, axis=0)
    heading = np.arctan2(seg[:, 1], seg[:, 0])
    left = np.stack([-np.sin(heading), np.cos(heading)], axis=1)
    # Offset every vertex by the lane to its left (mitre offsets at joints).
    normals = np.vstack([left[:1], 0.5 * (left[:-1] + left[1:]), left[-1:]])
    offset_line = line + (-drive.lane if drive.reverse else drive.lane) * normals
    seg = np.diff(offset_line, axis=0)
    seg_len = np.hypot(seg[:, 0], seg[:, 1])
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])
    return offset_line, cum, np.arctan2(seg[:, 1], seg[:, 0]), float(cum[-1])


def poses(scene: Scene, drive: Campaign, sensor: SensorConfig, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vehicle pose at given times.

    Args:
        scene: the scene.
        drive: the campaign.
        sensor: gives the speed.
        times: (N,) seconds since the start of the drive.

    Returns:
        ``(xy, yaw)``: (N, 2) vehicle position at ground level, metres, map frame, and
        (N,) heading, radians from +x.
    """
    line, cum, heading, _ = _trajectory(scene, drive)
    s = np.clip(times * sensor.speed, 0.0, cum[-1])
    k = np.clip(np.searchsorted(cum, s, side='right') - 1, 0, len(heading) - 1)
    frac = (s - cum[k]) / np.maximum(cum[k + 1] - cum[k], 1e-12)
    xy = line[k] + frac[:, None] * (line[k + 1] - line[k])
    return xy, heading[k]


def drive_duration(scene: Scene, drive: Campaign, sensor: SensorConfig) -> float:
    """Seconds the drive takes."""
    return _trajectory(scene, drive)[3] / sensor.speed


def simulate_campaign(scene: Scene, index: int = 0, sensor: SensorConfig | None = None, *,
                      xyz_dtype: str = 'f8', chunk_rays: int = 200_000,
                      progress: Callable[[float], None] | None = None) -> Cloud:
    """Scan a scene in one campaign.

    Args:
        scene: the scene.
        index: campaign number (lane, direction, parked cars and noise follow from it).
        sensor: sensor settings; the scene's default if None.
        xyz_dtype: ``'f8'`` or ``'f4'`` for the coordinate fields (map frame).
        chunk_rays: shots ray-cast at once (memory about 1 kB per shot).
        progress: called with the seconds of drive simulated after every chunk.

    Returns:
        The returns, time-ordered, with the fields of :data:`~uncertain_facade_map.io.cloud.SIMULATED_FIELDS`,
        and the scene's map origin.
    """
    sensor = sensor or SCENE_SENSORS.get(scene.name, SensorConfig())
    drive = campaign(scene, index)
    rng = np.random.default_rng(drive.seed)
    cars = parked_cars(scene, np.random.default_rng([drive.seed, 1]))
    caster = scene.caster(cars)
    duration = drive_duration(scene, drive, sensor)
    per_line = int(round(360.0 / sensor.angular_step_deg))
    theta = np.deg2rad(np.arange(per_line) * sensor.angular_step_deg)
    n_lines = int(duration * sensor.scan_rate_hz)
    lines_per_chunk = max(1, chunk_rays // (per_line * len(sensor.mount)))
    yaws = np.deg2rad(np.asarray(sensor.scanner_yaws_deg))
    tilt = np.deg2rad(sensor.tilt_deg)
    mounts = np.asarray(sensor.mount, dtype=np.float64)
    dtype = simulated_dtype(xyz_dtype)
    # Per scanner: directions of the shots it fires in the vehicle frame, and their indices.
    shots = []
    for yaw_s in yaws:
        # Scan plane: horizontal axis h at the scanner's yaw, "up" axis tilted about h.
        h = np.array([np.cos(yaw_s), np.sin(yaw_s), 0.0])
        side = np.array([-np.sin(yaw_s), np.cos(yaw_s), 0.0])
        up = np.cos(tilt) * np.array([0.0, 0.0, 1.0]) + np.sin(tilt) * side
        local = np.cos(theta)[:, None] * h + np.sin(theta)[:, None] * up  # (per_line, 3)
        fired = np.flatnonzero(local[:, 2] >= np.sin(np.deg2rad(sensor.elevation_min_deg)))
        shots.append((fired, local[fired]))
    parts = []
    for first in range(0, n_lines, lines_per_chunk):
        lines = np.arange(first, min(first + lines_per_chunk, n_lines))
        origins, dirs, times = [], [], []
        for (fired, local), m in zip(shots, mounts):
            # Shot j of line i leaves at (i + j / per_line) / rate seconds into the drive.
            t_rel = ((lines[:, None] + fired[None, :] / per_line) / sensor.scan_rate_hz).ravel()
            xy, yaw = poses(scene, drive, sensor, t_rel)
            cy, sy = np.cos(yaw), np.sin(yaw)
            lx = np.tile(local[:, 0], len(lines))
            ly = np.tile(local[:, 1], len(lines))
            lz = np.tile(local[:, 2], len(lines))
            dirs.append(np.stack([cy * lx - sy * ly, sy * lx + cy * ly, lz], axis=1))
            origins.append(np.stack([xy[:, 0] + cy * m[0] - sy * m[1], xy[:, 1] + sy * m[0] + cy * m[1],
                                     np.full(len(t_rel), m[2])], axis=1))
            times.append(t_rel)
        o = np.concatenate(origins)
        d = np.concatenate(dirs)
        t_shot = np.concatenate(times)
        hits = caster.cast(o, d, rng)
        keep = np.isfinite(hits.t) & (hits.t >= sensor.range_min) & (hits.t <= sensor.range_max)
        idx = np.flatnonzero(keep)
        t = hits.t[idx]
        outlier = np.zeros(len(idx), dtype=np.uint8)
        building = hits.label[idx] == CLASS_BUILDING
        if sensor.outlier_share > 0:
            pick = building & (rng.random(len(idx)) < sensor.outlier_share)
            gap = rng.uniform(*sensor.outlier_gap, size=int(pick.sum()))
            t[pick] = np.maximum(t[pick] - gap, sensor.range_min)
            outlier[pick] = 1
        t = t + rng.normal(0.0, sensor.range_noise, size=len(t)) if sensor.range_noise > 0 else t
        pts = np.empty(len(idx), dtype=dtype)
        xyz = o[idx] + t[:, None] * d[idx]
        for k, name in enumerate(('x', 'y', 'z')):
            pts[name] = xyz[:, k]
            pts['origin_' + name] = o[idx, k]
        pts['time'] = drive.start_time + t_shot[idx]
        pts['building_id'] = hits.building_id[idx]
        pts['class'] = hits.label[idx]
        pts['gt_facade'] = hits.facade_id[idx]
        pts['gt_outlier'] = outlier
        order = np.argsort(pts['time'], kind='stable')
        parts.append(pts[order])
        if progress is not None:
            progress(float(min((lines[-1] + 1) / sensor.scan_rate_hz, duration)))
    points = np.concatenate(parts) if parts else np.empty(0, dtype=dtype)
    return Cloud(points, scene.map_origin)


def with_overrides(sensor: SensorConfig, **overrides: object) -> SensorConfig:
    """Return ``sensor`` with the non-None ``overrides`` applied (validated again)."""
    return replace(sensor, **{k: v for k, v in overrides.items() if v is not None})
