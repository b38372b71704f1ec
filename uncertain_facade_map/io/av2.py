"""Argoverse 2 sensor logs (feather files) read into plain arrays, and the clouds derived from them.

A log folder as Argoverse 2 publishes it::

    LOG/sensors/lidar/<stamp_ns>.feather        one sweep of the two stacked 32-beam lidars
    LOG/city_SE3_egovehicle.feather             ego poses in the city frame (about 170 Hz)
    LOG/calibration/egovehicle_SE3_sensor.feather   sensor extrinsics in the ego frame

A sweep's points are in the ego-vehicle frame *at the sweep's stamp*: Argoverse has already
motion-compensated them (each point moved by the ego motion between its firing,
``stamp + offset_ns``, and the stamp), so one pose per sweep places the whole sweep.
Coordinates are stored as float16 (7.8 mm steps at 8-16 m range, 15.6 mm at 16-32 m).
Lasers 0-31 belong to the upper lidar (``up_lidar``), 32-63 to the lower (``down_lidar``).

:func:`read_av2_log` reads a folder (pyarrow, imported inside it); :func:`lidar_clouds` gives
a sweep as its lidars would publish it (float32, each in its own lidar frame);
:func:`reference_clouds` takes exactly those float32 points into a local map frame with
plain numpy, straight from the ego poses and extrinsics, with every point's sensor origin:
the reference against which anything that transforms the lidar clouds is checked.

Frames: ``city`` (Argoverse's city frame, metres, z up), ``egovehicle`` (x forward, z up),
the lidar frames, and the local map frame = city frame minus a map origin
(:func:`map_origin_of`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError

__all__ = ['DOCUMENTED_LIDARS', 'LIDARS', 'LASERS_PER_LIDAR', 'LIDAR_DTYPE', 'REFERENCE_DTYPE', 'Av2Extrinsic', 'Av2Log', 'Av2Poses',
           'Av2Sweep', 'lidar_clouds', 'map_origin_of', 'read_av2_log', 'reference_clouds', 'rotation_matrices']

#: The lidars of an Argoverse 2 sweep, in laser-number order (lasers 0-31, then 32-63).
LIDARS = ('up_lidar', 'down_lidar')
LASERS_PER_LIDAR = 32
#: A lidar's cloud (:func:`lidar_clouds`): float32 coordinates in the lidar frame (metres),
#: intensity as float32 and the ring (the laser within its lidar, 0-31) as uint16, as the
#: Velodyne ROS driver publishes them.
LIDAR_DTYPE = np.dtype([('x', 'f4'), ('y', 'f4'), ('z', 'f4'), ('intensity', 'f4'), ('ring', 'u2')])
#: A reference cloud (:func:`reference_clouds`): map-frame coordinates and sensor origin
#: (float64, metres), intensity and ring as in :data:`LIDAR_DTYPE`.
REFERENCE_DTYPE = np.dtype([('x', 'f8'), ('y', 'f8'), ('z', 'f8'), ('origin_x', 'f8'), ('origin_y', 'f8'),
                            ('origin_z', 'f8'), ('intensity', 'f4'), ('ring', 'u2')])

_POSE_COLUMNS = ('tx_m', 'ty_m', 'tz_m', 'qx', 'qy', 'qz', 'qw')
#: The lidars' extrinsics of an Argoverse 2 car as av2-api documents them (the example
#: ``calibration/egovehicle_SE3_sensor.feather`` of src/av2/datasets/sensor/README.md: the
#: upper lidar upright 1.64 m up, the lower one upside down 1.57 m up, both 1.35 m ahead of
#: the ego origin): what :func:`read_av2_log` takes for a log without ``calibration/`` (some
#: public sample logs ship without it). The cars differ by millimetres and tenths of a
#: degree (log 7fab2350: the lower lidar 1.53 m up, rolled 5.9 degrees further).
DOCUMENTED_LIDARS = {
    'up_lidar': ((1.350180, 0.0, 1.640420), (0.0, 0.0, -0.002848, 0.999996)),
    'down_lidar': ((1.355162, 0.000133, 1.565252), (-0.994497, 0.104767, 0.000243, -0.000089)),
}
_SWEEP_COLUMNS = ('x', 'y', 'z', 'intensity', 'laser_number', 'offset_ns')


@dataclass(frozen=True)
class Av2Sweep:
    """One lidar sweep of an Argoverse 2 log.

    Attributes:
        stamp_ns: the sweep's stamp, integer nanoseconds (Argoverse's clock; the file name).
        xyz: (N, 3) float64, metres, ego-vehicle frame at ``stamp_ns`` (motion-compensated
            by Argoverse; float16 values as stored).
        intensity: (N,) uint8.
        laser_number: (N,) uint8, 0-63 (0-31 ``up_lidar``, 32-63 ``down_lidar``).
        offset_ns: (N,) int64, each point's firing time minus ``stamp_ns``, nanoseconds.
    """

    stamp_ns: int
    xyz: np.ndarray
    intensity: np.ndarray
    laser_number: np.ndarray
    offset_ns: np.ndarray


@dataclass(frozen=True)
class Av2Poses:
    """Ego poses: the pose of ``egovehicle`` in the city frame (city_SE3_egovehicle).

    Attributes:
        stamps_ns: (M,) int64, increasing, nanoseconds.
        translations: (M, 3) float64, metres, city frame.
        quaternions: (M, 4) float64, x, y, z, w (unit), rotating ego-frame vectors into the
            city frame.
    """

    stamps_ns: np.ndarray
    translations: np.ndarray
    quaternions: np.ndarray

    def at(self, stamp_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """The ego pose at ``stamp_ns``: the recorded one if a pose has that stamp, else
        interpolated between its neighbours (translation linearly, rotation by slerp).

        Returns:
            ``(translation (3,), quaternion (4,) x, y, z, w)``, city frame.

        Raises:
            InputError: ``stamp_ns`` lies outside the poses' time span.
        """
        stamps = self.stamps_ns
        hi = int(np.searchsorted(stamps, stamp_ns))
        if hi < len(stamps) and stamps[hi] == stamp_ns:
            return self.translations[hi].copy(), self.quaternions[hi].copy()
        if hi == 0 or hi == len(stamps):
            raise InputError(f'no ego pose around {stamp_ns} ns: the poses span {stamps[0]}-{stamps[-1]} ns')
        lo = hi - 1
        s = (stamp_ns - stamps[lo]) / (stamps[hi] - stamps[lo])
        translation = (1 - s) * self.translations[lo] + s * self.translations[hi]
        q0, q1 = self.quaternions[lo], self.quaternions[hi]
        if q0 @ q1 < 0:
            q1 = -q1
        angle = np.arccos(np.clip(q0 @ q1, -1.0, 1.0))
        if angle < 1e-9:
            q = (1 - s) * q0 + s * q1
        else:
            q = (np.sin((1 - s) * angle) * q0 + np.sin(s * angle) * q1) / np.sin(angle)
        return translation, q / np.linalg.norm(q)


@dataclass(frozen=True)
class Av2Extrinsic:
    """A sensor's pose in the ego-vehicle frame (egovehicle_SE3_sensor).

    Attributes:
        translation: (3,) float64, metres, ego frame.
        quaternion: (4,) float64, x, y, z, w (unit), rotating sensor-frame vectors into the ego frame.
    """

    translation: np.ndarray
    quaternion: np.ndarray


@dataclass(frozen=True)
class Av2Log:
    """An Argoverse 2 log read by :func:`read_av2_log`.

    Attributes:
        path: the log folder.
        sweeps: the lidar sweeps, by stamp.
        poses: the ego poses.
        extrinsics: sensor name (``'up_lidar'``, ``'down_lidar'``, ``'ring_front_center'``,
            ...) -> its extrinsic.
        warnings: what was assumed in reading it (e.g. the documented lidar layout for a
            log without ``calibration/``), one line each, for the user to see.
    """

    path: Path
    sweeps: list[Av2Sweep]
    poses: Av2Poses
    extrinsics: dict[str, Av2Extrinsic] = field(default_factory=dict)
    warnings: tuple[str, ...] = ()


def rotation_matrices(quaternions: np.ndarray) -> np.ndarray:
    """Rotation matrices of unit quaternions.

    Args:
        quaternions: (..., 4) x, y, z, w; normalised here.

    Returns:
        (..., 3, 3) float64: ``R @ v`` rotates a vector ``v`` by the quaternion.
    """
    q = np.asarray(quaternions, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def _read_table(path: Path, columns: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The named columns of a feather file as numpy arrays.

    Raises:
        InputError: pyarrow is missing, the file is missing or unreadable, or lacks a column.
    """
    try:
        import pyarrow.feather as feather
    except ImportError as err:
        raise InputError('reading Argoverse 2 logs needs pyarrow (pip install pyarrow)') from err
    if not path.is_file():
        raise InputError(f'{path} not found: not an Argoverse 2 log folder?')
    try:
        table = feather.read_table(str(path))
    except Exception as err:  # pyarrow raises ArrowInvalid, OSError and more for broken files
        raise InputError(f'cannot read {path} as a feather file: {str(err).splitlines()[0] if str(err) else err!r}') from err
    missing = [c for c in columns if c not in table.column_names]
    if missing:
        raise InputError(f'{path} lacks the column(s) {", ".join(missing)} (has {", ".join(table.column_names)})')
    return {c: table.column(c).to_numpy() for c in columns}


def read_av2_log(path: str | Path, *, max_sweeps: int | None = None) -> Av2Log:
    """Read an Argoverse 2 log folder: its lidar sweeps, ego poses and sensor extrinsics.

    Args:
        path: the log folder (with ``sensors/lidar/``, ``city_SE3_egovehicle.feather`` and
            ``calibration/egovehicle_SE3_sensor.feather``; without the ``calibration/``
            folder the lidars take :data:`DOCUMENTED_LIDARS`, said in ``warnings``).
        max_sweeps: read only the first sweeps (by stamp); None for all.

    Returns:
        The :class:`Av2Log` (arrays as described there).

    Raises:
        InputError: a file is missing or unreadable, lacks a column, no sweep is found, the
            pose stamps do not increase, or pyarrow is not installed.
    """
    root = Path(path)
    if not root.is_dir():
        raise InputError(f'{root} is not a folder: give an Argoverse 2 log folder')
    files = sorted((p for p in (root / 'sensors' / 'lidar').glob('*.feather') if p.stem.isdigit()),
                   key=lambda p: int(p.stem))
    if not files:
        raise InputError(f'no lidar sweep in {root / "sensors" / "lidar"} (files named <stamp_ns>.feather)')
    sweeps = []
    for file in files[:max_sweeps]:
        cols = _read_table(file, _SWEEP_COLUMNS)
        xyz = np.stack([cols[c].astype(np.float64) for c in 'xyz'], axis=1)
        sweeps.append(Av2Sweep(stamp_ns=int(file.stem), xyz=xyz, intensity=cols['intensity'].astype(np.uint8),
                               laser_number=cols['laser_number'].astype(np.uint8),
                               offset_ns=cols['offset_ns'].astype(np.int64)))

    cols = _read_table(root / 'city_SE3_egovehicle.feather', ('timestamp_ns',) + _POSE_COLUMNS)
    order = np.argsort(cols['timestamp_ns'], kind='stable')
    stamps = cols['timestamp_ns'].astype(np.int64)[order]
    if len(stamps) == 0 or (np.diff(stamps) <= 0).any():
        raise InputError(f'{root / "city_SE3_egovehicle.feather"}: no poses, or two with one stamp')
    poses = Av2Poses(stamps_ns=stamps,
                     translations=np.stack([cols[c] for c in ('tx_m', 'ty_m', 'tz_m')], 1).astype(np.float64)[order],
                     quaternions=np.stack([cols[c] for c in ('qx', 'qy', 'qz', 'qw')], 1).astype(np.float64)[order])

    calibration = root / 'calibration' / 'egovehicle_SE3_sensor.feather'
    warnings: tuple[str, ...] = ()
    if not calibration.exists() and not calibration.parent.exists():
        # Some public sample logs ship without calibration/: the documented layout, said so.
        extrinsics = {name: Av2Extrinsic(np.array(t, float), np.array(q, float))
                      for name, (t, q) in DOCUMENTED_LIDARS.items()}
        warnings = (f'{root} has no calibration/ folder: the lidars are placed as av2-api documents an Argoverse 2 '
                    f"car's (up_lidar 1.64 m, down_lidar 1.57 m above the ego origin, 1.35 m ahead); this car's may "
                    f'differ by millimetres and tenths of a degree',)
    else:
        cols = _read_table(calibration, ('sensor_name',) + _POSE_COLUMNS)
        extrinsics = {str(name): Av2Extrinsic(translation=np.array([cols[c][k] for c in ('tx_m', 'ty_m', 'tz_m')],
                                                                   float),
                                              quaternion=np.array([cols[c][k] for c in ('qx', 'qy', 'qz', 'qw')],
                                                                  float))
                      for k, name in enumerate(cols['sensor_name'])}
    return Av2Log(path=root, sweeps=sweeps, poses=poses, extrinsics=extrinsics, warnings=warnings)


def _lidar_extrinsics(log: Av2Log) -> list[Av2Extrinsic]:
    missing = [name for name in LIDARS if name not in log.extrinsics]
    if missing:
        raise InputError(f'{log.path}: no extrinsic of {", ".join(missing)} in calibration/egovehicle_SE3_sensor.feather')
    return [log.extrinsics[name] for name in LIDARS]


def map_origin_of(log: Av2Log) -> np.ndarray:
    """The local map frame's origin: the first sweep's ego position, rounded to metres.

    Returns:
        (3,) float64, metres, city frame (as the real-data folder's convert.py chooses it).
    """
    translation, _ = log.poses.at(log.sweeps[0].stamp_ns)
    return np.round(translation, 0)


def lidar_clouds(log: Av2Log, sweep: Av2Sweep) -> dict[str, np.ndarray]:
    """A sweep as its two lidars publish it: each lidar's points in its own frame, float32.

    The ego-frame points are taken into the lidar frame by the inverse extrinsic,
    ``p_lidar = R_ext^T (p_ego - t_ext)``, in float64, then rounded to float32. The points
    stay motion-compensated to ``sweep.stamp_ns`` (so a cloud needs one pose, at its stamp,
    and carries no per-point time).

    Returns:
        ``{lidar: points}`` for :data:`LIDARS` in that order, each a structured array (n,)
        of :data:`LIDAR_DTYPE` in the sweep's point order (ring = laser number - 32 for
        ``down_lidar``).

    Raises:
        InputError: the log lacks a lidar's extrinsic.
    """
    out = {}
    for k, (name, extrinsic) in enumerate(zip(LIDARS, _lidar_extrinsics(log))):
        take = sweep.laser_number // LASERS_PER_LIDAR == k
        # Row vectors: (p - t) @ R equals R^T (p - t) for each point.
        local = (sweep.xyz[take] - extrinsic.translation) @ rotation_matrices(extrinsic.quaternion)
        points = np.zeros(int(take.sum()), LIDAR_DTYPE)
        points['x'], points['y'], points['z'] = local.T
        points['intensity'] = sweep.intensity[take]
        points['ring'] = sweep.laser_number[take] - k * LASERS_PER_LIDAR
        out[name] = points
    return out


def reference_clouds(log: Av2Log, map_origin: np.ndarray | None = None) -> list[tuple[int, np.ndarray]]:
    """The lidars' float32 points (:func:`lidar_clouds`) in the local map frame, by plain numpy.

    Each lidar point (float32, as published) goes into the ego frame by its lidar's extrinsic
    and into the city frame by the ego pose at the sweep's stamp, ``p_city = R_ego (R_ext p +
    t_ext) + t_ego``, in float64, minus the map origin. The sensor origin of every point is
    its lidar's position at the sweep's stamp, ``R_ego t_ext + t_ego - map_origin``. No
    transform code of the project is used: this is the reference for it.

    Args:
        log: the log.
        map_origin: (3,) metres, city frame; None for :func:`map_origin_of`.

    Returns:
        ``[(stamp_ns, points), ...]`` per sweep, points a structured array of
        :data:`REFERENCE_DTYPE`, the lidars' points one after the other in :data:`LIDARS`
        order (as :func:`lidar_clouds`), map frame.

    Raises:
        InputError: a lidar's extrinsic is missing, or a sweep lies outside the poses' span.
    """
    origin = map_origin_of(log) if map_origin is None else np.asarray(map_origin, dtype=np.float64)
    out = []
    for sweep in log.sweeps:
        t_ego, q_ego = log.poses.at(sweep.stamp_ns)
        r_ego = rotation_matrices(q_ego)
        parts = []
        for name, points in lidar_clouds(log, sweep).items():
            extrinsic = log.extrinsics[name]
            local = np.stack([points[c].astype(np.float64) for c in 'xyz'], axis=1)
            ego = local @ rotation_matrices(extrinsic.quaternion).T + extrinsic.translation
            where = ego @ r_ego.T + t_ego - origin
            sensor = r_ego @ extrinsic.translation + t_ego - origin
            part = np.zeros(len(points), REFERENCE_DTYPE)
            part['x'], part['y'], part['z'] = where.T
            part['origin_x'], part['origin_y'], part['origin_z'] = sensor
            part['intensity'], part['ring'] = points['intensity'], points['ring']
            parts.append(part)
        out.append((sweep.stamp_ns, np.concatenate(parts)))
    return out
