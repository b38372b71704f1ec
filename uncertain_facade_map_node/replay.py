"""Publish a recording to a running facade_mapper, with its frames, transforms and timing.

The wheel set has no ``ros2 bag play``; ``uncertain-facade-map replay --mode publish``
reads a bag with rosbags (:mod:`msg_adapters.bag_io`) and republishes it through rclpy
with this module, as the robot published it: the PointCloud2 scans in their own frames on
their own topic (or ``--publish-topic``), and the bag's poses on their topics (/tf,
/tf_static latched as tf2's static broadcaster does, ``sensor_pose``, odometry), all in the
order and spacing of their header stamps. Afterwards it reads the node's diagnostics to say
how many clouds the node actually received, not only how many were sent.
"""

from __future__ import annotations

import os
import threading
import time
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from uncertain_facade_map.errors import InputError

#: The node's status in /diagnostics (``facade_mapper: map``).
_STATUS_SUFFIX = 'facade_mapper: map'
#: A cloud larger than this (bytes) is lost whole over Fast DDS's defaults to a best-effort
#: subscriber on the test machine (docs/node.md, "Large clouds over DDS").
LARGE_CLOUD_BYTES = 116_000


def dds_profile_hint(size: int) -> str | None:
    """Why clouds of ``size`` bytes may have been lost, and the remedy, when they are large and
    no Fast DDS profile is set; None otherwise (shared by the node and publish replay)."""
    if size <= LARGE_CLOUD_BYTES or os.environ.get('FASTRTPS_DEFAULT_PROFILES_FILE'):
        return None
    return (f"clouds of {size / 1e6:.1f} MB are lost whole to DDS fragmentation with Fast DDS's defaults: export "
            'FASTRTPS_DEFAULT_PROFILES_FILE=<repository>/config/fastdds_large_clouds.xml for the node and for what '
            'publishes the clouds (docs/node.md, "Large clouds over DDS")')
#: Seconds of transforms kept around a window of scans, so the node can interpolate at its ends.
TRANSFORM_MARGIN = 1.0


class _NodeWatch:
    """The latest accounts of a facade_mapper, read from /diagnostics in a thread of its own."""

    def __init__(self, node: Any, context: Any) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor

        self.values: dict[str, str] | None = None
        self._lock = threading.Lock()
        node.create_subscription(DiagnosticArray, '/diagnostics', self._callback, 10)
        self._executor = SingleThreadedExecutor(context=context)
        self._executor.add_node(node)
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._stop = False
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop:
            try:
                self._executor.spin_once(timeout_sec=0.1)
            except Exception:  # noqa: BLE001 - shutting down
                return

    def _callback(self, msg: Any) -> None:
        for status in msg.status:
            if str(status.name).endswith(_STATUS_SUFFIX):
                with self._lock:
                    self.values = {kv.key: kv.value for kv in status.values}

    def received(self) -> int | None:
        with self._lock:
            return None if self.values is None else int(self.values.get('clouds_received', 0))

    def wait_for_values(self, seconds: float) -> int | None:
        deadline = time.monotonic() + seconds
        while self.received() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        return self.received()

    def close(self) -> None:
        self._stop = True
        self._thread.join(2.0)
        self._executor.shutdown()


def _groups(transforms: Sequence[tuple[str, bool, Any]]) -> list[tuple[int, str, bool, list[Any]]]:
    """Transforms as messages again: consecutive ones of one topic and stamp form one message."""
    out: list[tuple[int, str, bool, list[Any]]] = []
    for topic, static, t in transforms:
        if out and out[-1][1] == topic and out[-1][0] == t.stamp_ns:
            out[-1][3].append(t)
        else:
            out.append((t.stamp_ns, topic, static, [t]))
    return out


def publish_recording(scans: Sequence[tuple[int, np.ndarray, str]] | Callable[[], Iterable[tuple[int, np.ndarray, str]]],
                      transforms: Sequence[tuple[str, bool, Any]] = (), *, pose_types: dict[str, str] | None = None,
                      topic: str = '/points', rate: float = 1.0, loop: bool = False, reliable: bool = True,
                      wait_subscriber: float = 10.0, wait_node: float = 10.0, window: tuple[int, int] | None = None,
                      progress: Callable[[int], None] | None = None) -> dict[str, Any]:
    """Publish clouds in their own frames and the recording's transforms, with their recorded spacing / ``rate``.

    Args:
        scans: ``(stamp_ns, points, frame_id)`` in recorded order (structured arrays), or a
            function returning an iterator of them (a bag streamed: called once per lap).
        transforms: ``(topic, static, StampedTransform)`` of the recording's pose topics
            (``msg_adapters.bag_io.BagClouds.transforms``); the dynamic ones are sent in
            stamp order between the clouds, from :data:`TRANSFORM_MARGIN` before the first
            cloud to as long after the last.
        pose_types: topic -> message type of those topics (``BagClouds.pose_topics``); a
            topic missing here is published as tf2_msgs/TFMessage.
        topic: topic of the clouds.
        rate: playback speed factor (> 0): 2 plays twice as fast.
        loop: start again after the last scan (stamps moved on by the recording's length
            each time), until interrupted.
        reliable: reliable QoS for the clouds (else best effort, as sensor drivers publish).
        wait_subscriber: seconds to wait for a subscriber of the clouds (0: don't).
        wait_node: after the last cloud, the node's diagnostics are read until they count
            every cloud published, or until they counted no more for this many seconds (a
            node still taking clouds in is waited for); 0: don't read them.
        window: ``(first, last)`` stamps (ns) of the clouds, when they are a window of the
            recording: only the poses within :data:`TRANSFORM_MARGIN` of it are sent.
        progress: called with the number of scans published after each one.

    Returns:
        ``published`` (scans), ``transforms`` (published), ``seconds`` (wall time),
        ``subscribers``, ``topic``, ``pose_topics`` (published), ``received`` (a line: how
        many clouds the node counted, from its /diagnostics), ``warnings`` (lines: clouds
        that never reached the node, and why that may be), ``lost`` (True when the node's
        diagnostics counted fewer clouds than were published).

    Raises:
        InputError: a non-positive rate, or no subscriber within ``wait_subscriber``.
    """
    import rclpy
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    from sensor_msgs.msg import PointCloud2

    import msg_adapters as ma
    from msg_adapters import transforms as mt
    from msg_adapters.bag_io import ODOMETRY, TF_TYPES, TFMESSAGE

    if not rate > 0:
        raise InputError(f'--rate must be > 0, got {rate}')
    if not callable(scans):
        recorded = list(scans)
        scans = lambda: iter(recorded)  # noqa: E731 - one lap of a list
    margin = int(TRANSFORM_MARGIN * 1e9)
    pose_types = dict(pose_types or {})
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('facade_replay', context=context)
    watch = None
    try:
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE) if reliable else qos_profile_sensor_data
        pub = node.create_publisher(PointCloud2, topic, qos)
        types = ma.rclpy_types()
        groups = _groups(transforms)
        ttypes = mt.transform_types_rclpy(require_tf2_msgs=any(pose_types.get(t, TFMESSAGE) in TF_TYPES
                                                               for _, t, _, _ in groups))
        pose_pubs: dict[str, tuple[Any, Callable[[list[Any]], Any]]] = {}
        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                             reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
        for _, name, static, _ in groups:
            if name in pose_pubs:
                continue
            kind = pose_types.get(name, TFMESSAGE)
            if kind in TF_TYPES:  # tf2_msgs/msg/TFMessage, ROS 1's tf/msg/tfMessage
                pose_pubs[name] = (node.create_publisher(ttypes.TFMessage, name, latched if static else 100),
                                   lambda ts: mt.tf_message(ts, ttypes))
            elif kind == ODOMETRY:
                pose_pubs[name] = (node.create_publisher(ttypes.Odometry, name, 100),
                                   lambda ts: mt.odometry_msg(ts[0], ttypes))
            else:
                pose_pubs[name] = (node.create_publisher(ttypes.TransformStamped, name, 100),
                                   lambda ts: mt.transform_stamped_msg(ts[0], ttypes))
        deadline = time.monotonic() + wait_subscriber
        while wait_subscriber > 0 and pub.get_subscription_count() == 0:
            if time.monotonic() > deadline:
                raise InputError(f'no subscriber on {pub.topic_name} within {wait_subscriber:g} s: '
                                 'is facade_mapper running (same ROS_DOMAIN_ID, its points remapped to this topic)?')
            time.sleep(0.05)
        if wait_node > 0:
            watch = _NodeWatch(node, context)
            watch.wait_for_values(min(wait_node, 3.0))
        before = watch.received() if watch is not None else None
        if wait_subscriber > 0:
            time.sleep(0.5)  # let the subscriber's side finish matching
        # Static transforms first, latched: all of a topic's in one message, as tf2's static broadcaster.
        statics: dict[str, dict[tuple[str, str], Any]] = {}
        for _, name, static, ts in groups:
            if static:
                for t in ts:
                    statics.setdefault(name, {})[(t.parent, t.child)] = t
        for name, table in statics.items():
            pose_pubs[name][0].publish(pose_pubs[name][1](list(table.values())))
        dynamic = sorted((g for g in groups if not g[2] and (window is None or window[0] - margin <= g[0]
                                                              <= window[1] + margin)), key=lambda g: g[0])
        published = sent_transforms = lap = 0
        largest = 0
        started = time.monotonic()
        shift, t0, length = 0, None, 0

        def wait_until(stamp: int) -> None:
            wait = lap_start + (stamp - t0) / 1e9 / rate - time.monotonic()
            if wait > 0:
                time.sleep(wait)

        def send_poses(upto: int) -> None:
            """Publish the dynamic poses not sent yet stamped up to ``upto``, each at its time."""
            nonlocal next_pose, sent_transforms
            while next_pose < len(dynamic) and dynamic[next_pose][0] <= upto:
                stamp, name, _, ts = dynamic[next_pose]
                wait_until(stamp)
                if shift:
                    ts = [mt.StampedTransform(t.parent, t.child, t.stamp_ns + shift, t.translation, t.rotation)
                          for t in ts]
                pose_pubs[name][0].publish(pose_pubs[name][1](ts))
                sent_transforms += len(ts)
                next_pose += 1

        while True:
            next_pose = 0
            lap_start = time.monotonic()
            first = last = None
            for stamp_ns, points, frame in scans():
                if first is None:
                    first = stamp_ns
                    while next_pose < len(dynamic) and dynamic[next_pose][0] < stamp_ns - margin:
                        next_pose += 1  # poses long before the first cloud
                    if t0 is None:  # the timeline starts with the first pose sent, or the first cloud
                        t0 = min(stamp_ns, dynamic[next_pose][0]) if next_pose < len(dynamic) else stamp_ns
                send_poses(stamp_ns)  # a pose before a cloud of the same stamp
                wait_until(stamp_ns)
                pub.publish(ma.pointcloud2_from_structured(points, stamp_ns=stamp_ns + shift, frame_id=frame,
                                                           msg_types=types))
                largest = max(largest, points.nbytes)
                last = stamp_ns
                published += 1
                if progress is not None:
                    progress(published)
            if last is not None:
                send_poses(last + margin)  # the poses just after the last cloud: the node interpolates to it
            lap += 1
            if not loop or first is None:
                break
            length = length or (last - first + int(1e8))  # the next lap's stamps follow this one's
            shift = lap * length
        if reliable:
            from rclpy.duration import Duration

            pub.wait_for_all_acked(Duration(seconds=10.0))
        seconds = time.monotonic() - started
        received, warnings, lost = _received(watch, before, published, wait_node, largest, reliable)
        return {'published': published, 'seconds': seconds, 'subscribers': pub.get_subscription_count(),
                'topic': pub.topic_name, 'transforms': sent_transforms + sum(len(t) for t in statics.values()),
                'pose_topics': sorted(pose_pubs), 'received': received, 'warnings': warnings, 'lost': lost}
    finally:
        if watch is not None:
            watch.close()
        node.destroy_node()
        rclpy.shutdown(context=context)


def _received(watch: _NodeWatch | None, before: int | None, published: int, wait_node: float, largest: int,
              reliable: bool) -> tuple[str, list[str], bool]:
    """The line saying how many clouds the node counted, warnings when some never reached it, and
    whether some did not (False when the node's count could not be read)."""
    if watch is None:
        return 'the node was not asked how many clouds it received (--wait-node 0)', [], False
    if before is None:
        return ('no facade_mapper diagnostics on /diagnostics: cannot tell how many clouds the node received '
                '(is it running in this ROS domain?)'), [], False
    # While the node's count still rises it is taking the clouds in (a node slower than the
    # recording reads them from its DDS queue long after the last was sent): wait until it
    # has them all, or until it counted none more for wait_node seconds.
    got, steady = watch.received() - before, time.monotonic()
    while got < published:
        time.sleep(0.2)
        now = watch.received() - before
        if now != got:
            got, steady = now, time.monotonic()
        elif time.monotonic() - steady > wait_node:
            break
    values = watch.values or {}
    line = (f'the node received {got:,} of the {published:,} clouds published (its diagnostics: '
            f'{values.get("clouds_mapped", "?")} mapped, {values.get("clouds_waiting", "?")} waiting, '
            f'{values.get("clouds_dropped", "?")} dropped, {values.get("clouds_rejected", "?")} rejected in all)')
    warnings = []
    if got < published:
        warnings.append(f'{published - got:,} of {published:,} clouds never reached the node')
        hint = dds_profile_hint(largest)
        if hint is not None:
            warnings.append(hint)
        elif not reliable:
            warnings.append('best-effort publishing (--best-effort) may lose clouds; the default is reliable')
    return line, warnings, got < published
