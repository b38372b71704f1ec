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
``rosbags.highlevel.AnyReader`` and decodes the PointCloud2 topic with each cloud's frame,
and the poses a robot records beside it: every ``tf2_msgs/msg/TFMessage`` topic (``/tf``;
a topic named ``tf_static`` holds static transforms; ROS 1's ``tf/tfMessage`` too), ``geometry_msgs/msg/TransformStamped``
topic (such as the node's ``sensor_pose``) and ``nav_msgs/msg/Odometry`` topic
(:data:`POSE_TYPES`), so that the clouds can be put into the map frame exactly as the node
does (:meth:`BagClouds.transform_buffer`). :func:`read_bag_cloud` joins the scans of a bag
into one map-frame cloud for ``build``.
"""

from __future__ import annotations

import math
import shutil
import sqlite3
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Mapping, Sequence

import numpy as np

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.io.cloud import Cloud
from uncertain_facade_map.io.inputs import load_inputs as core_load_inputs
from uncertain_facade_map.transforms import TransformBuffer

from .pointcloud2 import pointcloud2_from_structured, rosbags_types, structured_from_pointcloud2
from .transforms import StampedTransform, header_stamp_ns, stamped_transforms, transform_arrays

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
TRANSFORMSTAMPED = 'geometry_msgs/msg/TransformStamped'
ODOMETRY = 'nav_msgs/msg/Odometry'
#: ROS 1's tf (before tf2) recorded /tf as tf/tfMessage, the same fields as tf2_msgs/TFMessage.
TF1MESSAGE = 'tf/msg/tfMessage'
#: Transform lists: tf2_msgs/TFMessage and ROS 1's tf/tfMessage.
TF_TYPES = (TFMESSAGE, TF1MESSAGE)
#: The message types read as poses of frames: transforms, the node's sensor_pose, odometry.
POSE_TYPES = (TFMESSAGE, TF1MESSAGE, TRANSFORMSTAMPED, ODOMETRY)


def is_static_topic(topic: str) -> bool:
    """Whether a TFMessage topic holds static transforms (``/tf_static``, ``/robot/tf_static``)."""
    return topic.rstrip('/').split('/')[-1] == 'tf_static'


@dataclass
class BagClouds:
    """Point cloud scans read from a bag.

    Attributes:
        scans: ``[(stamp_ns, points), ...]`` in bag order (receive time); ``stamp_ns`` is the
            header stamp in integer nanoseconds, ``points`` a packed structured array (N,)
            as given by :func:`~msg_adapters.pointcloud2.structured_from_pointcloud2`.
        map_origin: (3,) float64, metres; zeros if the bag records none.
        topic: the PointCloud2 topic read.
        frame_ids: each scan's ``header.frame_id``, in the order of ``scans``.
        transforms: the poses of the bag's pose topics (:data:`POSE_TYPES`) in bag order,
            as ``(topic, static, transform)``.
        pose_topics: topic -> message type of the pose topics read.
        n_clouds: clouds on the topic (``len(scans)`` unless only the first were read).
    """

    scans: list[tuple[int, np.ndarray]]
    map_origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    topic: str = ''
    frame_ids: list[str] = field(default_factory=list)
    transforms: list[tuple[str, bool, StampedTransform]] = field(default_factory=list)
    pose_topics: dict[str, str] = field(default_factory=dict)
    n_clouds: int = 0

    def transform_buffer(self, cache_time: float = math.inf) -> tuple[TransformBuffer, list[str]]:
        """Every transform of the bag in one buffer (as the node's, but keeping them all).

        Returns:
            (the buffer, the reasons of the transforms it refused, e.g. a frame given two
            parents, as ``'TOPIC: reason'``).
        """
        buffer = TransformBuffer(cache_time=cache_time)
        refused: list[str] = []
        groups: dict[tuple[str, bool], list[StampedTransform]] = {}
        for topic, static, t in self.transforms:
            groups.setdefault((topic, static), []).append(t)
        for (topic, static), items in groups.items():
            why: list[str] = []
            buffer.set_transforms(**transform_arrays(items), static=static, strict=False, refused=why)
            refused += [f'{topic}: {w}' for w in why]
        return buffer, refused

    def cloud_frames(self) -> dict[str, int]:
        """The frames of the clouds, with the number of clouds in each, in order of appearance."""
        return dict(Counter(self.frame_ids))

    @property
    def located_scans(self) -> list[tuple[int, np.ndarray, str]]:
        """``(stamp_ns, points, frame_id)`` of each scan, in bag order."""
        frames = self.frame_ids or [''] * len(self.scans)
        return [(stamp, points, frame) for (stamp, points), frame in zip(self.scans, frames)]


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


def _qos(profile: str) -> list[Any]:
    """A QoS profile of :data:`QOS_PROFILES` as rosbags Qos, for a connection's offered profiles:
    ``'sensor'``, rclcpp's sensor data (best effort, volatile, keep last 5); ``'reliable'``,
    rclcpp's default (reliable, volatile, keep last 10: /tf, poses, odometry); ``'latched'``
    (reliable, transient local, keep last 1: ``/map_origin``, ``/tf_static``)."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    depth, reliability, durability = {
        'sensor': (5, QosReliability.BEST_EFFORT, QosDurability.VOLATILE),
        'reliable': (10, QosReliability.RELIABLE, QosDurability.VOLATILE),
        'latched': (1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL),
    }[profile]
    zero = QosTime(0, 0)
    return [Qos(QosHistory.KEEP_LAST, depth, reliability, durability, zero, zero, QosLiveliness.AUTOMATIC, zero,
                False)]


def _bag_typestore(ros1: bool) -> Any:
    """The rosbags typestore of a new bag: ROS 2 Jazzy, or ROS 1 Noetic with tf2_msgs/msg/TFMessage added."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    if not ros1:
        return get_typestore(Stores.ROS2_JAZZY)
    typestore = get_typestore(Stores.ROS1_NOETIC)  # a new instance: registering stays local
    if TFMESSAGE not in typestore.types:
        typestore.register(get_types_from_msg(_TFMESSAGE_DEFINITION, TFMESSAGE))
    return typestore


def pose_message(topic: str, msgtype: str, transforms: Sequence[StampedTransform]) -> ExtraMessage:
    """An extra message for :func:`write_bag` holding poses: a ``tf2_msgs/msg/TFMessage`` of
    ``transforms``, or a ``geometry_msgs/msg/TransformStamped`` or ``nav_msgs/msg/Odometry``
    of the one transform given (:mod:`msg_adapters.transforms` builds it from the bag's
    typestore). Stamped with the first transform's stamp.

    Raises:
        InputError: another message type, no transform, or several for a single-pose type.
    """
    from .transforms import odometry_msg, tf_message, transform_stamped_msg, transform_types_rosbags

    items = list(transforms)
    if not items:
        raise InputError(f'no transform for a {msgtype} on {topic}')
    if msgtype == TFMESSAGE:
        return topic, msgtype, items[0].stamp_ns, lambda store: tf_message(items, transform_types_rosbags(store))
    if len(items) != 1 or msgtype not in (TRANSFORMSTAMPED, ODOMETRY):
        raise InputError(f'a {msgtype} on {topic} holds one pose of type {TRANSFORMSTAMPED} or {ODOMETRY}, '
                         f'got {len(items)}')
    build = transform_stamped_msg if msgtype == TRANSFORMSTAMPED else odometry_msg
    return topic, msgtype, items[0].stamp_ns, lambda store: build(items[0], transform_types_rosbags(store))


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
            points_conn = connect(topic, POINTCLOUD2, _qos('sensor'))
            origin_conn = connect(ORIGIN_TOPIC, POINTSTAMPED, _qos('latched'), latched=True)
            extra_conns = {(t, m): None for t, m, _s, _f in extra_list}
            for key in extra_conns:
                profile = qos_of.get(key[0])
                extra_conns[key] = connect(*key, _qos(profile) if profile else None,
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


#: Clouds whose frames :func:`read_bag` reads without keeping the clouds (``clouds=False``).
PEEK_CLOUDS = 50


def read_bag(
    paths: str | Path | Sequence[str | Path],
    *,
    topic: str | None = None,
    poses: Sequence[str] | None = None,
    clouds: bool = True,
) -> BagClouds:
    """Read every PointCloud2 scan of one topic of a bag, its frames, poses and map origin.

    Args:
        paths: one ROS 2 bag (directory with metadata.yaml, or a ``.db3`` / ``.mcap``
            file) or one or more ROS 1 ``.bag`` files.
        topic: the PointCloud2 topic; None to use the bag's only PointCloud2 topic.
        poses: the pose topics to read; None for every topic of a type in
            :data:`POSE_TYPES`, ``[]`` for none.
        clouds: False to read the poses and the map origin only, with the first
            :data:`PEEK_CLOUDS` clouds (their frames and fields: ``frame_ids``, ``scans``)
            and the number of clouds (``n_clouds``); the clouds themselves are then
            streamed by :func:`stream_scans`, so that a long bag never sits in memory.

    Returns:
        :class:`BagClouds` with the scans and their frames in bag order, the transforms of
        the pose topics, the map origin ((3,) float64, metres: from ``/map_origin``, else
        the ROS 2 custom_data key :data:`ORIGIN_KEY`, else zeros) and the topic read.

    Raises:
        InputError: a path is missing or not a bag; ``topic`` is None and the bag has zero
            or several PointCloud2 topics, or ``topic`` is not a PointCloud2 topic of the
            bag (the message lists the topics found); a pose topic that is not one of
            :data:`POSE_TYPES`; a message cannot be decoded.
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

        if poses is None:
            pose_topics = {t: m for t, m in topics.items() if m in POSE_TYPES}
        else:
            bad = [t for t in poses if topics.get(t) not in POSE_TYPES]
            if bad:
                raise InputError(f'{", ".join(bad)}: no pose topic of the bag (types {", ".join(POSE_TYPES)}); '
                                 f'topics: {_topics_text(topics)}')
            pose_topics = {t: topics[t] for t in poses}
        n_clouds = sum(int(getattr(c, 'msgcount', 0) or 0) for c in reader.connections if c.topic == topic)
        wanted = [c for c in reader.connections
                  if (c.topic == topic and clouds) or c.topic == ORIGIN_TOPIC or c.topic in pose_topics]
        scans: list[tuple[int, np.ndarray]] = []
        frames: list[str] = []
        transforms: list[tuple[str, bool, StampedTransform]] = []
        origin: np.ndarray | None = None
        if not clouds:
            for stamp_ns, points, frame in _scans_of(reader, topic, PEEK_CLOUDS):
                scans.append((stamp_ns, points))
                frames.append(frame)
        for conn, _time, raw in reader.messages(connections=wanted):
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except Exception as err:  # rosbags raises several types for corrupt data
                raise InputError(
                    f'cannot decode a {conn.msgtype} on {conn.topic}: {err}') from None
            if conn.topic == topic:
                stamp_ns, points, frame = _scan(msg)
                scans.append((stamp_ns, points))
                frames.append(frame)
            elif conn.topic in pose_topics:
                static = conn.msgtype in TF_TYPES and is_static_topic(conn.topic)
                transforms += [(conn.topic, static, t) for t in stamped_transforms(msg)]
            elif origin is None and conn.msgtype == POINTSTAMPED:
                p = msg.point
                origin = np.array([p.x, p.y, p.z], dtype=np.float64)
        if origin is None:
            origin = _custom_origin(reader)
    finally:
        reader.close()
    if origin is None:
        origin = np.zeros(3)
    return BagClouds(scans=scans, map_origin=origin, topic=topic, frame_ids=frames, transforms=transforms,
                     pose_topics=pose_topics, n_clouds=n_clouds if not clouds else len(scans))


def _scan(msg: Any) -> tuple[int, np.ndarray, str]:
    """(stamp_ns, points, frame_id) of a PointCloud2 message."""
    return header_stamp_ns(msg.header), structured_from_pointcloud2(msg), str(msg.header.frame_id)


def _scans_of(reader: Any, topic: str, limit: int | None = None) -> Iterator[tuple[int, np.ndarray, str]]:
    """The clouds of a topic of an open reader, decoded one at a time (the first ``limit``)."""
    conns = [c for c in reader.connections if c.topic == topic]
    for k, (conn, _time, raw) in enumerate(reader.messages(connections=conns)):
        if limit is not None and k >= limit:
            return
        try:
            msg = reader.deserialize(raw, conn.msgtype)
        except Exception as err:  # rosbags raises several types for corrupt data
            raise InputError(f'cannot decode a {conn.msgtype} on {conn.topic}: {err}') from None
        yield _scan(msg)


def stream_scans(paths: str | Path | Sequence[str | Path], topic: str) -> Iterator[tuple[int, np.ndarray, str]]:
    """The clouds of a bag's PointCloud2 topic, ``(stamp_ns, points, frame_id)`` one at a time in
    bag order, never all in memory (for replay of long bags).

    Raises:
        InputError: a path is missing or not a bag, or a message cannot be decoded.
    """
    reader = _open_reader(_paths(paths))
    try:
        yield from _scans_of(reader, topic)
    finally:
        reader.close()


def no_transform_message(path: str, bag: BagClouds, missing: dict[str, str], map_frame: str,
                         buffer: TransformBuffer) -> str:
    """One line refusing a bag whose clouds no transform puts into the map frame."""
    frames = ', '.join(f'"{f}" ({n} clouds)' for f, n in bag.cloud_frames().items())
    tree = repr(buffer).replace('\n', '; ') if buffer.frames() else 'none'
    poses = ', '.join(f'{t} ({m})' for t, m in bag.pose_topics.items()) or 'none'
    why = next(iter(missing.values()))
    return (f'{path}: the clouds on {bag.topic} are in {frames}, not in the map frame "{map_frame}" '
            f'(input.frame_id), and no transform connects them with it ({why}); pose topics read: {poses}; '
            f'transforms: {tree}. Set input.frame_id to the fixed frame of the transforms, or record /tf and '
            '/tf_static (or sensor_pose) with the clouds; nothing was mapped as if in the map frame')


def refuse_unplaceable(path: str, bag: BagClouds, buffer: TransformBuffer, map_frame: str) -> None:
    """InputError when no cloud of the bag can be put into the map frame (see :func:`no_transform_message`)."""
    from uncertain_facade_map.io.scans import frames_without_transform

    frames = bag.cloud_frames()
    missing = frames_without_transform(frames, buffer, map_frame)
    if frames and len(missing) == len(frames):
        raise InputError(no_transform_message(path, bag, missing, map_frame, buffer))


def _placed(scan: Any, placement: Any) -> np.ndarray:
    """The finite points of a placed scan as a structured array in the map frame: x, y, z
    and sensor origins (when known) as float64, the other fields as they were."""
    from uncertain_facade_map.io.scans import ORIGIN_FIELDS

    points = scan.points[scan.finite]
    xyz, origins = scan.map_frame_points(placement)
    coords = ('x', 'y', 'z') + (ORIGIN_FIELDS if origins is not None else ())
    rest = [(n, points.dtype.fields[n][0]) for n in points.dtype.names if n not in ('x', 'y', 'z') + ORIGIN_FIELDS]
    out = np.zeros(len(points), dtype=[(n, 'f8') for n in coords] + rest)
    for k, n in enumerate(coords):
        out[n] = xyz[:, k] if k < 3 else origins[:, k - 3]
    for n, _t in rest:
        out[n] = points[n]
    return out


def read_bag_cloud(paths: str | Path | Sequence[str | Path], topic: str | None = None, config: Any = None,
                   warn: Callable[[str], None] | None = None) -> Cloud:
    """Read all scans of a bag's PointCloud2 topic as one cloud in the map frame.

    Args:
        paths: as for :func:`read_bag`.
        topic: as for :func:`read_bag`.
        config: a :class:`~uncertain_facade_map.params.Config`: clouds in other frames than
            ``input.frame_id`` are put into it as the node does (the bag's pose topics,
            ``input.time_field``, ``node.pose_tolerance``: :class:`~uncertain_facade_map.io.scans.Scan`),
            with their sensor origins; None: the clouds are taken as in the map frame.
        warn: called with one line about clouds that could not be placed (dropped).

    Returns:
        A :class:`~uncertain_facade_map.io.cloud.Cloud` with the points of all scans in bag
        order (map frame, metres) and the bag's map origin. Clouds in other frames give
        their finite points with x, y, z and origin_x/y/z as float64.

    Raises:
        InputError: as :func:`read_bag`; also if the topic has no message, the scans'
            fields differ, the points lack x, y or z, or no cloud can be put into the map
            frame (:func:`refuse_unplaceable`).
    """
    from uncertain_facade_map.io.scans import Scan

    name = ', '.join(str(p) for p in ([paths] if isinstance(paths, (str, Path)) else paths))
    bag = read_bag(paths, topic=topic, poses=None if config is not None else [])
    if not bag.scans:
        raise InputError(f'topic {bag.topic} of the bag has no messages')
    map_frame = None if config is None else config.input.frame_id
    if map_frame is None or all(f == map_frame for f in bag.frame_ids):
        dtypes = {pts.dtype for _stamp, pts in bag.scans}
        if len(dtypes) > 1:
            raise InputError(f'scans on {bag.topic} have different fields: '
                             + '; '.join(str(d) for d in dtypes))
        return Cloud(np.concatenate([pts for _stamp, pts in bag.scans]), bag.map_origin)
    buffer, _refused = bag.transform_buffer()
    refuse_unplaceable(name, bag, buffer, map_frame)
    parts, rejected = [], Counter()
    for stamp, points, frame in bag.located_scans:
        try:
            scan = Scan.of(points, frame, stamp, config.input)
            parts.append(_placed(scan, scan.place(buffer, map_frame, config.node.pose_tolerance)))
        except InputError as exc:  # no transform (TransformError), or a time field that cannot be read
            rejected[str(exc).splitlines()[0]] += 1
    if rejected and warn is not None:
        warn(f'{name}: {sum(rejected.values())} of {len(bag.scans)} clouds dropped, not placed in '
             f'"{map_frame}": {rejected.most_common(1)[0][0]}')
    if not parts:
        raise InputError(f'{name}: no cloud on {bag.topic} could be put into the map frame "{map_frame}"')
    names = {p.dtype.names for p in parts}
    if len(names) > 1:  # some clouds without sensor origins (in the map frame): keep the common fields
        common = [n for n in parts[0].dtype.names if all(n in p.dtype.names for p in parts)]
        if warn is not None and not all(n in common for n in ('origin_x', 'origin_y', 'origin_z')):
            warn(f'{name}: some clouds have no sensor origins: mapped without any')
        parts = [p[common] for p in parts]
    dtypes = {p.dtype for p in parts}
    if len(dtypes) > 1:
        raise InputError(f'scans on {bag.topic} have different fields: ' + '; '.join(str(d) for d in dtypes))
    return Cloud(np.concatenate(parts), bag.map_origin)


def load_inputs(paths: str | Path | Sequence[str | Path], topic: str | None = None, *,
                max_distance: float | None = None, warn: Callable[[str], None] | None = None,
                config: Any = None) -> Cloud:
    """Point cloud files and ROS bags joined into one cloud: the core's
    :func:`~uncertain_facade_map.io.inputs.load_inputs` with bags read by :func:`read_bag_cloud`
    (``max_distance`` and ``warn`` as there; ``config`` as for :func:`read_bag_cloud`).

    Raises:
        InputError: as the core's ``load_inputs`` and :func:`read_bag_cloud`.
    """
    return core_load_inputs(paths, topic=topic,
                            read_bag=lambda path, t: read_bag_cloud([path], topic=t, config=config, warn=warn),
                            max_distance=max_distance, warn=warn)
