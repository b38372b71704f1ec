"""Poses as a user writes them: x, y, z (metres) and roll, pitch, yaw (radians), the ROS
convention (``R = Rz(yaw) Ry(pitch) Rx(roll)``, fixed axes X, Y, Z), and prior covariances
from standard deviations."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ['covariance_from_std', 'pose_from_xyzrpy', 'xyzrpy_from_pose']


def pose_from_xyzrpy(xyzrpy: np.ndarray) -> np.ndarray:
    """(4, 4) sensor -> map from (6,) x, y, z (m), roll, pitch, yaw (rad)."""
    xyzrpy = np.asarray(xyzrpy, dtype=np.float64)
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler('xyz', xyzrpy[3:]).as_matrix()  # extrinsic x, y, z = Rz Ry Rx
    pose[:3, 3] = xyzrpy[:3]
    return pose


def xyzrpy_from_pose(pose: np.ndarray) -> np.ndarray:
    """(6,) x, y, z (m), roll, pitch, yaw (rad) of a (4, 4) pose."""
    pose = np.asarray(pose, dtype=np.float64)
    return np.concatenate([pose[:3, 3], Rotation.from_matrix(pose[:3, :3]).as_euler('xyz')])


def covariance_from_std(std: np.ndarray) -> np.ndarray:
    """(6, 6) diagonal covariance from (6,) standard deviations (m, m, m, rad, rad, rad)."""
    return np.diag(np.asarray(std, dtype=np.float64) ** 2)
