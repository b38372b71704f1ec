"""Publish recorded scans to a running facade_mapper, with their recorded timing.

The wheel set has no ``ros2 bag play``; ``uncertain-facade-map replay --mode publish``
reads a bag with rosbags (:mod:`msg_adapters.bag_io`) and republishes its PointCloud2
scans through rclpy with this module.
"""

from __future__ import annotations

import time
from typing import Any, Callable, Sequence

import numpy as np

from uncertain_facade_map.errors import InputError


def select_window(scans: Sequence[tuple[int, np.ndarray]], start: float = 0.0,
                  duration: float | None = None) -> list[tuple[int, np.ndarray]]:
    """The scans from ``start`` seconds after the first one, for ``duration`` seconds.

    Args:
        scans: ``(stamp_ns, points)`` in recorded order.
        start: seconds into the recording, >= 0.
        duration: seconds to take, > 0; None for the rest.

    Returns:
        The scans whose stamp lies in the window, in recorded order.

    Raises:
        InputError: a negative start, a non-positive duration, or an empty window.
    """
    if start < 0:
        raise InputError(f'--start must be >= 0 s, got {start}')
    if duration is not None and duration <= 0:
        raise InputError(f'--duration must be > 0 s, got {duration}')
    if not scans:
        raise InputError('the recording has no scans')
    t0 = scans[0][0] + int(round(start * 1e9))
    t1 = None if duration is None else t0 + int(round(duration * 1e9))
    out = [s for s in scans if s[0] >= t0 and (t1 is None or s[0] < t1)]
    if not out:
        length = (scans[-1][0] - scans[0][0]) / 1e9
        raise InputError(f'no scans between {start} s and {"the end" if t1 is None else f"{start + duration} s"} '
                         f'of a recording of {length:.1f} s')
    return out


def publish_scans(scans: Sequence[tuple[int, np.ndarray]], *, topic: str = 'points', frame_id: str = 'map',
                  rate: float = 1.0, loop: bool = False, reliable: bool = True, wait_subscriber: float = 10.0,
                  progress: Callable[[int], None] | None = None) -> dict[str, Any]:
    """Publish scans as PointCloud2 with their recorded spacing divided by ``rate``.

    Args:
        scans: ``(stamp_ns, points)`` in recorded order (structured arrays in ``frame_id``).
        topic: topic to publish on.
        frame_id: header frame of the clouds.
        rate: playback speed factor (> 0): 2 plays twice as fast.
        loop: start again from the first scan after the last, until interrupted.
        reliable: reliable QoS (else best effort, as sensor drivers publish).
        wait_subscriber: seconds to wait for a subscriber before publishing (0: don't).
        progress: called with the number of scans published after each one.

    Returns:
        ``{'published': scans published, 'seconds': wall time, 'subscribers': count}``.

    Raises:
        InputError: a non-positive rate, or no subscriber within ``wait_subscriber``.
    """
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    from sensor_msgs.msg import PointCloud2

    import msg_adapters as ma

    if not rate > 0:
        raise InputError(f'--rate must be > 0, got {rate}')
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('facade_replay', context=context)
    try:
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE) if reliable else qos_profile_sensor_data
        pub = node.create_publisher(PointCloud2, topic, qos)
        types = ma.rclpy_types()
        deadline = time.monotonic() + wait_subscriber
        while wait_subscriber > 0 and pub.get_subscription_count() == 0:
            if time.monotonic() > deadline:
                raise InputError(f'no subscriber on {pub.topic_name} within {wait_subscriber:g} s: '
                                 'is facade_mapper running (same ROS_DOMAIN_ID)?')
            time.sleep(0.05)
        if wait_subscriber > 0:
            time.sleep(0.5)  # let the subscriber's side finish matching
        published = 0
        started = time.monotonic()
        while True:
            t0 = scans[0][0]
            lap = time.monotonic()
            for stamp_ns, points in scans:
                due = lap + (stamp_ns - t0) / 1e9 / rate
                wait = due - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
                pub.publish(ma.pointcloud2_from_structured(points, stamp_ns=stamp_ns, frame_id=frame_id,
                                                           msg_types=types))
                published += 1
                if progress is not None:
                    progress(published)
            if not loop:
                break
        # Reliable delivery of the last scans before the node goes away.
        if reliable:
            from rclpy.duration import Duration

            pub.wait_for_all_acked(Duration(seconds=10.0))
        return {'published': published, 'seconds': time.monotonic() - started,
                'subscribers': pub.get_subscription_count()}
    finally:
        node.destroy_node()
        rclpy.shutdown(context=context)
