"""Scans of a simulated campaign in the sensor frame, with the true pose, for the localiser's
tests on a real map.

A scan is the campaign's points (all classes: ground, cars and trees as well as walls) of a
time window holding ``n_points`` points, expressed in the frame of the lidar (scanner 0's
mount) at the window's middle: a de-skewed scan, whose true pose against the map of
campaign 0 is the vehicle's path pose at that time (without the campaign's registration
offset, which moved its recorded points, not the world) times the mount.
"""

from __future__ import annotations

import numpy as np

from uncertain_facade_map.localisation import se3
from uncertain_facade_map.simulation.campaign import SCENE_SENSORS, SensorConfig, campaign, poses
from uncertain_facade_map.simulation.export import vehicle_poses


def _vehicle(position: np.ndarray, yaw: float, mount: np.ndarray) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = se3.so3_exp(np.array([0.0, 0.0, yaw]))
    pose[:3, 3] = position + pose[:3, :3] @ mount
    return pose


def sensor_scan(scene, cloud, index: int, fraction: float, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) points in the lidar frame and the (4, 4) true pose (lidar -> map) of the window
    of ``n_points`` points starting ``fraction`` of the way through campaign ``index``'s cloud."""
    sensor = SCENE_SENSORS.get(scene.name, SensorConfig())
    drive = campaign(scene, index)
    order = np.argsort(cloud.points['time'], kind='stable')
    start = int(fraction * (len(order) - n_points))
    pts = cloud.points[order[start:start + n_points]]
    t_mid = float(np.median(pts['time']))
    mount = np.asarray(sensor.mount[0], dtype=np.float64)
    stamp = np.array([int(round(t_mid * 1e9))], dtype=np.int64)
    pos_off, quat = vehicle_poses(scene, drive, sensor, stamp)  # with the registration offset: the recorded frame
    recorded = _vehicle(pos_off[0], 2.0 * np.arctan2(quat[0, 2], quat[0, 3]), mount)
    xy, yaw = poses(scene, drive, sensor, np.array([t_mid - drive.start_time]))
    truth = _vehicle(np.array([xy[0, 0], xy[0, 1], 0.0]), float(yaw[0]), mount)
    xyz = np.stack([pts['x'], pts['y'], pts['z']], axis=1).astype(np.float64)
    return se3.transform_points(se3.inverse(recorded), xyz), truth
