"""Vectorised unit-quaternion helpers, quaternions in ROS order ``(x, y, z, w)``.

Every function takes arrays of shape ``(..., 4)`` (quaternions) or ``(..., 3)``
(vectors), float64, and broadcasts over the leading axes, so one call handles a single
rotation or 10^5 of them. A quaternion ``q = (x, y, z, w) = (sin(a/2) u, cos(a/2))``
rotates by the angle ``a`` about the unit axis ``u``; ``q`` and ``-q`` are the same
rotation. Rotation matrices act on column vectors: ``v' = R @ v``.

The interpolation :func:`slerp` is Shoemake's spherical linear interpolation (K. Shoemake,
"Animating rotation with quaternion curves", SIGGRAPH '85, Computer Graphics 19(3),
pp. 245-254, 1985):

    slerp(q0, q1; u) = sin((1 - u) theta) / sin(theta) q0 + sin(u theta) / sin(theta) q1,
    cos(theta) = q0 . q1,

the constant-angular-velocity path on the unit sphere, taken the short way (``q1`` is
negated when ``q0 . q1 < 0``, which is the same rotation), as tf2 does.
"""

from __future__ import annotations

import numpy as np

from uncertain_facade_map.errors import InputError

#: Below this angle (radians, between the two quaternions on the 4-sphere) :func:`slerp`
#: uses the normalised linear interpolation: the two differ by O(theta^3) there.
SLERP_LERP_ANGLE = 1e-9


def _as_quaternions(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    if q.shape[-1:] != (4,):
        raise InputError(f'quaternions have a last axis of 4 (x, y, z, w), got shape {q.shape}')
    return q


def normalise(q: np.ndarray) -> np.ndarray:
    """Unit quaternions of the same rotations.

    Args:
        q: (..., 4) quaternions (x, y, z, w), any non-zero length.

    Returns:
        (..., 4) float64, each of unit length (a zero quaternion gives NaN).
    """
    q = _as_quaternions(q)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices of quaternions.

    Uses the homogeneous form (``s = 2 / |q|^2``), so a quaternion of any non-zero length
    gives the rotation of its normalised self.

    Args:
        q: (..., 4) quaternions (x, y, z, w).

    Returns:
        (..., 3, 3) float64 rotation matrices, ``v' = R @ v``.
    """
    q = _as_quaternions(q)
    x, y, z, w = np.moveaxis(q, -1, 0)
    s = 2.0 / (x * x + y * y + z * z + w * w)
    xx, yy, zz = s * x * x, s * y * y, s * z * z
    xy, xz, yz = s * x * y, s * x * z, s * y * z
    wx, wy, wz = s * w * x, s * w * y, s * w * z
    out = np.empty(q.shape[:-1] + (3, 3))
    out[..., 0, 0] = 1.0 - (yy + zz)
    out[..., 0, 1] = xy - wz
    out[..., 0, 2] = xz + wy
    out[..., 1, 0] = xy + wz
    out[..., 1, 1] = 1.0 - (xx + zz)
    out[..., 1, 2] = yz - wx
    out[..., 2, 0] = xz - wy
    out[..., 2, 1] = yz + wx
    out[..., 2, 2] = 1.0 - (xx + yy)
    return out


def from_matrix(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternions of rotation matrices, by Shepperd's method, with ``w >= 0``.

    Shepperd's method (S. W. Shepperd, "Quaternion from rotation matrix", Journal of
    Guidance and Control 1(3), 1978) takes the square root of the largest of ``4 w^2,
    4 x^2, 4 y^2, 4 z^2`` so that it stays accurate near 180 degrees.

    Args:
        rotation: (..., 3, 3) rotation matrices.

    Returns:
        (..., 4) float64 unit quaternions (x, y, z, w) with ``w >= 0``.
    """
    m = np.asarray(rotation, dtype=np.float64)
    if m.shape[-2:] != (3, 3):
        raise InputError(f'rotation matrices are (..., 3, 3), got shape {m.shape}')
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    # candidates 4w^2, 4x^2, 4y^2, 4z^2 from the trace and the diagonal
    cand = np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    pick = np.argmax(cand, axis=-1)
    r = np.sqrt(np.maximum(np.take_along_axis(cand, pick[..., None], -1)[..., 0], 0.0))  # 2|component|
    d = 0.5 / r
    a12, a21 = m[..., 1, 2], m[..., 2, 1]
    a02, a20 = m[..., 0, 2], m[..., 2, 0]
    a01, a10 = m[..., 0, 1], m[..., 1, 0]
    rows = {
        0: ((a21 - a12) * d, (a02 - a20) * d, (a10 - a01) * d, 0.5 * r),
        1: (0.5 * r, (a01 + a10) * d, (a02 + a20) * d, (a21 - a12) * d),
        2: ((a01 + a10) * d, 0.5 * r, (a12 + a21) * d, (a02 - a20) * d),
        3: ((a02 + a20) * d, (a12 + a21) * d, 0.5 * r, (a10 - a01) * d),
    }
    out = np.zeros(m.shape[:-2] + (4,))
    for k, comps in rows.items():
        sel = pick == k
        if np.any(sel):
            out[sel] = np.stack([c[sel] for c in comps], -1)
    out /= np.linalg.norm(out, axis=-1, keepdims=True)
    return np.where(out[..., 3:4] < 0, -out, out)


def multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products ``a * b``: the rotation ``b`` first, then ``a``.

    ``to_matrix(multiply(a, b)) == to_matrix(a) @ to_matrix(b)``.

    Args:
        a, b: (..., 4) quaternions (x, y, z, w), broadcast against each other.

    Returns:
        (..., 4) float64.
    """
    a, b = _as_quaternions(a), _as_quaternions(b)
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack([
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ], -1)


def conjugate(q: np.ndarray) -> np.ndarray:
    """Conjugates ``(-x, -y, -z, w)``: the inverse rotations of unit quaternions.

    Args:
        q: (..., 4) quaternions.

    Returns:
        (..., 4) float64.
    """
    q = _as_quaternions(q)
    return q * np.array([-1.0, -1.0, -1.0, 1.0])


def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors by unit quaternions: ``v' = q v q*``.

    Computed as ``v + 2 w (u x v) + 2 u x (u x v)`` with ``u = (x, y, z)``.

    Args:
        q: (..., 4) unit quaternions (x, y, z, w).
        v: (..., 3) vectors; broadcast against ``q``'s leading axes.

    Returns:
        (..., 3) float64 rotated vectors.
    """
    q = _as_quaternions(q)
    v = np.asarray(v, dtype=np.float64)
    u, w = q[..., :3], q[..., 3:4]
    c = np.cross(u, v)
    return v + 2.0 * w * c + 2.0 * np.cross(u, c)


def slerp(q0: np.ndarray, q1: np.ndarray, u: np.ndarray | float) -> np.ndarray:
    """Spherical linear interpolation (Shoemake 1985), shortest path, vectorised.

    The angle is computed as ``theta = 2 atan2(|q1 - q0|, |q1 + q0|)``, accurate for every
    angle (``arccos`` of the dot product loses half the digits near 0). Below
    :data:`SLERP_LERP_ANGLE` the normalised linear interpolation is returned. At ``u = 0``
    and ``u = 1`` the result is ``q0`` and (the sign-aligned) ``q1``.

    Args:
        q0, q1: (..., 4) unit quaternions (x, y, z, w), broadcast against each other.
        u: (...) interpolation fractions (0 gives q0, 1 gives q1; values outside [0, 1]
            extrapolate along the same great circle).

    Returns:
        (..., 4) float64 unit quaternions.
    """
    q0, q1 = _as_quaternions(q0), _as_quaternions(q1)
    q0, q1 = np.broadcast_arrays(q0, q1)
    u = np.asarray(u, dtype=np.float64)
    dot = np.einsum('...i,...i->...', q0, q1)
    q1 = np.where((dot < 0.0)[..., None], -q1, q1)
    diff, total = q1 - q0, q1 + q0
    theta = 2.0 * np.arctan2(np.sqrt(np.einsum('...i,...i->...', diff, diff)),
                             np.sqrt(np.einsum('...i,...i->...', total, total)))
    small = theta < SLERP_LERP_ANGLE
    if not np.any(small):
        sin_theta = np.sin(theta)
        w0 = np.sin((1.0 - u) * theta) / sin_theta
        w1 = np.sin(u * theta) / sin_theta
        return w0[..., None] * q0 + w1[..., None] * q1
    safe = np.where(small, 1.0, theta)
    sin_theta = np.sin(safe)
    w0 = np.where(small, 1.0 - u, np.sin((1.0 - u) * safe) / sin_theta)
    w1 = np.where(small, u, np.sin(u * safe) / sin_theta)
    out = w0[..., None] * q0 + w1[..., None] * q1
    return np.where(small[..., None], out / np.linalg.norm(out, axis=-1, keepdims=True), out)
