"""Scene description as JSON, splitting a campaign into sensor messages, and a campaign as a robot
records it (clouds in the lidar frame at each point's time, vehicle poses for /tf)."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from ..errors import InputError
from ..io.cloud import Cloud
from .campaign import Campaign, SensorConfig
from .scene import Scene

#: Format tag of scene.json.
SCENE_FORMAT = 'uncertain_facade_map.scene/1'


def _jsonable(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        out = {'type': type(obj).__name__}
        out.update({f.name: _jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)})
        return out
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (list, tuple)):
        return [_jsonable(x) for x in obj]
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    return obj


def scene_description(scene: Scene, sensor: SensorConfig, campaigns: list[tuple[Campaign, int, dict[str, str]]]) -> dict:
    """Everything needed to understand and rebuild a simulated data set.

    The scene is rebuilt exactly by ``build_scene(name, seed)``; the geometry is listed so
    that other tools can read the truth without this package (for a hard scene with its
    walls and the relief of every façade: depth r(u, v) of :mod:`.walls`).

    Args:
        scene: the scene.
        sensor: the sensor used.
        campaigns: per campaign, (campaign, number of points, {format: file name}).

    Returns:
        A JSON-serialisable dict.
    """
    description = {
        'format': SCENE_FORMAT,
        'scene': scene.name,
        'seed': scene.seed,
        'map_origin': scene.map_origin.tolist(),
        'frame': 'map: metres, z up, ground at z = 0; georeferenced = map + map_origin',
        'sensor': _jsonable(sensor),
        'campaigns': [dict(_jsonable(c), points=n, files=files, role='mapped' if c.index == 0 else 'reference')
                      for c, n, files in campaigns],
        'street': _jsonable(scene.street),
        'buildings': [_jsonable(b) for b in scene.buildings],
        'static_occluders': [_jsonable(o) for o in scene.static_occluders],
    }
    if scene.walls is not None:
        # Walls as built: the relief of each façade is part of the truth (see simulation/walls.py).
        description['walls'] = _jsonable(scene.walls)
        description['reliefs'] = {str(k): _jsonable(r) for k, r in scene.reliefs.items()}
    return description


def write_scene_json(path: str | Path, description: dict) -> Path:
    """Write a scene description (see :func:`scene_description`)."""
    path = Path(path)
    path.write_text(json.dumps(description, indent=1))
    return path


def read_scene_json(path: str | Path) -> dict:
    """Read a scene description.

    Raises:
        InputError: missing file, invalid JSON or another format.
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f'no such file: {path}') from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f'{path}: not a JSON file ({exc})') from None
    if not isinstance(data, dict) or data.get('format') != SCENE_FORMAT:
        raise InputError(f'{path}: not a scene description ({SCENE_FORMAT})')
    return data


def split_scans(cloud: Cloud, period: float) -> Iterator[tuple[int, np.ndarray]]:
    """Split a time-ordered cloud into messages as a sensor sends them.

    Args:
        cloud: points with a ``time`` field (seconds since the UNIX epoch), time-ordered.
        period: seconds of data per message.

    Yields:
        ``(stamp_ns, points)``: the start of each period in nanoseconds and its points.

    Raises:
        InputError: no ``time`` field, or a period that is not positive.
    """
    if period <= 0:
        raise InputError(f'scan period must be positive, got {period}')
    if 'time' not in cloud.fields:
        raise InputError('the cloud has no time field to split it into scans')
    if not len(cloud):
        return
    t = cloud.points['time']
    # Integer nanoseconds avoid float rounding at period boundaries.
    t_ns = np.round(t * 1e9).astype(np.int64)
    period_ns = int(round(period * 1e9))
    slot = (t_ns - t_ns[0]) // period_ns
    bounds = np.flatnonzero(np.diff(slot)) + 1
    starts = np.concatenate([[0], bounds])
    ends = np.concatenate([bounds, [len(t)]])
    for a, b in zip(starts, ends):
        yield int(t_ns[0] + slot[a] * period_ns), cloud.points[a:b]


#: Frames of a drive recorded as a robot records it: the vehicle, and its lidar (scanner 0's mount).
VEHICLE_FRAME = 'base_link'
LIDAR_FRAME = 'lidar'


@dataclass(frozen=True, eq=False)
class RobotRecording:
    """A simulated drive as a robot records it (:func:`robot_recording`).

    Attributes:
        scans: ``[(stamp_ns, points, LIDAR_FRAME)]``: each message's points in the lidar frame
            at their own time (x, y, z and the sensor origin fields moved; ``time`` kept).
        vehicle: (K,) int64 stamps, (K, 3) translations and (K, 4) quaternions (x, y, z, w)
            of ``map -> base_link`` (for /tf).
        mount: (3,) translation and (4,) quaternion of ``base_link -> lidar`` (for /tf_static).
    """

    scans: list[tuple[int, np.ndarray, str]]
    vehicle: tuple[np.ndarray, np.ndarray, np.ndarray]
    mount: tuple[np.ndarray, np.ndarray]


def vehicle_poses(scene: Scene, drive: Campaign, sensor: SensorConfig, stamps_ns: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """``map -> base_link`` at absolute times: the drive's path on the ground, heading as yaw,
    moved by the campaign's registration offset.

    Args:
        stamps_ns: (K,) int64 nanoseconds since the UNIX epoch.

    Returns:
        (K, 3) translations (metres, map frame) and (K, 4) quaternions (x, y, z, w).
    """
    from .campaign import _registration, poses

    t = (np.asarray(stamps_ns, dtype=np.int64) - int(round(drive.start_time * 1e9))) / 1e9
    xy, yaw = poses(scene, drive, sensor, t)
    position = np.column_stack([xy, np.zeros(len(xy))])
    offset = _registration(scene, drive, sensor)
    if offset is not None:
        from .campaign import _move

        position = _move(position, offset)
        yaw = yaw + offset[2]
    quat = np.column_stack([np.zeros((len(yaw), 2)), np.sin(yaw / 2), np.cos(yaw / 2)])
    return position, quat


def robot_recording(cloud: Cloud, scene: Scene, drive: Campaign, sensor: SensorConfig, period: float,
                    tf_rate: float = 50.0) -> RobotRecording:
    """A simulated campaign as a robot records it: clouds in the lidar frame, poses on /tf.

    Each point is moved from the map frame into the lidar frame by the vehicle's pose at the
    point's own time (as a lidar measures it, the vehicle moving), so a mapper must place
    every point at its time (motion compensation) to get the map frame back. The vehicle
    poses are sampled at ``tf_rate`` from one period before the first point to one after the
    last; the drive is straight at constant speed between the street's bends, so
    interpolating them (linear in position, slerp in yaw) gives the pose at any time.

    Args:
        cloud: the campaign (map frame, with ``time``, seconds since the UNIX epoch).
        scene, drive, sensor: what simulated it.
        period: seconds of data per message.
        tf_rate: vehicle poses per second (> 0).

    Returns:
        The :class:`RobotRecording`.

    Raises:
        InputError: no ``time`` field, a non-positive period or rate.
    """
    if not tf_rate > 0:
        raise InputError(f'the rate of the vehicle poses must be positive, got {tf_rate}')
    from ..transforms import rotations

    mount_t = np.asarray(sensor.mount[0], dtype=np.float64)
    mount_q = np.array([0.0, 0.0, 0.0, 1.0])
    scans = []
    for stamp, points in split_scans(cloud, period):
        times = np.round(points['time'] * 1e9).astype(np.int64)
        t, q = vehicle_poses(scene, drive, sensor, times)
        inverse = rotations.conjugate(q)
        local = points.copy()
        for fields in (('x', 'y', 'z'), ('origin_x', 'origin_y', 'origin_z')):
            if not all(f in (points.dtype.names or ()) for f in fields):
                continue
            xyz = np.stack([points[f].astype(np.float64) for f in fields], axis=1)
            moved = rotations.rotate(inverse, xyz - t) - mount_t  # base_link, then the lidar (no rotation)
            for k, f in enumerate(fields):
                local[f] = moved[:, k]
        scans.append((stamp, local, LIDAR_FRAME))
    if not scans:
        raise InputError('the campaign has no points to record')
    step = int(round(1e9 / tf_rate))
    first, last = scans[0][0] - int(period * 1e9), int(np.round(cloud.points['time'].max() * 1e9)) + int(period * 1e9)
    stamps = np.arange(first, last + step, step, dtype=np.int64)
    t, q = vehicle_poses(scene, drive, sensor, stamps)
    return RobotRecording(scans, (stamps, t, q), (mount_t, mount_q))


def sensor_poses(scene: Scene, drive: Campaign, sensor: SensorConfig, t_mid: float) -> tuple[np.ndarray, np.ndarray]:
    """The lidar's pose at ``t_mid`` (seconds since the UNIX epoch) as the campaign recorded it
    and as it truly was: two (4, 4) ``lidar -> map`` matrices.

    The recorded pose carries the campaign's registration offset (:func:`vehicle_poses`): the
    campaign's points lie where it put them, so moving them back by it gives what the lidar
    measured. The true pose is the drive's path pose without that offset, times the mount of
    scanner 0: what a localiser should find against a map of the true world.
    """
    from .campaign import poses

    mount = np.eye(4)
    mount[:3, 3] = np.asarray(sensor.mount[0], dtype=np.float64)

    def vehicle(position: np.ndarray, yaw: float) -> np.ndarray:
        out = np.eye(4)
        c, s = np.cos(yaw), np.sin(yaw)
        out[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
        out[:3, 3] = position
        return out @ mount

    position, quat = vehicle_poses(scene, drive, sensor, np.array([int(round(t_mid * 1e9))], dtype=np.int64))
    recorded = vehicle(position[0], 2.0 * np.arctan2(quat[0, 2], quat[0, 3]))
    xy, yaw = poses(scene, drive, sensor, np.array([t_mid - drive.start_time]))
    return recorded, vehicle(np.array([xy[0, 0], xy[0, 1], 0.0]), float(yaw[0]))


def sensor_scan(scene: Scene, index: int, sensor: SensorConfig, start: float, seconds: float,
                max_points: int | None = None, rng: np.random.Generator | None = None
                ) -> tuple[np.ndarray, np.ndarray, float]:
    """A scan of campaign ``index`` in the lidar frame, with its true pose: what a localiser is given.

    The campaign is simulated over ``[start, start + seconds]`` seconds of its drive only;
    all its returns (ground, cars, trees and walls alike) are moved into the lidar frame at
    the window's middle by the recorded pose (:func:`sensor_poses`), as a de-skewed sweep.

    Args:
        start: seconds after the drive's start.
        seconds: length of the window.
        max_points: keep at most this many points (a seeded draw); None: all.
        rng: the draw (default: seeded 0).

    Returns:
        ``(xyz, truth, t_mid)``: (N, 3) float64 points, metres, lidar frame; the (4, 4) true
        ``lidar -> map`` pose; the window's middle, seconds since the UNIX epoch.
    """
    from .campaign import campaign, simulate_campaign

    drive = campaign(scene, index)
    window = simulate_campaign(scene, index, sensor, window=(float(start), float(start + seconds)))
    t_mid = drive.start_time + start + seconds / 2
    recorded, truth = sensor_poses(scene, drive, sensor, t_mid)
    p = window.points
    xyz = np.stack([p['x'], p['y'], p['z']], axis=1).astype(np.float64)
    xyz = (xyz - recorded[:3, 3]) @ recorded[:3, :3]  # into the lidar frame: R^T (x - t)
    if max_points is not None and len(xyz) > max_points:
        rng = np.random.default_rng(0) if rng is None else rng
        xyz = xyz[np.sort(rng.choice(len(xyz), max_points, replace=False))]
    return xyz, truth, t_mid
