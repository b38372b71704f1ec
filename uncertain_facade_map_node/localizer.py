"""The ``facade_localizer`` node: a scan's 6-DoF pose against the uncertain façade map.

A thin shell around the core's :func:`~uncertain_facade_map.localisation.localise`: it asks
the map as any client would, through the mapper's ``query_points`` service
(``localizer.query_service``), in batches of ``localise.batch_points`` points.

Topics (names relative, remap with ``--ros-args -r``):

- subscribed: ``scan`` (sensor_msgs/PointCloud2 in the sensor frame; sensor-data QoS, the
  newest scan only: a scan that arrives while one is being localised replaces the waiting
  one) and ``prior_pose`` (geometry_msgs/PoseWithCovarianceStamped: the pose of the scan's
  frame in ``localizer.map_frame``, from GNSS, odometry or an operator; an all-zero
  covariance means "unknown" and takes ``localise.prior_std_*``);
- published: ``pose`` (PoseWithCovarianceStamped of the scan's frame in the map frame, at the
  scan's stamp, with the covariance of the solution), with ``localizer.publish_tf`` the
  transform map -> scan frame on ``/tf``, and every second ``/diagnostics`` (the counters
  below, and the last solve's time, points used, rounds, whether it converged and its
  status: ``ambiguous`` when another pose explains the scan nearly as well, ``inconsistent``
  when its residuals exceed their variances; WARN while scans fail, wait for a prior or come
  out ambiguous or inconsistent, whose poses carry a covariance that says so).

The prior of a scan is the newest ``prior_pose`` when it is at most ``localizer.prior_max_age``
seconds from the scan's stamp and newer than the last estimate; otherwise the last estimate
moved on by the last estimated motion (constant velocity over the stamps' gap), its
covariance grown by ``localizer.motion_std_*`` per second. With neither, the scan waits
for a prior (counted once as ``scans_without_prior``): it is localised when a prior pose
arrives (a prior often comes a little after its scan) and given up when a newer scan comes.

No exception escapes a callback: a failure (the map service missing, a bad scan or prior)
is logged and counted, and the node goes on with the next scan.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2

import msg_adapters as ma
from msg_adapters import localisation as ml
from msg_adapters import map_messages as mm
from msg_adapters import transforms as mt
from uncertain_facade_map.errors import FacadeMapError, InputError
from uncertain_facade_map.io.scans import points_xyz
from uncertain_facade_map.localisation import PoseEstimate, covariance_from_std, localise
from uncertain_facade_map.localisation.se3 import inverse, se3_exp, se3_log
from uncertain_facade_map.params import LOCALIZER_NAME, LOCALIZER_SECTIONS, Config
from uncertain_facade_map.srv import QueryPoints
from uncertain_facade_map_node.runtime import declare_config, spin


class FacadeLocalizerNode(Node):
    """Localises each scan against the map served by ``query_points``."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(LOCALIZER_NAME, **kwargs)
        try:
            self.config: Config = declare_config(self, LOCALIZER_SECTIONS)
        except InputError as exc:
            self.get_logger().fatal(f'bad parameters: {exc}')
            raise
        cfg = self.config.localizer
        self.types = mt.transform_types_rclpy(require_tf2_msgs=cfg.publish_tf)
        self.counters = {'scans_received': 0, 'scans_localised': 0, 'scans_failed': 0, 'scans_without_prior': 0,
                         'scans_skipped': 0, 'priors_received': 0, 'priors_rejected': 0, 'scans_ambiguous': 0,
                         'scans_inconsistent': 0}
        self._lock = threading.Lock()
        self._prior: ml.PosePrior | None = None
        self._last: tuple[int, np.ndarray, np.ndarray] | None = None  # (stamp ns, pose, covariance)
        self._velocity: np.ndarray | None = None  # (6,) twist of the last motion per second, sensor frame
        self._pending: Any = None  # the newest scan waiting
        self._waiting: Any = None  # a scan that found no prior, tried again when one arrives
        self._wake = threading.Event()
        self.last_estimate: PoseEstimate | None = None

        self.client = self.create_client(QueryPoints, cfg.query_service, callback_group=ReentrantCallbackGroup())
        qos = QoSProfile(depth=2, reliability=qos_profile_sensor_data.reliability,
                         durability=qos_profile_sensor_data.durability, history=qos_profile_sensor_data.history)
        self.create_subscription(PointCloud2, 'scan', self.scan_callback, qos,
                                 callback_group=MutuallyExclusiveCallbackGroup())
        self.create_subscription(PoseWithCovarianceStamped, 'prior_pose', self.prior_callback, 10,
                                 callback_group=MutuallyExclusiveCallbackGroup())
        self.pub_pose = self.create_publisher(PoseWithCovarianceStamped, 'pose', 10)
        self.pub_tf = None
        if cfg.publish_tf:
            from tf2_msgs.msg import TFMessage

            self.pub_tf = self.create_publisher(TFMessage, '/tf', 100)
        from diagnostic_msgs.msg import DiagnosticArray

        self.diag_types = mm.rclpy_map_types()
        self.pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self._reported: dict[str, int] = {}
        self.create_timer(1.0, self.diagnostics_callback, callback_group=MutuallyExclusiveCallbackGroup())
        self._thread = threading.Thread(target=self._run, name='localizer', daemon=True)
        self._stop = False
        self._thread.start()
        self.get_logger().info(f'localising scans on "{self.resolve_topic_name("scan")}" in frame "{cfg.map_frame}" '
                               f'against the map of service "{cfg.query_service}"')

    # -- input ------------------------------------------------------------------------
    def prior_callback(self, msg: Any) -> None:
        """Keep the newest prior pose (refused if it is not in the map frame or cannot be right)."""
        try:
            prior = ml.prior_from_msg(msg)
            if prior.frame_id != self.config.localizer.map_frame:
                raise InputError(f'prior pose is in frame "{prior.frame_id}", not the map frame '
                                 f'"{self.config.localizer.map_frame}"')
        except InputError as exc:
            with self._lock:
                self.counters['priors_rejected'] += 1
            self.get_logger().warning(f'prior rejected: {exc}', throttle_duration_sec=5.0)
            return
        with self._lock:
            self.counters['priors_received'] += 1
            self._prior = prior
            waiting = self._waiting is not None
        if waiting:
            self._wake.set()

    def scan_callback(self, msg: Any) -> None:
        """Hand the scan to the localising thread (a scan still waiting is replaced)."""
        with self._lock:
            self.counters['scans_received'] += 1
            if self._pending is not None:
                self.counters['scans_skipped'] += 1
            self._pending = msg
            if self._waiting is not None:  # the scan waiting for a prior is given up for the newer one
                self.counters['scans_skipped'] += 1
                self._waiting = None
        self._wake.set()

    def diagnostics_callback(self) -> None:
        """Publish the counters and the last solve (WARN while scans fail or wait for a prior)."""
        with self._lock:
            values: dict[str, Any] = dict(self.counters)
        est = self.last_estimate
        if est is not None:
            values.update(last_seconds=round(est.seconds, 4), last_points_used=est.points_used,
                          last_queries=est.queries, last_converged=est.converged, last_status=est.status,
                          last_residual_ratio=round(est.residual_ratio, 3))
        kinds = ('scans_failed', 'scans_without_prior', 'scans_ambiguous', 'scans_inconsistent')
        new = {k: values[k] - self._reported.get(k, 0) for k in kinds}
        troubles = sum(new.values())
        self._reported = {k: int(values[k]) for k in kinds}
        message = ('localising' if not troubles else f'in the last second: {new["scans_failed"]} scans failed, '
                   f'{new["scans_without_prior"]} waited for a prior, {new["scans_ambiguous"]} were ambiguous, '
                   f'{new["scans_inconsistent"]} inconsistent with the map')
        self.pub_diag.publish(mm.diagnostic_array(f'{LOCALIZER_NAME}: pose', 1 if troubles else 0, message, values,
                                                  LOCALIZER_NAME, self.get_clock().now().nanoseconds,
                                                  self.diag_types))

    # -- the localising thread --------------------------------------------------------------
    def _run(self) -> None:
        while not self._stop:
            self._wake.wait(0.5)
            self._wake.clear()
            with self._lock:
                msg, self._pending = self._pending, None
                retry = msg is None
                if retry:
                    msg, self._waiting = self._waiting, None
            if msg is None:
                continue
            try:
                if not self._localise(msg):
                    with self._lock:
                        if self._pending is None:
                            self._waiting = msg
                        else:
                            self.counters['scans_skipped'] += 1
                        if not retry:
                            self.counters['scans_without_prior'] += 1
                    if not retry:
                        self.get_logger().warning('scan waits for a prior pose on "prior_pose"',
                                                  throttle_duration_sec=5.0)
            except Exception as exc:  # noqa: BLE001 - the thread must live on: logged and counted
                with self._lock:
                    self.counters['scans_failed'] += 1
                kind = '' if isinstance(exc, (FacadeMapError, TimeoutError)) else f'{type(exc).__name__}: '
                self.get_logger().error(f'scan not localised: {kind}{exc}', throttle_duration_sec=5.0)

    def _prior_for(self, stamp_ns: int) -> tuple[np.ndarray, np.ndarray] | None:
        """The prior pose and covariance of a scan at ``stamp_ns`` (see the module)."""
        cfg, loc = self.config.localizer, self.config.localise
        with self._lock:
            prior, last, velocity = self._prior, self._last, self._velocity
        default = covariance_from_std([*loc.prior_position_std, *np.deg2rad(loc.prior_rotation_std)])
        fresh = prior is not None and abs(prior.stamp_ns - stamp_ns) <= cfg.prior_max_age * 1e9 and \
            (last is None or prior.stamp_ns > last[0])
        if fresh:
            return prior.pose, default if prior.covariance is None else prior.covariance
        if last is None:
            return None
        dt = max(0.0, (stamp_ns - last[0]) * 1e-9)
        # Constant velocity in the sensor's own frame (a vehicle keeps its speed and turn rate).
        pose = last[1] if velocity is None else last[1] @ se3_exp(velocity * dt)
        growth = np.r_[np.full(3, cfg.motion_std_position) ** 2, np.full(3, np.deg2rad(cfg.motion_std_rotation)) ** 2]
        return pose, last[2] + np.diag(growth) * max(dt, 1e-3)

    def _localise(self, msg: Any) -> bool:
        """Localise the scan and publish its pose; False (nothing done) when it has no prior."""
        stamp = ma.header_stamp_ns(msg.header)
        xyz = points_xyz(ma.structured_from_pointcloud2(msg))
        xyz = xyz[np.isfinite(xyz).all(axis=1)]
        prior = self._prior_for(stamp)
        if prior is None:
            return False
        estimate = localise(xyz, prior[0], prior[1], self._query, self.config.localise)
        self.last_estimate = estimate
        with self._lock:
            if self._last is not None and stamp > self._last[0]:
                step = inverse(self._last[1]) @ estimate.pose  # the motion in the last pose's frame
                self._velocity = se3_log(step) / ((stamp - self._last[0]) * 1e-9)
            self._last = (stamp, estimate.pose, estimate.covariance)
            self.counters['scans_localised'] += 1
            if estimate.status in ('ambiguous', 'inconsistent'):
                self.counters[f'scans_{estimate.status}'] += 1
        frame = self.config.localizer.map_frame
        self.pub_pose.publish(ml.pose_with_covariance_msg(frame, stamp, estimate.pose, estimate.covariance,
                                                          self.types))
        if self.pub_tf is not None:
            from uncertain_facade_map.transforms.rotations import from_matrix

            child = self.config.localizer.tf_child or str(msg.header.frame_id)
            t = mt.StampedTransform(frame, child, stamp, estimate.pose[:3, 3], from_matrix(estimate.pose[:3, :3]))
            self.pub_tf.publish(mt.tf_message([t], self.types))
        self.get_logger().debug(f'scan at {stamp * 1e-9:.3f} s: {estimate.points_used} points, '
                                f'{estimate.iterations} iterations, {estimate.seconds * 1e3:.0f} ms')
        return True

    def _query(self, xyz: np.ndarray) -> Any:
        """Ask the map at (M, 3) map-frame points through the service (blocking this thread)."""
        timeout = self.config.localizer.query_timeout
        if not self.client.wait_for_service(timeout_sec=timeout):
            raise InputError(f'the map service "{self.config.localizer.query_service}" is not available')
        done = threading.Event()
        future = self.client.call_async(ml.fill_query_request(QueryPoints.Request(), xyz))
        future.add_done_callback(lambda _f: done.set())
        if not done.wait(timeout):
            future.cancel()
            raise TimeoutError(f'the map service did not answer within {timeout} s')
        return ml.query_answers(future.result(), len(xyz))

    def destroy_node(self) -> None:
        self._stop = True
        self._wake.set()
        self._thread.join(5.0)
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    """Run the node until Ctrl-C or shutdown (``ros2 run uncertain_facade_map facade_localizer``)."""
    spin(FacadeLocalizerNode, LOCALIZER_NAME, args, threads=3)

if __name__ == '__main__':
    main()
