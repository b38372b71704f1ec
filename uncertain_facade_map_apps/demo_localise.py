"""The demo's last step: localise part of another drive against the map the node just built.

A ``facade_localizer`` node is started beside the running ``facade_mapper``; this process
plays the rest of the robot: for scans of campaign 1 (the other lane, the other direction)
spread along the drive, it publishes a prior pose perturbed like GNSS in a street canyon
(:func:`~uncertain_facade_map.evaluation.localisation.perturb`: 0.5-3 m, 1-5 degrees, seeded)
and the scan in the lidar frame (:func:`~uncertain_facade_map.simulation.export.sensor_scan`),
and reads the localiser's pose. The localiser asks the map only through ``query_points``.
It draws the trajectory (truth, priors, estimates) over the map's façades and the errors.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .ros_client import SpinningClient

ROOT = Path(__file__).resolve().parent.parent
#: Seconds of returns in one scan (the street's profile scanners give about 56,000 a second).
SCAN_SECONDS = 1.0
#: Points per scan at most (the localiser's batch: issue 28's figure is for 20,000).
SCAN_POINTS = 20_000


@dataclass
class Localised:
    """One scan's outcome: truth, prior and estimate ((4, 4) lidar -> map), the estimate's (6, 6)
    covariance, its horizontal and heading errors (m, degrees) and the latency from publishing the
    scan to receiving its pose (s)."""

    truth: np.ndarray
    prior: np.ndarray
    pose: np.ndarray
    covariance: np.ndarray
    horizontal: float
    heading: float
    latency: float


class _Robot(SpinningClient):
    """Publishes priors and scans, receives the localiser's poses (a context of its own)."""

    def __init__(self, domain: int) -> None:
        from geometry_msgs.msg import PoseWithCovarianceStamped
        from sensor_msgs.msg import PointCloud2

        super().__init__('demo_robot', domain)
        self.scan_pub = self.node.create_publisher(PointCloud2, 'scan', 10)
        self.prior_pub = self.node.create_publisher(PoseWithCovarianceStamped, 'prior_pose', 10)
        self.poses: dict[int, tuple[float, Any]] = {}
        self.got = threading.Condition()
        self.node.create_subscription(PoseWithCovarianceStamped, 'pose', self._pose_callback, 10)
        self._start()

    def _pose_callback(self, msg: Any) -> None:
        stamp = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
        with self.got:
            self.poses[stamp] = (time.monotonic(), msg)
            self.got.notify_all()

    def wait_subscribed(self, proc: subprocess.Popen, timeout: float = 60.0) -> None:
        deadline = time.monotonic() + timeout
        while self.scan_pub.get_subscription_count() == 0 or self.prior_pub.get_subscription_count() == 0:
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError('facade_localizer did not start (see facade_localizer.log)')
            time.sleep(0.1)

    def wait_pose(self, stamp: int, timeout: float) -> tuple[float, Any] | None:
        deadline = time.monotonic() + timeout
        with self.got:
            while stamp not in self.poses:
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self.got.wait(left)
            return self.poses[stamp]


def localise_drive(scene_name: str, out: Path, env: dict, scans: int = 12, seed: int = 0,
                   progress: Any = print) -> list[Localised]:
    """Localise ``scans`` scans of campaign 1 through a ``facade_localizer`` started here,
    against the ``query_points`` of the running mapper. Writes ``facade_localizer.yaml`` and
    ``facade_localizer.log`` into ``out``.

    Raises:
        RuntimeError: the node did not start, or answered no scan.
    """
    import msg_adapters as ma
    from msg_adapters.localisation import pose_with_covariance_msg, prior_from_msg
    from msg_adapters.transforms import transform_types_rclpy
    from uncertain_facade_map.evaluation.localisation import (
        centred_error,
        heading,
        perturb,
        prior_covariance,
        wrap_degrees,
    )
    from uncertain_facade_map.io.parameter_file import dump_config
    from uncertain_facade_map.params import LOCALIZER_NAME, Config
    from uncertain_facade_map.simulation.campaign import SCENE_SENSORS, SensorConfig, campaign, drive_duration
    from uncertain_facade_map.simulation.export import sensor_scan
    from uncertain_facade_map.simulation.scenes import build_scene

    scene = build_scene(scene_name)
    sensor = SCENE_SENSORS.get(scene_name, SensorConfig())
    duration = drive_duration(scene, campaign(scene, 1), sensor)
    starts = duration * 0.05 + (np.arange(scans) + 0.5) / scans * (duration * 0.9 - SCAN_SECONDS)
    rng = np.random.default_rng(seed)
    cases = [sensor_scan(scene, 1, sensor, float(t0), SCAN_SECONDS, SCAN_POINTS, rng) for t0 in starts]
    params = out / f'{LOCALIZER_NAME}.yaml'
    params.write_text(dump_config(Config(), LOCALIZER_NAME))
    log = open(out / f'{LOCALIZER_NAME}.log', 'wb')
    proc = subprocess.Popen([sys.executable, '-m', 'uncertain_facade_map_node.localizer', '--ros-args',
                             '--params-file', str(params)], env=env, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
    robot = _Robot(int(env.get('ROS_DOMAIN_ID', '0')))
    types, cloud_types = transform_types_rclpy(require_tf2_msgs=False), ma.rclpy_types()
    covariance = prior_covariance()
    done: list[Localised] = []
    try:
        robot.wait_subscribed(proc)
        for k, (xyz, truth, t_mid) in enumerate(cases):
            stamp = int(round(t_mid * 1e9))
            prior, _ = perturb(truth, rng)
            robot.prior_pub.publish(pose_with_covariance_msg('map', stamp, prior, covariance, types))
            time.sleep(0.1)  # the prior before its scan
            points = np.zeros(len(xyz), dtype=[('x', 'f4'), ('y', 'f4'), ('z', 'f4')])
            points['x'], points['y'], points['z'] = xyz.T
            sent = time.monotonic()
            robot.scan_pub.publish(ma.pointcloud2_from_structured(points, stamp_ns=stamp, frame_id='lidar',
                                                                  msg_types=cloud_types))
            got = robot.wait_pose(stamp, 120.0 if k == 0 else 30.0)  # the first waits for the map's reading
            if got is None:
                progress(f'      scan {k + 1}: no pose within the time allowed')
                continue
            estimate = prior_from_msg(got[1])
            d = centred_error(estimate.pose, truth)
            turn = wrap_degrees(np.rad2deg(heading(estimate.pose) - heading(truth)))
            done.append(Localised(truth, prior, estimate.pose, estimate.covariance, float(np.hypot(d[0], d[1])),
                                  float(abs(turn)), got[0] - sent))
    finally:
        robot.close()
        proc.send_signal(2)
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()
    if not done:
        raise RuntimeError(f'facade_localizer answered no scan; see {out / (LOCALIZER_NAME + ".log")}')
    return done


def plot_localisation(results: list[Localised], fmap: Any, path: Path) -> Path:
    """Top view of the façades with the true, prior and estimated positions (each estimate
    with its 95 % horizontal ellipse, magnified), and the errors per scan."""
    from matplotlib.patches import Ellipse

    from .plots import _figure, _save

    fig = _figure(12.0, 5.0)
    ax, bx = fig.subplots(1, 2, width_ratios=[2.2, 1])
    for f in fmap.facades:
        u0, u1 = f.plane_extent[:2]
        ends = f.frame.to_world(np.array([[u0, 0.0, 0.0], [u1, 0.0, 0.0]]))
        ax.plot(ends[:, 0], ends[:, 1], color='0.55', lw=2, solid_capstyle='butt')
    truth = np.array([r.truth[:3, 3] for r in results])
    prior = np.array([r.prior[:3, 3] for r in results])
    est = np.array([r.pose[:3, 3] for r in results])
    for p, t in zip(prior, truth):
        ax.plot([p[0], t[0]], [p[1], t[1]], color='tab:orange', lw=0.6, alpha=0.6)
    ax.scatter(prior[:, 0], prior[:, 1], s=14, color='tab:orange', label='prior (GNSS-like)')
    ax.scatter(truth[:, 0], truth[:, 1], s=40, facecolors='none', edgecolors='k', label='truth')
    ax.scatter(est[:, 0], est[:, 1], s=10, color='tab:blue', label='estimate')
    scale = 20.0
    for r in results:
        w, v = np.linalg.eigh(r.covariance[:2, :2])
        angle = np.degrees(np.arctan2(v[1, 1], v[0, 1]))
        width, height = 2 * scale * np.sqrt(5.991 * np.maximum(w[::-1], 0.0))
        ax.add_patch(Ellipse(r.pose[:2, 3], width, height, angle=angle, fill=False, color='tab:blue', lw=0.8))
    ax.set_aspect('equal')
    ax.set_xlabel('x (m, map frame)')
    ax.set_ylabel('y (m)')
    ax.set_title(f'facade_localizer on {len(results)} scans of another drive (95 % ellipses x{scale:g})')
    ax.legend(loc='best', fontsize=8)
    k = np.arange(1, len(results) + 1)
    bx.semilogy(k, [max(r.horizontal, 1e-4) for r in results], 'o-', color='tab:blue', label='horizontal error (m)')
    bx.semilogy(k, [np.linalg.norm(r.prior[:2, 3] - r.truth[:2, 3]) for r in results], 's', color='tab:orange',
                label='prior horizontal error (m)')
    bx.semilogy(k, [2 * np.sqrt(np.trace(r.covariance[:2, :2])) for r in results], '--', color='0.4',
                label='2 x estimated std (m)')
    bx.axhline(0.2, color='tab:red', lw=0.8, ls=':')
    bx.set_xlabel('scan')
    bx.set_title('errors')
    bx.legend(fontsize=8)
    return _save(fig, path, 130)


def summary(results: list[Localised]) -> str:
    """One line: horizontal error median / max, share within 0.2 m and 1 degree, latency median."""
    h = np.array([r.horizontal for r in results])
    g = np.array([r.heading for r in results])
    lat = np.array([r.latency for r in results[1:]] or [results[0].latency])
    return (f'{len(results)} scans of campaign 1: horizontal error median {np.median(h) * 100:.1f} cm (max '
            f'{h.max():.2f} m), {np.mean((h <= 0.2) & (g <= 1.0)):.0%} within 0.2 m and 1 deg; '
            f'{np.median(lat) * 1000:.0f} ms from a scan to its pose (median, service round trips included)')


__all__ = ['Localised', 'localise_drive', 'plot_localisation', 'summary']
