"""One live scan, in its own frame, to building points in the map frame.

The node and offline replay (:func:`uncertain_facade_map.mapping.worker.map_scans`) map a
scan by the same three calls (:class:`Scan`: ``Scan.of``, ``place``, ``building_points``), so
that both make the same map:

1. ``Scan.of`` -- the scan's finite points and, when it must be moved and has the per-point
   time field ``input.time_field``, each one's absolute time (the span a transform must cover).
2. :func:`uncertain_facade_map.transforms.place_scan` -- its pose(s) in the map frame from
   the transform buffer: at each point's time (motion compensation), or at the stamp
   (the node may wait for the transform first).
3. :func:`select_scan_points` -- the finite points moved into the map frame, each with its
   sensor origin (the cloud's own origin fields moved alike, or the scan frame's origin at
   the point's time); the whole scan refused if a point lies beyond ``node.max_coordinate``
   of the map origin (a corrupted cloud); then its building points: by class, or, in a
   scan without the class field, by the selection, in the map frame (z up) with those
   origins.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..errors import ExtrapolationError, InputError
from ..params import InputConfig, SelectionConfig
from ..transforms import Placement, ScanPose, TransformBuffer, place_scan, point_times
from .cloud import Cloud
from .inputs import _integer_values, _selects, swapped_plausible

if TYPE_CHECKING:
    from ..selection import Selection

#: The sensor origin fields a cloud may carry (in its own frame).
ORIGIN_FIELDS = ('origin_x', 'origin_y', 'origin_z')


class ScanRejected(InputError):
    """A scan that cannot be right (points absurdly far from the map origin), refused whole."""


@dataclass(frozen=True, eq=False)
class ScanPoints:
    """The building points of one live scan, and what was left out.

    Attributes:
        xyz: (N, 3) float64 building points with finite coordinates, metres, map frame (the
            scan's own frame when no pose was given).
        building_id: (N,) int64 building ids, or None.
        sensor_origins: (N, 3) float64 sensor positions, metres, same frame, or None.
        nonfinite: number of points skipped for NaN or infinite coordinates.
        not_building: number of finite points of another class, or not selected.
        selection: what the selection found when the scan had no class field, else None.
    """

    xyz: np.ndarray
    building_id: np.ndarray | None
    sensor_origins: np.ndarray | None
    nonfinite: int
    not_building: int
    selection: Selection | None = None


def points_xyz(points: np.ndarray) -> np.ndarray:
    """(M, 3) float64 coordinates of a scan; InputError without numeric x, y, z fields."""
    names = points.dtype.names or ()
    missing = [c for c in ('x', 'y', 'z') if c not in names]
    if missing:
        raise InputError(f'no {", ".join(missing)} field (fields: {", ".join(names) or "none"})')
    for c in ('x', 'y', 'z'):
        if points.dtype[c].kind not in 'iuf' or points.dtype[c].shape:
            raise InputError(f'field {c!r} must be a number, found type {points.dtype[c]}')
    return np.stack([points[c].astype(np.float64) for c in ('x', 'y', 'z')], axis=1)


@dataclass(eq=False)
class Scan:
    """A scan as it arrived: its points in its own frame, its stamp, and what placing it needs.

    Attributes:
        points: (M,) structured array (a PointCloud2's fields).
        frame_id: the frame of the points (``header.frame_id``).
        stamp_ns: the header stamp, integer nanoseconds.
        finite: (M,) bool, the points with finite coordinates.
        xyz: (M, 3) float64 coordinates of all points, the scan's frame (read once).
        time_field: ``input.time_field``: the per-point times are read (once, by
            :attr:`times`) only for a scan that must be moved into the map frame.
    """

    points: np.ndarray
    frame_id: str
    stamp_ns: int
    finite: np.ndarray
    time_field: str = ''
    xyz: np.ndarray | None = None
    _times: tuple[np.ndarray | None] | None = None

    @classmethod
    def of(cls, points: np.ndarray, frame_id: str, stamp_ns: int, config: InputConfig) -> Scan:
        """A scan from its points, frame and stamp.

        Raises:
            InputError: no numeric x, y or z field.
        """
        xyz = points_xyz(points)
        return cls(points, str(frame_id), int(stamp_ns), np.isfinite(xyz).all(axis=1), config.time_field, xyz)

    @property
    def times(self) -> np.ndarray | None:
        """(F,) int64 absolute nanoseconds of the finite points from the time field, or None
        (read once; InputError for a field that is not a number, NaN, or mixed conventions)."""
        if self._times is None:
            field = self.time_field
            names = self.points.dtype.names or ()
            times = point_times(self.points[self.finite], self.stamp_ns, field) if field and field in names else None
            self._times = (times,)
        return self._times[0]

    @property
    def span_ns(self) -> tuple[int, int]:
        """First and last time the scan's transform must cover (its points' times, else its stamp)."""
        times = self.times
        if times is None or not len(times):
            return self.stamp_ns, self.stamp_ns
        return int(times.min()), int(times.max())

    def place(self, buffer: TransformBuffer | None, map_frame: str, tolerance: float,
              final: bool = True) -> Placement | None:
        """The scan's pose in the map frame (:func:`~uncertain_facade_map.transforms.place_scan`).

        Args:
            buffer: the transforms; None for none (only a scan in the map frame is placed).
            map_frame: ``input.frame_id``.
            tolerance: seconds (``node.pose_tolerance``).
            final: no more waiting: the nearest pose within ``tolerance``, or the error.

        Returns:
            The placement, or None while ``final`` is False and the transform may come.

        Raises:
            TransformError: the scan cannot be placed (see ``place_scan``).
            InputError: a bad time field (see :attr:`times`).
        """
        if self.frame_id == map_frame:
            return Placement(None)
        buffer = buffer if buffer is not None else TransformBuffer()
        return place_scan(buffer, map_frame, self.frame_id, self.stamp_ns, self.times,
                          n_points=int(self.finite.sum()), tolerance=tolerance, final=final)

    def map_frame_points(self, placement: Placement) -> tuple[np.ndarray, np.ndarray | None]:
        """Its finite points (F, 3) in the map frame, and their sensor origins (F, 3) or None
        (as :func:`select_scan_points` moves them, before any selection)."""
        return _moved(self.points, self.finite, self.xyz[self.finite], placement.pose)

    def building_points(self, placement: Placement, config: InputConfig, selection: SelectionConfig | None,
                        max_coordinate: float | None) -> ScanPoints:
        """Its building points in the map frame (:func:`select_scan_points` with the placement's pose)."""
        return select_scan_points(self.points, config, selection, pose=placement.pose, max_coordinate=max_coordinate,
                                  xyz=self.xyz)


def _moved(points: np.ndarray, keep: np.ndarray, xyz: np.ndarray, pose: ScanPose | None
           ) -> tuple[np.ndarray, np.ndarray | None]:
    """The kept points (F, 3) and their sensor origins (F, 3) or None, moved by ``pose``:
    the cloud's own origin fields moved alike, or else the frame's origin at each point's
    time; as they are without a pose."""
    origins = _origin_fields(points, keep)
    if pose is None:
        return xyz, origins
    moved = pose.apply(xyz)
    return moved, (pose.transform_origins(origins) if origins is not None else pose.origins(len(moved)))


def _origin_fields(points: np.ndarray, keep: np.ndarray) -> np.ndarray | None:
    """(F, 3) float64 origins of the kept points from the cloud's origin fields, or None
    when it has none or any is not finite."""
    if not all(c in (points.dtype.names or ()) for c in ORIGIN_FIELDS):
        return None
    origins = np.stack([points[c][keep].astype(np.float64) for c in ORIGIN_FIELDS], 1)
    return origins if np.isfinite(origins).all() else None


def select_scan_points(points: np.ndarray, config: InputConfig, selection: SelectionConfig | None = None,
                       sensor_origin: np.ndarray | None = None, *, pose: ScanPose | None = None,
                       max_coordinate: float | None = None, xyz: np.ndarray | None = None) -> ScanPoints:
    """Building points of one scan (a PointCloud2 as a structured array), tolerant of gaps.

    Unlike :func:`~uncertain_facade_map.io.inputs.select_building_points` (whole inputs,
    where a NaN is an error), a live scan may hold NaN or infinite points (no return): they
    are skipped and counted. A scan without building points gives empty arrays. Used alike
    by the node and by offline replay, so both map the same points.

    Args:
        points: (M,) structured array with at least numeric fields ``x``, ``y``, ``z``;
            ``config.class_field``, ``config.building_id_field`` and ``origin_x``,
            ``origin_y``, ``origin_z`` are used when present.
        config: which class values are building.
        selection: the selection's parameters for scans without classes; None for none
            (such a scan is all building).
        sensor_origin: (3,) sensor position, metres, for the selection when the scan has
            neither origin fields nor a pose (e.g. zeros for a scan in its sensor's frame);
            None if unknown.
        pose: the scan's pose(s) in the map frame for its F finite points, in order
            (:func:`~uncertain_facade_map.transforms.place_scan`); None: the scan is in the
            map frame already. With a pose, each point's sensor origin is its origin fields
            moved by the same pose, or else the scan frame's origin at the point's time.
        max_coordinate: metres (``node.max_coordinate``): a finite point (or sensor origin)
            farther than this from the map origin in x, y or z refuses the whole scan; None
            for no check.
        xyz: (M, 3) float64 coordinates of ``points`` when read already (:class:`Scan`).

    Returns:
        The building points, in the map frame when a pose is given.

    Raises:
        InputError: no x, y or z field (the message lists the fields), a coordinate or
            class field that is not numeric, or a class or building id field that holds
            non-integer values.
        ScanRejected: a point or sensor origin beyond ``max_coordinate`` (the message says
            when the other byte order would make the points plausible).
    """
    xyz = points_xyz(points) if xyz is None else xyz
    names = points.dtype.names or ()
    keep = np.isfinite(xyz).all(axis=1)
    nonfinite = int((~keep).sum())
    finite_xyz, origins = _moved(points, keep, xyz[keep], pose)
    if max_coordinate is not None:
        _check_bound(points, finite_xyz, origins, max_coordinate)
    building = np.ones(len(finite_xyz), dtype=bool)
    found = None
    if _selects(names, config, selection):
        from ..selection import select_building_points as select_walls

        found = select_walls(finite_xyz, origins if origins is not None else sensor_origin, selection)
        building = found.mask
    elif config.class_field in names:
        classes = _integer_values(Cloud(points), config.class_field, 'class')[keep]
        building = np.isin(classes, np.asarray(config.building_classes, dtype=np.int64))
    not_building = int((~building).sum())
    ids = None
    if config.building_id_field in names:
        ids = _integer_values(Cloud(points), config.building_id_field, 'building id')[keep][building]
    return ScanPoints(finite_xyz[building], ids, None if origins is None else origins[building], nonfinite,
                      not_building, found)


def _check_bound(points: np.ndarray, xyz: np.ndarray, origins: np.ndarray | None, bound: float) -> None:
    """ScanRejected when a map-frame point or sensor origin lies beyond ``bound`` of the map origin."""
    far = ~(np.abs(xyz) <= bound).all(axis=1)
    if far.any():
        example = xyz[np.flatnonzero(far)[0]].tolist()
        hint = ''
        if swapped_plausible(points, bound, centre=np.zeros(3)):
            hint = '; read in the other byte order they would be plausible: is is_bigendian wrong?'
        raise ScanRejected(f'{int(far.sum()):,} of {len(xyz):,} points lie beyond node.max_coordinate = {bound:g} m '
                           f'of the map origin, e.g. {example}{hint}')
    if origins is not None and not (np.abs(origins) <= bound).all():
        raise ScanRejected(f'sensor origins lie beyond node.max_coordinate = {bound:g} m of the map origin')


def frames_without_transform(frames: dict[str, int] | list[str], buffer: TransformBuffer,
                             map_frame: str) -> dict[str, str]:
    """The cloud frames that no transform of ``buffer`` connects with the map frame, at any time.

    Args:
        frames: the clouds' frames (a frame -> count mapping, or a list).
        buffer: the transforms of a recording.
        map_frame: ``input.frame_id``.

    Returns:
        frame -> why (an unknown frame, or one in another tree), for each frame that can
        never be placed; frames equal to ``map_frame`` are always placed.
    """
    out = {}
    for frame in frames:
        if frame == map_frame:
            continue
        err = buffer.why_not(map_frame, frame, 0)
        if err is not None and not isinstance(err, ExtrapolationError):
            out[frame] = str(err)
    return out
