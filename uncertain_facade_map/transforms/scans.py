"""From a cloud in its own frame to map-frame points: per-point times and per-point poses.

A lidar sweep takes ~0.1 s, during which a vehicle at 10 m/s moves 1 m. Drivers that
give each point its firing time let every point be placed with the sensor pose at that
time (motion compensation, "deskewing"): :func:`point_times` reads those times,
:func:`locate_scan` looks up one pose per distinct time, :class:`ScanPose` applies them.

Per-point time fields of common drivers (what :func:`point_times` relies on):

* velodyne_pointcloud (ROS 1 and 2, ``PointXYZIRT``): ``time``, float32, seconds relative
  to the cloud's header stamp.
* ouster-ros (``ouster_ros::Point``): ``t``, uint32, nanoseconds relative to the scan's
  first column, which is the header stamp.
* HesaiLidar_ROS_2.0 (``PointXYZIT``) and rslidar_sdk: ``timestamp``, float64, absolute
  UNIX seconds.
* livox_ros_driver2 (``PointXYZRTLT``): ``timestamp``, float64 holding absolute UNIX
  *nanoseconds* (the packet time plus the point's offset, cast to double).

Hence the rule: a float field holds seconds, an integer field nanoseconds; magnitudes
above 1e8 s (float; 1e8 s after the epoch is 1973) or 1e17 ns (integer) are absolute UNIX
times, smaller ones offsets from the header stamp (which may be negative: some drivers
stamp the end of the sweep); a float field above 1e17 holds absolute nanoseconds (Livox).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from uncertain_facade_map.errors import ExtrapolationError, InputError, TransformError

from .buffer import TransformBuffer

#: A float time field beyond this many seconds holds absolute UNIX seconds (after 1973).
ABSOLUTE_SECONDS = 1e8
#: An integer time field (or a float one, Livox) beyond this holds absolute UNIX nanoseconds.
ABSOLUTE_NANOSECONDS = 1e17


def point_times(points: np.ndarray, stamp_ns: int, field: str) -> np.ndarray | None:
    """Absolute time of each point of a cloud, from its per-point time field.

    Args:
        points: structured array (N,) of a cloud (e.g. from
            ``msg_adapters.structured_from_pointcloud2``); drop invalid points (NaN
            coordinates, zero times) first if the driver leaves their time unset.
        stamp_ns: the cloud's header stamp, integer nanoseconds (the origin of relative
            times).
        field: name of the time field; '' for none.

    Returns:
        (N,) int64 nanoseconds since the UNIX epoch (or of the stamp's clock), one per
        point; None when ``field`` is '' or the cloud has no such field. Conventions: see
        the module docstring (float = seconds, integer = nanoseconds; large values
        absolute, small ones relative to ``stamp_ns``).

    Raises:
        InputError: the field is not a scalar number; has NaN or infinite values; mixes
            absolute and relative times; or holds absolute UNIX seconds in float32 (128 s
            resolution: unusable).
    """
    if not field:
        return None
    names = points.dtype.names or ()
    if field not in names:
        return None
    values = points[field]
    kind = values.dtype.kind
    if values.ndim != 1 or kind not in 'iuf':
        raise InputError(f'time field "{field}" must hold one number per point, got {points.dtype[field]}')
    stamp = int(stamp_ns)
    if values.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    if kind == 'f':
        v = values.astype(np.float64)
        finite = np.isfinite(v)
        if not finite.all():
            raise InputError(f'time field "{field}" has {int((~finite).sum()):,} NaN or infinite values of '
                             f'{v.shape[0]:,}')
        mag = np.abs(v)
        ns = mag > ABSOLUTE_NANOSECONDS
        sec = (mag > ABSOLUTE_SECONDS) & ~ns
        _one_kind(field, ns | sec, 'absolute')
        if ns.all():  # Livox: absolute nanoseconds in a double
            return np.rint(v).astype(np.int64)
        if sec.all():
            if values.dtype.itemsize < 8:
                raise InputError(f'time field "{field}" holds absolute UNIX seconds in {values.dtype}: a resolution '
                                 f'of {float(np.spacing(np.float32(v.max()))):g} s, unusable for per-point times')
            whole = np.floor(v)  # split so that the fraction keeps its digits
            return whole.astype(np.int64) * 1_000_000_000 + np.rint((v - whole) * 1e9).astype(np.int64)
        return stamp + np.rint(v * 1e9).astype(np.int64)
    if kind == 'u' and values.dtype.itemsize == 8 and int(values.max()) > np.iinfo(np.int64).max:
        raise InputError(f'time field "{field}" has values beyond 2**63 ns')
    v = values.astype(np.int64)
    absolute = np.abs(v) > ABSOLUTE_NANOSECONDS
    _one_kind(field, absolute, 'absolute')
    return v.copy() if absolute.all() else stamp + v


def _one_kind(field: str, absolute: np.ndarray, what: str) -> None:
    """InputError when some but not all times of the field are absolute."""
    n_abs = int(absolute.sum())
    if 0 < n_abs < absolute.shape[0]:
        raise InputError(f'time field "{field}" mixes {what} times ({n_abs:,} points) and offsets from the stamp '
                         f'({absolute.shape[0] - n_abs:,} points): drop the points whose time is unset')


@dataclass(frozen=True, eq=False)
class ScanPose:
    """Poses of a cloud's frame in a target frame: one for all points, or one per point time.

    Attributes:
        rotations: (K, 3, 3) float64; pose k maps source to target:
            ``p_target = rotations[k] @ p_source + translations[k]``.
        translations: (K, 3) float64, metres.
        index: (N,) int64 in ``0..K-1``, the pose of each point; None when ``K == 1`` and
            one pose serves every point.
        n: number of points when ``index`` is None (None: any number; then
            :meth:`origins` needs its argument). Set from ``index`` otherwise.
    """

    rotations: np.ndarray
    translations: np.ndarray
    index: np.ndarray | None = None
    n: int | None = None

    def __post_init__(self) -> None:
        r = np.asarray(self.rotations, dtype=np.float64)
        t = np.asarray(self.translations, dtype=np.float64)
        if r.ndim != 3 or r.shape[1:] != (3, 3) or t.shape != (r.shape[0], 3) or r.shape[0] == 0:
            raise InputError(f'a scan pose has rotations (K, 3, 3) and translations (K, 3), K >= 1, got shapes '
                             f'{r.shape} and {t.shape}')
        object.__setattr__(self, 'rotations', r)
        object.__setattr__(self, 'translations', t)
        if self.index is None:
            if r.shape[0] != 1:
                raise InputError(f'{r.shape[0]} poses need an index saying which pose each point takes')
        else:
            idx = np.asarray(self.index)
            if idx.ndim != 1 or (idx.size and idx.dtype.kind not in 'iu'):
                raise InputError(f'the pose index must be a 1-D integer array, got {idx.dtype} {idx.shape}')
            idx = idx.astype(np.int64, copy=False)
            if idx.size and (idx.min() < 0 or idx.max() >= r.shape[0]):
                raise InputError(f'pose index outside 0..{r.shape[0] - 1}')
            object.__setattr__(self, 'index', idx)
            object.__setattr__(self, 'n', int(idx.shape[0]))

    @classmethod
    def identity(cls, n: int | None = None) -> ScanPose:
        """The pose of a cloud already in the target frame (n points, or any number)."""
        return cls(np.eye(3)[None], np.zeros((1, 3)), None, None if n is None else int(n))

    @property
    def single(self) -> bool:
        """True when one pose serves every point."""
        return self.index is None

    def _check(self, xyz: np.ndarray, what: str) -> np.ndarray:
        p = np.asarray(xyz, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise InputError(f'{what} must be (N, 3), got shape {p.shape}')
        if self.n is not None and p.shape[0] != self.n:
            raise InputError(f'{what} has {p.shape[0]:,} rows, the scan pose is for {self.n:,} points')
        return p

    def apply(self, xyz: np.ndarray) -> np.ndarray:
        """Points in the target frame, each moved by the pose at its time.

        Args:
            xyz: (N, 3) points in the source frame, metres.

        Returns:
            (N, 3) float64 in the target frame.

        Raises:
            InputError: wrong shape, or N differs from the pose's number of points.
        """
        p = self._check(xyz, 'points')
        if self.index is None:
            return p @ self.rotations[0].T + self.translations[0]
        return np.einsum('nij,nj->ni', self.rotations[self.index], p) + self.translations[self.index]

    def transform_origins(self, origins_in_source: np.ndarray) -> np.ndarray:
        """Sensor origins a cloud carries in its own frame (origin_x/y/z fields), in the target frame.

        Args:
            origins_in_source: (N, 3) each point's sensor origin in the source frame, metres.

        Returns:
            (N, 3) float64 in the target frame (the same per-point poses as :meth:`apply`).
        """
        return self.apply(self._check(origins_in_source, 'origins'))

    def origins(self, n: int | None = None) -> np.ndarray:
        """The source frame's origin in the target frame at each point's time.

        For a cloud in its sensor's frame this is each point's sensor origin (the ray
        start).

        Args:
            n: number of points; needed only when the pose has no index and no ``n``.

        Returns:
            (N, 3) float64, metres, target frame.

        Raises:
            InputError: the number of points is unknown, or ``n`` contradicts it.
        """
        if self.index is not None:
            if n is not None and int(n) != self.n:
                raise InputError(f'the scan pose is for {self.n:,} points, not {int(n):,}')
            return self.translations[self.index]
        count = self.n if n is None else int(n)
        if count is None:
            raise InputError('the number of points of this scan pose is unknown: pass n')
        if self.n is not None and count != self.n:
            raise InputError(f'the scan pose is for {self.n:,} points, not {count:,}')
        return np.repeat(self.translations, count, axis=0)

    def select(self, mask: Any) -> ScanPose:
        """The poses of a subset of the points.

        Args:
            mask: (N,) booleans, or integer indices into the N points.

        Returns:
            ScanPose for the selected points (the K poses are kept).
        """
        m = np.asarray(mask)
        if self.index is not None:
            return ScanPose(self.rotations, self.translations, self.index[m])
        if m.dtype == bool:
            if self.n is not None and m.shape != (self.n,):
                raise InputError(f'mask of shape {m.shape} for a scan pose of {self.n:,} points')
            count = int(m.sum())
        else:
            count = int(m.size)
        return ScanPose(self.rotations, self.translations, None, count)


def locate_scan(buffer: TransformBuffer, target: str, source: str, stamp_ns: int,
                times_ns: np.ndarray | None = None, *, n_points: int | None = None,
                max_extrapolation: float | None = None) -> ScanPose:
    """Pose(s) of a cloud's frame ``source`` in ``target``, at its stamp or at each point's time.

    Args:
        buffer: the transforms.
        target: frame to map into (e.g. ``map``).
        source: the cloud's ``header.frame_id``.
        stamp_ns: the cloud's stamp, integer nanoseconds (0: latest common time).
        times_ns: (N,) int64 absolute point times (:func:`point_times`), or None for one
            pose at ``stamp_ns``. One lookup is made per distinct time (``np.unique``),
            vectorised through :meth:`TransformBuffer.lookup_many`.
        n_points: number of points, recorded in a single pose (for :meth:`ScanPose.origins`).
        max_extrapolation: seconds the lookups may hold an edge's first or last sample, this
            call's instead of the buffer's (None).

    Returns:
        :class:`ScanPose` (K = 1 and no index without times; K distinct times and an
        index with them).

    Raises:
        UnknownFrameError, ConnectivityError, ExtrapolationError: from the buffer (for a
            sweep: the first or last point time outside the poses' span).
        InputError: ``times_ns`` not a 1-D integer array.
    """
    if times_ns is None:
        rigid = buffer.lookup(target, source, stamp_ns, max_extrapolation=max_extrapolation)
        return ScanPose(rigid.rotation[None], rigid.translation[None], None, n_points)
    times = np.asarray(times_ns)
    if times.ndim != 1 or (times.size and times.dtype.kind not in 'iu'):
        raise InputError(f'point times must be a 1-D integer array of nanoseconds, got {times.dtype} {times.shape}')
    distinct, index = np.unique(times.astype(np.int64, copy=False), return_inverse=True)
    if distinct.size == 0:
        rigid = buffer.lookup(target, source, stamp_ns, max_extrapolation=max_extrapolation)
        return ScanPose(rigid.rotation[None], rigid.translation[None], np.zeros(0, dtype=np.int64))
    rots, trans = buffer.lookup_many(target, source, distinct, max_extrapolation=max_extrapolation)
    return ScanPose(rots, trans, index.reshape(-1).astype(np.int64, copy=False))


@dataclass(frozen=True, eq=False)
class Placement:
    """How a cloud was put into the target frame (:func:`place_scan`).

    Attributes:
        pose: the cloud's pose(s) in the target frame; None when the cloud is in it already.
        note: '' when every point got the transform at its own time (or the stamp); else
            how the cloud was placed instead, for the logs (a pose held beyond the data, or
            one pose at the stamp because no transforms cover the sweep's point times).
    """

    pose: ScanPose | None
    note: str = ''


def _may_come(err: TransformError) -> bool:
    """Whether waiting for more transforms may answer a lookup that failed with ``err``."""
    return not isinstance(err, ExtrapolationError) or err.future


def place_scan(buffer: TransformBuffer, target: str, source: str, stamp_ns: int, times_ns: np.ndarray | None, *,
               n_points: int, tolerance: float, final: bool) -> Placement | None:
    """The pose of a cloud in ``target``: the one rule the node and offline replay share.

    1. A cloud in ``target`` needs no pose.
    2. If the transforms cover the stamp and every point time (the sweep's span), each
       point gets the transform at its time (tf2's lookup: interpolated, never
       extrapolated).
    3. Otherwise, while more transforms may come (a newer sample, an unknown frame or
       tree) and the caller may still wait (``final`` False): None, wait.
    4. Finally (the node's ``node.transform_timeout`` passed, or the data can never come):
       the same, holding the edges' first or last samples up to ``tolerance`` seconds;
       else, for a cloud with point times, one pose at its stamp (no motion compensation);
       else the lookup's error.

    Args:
        buffer: the transforms.
        target: the map frame.
        source: the cloud's ``header.frame_id``.
        stamp_ns: the cloud's stamp, integer nanoseconds.
        times_ns: (N,) int64 absolute time of each point (:func:`point_times`), or None.
        n_points: N, the number of points the pose is for.
        tolerance: seconds (``node.pose_tolerance``), >= 0.
        final: no more waiting (see 3 and 4).

    Returns:
        The :class:`Placement`, or None (wait) only when ``final`` is False.

    Raises:
        UnknownFrameError, ConnectivityError, ExtrapolationError: the cloud cannot be
            placed (when ``final``, or when the missing data can never come).
    """
    if source == target:
        return Placement(None)
    times = None if times_ns is None or len(times_ns) == 0 else np.asarray(times_ns, dtype=np.int64)
    lo, hi = (int(times.min()), int(times.max())) if times is not None else (int(stamp_ns), int(stamp_ns))
    err = buffer.why_not(target, source, lo, hi)
    if err is None:
        return Placement(locate_scan(buffer, target, source, stamp_ns, times, n_points=n_points))
    if not final and _may_come(err):
        return None
    if tolerance > 0 and isinstance(err, ExtrapolationError) and buffer.can_transform(
            target, source, lo, hi, max_extrapolation=tolerance):
        gap = err.stamp_ns - err.last_ns if err.future else err.first_ns - err.stamp_ns
        return Placement(locate_scan(buffer, target, source, stamp_ns, times, n_points=n_points,
                                     max_extrapolation=tolerance),
                         f'{gap / 1e9:.3f} s {"after" if err.future else "before"} the transforms of "{err.frame}" '
                         f'in "{err.parent}": held the nearest (node.pose_tolerance)')
    if times is not None:
        for hold in (0.0, tolerance):
            if buffer.can_transform(target, source, int(stamp_ns), max_extrapolation=hold):
                return Placement(locate_scan(buffer, target, source, stamp_ns, None, n_points=n_points,
                                             max_extrapolation=hold),
                                 f'no transforms over its points\' times ({(hi - lo) / 1e9:.3f} s): one pose at its '
                                 'stamp, without motion compensation')
    raise err
