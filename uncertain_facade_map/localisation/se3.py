"""Rigid motions: the exponential and logarithm of SO(3) and SE(3), and their left Jacobians.

A twist ``xi = (rho, phi)`` is (6,): a translational part ``rho`` (metres) then a rotation
vector ``phi`` (radians, axis times angle), the order of a ROS pose covariance
(x, y, z, rotation about X, Y, Z). ``se3_exp(xi)`` is the (4, 4) homogeneous matrix
``[[R(phi), J(phi) rho], [0, 1]]`` with ``J`` the left Jacobian of SO(3) (Barfoot, *State
Estimation for Robotics*, 2017, sections 7.1.3-7.1.5). Functions of vectors accept stacks
``(..., 3)`` where the signature says so; the rest work on one element.
"""

from __future__ import annotations

import numpy as np

__all__ = ['compose', 'inverse', 'se3_exp', 'se3_left_jacobian', 'se3_left_jacobian_inverse', 'se3_log', 'skew',
           'so3_exp', 'so3_left_jacobian', 'so3_left_jacobian_inverse', 'so3_log', 'transform_points']

#: Below this angle (radians) the series expansions replace the closed forms.
_SMALL = 1e-5


def skew(v: np.ndarray) -> np.ndarray:
    """The cross-product matrices ``[v]x`` (..., 3, 3) of vectors ``v`` (..., 3): ``[v]x @ u = v x u``."""
    v = np.asarray(v, dtype=np.float64)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def so3_exp(phi: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors ``phi`` (..., 3), radians (Rodrigues)."""
    phi = np.asarray(phi, dtype=np.float64)
    theta = np.linalg.norm(phi, axis=-1)[..., None, None]
    k = skew(phi)
    k2 = k @ k
    small = theta < _SMALL
    t = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(t) / t)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(t)) / t**2)
    return np.eye(3) + a * k + b * k2


def so3_log(rot: np.ndarray) -> np.ndarray:
    """The rotation vector (3,) of a rotation matrix (3, 3), angle in [0, pi]."""
    rot = np.asarray(rot, dtype=np.float64)
    vee = np.array([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]])
    sin2 = np.linalg.norm(vee)  # 2 sin(theta)
    cos = (np.trace(rot) - 1.0) / 2.0
    theta = float(np.arctan2(sin2 / 2.0, cos))  # precise at 0 and pi, unlike arccos
    if theta < _SMALL:
        return 0.5 * (1.0 + theta**2 / 6.0) * vee
    if np.pi - theta < 1e-3:  # near pi: the axis from the symmetric part, its sign from vee
        sym = (rot + rot.T) / 2.0 - cos * np.eye(3)
        col = int(np.argmax(np.diag(sym)))
        axis = sym[:, col] / np.linalg.norm(sym[:, col])
        if axis @ vee < 0:
            axis = -axis
        return theta * axis
    return theta / sin2 * vee


def so3_left_jacobian(phi: np.ndarray) -> np.ndarray:
    """The left Jacobian (3, 3) of SO(3) at ``phi`` (3,): ``exp(phi + d) ~ exp(J d) exp(phi)``."""
    phi = np.asarray(phi, dtype=np.float64)
    theta = float(np.linalg.norm(phi))
    k = skew(phi)
    if theta < _SMALL:
        return np.eye(3) + 0.5 * k + k @ k / 6.0
    return (np.eye(3) + (1.0 - np.cos(theta)) / theta**2 * k + (theta - np.sin(theta)) / theta**3 * k @ k)


def so3_left_jacobian_inverse(phi: np.ndarray) -> np.ndarray:
    """The inverse (3, 3) of :func:`so3_left_jacobian` in closed form (|phi| < 2 pi)."""
    phi = np.asarray(phi, dtype=np.float64)
    theta = float(np.linalg.norm(phi))
    k = skew(phi)
    if theta < _SMALL:
        return np.eye(3) - 0.5 * k + k @ k / 12.0
    half = theta / 2.0
    return np.eye(3) - 0.5 * k + (1.0 - half / np.tan(half)) / theta**2 * k @ k


def _q_matrix(rho: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Barfoot's Q(rho, phi) (eq. 7.86), the upper-right block of the SE(3) left Jacobian."""
    theta = float(np.linalg.norm(phi))
    r, p = skew(rho), skew(phi)
    pr, rp, prp = p @ r, r @ p, p @ r @ p
    if theta < _SMALL:
        c1, c2, c3 = 1.0 / 6.0, -1.0 / 24.0, -1.0 / 120.0  # limits of the coefficients below
    else:
        s, c = np.sin(theta), np.cos(theta)
        c1 = (theta - s) / theta**3
        c2 = (theta**2 + 2.0 * c - 2.0) / (2.0 * theta**4)
        c3 = (2.0 * theta - 3.0 * s + theta * c) / (2.0 * theta**5)
    return (0.5 * r + c1 * (pr + rp + prp) + c2 * (p @ pr + rp @ p - 3.0 * prp) + c3 * (prp @ p + p @ prp))


def se3_left_jacobian(xi: np.ndarray) -> np.ndarray:
    """The left Jacobian (6, 6) of SE(3) at ``xi`` (6,): ``exp(xi + d) ~ exp(J d) exp(xi)``."""
    xi = np.asarray(xi, dtype=np.float64)
    jac = so3_left_jacobian(xi[3:])
    out = np.zeros((6, 6))
    out[:3, :3] = out[3:, 3:] = jac
    out[:3, 3:] = _q_matrix(xi[:3], xi[3:])
    return out


def se3_left_jacobian_inverse(xi: np.ndarray) -> np.ndarray:
    """The inverse (6, 6) of :func:`se3_left_jacobian` in closed form: ``log(exp(d) exp(xi)) ~ xi + J^-1 d``."""
    xi = np.asarray(xi, dtype=np.float64)
    inv = so3_left_jacobian_inverse(xi[3:])
    out = np.zeros((6, 6))
    out[:3, :3] = out[3:, 3:] = inv
    out[:3, 3:] = -inv @ _q_matrix(xi[:3], xi[3:]) @ inv
    return out


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """The (4, 4) rigid motion of a twist ``xi = (rho, phi)`` (6,)."""
    xi = np.asarray(xi, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = so3_exp(xi[3:])
    out[:3, 3] = so3_left_jacobian(xi[3:]) @ xi[:3]
    return out


def se3_log(pose: np.ndarray) -> np.ndarray:
    """The twist (6,) ``(rho, phi)`` of a (4, 4) rigid motion (rotation angle below pi)."""
    pose = np.asarray(pose, dtype=np.float64)
    phi = so3_log(pose[:3, :3])
    return np.concatenate([so3_left_jacobian_inverse(phi) @ pose[:3, 3], phi])


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` of (4, 4) rigid motions, re-orthonormalised (SVD) against drift."""
    out = np.asarray(a, dtype=np.float64) @ np.asarray(b, dtype=np.float64)
    u, _, vt = np.linalg.svd(out[:3, :3])
    out[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    return out


def inverse(pose: np.ndarray) -> np.ndarray:
    """The inverse (4, 4) of a rigid motion, from its transpose (no matrix inversion)."""
    pose = np.asarray(pose, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = pose[:3, :3].T
    out[:3, 3] = -pose[:3, :3].T @ pose[:3, 3]
    return out


def transform_points(pose: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """Points (N, 3) moved by a (4, 4) rigid motion: ``pose[:3, :3] @ x + pose[:3, 3]`` per row."""
    return np.asarray(xyz, dtype=np.float64) @ pose[:3, :3].T + pose[:3, 3]
