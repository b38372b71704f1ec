"""A mobile-mapping campaign: a vehicle with profile scanners driving the street.

The default sensor follows a Riegl VMX-250 type system: two 360-degree profile scanners on
the roof whose scan planes are vertical and turned +-45 degrees from the driving direction
(seen from above they form an X), so that each side of the street is scanned once looking
forward and once looking back, and walls across the street are seen too. Every shot is
ray-cast against the scene; the range gets Gaussian noise, and a share of the building
returns is replaced by returns from clutter in front of the façade (signs, poles,
misclassified as building) to act as outliers. Other sensors (spinning multi-beam lidars)
and the error model of the hard simulator (glass, mixed returns, range- and
incidence-dependent noise, plaster, quantisation, registration offsets) are set by
:class:`~.sensor.SensorConfig` and the scene's walls; the presets are in :mod:`.presets`.

Campaigns of one scene differ in lane, driving direction, parked cars and noise, as
separate drives of the same street on different days would.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..errors import InputError
from ..io.cloud import CLASS_BUILDING, Cloud, simulated_dtype
from .presets import SCENE_SENSORS, SENSOR_PRESETS
from .scene import CLASS_GROUND, Scene
from .scenes import parked_cars
from .sensor import SensorConfig, mixed_returns, quantise_float16, range_sigma, with_overrides

__all__ = ['CAMPAIGN_SPACING', 'EPOCH', 'SCENE_SENSORS', 'SENSOR_PRESETS', 'Campaign', 'SensorConfig', 'campaign',
           'drive_duration', 'poses', 'simulate_campaign', 'with_overrides', 'OUTLIER_CLUTTER', 'OUTLIER_GLASS',
           'OUTLIER_MIXED']

#: ``gt_outlier`` codes: clutter in front of a façade, a return from inside a room through
#: a window pane, a mixed return at a depth edge (0: none).
OUTLIER_CLUTTER, OUTLIER_GLASS, OUTLIER_MIXED = 1, 2, 3

#: Start time of campaign 0, seconds since the UNIX epoch (2023-11-14 22:13:20 UTC).
EPOCH = 1_700_000_000.0
#: Campaign k starts k weeks after campaign 0.
CAMPAIGN_SPACING = 7 * 86_400.0


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



@dataclass(frozen=True)
class _Scanner:
    """The shots one scanner fires per line, in the vehicle frame.

    Attributes:
        slot: (S,) position of each shot in its line, in units of 1 / ``per_line`` of the
            line's period (the shot leaves at (line + slot / per_line) / rate seconds).
        local: (S, 3) unit directions, vehicle frame (x forward, y left, z up).
        neighbour: (S,) the next shot along the scan direction in the same line, -1 for none.
        beam: (S,) index of the laser firing the shot, over all scanners.
    """

    slot: np.ndarray
    local: np.ndarray
    neighbour: np.ndarray
    beam: np.ndarray


def _scanners(sensor: SensorConfig) -> tuple[list[_Scanner], int, int]:
    """The scanners' shots, shots per line period (``per_line``) and the number of lasers."""
    per_line = int(round(360.0 / sensor.angular_step_deg))
    theta = np.deg2rad(np.arange(per_line) * sensor.angular_step_deg)
    yaws = np.deg2rad(np.asarray(sensor.scanner_yaws_deg))
    out, beams = [], 0
    if sensor.pattern == 'profile':
        tilt = np.deg2rad(sensor.tilt_deg)
        for yaw_s in yaws:
            # Scan plane: horizontal axis h at the scanner's yaw, "up" axis tilted about h.
            h = np.array([np.cos(yaw_s), np.sin(yaw_s), 0.0])
            side = np.array([-np.sin(yaw_s), np.cos(yaw_s), 0.0])
            up = np.cos(tilt) * np.array([0.0, 0.0, 1.0]) + np.sin(tilt) * side
            local = np.cos(theta)[:, None] * h + np.sin(theta)[:, None] * up  # (per_line, 3)
            fired = np.flatnonzero(local[:, 2] >= np.sin(np.deg2rad(sensor.elevation_min_deg)))
            following = np.r_[fired[1:] == fired[:-1] + 1, False]
            neighbour = np.where(following, np.arange(len(fired)) + 1, -1)
            out.append(_Scanner(fired, local[fired], neighbour, np.full(len(fired), beams)))
            beams += 1
    else:
        for yaw_s, elevations in zip(yaws, sensor.beam_elevations_deg):
            el = np.deg2rad(np.asarray(elevations, dtype=np.float64))
            az = yaw_s + theta
            # Beam-major order: shot (b, a) is number b * per_line + a; all beams fire at slot a.
            local = np.stack([np.cos(el)[:, None] * np.cos(az)[None, :], np.cos(el)[:, None] * np.sin(az)[None, :],
                              np.broadcast_to(np.sin(el)[:, None], (len(el), per_line))], axis=2).reshape(-1, 3)
            a = np.tile(np.arange(per_line), len(el))
            index = np.arange(len(a))
            out.append(_Scanner(a, local, np.where(a < per_line - 1, index + 1, -1),
                                beams + np.repeat(np.arange(len(el)), per_line)))
            beams += len(el)
    return out, per_line, beams


def _registration(scene: Scene, drive: Campaign, sensor: SensorConfig) -> tuple[np.ndarray, np.ndarray, float] | None:
    """The rigid offset of a campaign: (centre (3,), translation (3,), yaw rad), None for none."""
    if drive.index == 0 or not any(sensor.registration_sigma):
        return None
    rng = np.random.default_rng([drive.seed, 13])
    horizontal, vertical, yaw_deg = sensor.registration_sigma
    shift = np.array([*rng.normal(0.0, horizontal, 2), rng.normal(0.0, vertical)])
    centre = np.array([*scene.street.centreline.mean(axis=0), 0.0])
    return centre, shift, float(np.deg2rad(rng.normal(0.0, yaw_deg)))


def _move(points: np.ndarray, offset: tuple[np.ndarray, np.ndarray, float]) -> np.ndarray:
    """Apply a registration offset to (N, 3) map-frame points."""
    centre, shift, yaw = offset
    c, s = np.cos(yaw), np.sin(yaw)
    rel = points - centre
    return centre + shift + np.stack([c * rel[:, 0] - s * rel[:, 1], s * rel[:, 0] + c * rel[:, 1], rel[:, 2]], axis=1)


def _cos_incidence(scene: Scene, d: np.ndarray, label: np.ndarray, facade: np.ndarray) -> np.ndarray:
    """(N,) cosine of the incidence of rays ``d`` (N, 3): the façade's normal for façade hits
    (the sides of recesses and balconies take the wall's), z for the ground and roofs, 1
    (head-on) for everything else."""
    normals = np.array([f.frame.n for f in scene.facades]).reshape(-1, 3)
    cos = np.ones(len(d))
    on_facade = facade >= 0
    cos[on_facade] = np.einsum('ij,ij->i', d[on_facade], normals[facade[on_facade]])
    flat = (label == CLASS_GROUND) | ((label == CLASS_BUILDING) & ~on_facade)
    cos[flat] = d[flat, 2]
    return np.abs(cos)


def simulate_campaign(scene: Scene, index: int = 0, sensor: SensorConfig | None = None, *,
                      xyz_dtype: str = 'f8', chunk_rays: int = 200_000,
                      progress: Callable[[float], None] | None = None,
                      window: tuple[float, float] | None = None) -> Cloud:
    """Scan a scene in one campaign.

    Args:
        scene: the scene.
        index: campaign number (lane, direction, parked cars and noise follow from it).
        sensor: sensor settings; the scene's default (:data:`~.presets.SCENE_SENSORS`) if None.
        xyz_dtype: ``'f8'`` or ``'f4'`` for the coordinate fields (map frame).
        chunk_rays: shots ray-cast at once (memory about 1 kB per shot).
        progress: called with the seconds of drive simulated after every chunk.
        window: (start, end) seconds since the start of the drive: scan only the lines
            starting in it (e.g. one sweep); the whole drive if None.

    Returns:
        The returns, time-ordered, with the fields of :data:`~uncertain_facade_map.io.cloud.SIMULATED_FIELDS`,
        and the scene's map origin. ``gt_outlier`` is 0 for a return from the true surface
        (within the noise), :data:`OUTLIER_CLUTTER`, :data:`OUTLIER_GLASS` or
        :data:`OUTLIER_MIXED` for the artefacts.
    """
    sensor = sensor or SCENE_SENSORS.get(scene.name, SensorConfig())
    drive = campaign(scene, index)
    rng = np.random.default_rng(drive.seed)
    # The hard simulator's effects draw from their own streams, so the clean ones stay as they were.
    fx = np.random.default_rng([drive.seed, 11])
    bias = np.random.default_rng([0, 23]).normal(0.0, sensor.beam_bias, size=4096) if sensor.beam_bias > 0 else None
    cars = parked_cars(scene, np.random.default_rng([drive.seed, 1]))
    caster = scene.caster(cars)
    duration = drive_duration(scene, drive, sensor)
    scanners, per_line, _ = _scanners(sensor)
    n_lines = int(duration * sensor.scan_rate_hz)
    first_line, end_line = 0, n_lines
    if window is not None:
        # Lines starting in [start, end); a nanosecond of slack keeps rounding from adding a line.
        first_line = max(0, int(np.ceil(window[0] * sensor.scan_rate_hz - 1e-9)))
        end_line = min(n_lines, max(first_line, int(np.ceil(window[1] * sensor.scan_rate_hz - 1e-9))))
    # Profile scanners count the shots not fired too, as they always have (chunks fix the random draws).
    shots_per_line = per_line * len(scanners) if sensor.pattern == 'profile' else sum(len(sc.slot) for sc in scanners)
    lines_per_chunk = max(1, chunk_rays // shots_per_line)
    mounts = np.asarray(sensor.mount, dtype=np.float64)
    dtype = simulated_dtype(xyz_dtype)
    walls = scene.walls
    p_mixed = sensor.mixed_probability
    offset = _registration(scene, drive, sensor)
    parts = []
    for first in range(first_line, end_line, lines_per_chunk):
        lines = np.arange(first, min(first + lines_per_chunk, end_line))
        origins, dirs, times, vehicle_xy, vehicle_yaw, neighbours, beams = [], [], [], [], [], [], []
        block = 0
        for sc, m in zip(scanners, mounts):
            # Shot j of line i leaves at (i + slot_j / per_line) / rate seconds into the drive.
            t_rel = ((lines[:, None] + sc.slot[None, :] / per_line) / sensor.scan_rate_hz).ravel()
            xy, yaw = poses(scene, drive, sensor, t_rel)
            cy, sy = np.cos(yaw), np.sin(yaw)
            lx = np.tile(sc.local[:, 0], len(lines))
            ly = np.tile(sc.local[:, 1], len(lines))
            lz = np.tile(sc.local[:, 2], len(lines))
            dirs.append(np.stack([cy * lx - sy * ly, sy * lx + cy * ly, lz], axis=1))
            origins.append(np.stack([xy[:, 0] + cy * m[0] - sy * m[1], xy[:, 1] + sy * m[0] + cy * m[1],
                                     np.full(len(t_rel), m[2])], axis=1))
            times.append(t_rel)
            vehicle_xy.append(xy)
            vehicle_yaw.append(yaw)
            base = block + len(sc.slot) * np.arange(len(lines))[:, None]
            neighbours.append(np.where(sc.neighbour >= 0, base + sc.neighbour, -1).ravel())
            beams.append(np.tile(sc.beam, len(lines)))
            block += len(sc.slot) * len(lines)
        o = np.concatenate(origins)
        d = np.concatenate(dirs)
        t_shot = np.concatenate(times)
        hits = caster.cast(o, d, rng)
        t_all = hits.t
        code = np.zeros(len(t_all), dtype=np.uint8)
        if walls is not None and walls.glass_share > 0 or p_mixed > 0:
            t_all = hits.t.copy()
        if walls is not None and walls.glass_share > 0:
            # Shots through a window pane return from inside the room.
            at_facade = np.flatnonzero((hits.facade_id >= 0) & np.isfinite(hits.t))
            pane = np.zeros(len(at_facade), dtype=bool)
            fids = hits.facade_id[at_facade]
            for fid in np.unique(fids):
                sel = fids == fid
                rows = at_facade[sel]
                pane[sel] = scene.glass(int(fid), o[rows] + hits.t[rows, None] * d[rows])
            through = at_facade[pane & (fx.random(len(at_facade)) < walls.glass_share)]
            t_all[through] += fx.uniform(*walls.room_depth, size=len(through))
            code[through] = OUTLIER_GLASS
        if p_mixed > 0:
            # A footprint straddling a depth edge returns a range between both sides.
            mix, t_mix = mixed_returns(hits.t, np.concatenate(neighbours), sensor.mixed_gap, p_mixed, fx, code == 0)
            t_all[mix] = t_mix
            code[mix] = OUTLIER_MIXED
        keep = np.isfinite(t_all) & (t_all >= sensor.range_min) & (t_all <= sensor.range_max)
        idx = np.flatnonzero(keep)
        t = t_all[idx]
        outlier = code[idx]
        building = hits.label[idx] == CLASS_BUILDING
        if sensor.outlier_share > 0:
            pick = building & (rng.random(len(idx)) < sensor.outlier_share)
            gap = rng.uniform(*sensor.outlier_gap, size=int(pick.sum()))
            t[pick] = np.maximum(t[pick] - gap, sensor.range_min)
            outlier[pick] = OUTLIER_CLUTTER
        if sensor.clean_noise:
            t = t + rng.normal(0.0, sensor.range_noise, size=len(t)) if sensor.range_noise > 0 else t
        else:
            cos_inc = _cos_incidence(scene, d[idx], hits.label[idx], hits.facade_id[idx])
            t = t + rng.normal(0.0, 1.0, size=len(t)) * range_sigma(sensor, t, cos_inc)
        if walls is not None and walls.plaster > 0:
            # The plaster moves the surface along the façade normal; the ray meets it earlier or later.
            fid = hits.facade_id[idx]
            for f in np.unique(fid[(fid >= 0) & (outlier == 0)]):
                rows = np.flatnonzero((fid == f) & (outlier == 0))
                frame = scene.facades[int(f)].frame
                uv = frame.to_facade(o[idx[rows]] + t[rows, None] * d[idx[rows]])
                cos = np.maximum(np.abs(d[idx[rows]] @ frame.n), 0.1)
                t[rows] -= scene.reliefs[int(f)].plaster(uv[:, 0], uv[:, 1], walls.plaster, walls.plaster_cell) / cos
        if bias is not None:
            t = t + bias[np.concatenate(beams)[idx] % len(bias)]
        pts = np.empty(len(idx), dtype=dtype)
        xyz = o[idx] + t[:, None] * d[idx]
        origin_xyz = o[idx]
        if sensor.quantise == 'float16':
            xyz = quantise_float16(xyz, np.concatenate(vehicle_xy)[idx], np.concatenate(vehicle_yaw)[idx])
        if offset is not None:
            xyz, origin_xyz = _move(xyz, offset), _move(origin_xyz, offset)
        for k, name in enumerate(('x', 'y', 'z')):
            pts[name] = xyz[:, k]
            pts['origin_' + name] = origin_xyz[:, k]
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
