"""A ROS bag of an Argoverse 2 log "as the vehicle recorded it": lidar clouds in the lidars' frames, poses apart.

Command::

    python -m uncertain_facade_map_apps.av2_bag RAW_DIR OUT --storage mcap|sqlite3|rosbag1 \\
        --poses tf|pose|odometry [--map-frame map] [--reference REF.npz|REF_BAG]

RAW_DIR is an Argoverse 2 log folder (:mod:`uncertain_facade_map.io.av2`); OUT the bag to
create (a folder for mcap and sqlite3, a ``.bag`` file for rosbag1).

What the bag holds:

- ``/points`` (sensor_msgs/PointCloud2, sensor-data QoS): per sweep two clouds, first
  ``up_lidar`` (lasers 0-31), then ``down_lidar`` (lasers 32-63), each in its own frame
  (``header.frame_id`` = the lidar's name), the ego-frame points taken into the lidar frame
  by the inverse extrinsic. Fields x, y, z, intensity (float32) and ring (uint16, the laser
  within its lidar, 0-31), as the Velodyne ROS driver publishes them; ``header.stamp`` = the
  sweep's stamp. No per-point time field: Argoverse's points are already motion-compensated
  to the sweep's stamp, so one pose at that stamp places the whole cloud (a per-point time
  would invite compensating them twice). One topic for both lidars rather than one each:
  the mapper subscribes to one cloud topic and looks up the pose of each cloud's own frame,
  so both lidars reach it without a remap or a second subscription.
- the poses, by ``--poses``:

  - ``tf``: ``/tf`` (tf2_msgs/msg/TFMessage) ``MAP -> egovehicle`` at every ego pose stamp
    from 0.2 s before the first sweep to 0.2 s after the last (about 170 Hz), and
    ``/tf_static`` (one TFMessage, recorded with the transient-local QoS profile, a latching
    connection in ROS 1) ``egovehicle -> up_lidar`` and ``egovehicle -> down_lidar``;
  - ``pose``: ``/sensor_pose`` (geometry_msgs/TransformStamped, the mapper's pose topic)
    ``MAP -> up_lidar`` and ``MAP -> down_lidar`` at each sweep's stamp; no /tf;
  - ``odometry``: ``/odom`` (nav_msgs/Odometry, ``MAP -> egovehicle``, at the same stamps as
    /tf above; twist and covariances zero: Argoverse gives poses only) and ``/tf_static``.

- ``/map_origin`` (geometry_msgs/PointStamped, latched) and, in ROS 2 bags, the metadata's
  custom_data: the map frame is local, the city frame minus the first sweep's ego position
  rounded to metres, as :func:`msg_adapters.bag_io.write_bag` records it.

``--reference`` also writes the reference (:func:`uncertain_facade_map.io.av2.reference_clouds`):
the same float32 lidar points taken into the map frame by plain numpy, with their sensor
origins, as an NPZ cloud (a path ending in ``.npz``) or as a bag in the map frame (one
cloud per sweep on /points, same storage).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from msg_adapters.bag_io import ODOMETRY, STORAGES, TFMESSAGE, pose_message
from msg_adapters.bag_io import TRANSFORMSTAMPED as TRANSFORM_STAMPED
from msg_adapters.transforms import StampedTransform
from uncertain_facade_map.errors import InputError
from uncertain_facade_map.io.av2 import (
    LIDARS,
    Av2Log,
    lidar_clouds,
    map_origin_of,
    read_av2_log,
    reference_clouds,
)
from uncertain_facade_map.transforms import rotations

PROG = 'python -m uncertain_facade_map_apps.av2_bag'
POSE_MODES = ('tf', 'pose', 'odometry')
EGO_FRAME = 'egovehicle'
POINTS_TOPIC = '/points'
TF_TOPIC = '/tf'
TF_STATIC_TOPIC = '/tf_static'
POSE_TOPIC = '/sensor_pose'
ODOM_TOPIC = '/odom'
#: Ego poses go into the bag from this long before the first sweep to this long after the last.
POSE_MARGIN_NS = 200_000_000


def pose_stamps(log: Av2Log) -> np.ndarray:
    """Indices of the ego poses recorded: from POSE_MARGIN_NS before the first sweep to as long after the last.

    Returns:
        (K,) int indices into ``log.poses``, increasing.
    """
    first, last = log.sweeps[0].stamp_ns, log.sweeps[-1].stamp_ns
    stamps = log.poses.stamps_ns
    return np.flatnonzero((stamps >= first - POSE_MARGIN_NS) & (stamps <= last + POSE_MARGIN_NS))


def bag_contents(log: Av2Log, *, poses: str = 'tf', map_frame: str = 'map',
                 map_origin: np.ndarray | None = None) -> dict[str, Any]:
    """What :func:`write_av2_bag` records, as arguments of :func:`msg_adapters.bag_io.write_bag`.

    Args:
        log: the Argoverse 2 log.
        poses: ``'tf'``, ``'pose'`` or ``'odometry'`` (see the module's docstring).
        map_frame: name of the local map frame.
        map_origin: (3,) metres, city frame; None for :func:`~uncertain_facade_map.io.av2.map_origin_of`.

    Returns:
        ``{'scans': [(stamp_ns, points, lidar frame), ...], 'extra': [...], 'extra_qos': {...},
        'map_origin': (3,), 'frame_id': map_frame, 'topic': '/points'}``.

    Raises:
        InputError: unknown ``poses``, a lidar's extrinsic is missing, or a sweep lies
            outside the ego poses' span.
    """
    if poses not in POSE_MODES:
        raise InputError(f'unknown --poses {poses!r} (choose from {", ".join(POSE_MODES)})')
    origin = map_origin_of(log) if map_origin is None else np.asarray(map_origin, dtype=np.float64)
    scans = [(sweep.stamp_ns, points, name) for sweep in log.sweeps
             for name, points in lidar_clouds(log, sweep).items()]
    extrinsics = {name: log.extrinsics[name] for name in LIDARS}
    extra: list[tuple[str, str, int, Callable[[Any], Any]]] = []
    qos: dict[str, str] = {}
    ego = pose_stamps(log)
    start = int(log.poses.stamps_ns[ego[0]]) if len(ego) else log.sweeps[0].stamp_ns

    def ego_pose(k: int) -> tuple[int, np.ndarray, np.ndarray]:
        return (int(log.poses.stamps_ns[k]), log.poses.translations[k] - origin, log.poses.quaternions[k])

    if poses in ('tf', 'odometry'):
        static = [StampedTransform(EGO_FRAME, name, start, e.translation, e.quaternion)
                  for name, e in extrinsics.items()]
        extra.append(pose_message(TF_STATIC_TOPIC, TFMESSAGE, static))
        qos[TF_STATIC_TOPIC] = 'latched'
    if poses in ('tf', 'odometry'):
        topic, kind = (TF_TOPIC, TFMESSAGE) if poses == 'tf' else (ODOM_TOPIC, ODOMETRY)
        for k in ego:
            stamp, t, q = ego_pose(k)
            extra.append(pose_message(topic, kind, [StampedTransform(map_frame, EGO_FRAME, stamp, t, q)]))
        qos[topic] = 'reliable'
    else:
        for sweep in log.sweeps:
            t_ego, q_ego = log.poses.at(sweep.stamp_ns)
            for name, e in extrinsics.items():
                t = rotations.rotate(q_ego, e.translation) + t_ego - origin
                q = rotations.multiply(q_ego, e.quaternion)
                extra.append(pose_message(POSE_TOPIC, TRANSFORM_STAMPED,
                                          [StampedTransform(map_frame, name, sweep.stamp_ns, t, q)]))
        qos[POSE_TOPIC] = 'reliable'
    return {'scans': scans, 'extra': extra, 'extra_qos': qos, 'map_origin': origin, 'frame_id': map_frame,
            'topic': POINTS_TOPIC}


def write_av2_bag(raw_dir: str | Path, out: str | Path, *, storage: str, poses: str = 'tf', map_frame: str = 'map',
                  reference: str | Path | None = None) -> dict[str, Any]:
    """Write the bag of an Argoverse 2 log as its vehicle recorded it (see the module's docstring).

    Args:
        raw_dir: the Argoverse 2 log folder.
        out: the bag to create (must not exist): a folder for ``'mcap'``/``'sqlite3'``, a
            ``.bag`` file for ``'rosbag1'``.
        storage: ``'mcap'``, ``'sqlite3'`` or ``'rosbag1'``.
        poses: ``'tf'``, ``'pose'`` or ``'odometry'``.
        map_frame: the local map frame's name.
        reference: also write the reference clouds there: an NPZ cloud (``*.npz``) or a bag
            in the map frame with the same storage; None for none.

    Returns:
        A summary: ``{'bag': path, 'topics': {topic: count}, 'sweeps': n, 'points': n,
        'map_origin': [x, y, z], 'reference': path or None, 'warnings': [line, ...]}``
        (``warnings``: what was assumed, e.g. the documented lidar layout for a log without
        ``calibration/``).

    Raises:
        InputError: unreadable log, unknown storage or poses mode, ``out`` exists.
    """
    from msg_adapters.bag_io import ORIGIN_TOPIC, write_bag

    log = read_av2_log(raw_dir)
    contents = bag_contents(log, poses=poses, map_frame=map_frame)
    path = write_bag(out, contents['scans'], storage=storage, topic=contents['topic'], frame_id=map_frame,
                     map_origin=contents['map_origin'], extra=contents['extra'], extra_qos=contents['extra_qos'])
    topics = {POINTS_TOPIC: len(contents['scans']), ORIGIN_TOPIC: 1}
    for topic, *_ in contents['extra']:
        topics[topic] = topics.get(topic, 0) + 1
    written_reference = None
    if reference is not None:
        written_reference = write_reference(log, reference, storage=storage, map_frame=map_frame,
                                            map_origin=contents['map_origin'])
    return {'bag': path, 'topics': topics, 'sweeps': len(log.sweeps),
            'points': sum(len(p) for _s, p, _f in contents['scans']),
            'map_origin': contents['map_origin'].tolist(), 'reference': written_reference,
            'warnings': list(log.warnings)}


def write_reference(log: Av2Log, path: str | Path, *, storage: str = 'mcap', map_frame: str = 'map',
                    map_origin: np.ndarray | None = None) -> Path:
    """Write the reference clouds (:func:`~uncertain_facade_map.io.av2.reference_clouds`).

    Args:
        log: the log.
        path: ``*.npz``: one NPZ cloud, every sweep's points in order; else a bag (storage
            ``storage``) with one map-frame cloud per sweep on /points and /map_origin.
        storage: the bag storage for a non-NPZ path.
        map_frame: frame id of the bag's clouds.
        map_origin: as for ``reference_clouds``.

    Returns:
        The path written.
    """
    origin = map_origin_of(log) if map_origin is None else np.asarray(map_origin, dtype=np.float64)
    clouds = reference_clouds(log, origin)
    path = Path(path)
    if path.suffix == '.npz':
        from uncertain_facade_map.io.cloud import Cloud
        from uncertain_facade_map.io.npz import write_npz

        if path.exists():
            raise InputError(f'{path} exists already, not overwriting')
        write_npz(path, Cloud(np.concatenate([p for _s, p in clouds]), origin))
        return path
    from msg_adapters.bag_io import write_bag

    return write_bag(path, clouds, storage=storage, topic=POINTS_TOPIC, frame_id=map_frame, map_origin=origin)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split('\n')[0])
    parser.add_argument('raw_dir', metavar='RAW_DIR', help='Argoverse 2 log folder (sensors/lidar, poses, calibration; without '
                                                             "calibration/ the cars' documented lidar layout, with a warning)")
    parser.add_argument('out', metavar='OUT', help='bag to create: a folder (mcap, sqlite3) or a .bag file (rosbag1)')
    parser.add_argument('--storage', choices=STORAGES, default='mcap', help='bag storage (default mcap)')
    parser.add_argument('--poses', choices=POSE_MODES, default='tf',
                        help='tf: /tf and /tf_static; pose: /sensor_pose per lidar and sweep; '
                             'odometry: /odom and /tf_static (default tf)')
    parser.add_argument('--map-frame', default='map', help='name of the local map frame (default map)')
    parser.add_argument('--reference', metavar='PATH',
                        help='also write the map-frame reference clouds: an .npz cloud or a bag (same storage)')
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command; returns the exit status (0 ok, 2 bad input, 1 I/O failure)."""
    from .cli import run_reporting

    args = build_parser().parse_args(argv)
    return run_reporting(PROG, lambda: _write(args))


def _write(args: argparse.Namespace) -> int:
    summary = write_av2_bag(args.raw_dir, args.out, storage=args.storage, poses=args.poses,
                            map_frame=args.map_frame, reference=args.reference)
    for warning in summary['warnings']:
        print(f'{PROG}: warning: {warning}', file=sys.stderr)
    origin = ' '.join(f'{v:g}' for v in summary['map_origin'])
    print(f'wrote {summary["bag"]}: {summary["sweeps"]} sweeps, {summary["points"]:,} points, map origin {origin}')
    for topic, count in sorted(summary['topics'].items()):
        print(f'  {topic}: {count}')
    if summary['reference']:
        print(f'wrote the reference {summary["reference"]}')
    return 0

if __name__ == '__main__':
    sys.exit(main())
