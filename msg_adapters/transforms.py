"""Pose and transform messages <-> :class:`StampedTransform` <-> the core's TransformBuffer.

Reads message *attributes* only, never classes, so rclpy's generated messages and rosbags'
dataclasses (and plain stand-ins) work alike. Accepted messages:

* ``tf2_msgs/TFMessage`` (``/tf``, ``/tf_static``): has ``.transforms``, a list of
  TransformStamped;
* ``geometry_msgs/TransformStamped``: ``.header``, ``.child_frame_id``, ``.transform``;
* ``nav_msgs/Odometry``: ``.header``, ``.child_frame_id``, ``.pose.pose`` (position,
  orientation); the twist is not read;
* ``geometry_msgs/PoseStamped`` and ``PoseWithCovarianceStamped``: ``.header`` and
  ``.pose`` (``.pose.pose``), with an explicit ``child_frame`` (they name no child frame).

In each the transform maps child coordinates into ``header.frame_id`` (the parent):
``p_parent = R p_child + t``; an Odometry's pose is the pose of ``child_frame_id`` in
``header.frame_id``, the same thing. Stamps are integer nanoseconds.

The message builders take a ``types`` namespace of message classes, as
:mod:`.pointcloud2` and :mod:`.map_messages` do: :func:`transform_types_rosbags` and
:func:`transform_types_rclpy`.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any, Iterable, Sequence

import numpy as np

from uncertain_facade_map.errors import InputError, TransformError
from uncertain_facade_map.transforms import TransformBuffer

from .map_messages import _header
from .pointcloud2 import header_maker


@dataclass(eq=False)
class StampedTransform:
    """One transform of a message: the pose of ``child`` in ``parent`` at ``stamp_ns``.

    Attributes:
        parent: ``header.frame_id``.
        child: ``child_frame_id`` (or the ``child_frame`` given for a PoseStamped).
        stamp_ns: ``header.stamp`` in integer nanoseconds.
        translation: (3,) float64 metres, ``p_parent = R p_child + translation``.
        rotation: (4,) float64 quaternion ``(x, y, z, w)`` as in the message (not
            normalised, not checked: the buffer does that).
    """

    parent: str
    child: str
    stamp_ns: int
    translation: np.ndarray
    rotation: np.ndarray

    def __post_init__(self) -> None:
        self.parent, self.child, self.stamp_ns = str(self.parent), str(self.child), int(self.stamp_ns)
        self.translation = np.asarray(self.translation, dtype=np.float64).reshape(3)
        self.rotation = np.asarray(self.rotation, dtype=np.float64).reshape(4)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, StampedTransform):
            return NotImplemented
        return (self.parent == other.parent and self.child == other.child and self.stamp_ns == other.stamp_ns
                and np.array_equal(self.translation, other.translation)
                and np.array_equal(self.rotation, other.rotation))

    __hash__ = None  # type: ignore[assignment]  # mutable, compared by value


# --------------------------------------------------------------------------------------
# messages -> StampedTransform
# --------------------------------------------------------------------------------------


def header_stamp_ns(header: Any) -> int:
    """A message header's stamp, integer nanoseconds (rclpy's and rosbags' headers alike)."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _from_transform_stamped(msg: Any) -> StampedTransform:
    tr = msg.transform.translation
    q = msg.transform.rotation
    return StampedTransform(str(msg.header.frame_id), str(msg.child_frame_id), header_stamp_ns(msg.header),
                            (float(tr.x), float(tr.y), float(tr.z)),
                            (float(q.x), float(q.y), float(q.z), float(q.w)))


def _is_transform_stamped(msg: Any) -> bool:
    return hasattr(msg, 'header') and hasattr(msg, 'child_frame_id') and hasattr(msg, 'transform')


def stamped_transforms(msg: Any, *, child_frame: str | None = None) -> list[StampedTransform]:
    """The transforms a message carries, decided by its attributes.

    Args:
        msg: a TFMessage, TransformStamped, Odometry, PoseStamped or
            PoseWithCovarianceStamped of any implementation (rclpy, rosbags, ...).
        child_frame: the child frame for a PoseStamped / PoseWithCovarianceStamped
            (required there); for an Odometry it replaces ``child_frame_id``. Not used for
            TFMessage and TransformStamped.

    Returns:
        One :class:`StampedTransform` per transform, in message order (a TFMessage may give
        none).

    Raises:
        InputError: the message is none of these, or a pose message without
            ``child_frame``.
    """
    if hasattr(msg, 'transforms'):
        out = []
        for i, item in enumerate(msg.transforms):
            if not _is_transform_stamped(item):
                raise InputError(f'transform {i} of a TFMessage is a {type(item).__name__}, not a TransformStamped')
            out.append(_from_transform_stamped(item))
        return out
    if _is_transform_stamped(msg):
        return [_from_transform_stamped(msg)]
    if hasattr(msg, 'header') and hasattr(msg, 'pose'):
        pose = msg.pose.pose if hasattr(msg.pose, 'pose') else msg.pose
        if not (hasattr(pose, 'position') and hasattr(pose, 'orientation')):
            raise InputError(f'{type(msg).__name__} has a pose without position and orientation')
        child = child_frame if child_frame is not None else str(getattr(msg, 'child_frame_id', ''))
        if not child:
            kind = 'Odometry with an empty child_frame_id' if hasattr(msg, 'child_frame_id') else type(msg).__name__
            raise InputError(f'{kind} names no child frame: pass child_frame, the frame whose pose it gives')
        p, q = pose.position, pose.orientation
        return [StampedTransform(str(msg.header.frame_id), str(child), header_stamp_ns(msg.header),
                                 (float(p.x), float(p.y), float(p.z)),
                                 (float(q.x), float(q.y), float(q.z), float(q.w)))]
    raise InputError(f'{type(msg).__name__} is not a transform message: expected a tf2_msgs/TFMessage, '
                     f'geometry_msgs/TransformStamped, nav_msgs/Odometry or geometry_msgs/PoseStamped')


def feed(buffer: TransformBuffer, msg: Any, *, static: bool = False,
         child_frame: str | None = None) -> tuple[int, list[str]]:
    """Add every transform of a message to a buffer.

    Args:
        buffer: the core's :class:`~uncertain_facade_map.transforms.TransformBuffer`.
        msg: as :func:`stamped_transforms`.
        static: the transforms are static (``/tf_static``).
        child_frame: as :func:`stamped_transforms`.

    Returns:
        ``(accepted, reasons)``: how many transforms the buffer took, and one line per
        refused transform (a bad transform inside a TFMessage never stops the others).

    Raises:
        InputError: the message itself is not a transform message (see
            :func:`stamped_transforms`).
    """
    accepted, reasons = 0, []
    for t in stamped_transforms(msg, child_frame=child_frame):
        try:
            buffer.set_transform(t.parent, t.child, t.stamp_ns, t.translation, t.rotation, static=static)
        except TransformError as err:
            reasons.append(str(err))
        else:
            accepted += 1
    return accepted, reasons


def transform_arrays(transforms: Sequence[StampedTransform]) -> dict[str, Any]:
    """Many transforms as the arrays :meth:`TransformBuffer.set_transforms` takes.

    Returns:
        ``{'parents': [K str], 'children': [K str], 'stamps_ns': (K,) int64,
        'translations': (K, 3), 'rotations': (K, 4)}``, to pass as keyword arguments.
    """
    k = len(transforms)
    return {
        'parents': [t.parent for t in transforms],
        'children': [t.child for t in transforms],
        'stamps_ns': np.fromiter((t.stamp_ns for t in transforms), dtype=np.int64, count=k),
        'translations': np.array([t.translation for t in transforms], dtype=np.float64).reshape(k, 3),
        'rotations': np.array([t.rotation for t in transforms], dtype=np.float64).reshape(k, 4),
    }


# --------------------------------------------------------------------------------------
# StampedTransform -> messages
# --------------------------------------------------------------------------------------


def _need(types: Any, name: str) -> Any:
    cls = getattr(types, name, None)
    if cls is None:
        package = 'tf2_msgs' if name == 'TFMessage' else 'the ROS message packages'
        raise InputError(f'message class {name} is not available: {package} is not importable')
    return cls


def _vector(types: Any, cls_name: str, v: np.ndarray) -> Any:
    return _need(types, cls_name)(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _quaternion(types: Any, q: np.ndarray) -> Any:
    return types.Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))


def transform_stamped_msg(t: StampedTransform, types: Any) -> Any:
    """A ``geometry_msgs/TransformStamped`` of one transform.

    Args:
        t: the transform (stamp within 0 .. 2**31 s).
        types: namespace with ``TransformStamped``, ``Transform``, ``Vector3``,
            ``Quaternion``, ``Header``, ``Time``.

    Raises:
        InputError: stamp out of range.
    """
    return _need(types, 'TransformStamped')(
        header=_header(types, t.parent, t.stamp_ns),
        child_frame_id=str(t.child),
        transform=types.Transform(translation=_vector(types, 'Vector3', t.translation),
                                  rotation=_quaternion(types, t.rotation)))


def tf_message(transforms: Iterable[StampedTransform], types: Any) -> Any:
    """A ``tf2_msgs/TFMessage`` of transforms (for /tf or /tf_static).

    Raises:
        InputError: ``types.TFMessage`` is missing (tf2_msgs not importable), or a stamp
            out of range.
    """
    cls = _need(types, 'TFMessage')
    return cls(transforms=[transform_stamped_msg(t, types) for t in transforms])


def odometry_msg(t: StampedTransform, types: Any) -> Any:
    """A ``nav_msgs/Odometry`` whose pose is the transform (zero twist, zero covariances).

    Args:
        t: the pose of ``t.child`` (``child_frame_id``) in ``t.parent`` (``header.frame_id``).
        types: namespace with ``Odometry``, ``PoseWithCovariance``, ``Pose``, ``Point``,
            ``Quaternion``, ``TwistWithCovariance``, ``Twist``, ``Vector3``, ``Header``,
            ``Time``.
    """
    zeros = np.zeros(36)
    pose = types.Pose(position=_vector(types, 'Point', t.translation), orientation=_quaternion(types, t.rotation))
    twist = types.Twist(linear=_vector(types, 'Vector3', np.zeros(3)), angular=_vector(types, 'Vector3', np.zeros(3)))
    return _need(types, 'Odometry')(
        header=_header(types, t.parent, t.stamp_ns),
        child_frame_id=str(t.child),
        pose=types.PoseWithCovariance(pose=pose, covariance=zeros.copy()),
        twist=types.TwistWithCovariance(twist=twist, covariance=zeros.copy()))


def pose_stamped_msg(t: StampedTransform, types: Any) -> Any:
    """A ``geometry_msgs/PoseStamped`` of the transform (the child frame is not written)."""
    pose = types.Pose(position=_vector(types, 'Point', t.translation), orientation=_quaternion(types, t.rotation))
    return _need(types, 'PoseStamped')(header=_header(types, t.parent, t.stamp_ns), pose=pose)


# --------------------------------------------------------------------------------------
# message-class namespaces
# --------------------------------------------------------------------------------------

#: Attribute -> ROS message type, for :func:`transform_types_rosbags`.
TRANSFORM_TYPES: dict[str, str] = {
    'TFMessage': 'tf2_msgs/msg/TFMessage',
    'TransformStamped': 'geometry_msgs/msg/TransformStamped',
    'Transform': 'geometry_msgs/msg/Transform',
    'Vector3': 'geometry_msgs/msg/Vector3',
    'Quaternion': 'geometry_msgs/msg/Quaternion',
    'Point': 'geometry_msgs/msg/Point',
    'Pose': 'geometry_msgs/msg/Pose',
    'PoseStamped': 'geometry_msgs/msg/PoseStamped',
    'PoseWithCovariance': 'geometry_msgs/msg/PoseWithCovariance',
    'PoseWithCovarianceStamped': 'geometry_msgs/msg/PoseWithCovarianceStamped',
    'Twist': 'geometry_msgs/msg/Twist',
    'TwistWithCovariance': 'geometry_msgs/msg/TwistWithCovariance',
    'Odometry': 'nav_msgs/msg/Odometry',
    'Header': 'std_msgs/msg/Header',
    'Time': 'builtin_interfaces/msg/Time',
}


def transform_types_rosbags(typestore: Any = None) -> SimpleNamespace:
    """Message classes of a rosbags typestore for the builders of this module.

    Args:
        typestore: a ``rosbags.typesys`` typestore; None for ``Stores.ROS2_JAZZY``. With a
            ROS 1 store (Header has ``seq``) ``Header`` is wrapped to set ``seq=0``.

    Returns:
        Namespace with the classes of :data:`TRANSFORM_TYPES` and ``typestore``;
        ``TFMessage`` is None when the store lacks it (rosbags' ROS 1 stores do: register
        it from a bag's message definitions), and :func:`tf_message` then raises.

    Raises:
        InputError: the typestore lacks another of the types.
    """
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY) if typestore is None else typestore
    try:
        classes = {key: store.types[msgtype] for key, msgtype in TRANSFORM_TYPES.items() if key != 'TFMessage'}
    except KeyError as err:
        raise InputError(f'typestore has no message type {err.args[0]}') from None
    classes['TFMessage'] = store.types.get(TRANSFORM_TYPES['TFMessage'])
    classes['Header'] = header_maker(classes['Header'])
    return SimpleNamespace(**classes, typestore=store)


def transform_types_rclpy(*, require_tf2_msgs: bool = True) -> SimpleNamespace:
    """Message classes of rclpy (ROS 2 Python) for the builders of this module.

    The packages are imported here, lazily.

    Args:
        require_tf2_msgs: raise when ``tf2_msgs`` does not import; with False,
            ``TFMessage`` is None then (and :func:`tf_message` raises when called).

    Returns:
        Namespace with the classes of :data:`TRANSFORM_TYPES`.

    Raises:
        InputError: ``tf2_msgs`` is not importable (and ``require_tf2_msgs``).
        ImportError: the standard ROS 2 message packages are not installed.
    """
    from builtin_interfaces.msg import Time
    from geometry_msgs.msg import (
        Point,
        Pose,
        PoseStamped,
        PoseWithCovariance,
        PoseWithCovarianceStamped,
        Quaternion,
        Transform,
        TransformStamped,
        Twist,
        TwistWithCovariance,
        Vector3,
    )
    from nav_msgs.msg import Odometry
    from std_msgs.msg import Header

    try:
        from tf2_msgs.msg import TFMessage
    except ImportError as err:
        if require_tf2_msgs:
            raise InputError(f'the ROS 2 message package tf2_msgs is not importable ({err}): /tf and /tf_static '
                             f'need its TFMessage; build it with the project\'s interfaces (make venv)') from err
        TFMessage = None  # noqa: N806 - the class's name
    return SimpleNamespace(
        TFMessage=TFMessage, TransformStamped=TransformStamped, Transform=Transform, Vector3=Vector3,
        Quaternion=Quaternion, Point=Point, Pose=Pose, PoseStamped=PoseStamped,
        PoseWithCovariance=PoseWithCovariance, PoseWithCovarianceStamped=PoseWithCovarianceStamped, Twist=Twist,
        TwistWithCovariance=TwistWithCovariance,
        Odometry=Odometry, Header=Header, Time=Time)
