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
from uncertain_facade_map.simulation.campaign import SCENE_SENSORS, SensorConfig, campaign
from uncertain_facade_map.simulation.export import sensor_poses


def sensor_scan(scene, cloud, index: int, fraction: float, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) points in the lidar frame and the (4, 4) true pose (lidar -> map) of the window
    of ``n_points`` points starting ``fraction`` of the way through campaign ``index``'s cloud."""
    sensor = SCENE_SENSORS.get(scene.name, SensorConfig())
    order = np.argsort(cloud.points['time'], kind='stable')
    start = int(fraction * (len(order) - n_points))
    pts = cloud.points[order[start:start + n_points]]
    recorded, truth = sensor_poses(scene, campaign(scene, index), sensor, float(np.median(pts['time'])))
    xyz = np.stack([pts['x'], pts['y'], pts['z']], axis=1).astype(np.float64)
    return se3.transform_points(se3.inverse(recorded), xyz), truth
