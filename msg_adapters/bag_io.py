"""Point clouds in ROS 1 and ROS 2 bags, through rosbags (no ROS installation needed).

Writing: :func:`write_bag` stores scans as ``sensor_msgs/msg/PointCloud2`` in a ROS 2 bag
(storage ``'sqlite3'`` or ``'mcap'``, rosbag2 metadata version 9, the newest rosbags writes
and the one of ROS 2 Jazzy) or in a ROS 1 bag (``'rosbag1'``, one ``.bag`` file, format 2.0).
The map origin goes into every bag as one ``geometry_msgs/msg/PointStamped`` on
``/map_origin`` (float64, loss-free) and, for ROS 2, also into the metadata's
``custom_data`` under :data:`ORIGIN_KEY` as three ``repr`` floats. Clouds are in the map
frame unless a scan names its own frame (a lidar's, as a vehicle records them); further
messages (``extra``: /tf, /tf_static, poses ...) go in beside them, each topic with the QoS
profile asked for (``extra_qos``: /tf_static transient local). ROS 1 bags get
``tf2_msgs/msg/TFMessage``, which rosbags' Noetic typestore lacks, added.

Reading: :func:`read_bag` opens ROS 1 bags (a list of ``.bag`` files) or one ROS 2 bag (a
directory with ``metadata.yaml``, or a single ``.db3`` / ``.mcap`` file) with
``rosbags.highlevel.AnyReader`` and decodes the PointCloud2 topic.
"""

from __future__ import annotations

import shutil
import sqlite3
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.io.cloud import Cloud
from uncertain_facade_map.io.inputs import load_inputs as core_load_inputs

from .pointcloud2 import pointcloud2_from_structured, rosbags_types, structured_from_pointcloud2

#: custom_data key of ROS 2 bags holding the map origin, ``'x y z'`` as Python float reprs.
ORIGIN_KEY = 'uncertain_facade_map/map_origin'
#: Topic holding the map origin as one ``geometry_msgs/msg/PointStamped``.
ORIGIN_TOPIC = '/map_origin'
POINTCLOUD2 = 'sensor_msgs/msg/PointCloud2'
POINTSTAMPED = 'geometry_msgs/msg/PointStamped'
STORAGES = ('sqlite3', 'mcap', 'rosbag1')
#: rosbag2 metadata version written (rosbags writes 8 or 9; 9 is ROS 2 Jazzy's).
ROSBAG2_VERSION = 9

#: An extra message for :func:`write_bag`: (topic, msgtype, stamp_ns, make_msg), where
#: ``make_msg(typestore)`` returns the message built from that typestore's classes.
ExtraMessage = tuple[str, str, int, Callable[[Any], Any]]
#: QoS profiles :func:`write_bag` can record for an extra topic (its ``extra_qos`` values).
QOS_PROFILES = ('sensor', 'reliable', 'latched')
TFMESSAGE = 'tf2_msgs/msg/TFMessage'
#: tf2_msgs/msg/TFMessage, which rosbags' ROS 1 Noetic typestore lacks (ROS 1 md5sum
#: 94810edda583a504dfda3829e70d7eec, as tf2_msgs/TFMessage in Noetic bags).
_TFMESSAGE_DEFINITION = 'geometry_msgs/TransformStamped[] transforms\n'


@dataclass
class BagClouds:
    """Point cloud scans read from a bag.

    Attributes:
        scans: ``[(stamp_ns, points), ...]`` in bag order (receive time); ``stamp_ns`` is the
            header stamp in integer nanoseconds, ``points`` a packed structured array (N,)
            as given by :func:`~msg_adapters.pointcloud2.structured_from_pointcloud2`.
        map_origin: (3,) float64, metres; zeros if the bag records none.
        topic: the PointCloud2 topic read.
    """

    scans: list[tuple[int, np.ndarray]]
    map_origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    topic: str = ''


# --------------------------------------------------------------------------------------
# writing
# --------------------------------------------------------------------------------------


def _origin_text(origin: np.ndarray) -> str:
    """``'x y z'`` with Python reprs, which parse back to the same float64 values."""
    return ' '.join(repr(float(v)) for v in origin)


def _parse_origin_text(text: str) -> np.ndarray | None:
    """Parse :func:`_origin_text` output (commas and brackets tolerated); None if invalid."""
    parts = text.replace(',', ' ').replace('[', ' ').replace(']', ' ').split()
    try:
        values = np.array([float(p) for p in parts], dtype=np.float64)
    except ValueError:
        return None
    return values if values.shape == (3,) and np.isfinite(values).all() else None


def _sensor_qos() -> list[Any]:
    """rclcpp's sensor-data QoS (best effort, volatile, keep last 5) as rosbags Qos."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    zero = QosTime(0, 0)
    return [Qos(QosHistory.KEEP_LAST, 5, QosReliability.BEST_EFFORT, QosDurability.VOLATILE,
                zero, zero, QosLiveliness.AUTOMATIC, zero, False)]


def _reliable_qos() -> list[Any]:
    """rclcpp's default QoS (reliable, volatile, keep last 10) as rosbags Qos: /tf, poses, odometry."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    zero = QosTime(0, 0)
    return [Qos(QosHistory.KEEP_LAST, 10, QosReliability.RELIABLE, QosDurability.VOLATILE,
                zero, zero, QosLiveliness.AUTOMATIC, zero, False)]


def _bag_typestore(ros1: bool) -> Any:
    """The rosbags typestore of a new bag: ROS 2 Jazzy, or ROS 1 Noetic with tf2_msgs/msg/TFMessage added."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    if not ros1:
        return get_typestore(Stores.ROS2_JAZZY)
    typestore = get_typestore(Stores.ROS1_NOETIC)  # a new instance: registering stays local
    if TFMESSAGE not in typestore.types:
        typestore.register(get_types_from_msg(_TFMESSAGE_DEFINITION, TFMESSAGE))
    return typestore


def _latched_qos() -> list[Any]:
    """Reliable, transient-local, keep last 1: a latched topic such as ``/map_origin``."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    zero = QosTime(0, 0)
    return [Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
                zero, zero, QosLiveliness.AUTOMATIC, zero, False)]


def write_bag(
    path: str | Path,
    scans: Iterable[tuple[int, np.ndarray]],
    *,
    storage: str,
    topic: str = '/points',
    frame_id: str = 'map',
    map_origin: Sequence[float] = (0.0, 0.0, 0.0),
    extra: Iterable[ExtraMessage] | None = None,
    extra_qos: Mapping[str, str] | None = None,
) -> Path:
    """Write point cloud scans into a new ROS 1 or ROS 2 bag.

    Args:
        path: the bag to create: a directory for ``'sqlite3'`` and ``'mcap'`` (ROS 2), a
            file (conventionally ``*.bag``) for ``'rosbag1'``. Must not exist.
        scans: ``(stamp_ns, points)`` pairs: header stamp and receive time in integer
            nanoseconds since the UNIX epoch, and a structured array (N,) with fields of
            types i1, u1, i2, u2, i4, u4, f4 or f8 (coordinates in the map frame, metres);
            or ``(stamp_ns, points, frame_id)`` triples for clouds in another frame (a
            sensor's), whose header then names that frame.
        storage: ``'sqlite3'``, ``'mcap'`` or ``'rosbag1'``.
        topic: PointCloud2 topic name.
        frame_id: header frame id of the clouds and of the map origin message.
        map_origin: (3,) metres, recorded on ``/map_origin`` (stamped with the first scan's
            stamp, or the first extra message's, or 0) and, for ROS 2, in ``custom_data``.
        extra: further messages ``(topic, msgtype, stamp_ns, make_msg)``; ``make_msg`` is
            called with the bag's rosbags typestore (ROS 2 Jazzy, or ROS 1 Noetic with
            ``tf2_msgs/msg/TFMessage`` added, for ``'rosbag1'``) and returns the message to
            serialize.
        extra_qos: ``{topic: profile}`` for extra topics, profile one of
            :data:`QOS_PROFILES`: ``'sensor'`` (best effort, volatile, keep last 5),
            ``'reliable'`` (reliable, volatile, keep last 10) or ``'latched'`` (reliable,
            transient local, keep last 1, as /tf_static; a latching connection in ROS 1),
            recorded as the topic's offered QoS (ROS 2). Extra topics not named record none.

    Returns:
        The path of the bag written.

    Raises:
        InputError: unknown storage, the path exists, a non-finite or wrongly shaped map
            origin, an unknown QoS profile, or scans that cannot be encoded (see
            ``pointcloud2_from_structured``).
    """
    if storage not in STORAGES:
        raise InputError(f'unknown bag storage {storage!r} (choose from {", ".join(STORAGES)})')
    path = Path(path)
    if path.exists():
        raise InputError(f'{path} exists already, not overwriting')
    origin = np.asarray(map_origin, dtype=np.float64).reshape(-1)
    if origin.shape != (3,) or not np.isfinite(origin).all():
        raise InputError(f'map origin must be 3 finite numbers, got {map_origin!r}')

    qos_of = dict(extra_qos or {})
    unknown = sorted({q for q in qos_of.values() if q not in QOS_PROFILES})
    if unknown:
        raise InputError(f'unknown QoS profile {", ".join(map(repr, unknown))} '
                         f'(choose from {", ".join(QOS_PROFILES)})')

    ros1 = storage == 'rosbag1'
    typestore = _bag_typestore(ros1)
    types = rosbags_types(typestore)
    serialize = typestore.serialize_ros1 if ros1 else typestore.serialize_cdr
    extra_list = list(extra or ())

    def origin_msg(stamp_ns: int) -> Any:
        sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
        header = types.Header(stamp=types.Time(sec=sec, nanosec=nanosec), frame_id=frame_id)
        point = types.Point(x=float(origin[0]), y=float(origin[1]), z=float(origin[2]))
        return types.PointStamped(header=header, point=point)

    if ros1:
        from rosbags.rosbag1 import Writer as Writer1

        writer: Any = Writer1(path)
    else:
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as Writer2

        plugin = StoragePlugin.SQLITE3 if storage == 'sqlite3' else StoragePlugin.MCAP
        writer = Writer2(path, version=ROSBAG2_VERSION, storage_plugin=plugin)
        writer.set_custom_data(ORIGIN_KEY, _origin_text(origin))

    def connect(name: str, msgtype: str, qos: list[Any] | None = None,
                latched: bool = False) -> Any:
        if ros1:
            return writer.add_connection(name, msgtype, typestore=typestore,
                                         latching=1 if latched else None)
        return writer.add_connection(name, msgtype, typestore=typestore,
                                     offered_qos_profiles=qos or ())

    try:
        with writer:
            points_conn = connect(topic, POINTCLOUD2, _sensor_qos())
            origin_conn = connect(ORIGIN_TOPIC, POINTSTAMPED, _latched_qos(), latched=True)
            profiles = {'sensor': _sensor_qos, 'reliable': _reliable_qos, 'latched': _latched_qos}
            extra_conns = {(t, m): None for t, m, _s, _f in extra_list}
            for key in extra_conns:
                profile = qos_of.get(key[0])
                extra_conns[key] = connect(*key, profiles[profile]() if profile else None,
                                           latched=profile == 'latched')

            origin_written = False
            for stamp_ns, points, *cloud_frame in scans:
                stamp_ns = int(stamp_ns)
                if not origin_written:
                    writer.write(origin_conn, stamp_ns,
                                 serialize(origin_msg(stamp_ns), POINTSTAMPED))
                    origin_written = True
                msg = pointcloud2_from_structured(points, stamp_ns=stamp_ns,
                                                  frame_id=cloud_frame[0] if cloud_frame else frame_id,
                                                  msg_types=types)
                writer.write(points_conn, stamp_ns, serialize(msg, POINTCLOUD2))
            if not origin_written:
                stamp = min((int(e[2]) for e in extra_list), default=0)
                writer.write(origin_conn, stamp, serialize(origin_msg(stamp), POINTSTAMPED))
            for etopic, emsgtype, stamp_ns, make_msg in extra_list:
                writer.write(extra_conns[etopic, emsgtype], int(stamp_ns),
                             serialize(make_msg(typestore), emsgtype))
    except BaseException:
        _remove(path)  # the path did not exist before: leave no half-written bag behind
        raise
    return path


def _remove(path: Path) -> None:
    """Delete a file or directory tree if it exists."""
    if path.is_dir():
        shutil.rmtree(path, ignore_errors=True)
    elif path.exists():
        path.unlink()


# --------------------------------------------------------------------------------------
# reading
# --------------------------------------------------------------------------------------


def _paths(paths: str | Path | Sequence[str | Path]) -> list[Path]:
    """Normalise one path or several into a list of existing Paths.

    Raises:
        InputError: no path, or a path that does not exist.
    """
    items = [paths] if isinstance(paths, (str, Path)) else list(paths)
    out = [Path(p) for p in items]
    if not out:
        raise InputError('no bag path given')
    missing = [str(p) for p in out if not p.exists()]
    if missing:
        raise InputError(f'bag not found: {", ".join(missing)}')
    bare = [str(p) for p in out if p.is_dir() and not (p / 'metadata.yaml').exists()]
    if bare:
        raise InputError(f'not a ROS 2 bag (directory without metadata.yaml): {", ".join(bare)}')
    return out


def _open_reader(paths: list[Path]) -> Any:
    """Open an AnyReader on ``paths``, turning every failure into an InputError."""
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.rosbag1 import ReaderError as ReaderError1
    from rosbags.rosbag2 import ReaderError as ReaderError2

    names = ', '.join(str(p) for p in paths)
    errors = (AnyReaderError, ReaderError1, ReaderError2, OSError, sqlite3.Error,
              ValueError, KeyError, EOFError)
    try:
        reader = AnyReader(paths)
        reader.open()
    except errors as err:
        reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise InputError(f'cannot read {names} as a ROS 1 or ROS 2 bag: {reason}') from None
    return reader


def _topics(reader: Any) -> dict[str, str]:
    """Topic -> msgtype of an open AnyReader (``'?'`` for mixed types)."""
    return {name: info.msgtype or '?' for name, info in sorted(reader.topics.items())}


def _topics_text(topics: dict[str, str]) -> str:
    return ', '.join(f'{t} ({m})' for t, m in topics.items()) if topics else 'none'


def list_topics(paths: str | Path | Sequence[str | Path]) -> dict[str, str]:
    """Return the topics of a bag and their message types.

    Args:
        paths: one ROS 2 bag (directory, ``.db3`` or ``.mcap``) or one or more ROS 1
            ``.bag`` files.

    Returns:
        ``{topic: msgtype}``, sorted by topic, msgtype like ``'sensor_msgs/msg/PointCloud2'``.

    Raises:
        InputError: a path is missing or not a readable bag.
    """
    reader = _open_reader(_paths(paths))
    try:
        return _topics(reader)
    finally:
        reader.close()


def _custom_origin(reader: Any) -> np.ndarray | None:
    """The map origin from a ROS 2 bag's custom_data, if present (else None)."""
    for sub in getattr(reader, 'readers', ()):
        metadata = getattr(getattr(sub, 'storage', None), 'metadata', None)
        custom = getattr(metadata, 'custom', None) or {}
        text = custom.get(ORIGIN_KEY) if hasattr(custom, 'get') else None
        if isinstance(text, str) and (origin := _parse_origin_text(text)) is not None:
            return origin
    return None


def read_bag(
    paths: str | Path | Sequence[str | Path],
    *,
    topic: str | None = None,
) -> BagClouds:
    """Read every PointCloud2 scan of one topic of a bag, and its map origin.

    Args:
        paths: one ROS 2 bag (directory with metadata.yaml, or a ``.db3`` / ``.mcap``
            file) or one or more ROS 1 ``.bag`` files.
        topic: the PointCloud2 topic; None to use the bag's only PointCloud2 topic.

    Returns:
        :class:`BagClouds` with the scans in bag order, the map origin ((3,) float64,
        metres: from ``/map_origin``, else the ROS 2 custom_data key :data:`ORIGIN_KEY`,
        else zeros) and the topic read.

    Raises:
        InputError: a path is missing or not a bag; ``topic`` is None and the bag has zero
            or several PointCloud2 topics, or ``topic`` is not a PointCloud2 topic of the
            bag (the message lists the topics found); a message cannot be decoded.
    """
    reader = _open_reader(_paths(paths))
    try:
        topics = _topics(reader)
        clouds = [t for t, m in topics.items() if m == POINTCLOUD2]
        if topic is None:
            if len(clouds) != 1:
                what = 'no' if not clouds else f'{len(clouds)}'
                raise InputError(
                    f'bag has {what} {POINTCLOUD2} topics, '
                    f'{"choose one" if clouds else "nothing to read"}; '
                    f'topics: {_topics_text(topics)}'
                )
            topic = clouds[0]
        elif topics.get(topic) != POINTCLOUD2:
            raise InputError(
                f'bag has no {POINTCLOUD2} topic {topic!r}; topics: {_topics_text(topics)}'
            )

        wanted = [c for c in reader.connections if c.topic in (topic, ORIGIN_TOPIC)]
        scans: list[tuple[int, np.ndarray]] = []
        origin: np.ndarray | None = None
        for conn, _time, raw in reader.messages(connections=wanted):
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except Exception as err:  # rosbags raises several types for corrupt data
                raise InputError(
                    f'cannot decode a {conn.msgtype} on {conn.topic}: {err}') from None
            if conn.topic == topic:
                stamp = msg.header.stamp
                stamp_ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
                scans.append((stamp_ns, structured_from_pointcloud2(msg)))
            elif origin is None and conn.msgtype == POINTSTAMPED:
                p = msg.point
                origin = np.array([p.x, p.y, p.z], dtype=np.float64)
        if origin is None:
            origin = _custom_origin(reader)
    finally:
        reader.close()
    if origin is None:
        origin = np.zeros(3)
    return BagClouds(scans=scans, map_origin=origin, topic=topic)


def read_bag_cloud(paths: str | Path | Sequence[str | Path], topic: str | None = None) -> Cloud:
    """Read all scans of a bag's PointCloud2 topic as one cloud.

    Args:
        paths: as for :func:`read_bag`.
        topic: as for :func:`read_bag`.

    Returns:
        A :class:`~uncertain_facade_map.io.cloud.Cloud` with the points of all scans in bag
        order (map frame, metres) and the bag's map origin.

    Raises:
        InputError: as :func:`read_bag`; also if the topic has no message, the scans'
            fields differ, or the points lack x, y or z.
    """
    bag = read_bag(paths, topic=topic)
    if not bag.scans:
        raise InputError(f'topic {bag.topic} of the bag has no messages')
    dtypes = {pts.dtype for _stamp, pts in bag.scans}
    if len(dtypes) > 1:
        raise InputError(f'scans on {bag.topic} have different fields: '
                         + '; '.join(str(d) for d in dtypes))
    points = np.concatenate([pts for _stamp, pts in bag.scans])
    return Cloud(points, bag.map_origin)


def load_inputs(paths: str | Path | Sequence[str | Path], topic: str | None = None, *,
                max_distance: float | None = None, warn: Callable[[str], None] | None = None) -> Cloud:
    """Point cloud files and ROS bags joined into one cloud: the core's
    :func:`~uncertain_facade_map.io.inputs.load_inputs` with bags read by :func:`read_bag_cloud`
    (``max_distance`` and ``warn`` as there).

    Raises:
        InputError: as the core's ``load_inputs`` and :func:`read_bag_cloud`.
    """
    return core_load_inputs(paths, topic=topic, read_bag=lambda path, t: read_bag_cloud([path], topic=t),
                            max_distance=max_distance, warn=warn)
