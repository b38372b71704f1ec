"""Messages of the localiser (``facade_localizer``) <-> arrays.

Reads message *attributes* only, never classes (rclpy's messages, rosbags' dataclasses and
plain stand-ins alike):

* ``geometry_msgs/PoseWithCovarianceStamped`` (a prior pose: GNSS, odometry, the previous
  estimate) -> :class:`PosePrior`; and a pose with its covariance back into one;
* the ``QueryPoints`` request and response of the mapper's ``query_points`` service: the
  points written as 3 numbers each (``xyz``), the answers read into arrays
  (:func:`query_answers`).

Conventions (ROS): a pose is the pose of a child frame (here the scan's frame) in
``header.frame_id`` (the map frame), ``p_map = R p_child + t``, as a (4, 4) matrix. Its
covariance is 6 x 6, row-major in the message, in the order x, y, z (m), rotation about the
map frame's X, Y and Z axes (rad): a perturbation applied on the left in the map frame,
``T = exp(delta) T_hat``.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

import numpy as np

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.transforms.rotations import from_matrix, to_matrix

from .map_messages import QUERY_FIELDS, _encode, _header
from .transforms import _quaternion, _vector, stamped_transforms

__all__ = ['PosePrior', 'fill_query_request', 'pose_with_covariance_msg', 'prior_from_msg', 'query_answers']


@dataclass(frozen=True)
class PosePrior:
    """A pose with its covariance, as a PoseWithCovarianceStamped carries it.

    Attributes:
        frame_id: the frame the pose is in (``header.frame_id``).
        stamp_ns: ``header.stamp``, integer nanoseconds.
        pose: (4, 4) float64, child -> ``frame_id``.
        covariance: (6, 6) float64 (see the module), or None when the message's is all
            zeros (unknown: the receiver's default applies).
    """

    frame_id: str
    stamp_ns: int
    pose: np.ndarray
    covariance: np.ndarray | None


def prior_from_msg(msg: Any) -> PosePrior:
    """The pose and covariance of a ``PoseWithCovarianceStamped`` (or anything with
    ``header`` and ``pose.pose`` / ``pose.covariance``).

    Raises:
        InputError: missing fields, a quaternion of zero length or not finite, a position
            not finite, or a covariance that is not 36 finite numbers of a symmetric
            positive definite matrix (all zeros is accepted: unknown).
    """
    try:
        (t,) = stamped_transforms(msg, child_frame='prior')  # the pose, as any pose message's
        flat = np.asarray(msg.pose.covariance, dtype=np.float64).reshape(-1)
    except (InputError, AttributeError, TypeError, ValueError) as err:
        raise InputError(f'not a PoseWithCovarianceStamped: {err}') from err
    position, quat, stamp, frame = t.translation, t.rotation, t.stamp_ns, t.parent
    if not (np.isfinite(position).all() and np.isfinite(quat).all()):
        raise InputError('prior pose has a NaN or infinite position or orientation')
    norm = float(np.linalg.norm(quat))
    if not norm > 1e-9:
        raise InputError('prior pose has a zero quaternion')
    out = np.eye(4)
    out[:3, :3] = to_matrix(quat / norm)
    out[:3, 3] = position
    if flat.shape != (36,) or not np.isfinite(flat).all():
        raise InputError(f'prior covariance must be 36 finite numbers, got {flat.shape[0]}')
    covariance = flat.reshape(6, 6)
    if not covariance.any():
        return PosePrior(frame, stamp, out, None)
    if not np.allclose(covariance, covariance.T, rtol=1e-6, atol=1e-12):
        raise InputError('prior covariance is not symmetric')
    try:
        np.linalg.cholesky(covariance)
    except np.linalg.LinAlgError as err:
        raise InputError('prior covariance is not positive definite (a zero variance on a diagonal entry?)') from err
    return PosePrior(frame, stamp, out, covariance)


def pose_with_covariance_msg(frame_id: str, stamp_ns: int, pose: np.ndarray, covariance: np.ndarray,
                             types: Any) -> Any:
    """A ``geometry_msgs/PoseWithCovarianceStamped`` of a (4, 4) pose (child -> ``frame_id``)
    and its (6, 6) covariance (see the module).

    Args:
        types: namespace with ``PoseWithCovarianceStamped``, ``PoseWithCovariance``, ``Pose``,
            ``Point``, ``Quaternion``, ``Header``, ``Time``.

    Raises:
        InputError: wrong shapes, or a stamp out of range.
    """
    pose = np.asarray(pose, dtype=np.float64)
    covariance = np.asarray(covariance, dtype=np.float64)
    if pose.shape != (4, 4) or covariance.shape != (6, 6):
        raise InputError(f'pose must be (4, 4) and covariance (6, 6), got {pose.shape} and {covariance.shape}')
    body = types.Pose(position=_vector(types, 'Point', pose[:3, 3]), orientation=_quaternion(types, from_matrix(pose[:3, :3])))
    with_cov = types.PoseWithCovariance(pose=body, covariance=np.ascontiguousarray(covariance.reshape(-1)))
    return types.PoseWithCovarianceStamped(header=_header(types, frame_id, stamp_ns), pose=with_cov)


def fill_query_request(request: Any, xyz: np.ndarray, resolution: float = 0.0) -> Any:
    """Write (N, 3) map-frame points (metres) into a ``QueryPoints`` request as 3 numbers
    each (``xyz``; ``points`` left empty), the fast way for large batches."""
    xyz = np.ascontiguousarray(xyz, dtype=np.float64).reshape(-1, 3)
    request.xyz = _encode(None, type(request), xyz.reshape(-1), 'd')
    request.resolution = float(resolution)
    return request


def query_answers(response: Any, n: int) -> SimpleNamespace:
    """The answers of a ``QueryPoints`` response for ``n`` points as arrays: (n,) ``facade``,
    ``mean_depth``, ``variance``, ``noise_variance``, ``signed_distance``, ``p_occupied``
    and (n, 3) ``normal``.

    Raises:
        InputError: the service refused (``success`` false: its message), or answered a
            different number of points, or without normals (a mapper older than them).
    """
    if not getattr(response, 'success', False):
        raise InputError(f'query_points refused: {getattr(response, "message", "")}')
    out = {k: np.asarray(getattr(response, k), dtype=np.int64 if k == 'facade' else np.float64)
           for k in QUERY_FIELDS}
    bad = {k: len(v) for k, v in out.items() if len(v) != n}
    if bad:
        raise InputError(f'query_points answered {bad} for {n} points')
    normal = np.asarray(getattr(response, 'normal', ()), dtype=np.float64)
    if normal.size != 3 * n:
        raise InputError(f'query_points gave {normal.size} normal components for {n} points: the mapper is older '
                         f'than the normals (QueryPoints.normal); update it')
    return SimpleNamespace(**out, normal=normal.reshape(n, 3))
