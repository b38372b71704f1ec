"""The poses that put a cloud's frame into the map frame, into one transform buffer.

:class:`PoseListener` is the node's transform listener (tf2's ``TransformListener`` shape; tf2
itself is not in the wheel set): it subscribes to ``sensor_pose``
(geometry_msgs/TransformStamped), ``/tf`` and ``/tf_static`` (tf2_msgs/TFMessage, as tf2
subscribes: depth 100, the static ones transient local; ``node.use_tf``) and
``node.odometry_topic`` (nav_msgs/Odometry), all in a callback group of their own so that a
cloud's selection never holds up the pose it waits for, and writes every transform into a
:class:`~uncertain_facade_map.transforms.TransformBuffer` (tf2's BufferCore semantics).
A transform that cannot be right (a translation beyond ``node.max_coordinate``, a message
that does not convert) is refused and counted.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from geometry_msgs.msg import TransformStamped
from nav_msgs.msg import Odometry
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from msg_adapters import transforms as mt
from uncertain_facade_map.errors import InputError, TransformError
from uncertain_facade_map.mapping.accounts import Accounts
from uncertain_facade_map.params import NodeConfig
from uncertain_facade_map.transforms import TransformBuffer
from uncertain_facade_map_node.runtime import failed

__all__ = ['PoseListener']


class PoseListener:
    """Subscribes ``node`` to the pose sources and keeps their transforms in :attr:`buffer`.

    Args:
        node: the rclpy node the subscriptions belong to.
        config: ``node.*`` (``use_tf``, ``odometry_topic``, ``transform_cache``,
            ``pose_buffer``, ``max_coordinate``).
        accounts: where transforms received and poses rejected are counted.
    """

    def __init__(self, node: Any, config: NodeConfig, accounts: Accounts) -> None:
        self.buffer = TransformBuffer(cache_time=config.transform_cache, max_samples=config.pose_buffer)
        self._node = node
        self._config = config
        self._accounts = accounts
        #: The frame whose pose the latest sensor_pose or odometry message gave (the sensor's).
        self.follow_frame = ''
        group = MutuallyExclusiveCallbackGroup()
        node.create_subscription(TransformStamped, 'sensor_pose', self.pose_callback, 100, callback_group=group)
        #: The topics read, for the node's first log line.
        self.sources = ['sensor_pose']
        if config.use_tf:
            self._subscribe_tf(group)
        if config.odometry_topic:
            node.create_subscription(Odometry, config.odometry_topic, self.odometry_callback, 100,
                                     callback_group=group)
            self.sources.append(config.odometry_topic)

    def _subscribe_tf(self, group: Any) -> None:
        try:
            from tf2_msgs.msg import TFMessage
        except ImportError:
            self._node.get_logger().warning('tf2_msgs does not import: /tf and /tf_static are not read '
                                            '(node.use_tf); clouds in other frames need sensor_pose or '
                                            'node.odometry_topic')
            return
        dynamic = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        static = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                            durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self._node.create_subscription(TFMessage, '/tf', self.tf_callback, dynamic, callback_group=group)
        self._node.create_subscription(TFMessage, '/tf_static', self.tf_static_callback, static,
                                       callback_group=group)
        self.sources += ['/tf', '/tf_static']

    def add(self, msg: Any, source: str, static: bool = False) -> None:
        """Put the transforms of a message into the buffer; refuse (and count) the bad ones."""
        try:
            transforms = mt.stamped_transforms(msg)
        except (InputError, ValueError, TypeError) as exc:
            self._accounts.reject_pose(source, str(exc))
            return
        bound = self._config.max_coordinate
        for t in transforms:
            if not np.all(np.abs(t.translation) <= bound):
                self._accounts.reject_pose(source, f'"{t.parent}" -> "{t.child}": translation '
                                                   f'{t.translation.tolist()} beyond node.max_coordinate = {bound:g} m')
                continue
            try:
                self.buffer.set_transform(t.parent, t.child, t.stamp_ns, t.translation, t.rotation, static=static)
            except TransformError as exc:
                self._accounts.reject_pose(source, str(exc))
                continue
            self._accounts.pose_received()
            if source != '/tf' and not static:
                self.follow_frame = t.child  # sensor_pose and odometry: the sensor's pose

    def pose_callback(self, msg: Any) -> None:
        """A pose of a frame (``child_frame_id``) in another (``header.frame_id``)."""
        self._guard(self.add, msg, 'sensor_pose')

    def tf_callback(self, msg: Any) -> None:
        """The transforms of /tf."""
        self._guard(self.add, msg, '/tf')

    def tf_static_callback(self, msg: Any) -> None:
        """The static transforms of /tf_static."""
        self._guard(self.add, msg, '/tf_static', True)

    def odometry_callback(self, msg: Any) -> None:
        """The pose of an odometry message (``child_frame_id`` in ``header.frame_id``)."""
        self._guard(self.add, msg, self._config.odometry_topic)

    def _guard(self, fn: Any, *args: Any) -> None:
        """No exception escapes a pose callback (it would end the executor): logged and counted."""
        try:
            fn(*args)
        except Exception as exc:  # noqa: BLE001 - the node must live on
            failed(self._node, self._accounts, 'pose callback', exc)

    def xy(self, map_frame: str, *frames: str) -> np.ndarray | None:
        """The latest map-frame (x, y) of the first of ``frames`` the buffer can place (empty
        names and the map frame skipped), metres; None when it can place none."""
        for frame in frames:
            if not frame or frame == map_frame:
                continue
            try:
                return np.asarray(self.buffer.lookup(map_frame, frame, 0).translation, dtype=np.float64)[:2]
            except TransformError:
                continue
        return None
