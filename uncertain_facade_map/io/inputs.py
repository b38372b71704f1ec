"""The inputs of ``uncertain-facade-map build``: files and bags, joined, reduced to building points.

:func:`load_inputs` reads point cloud files (PLY, LAS/LAZ, PCD, NPZ through
:mod:`~uncertain_facade_map.io.clouds`) and ROS bags and joins them into one
:class:`~uncertain_facade_map.io.cloud.Cloud` in the map frame of the first input. ROS
bags are read by the caller's ``read_bag`` (``msg_adapters.bag_io.load_inputs`` passes its
rosbags reader): the core imports no ROS package, so without a reader a bag is refused with
a message saying how to read it.
:func:`select_building_points` then keeps the points the configuration calls building and
returns them as plain arrays (:class:`BuildingPoints`): by their class, or, in a cloud
without the class field, by :mod:`uncertain_facade_map.selection` (``selection.mode``);
:func:`select_scan_points` does the same for one live scan.

A path is taken as a bag if it is a directory (a ROS 2 bag folder, which must hold
``metadata.yaml``) or ends in ``.bag`` (ROS 1), ``.db3`` (ROS 2 sqlite3 storage) or
``.mcap`` (ROS 2 MCAP storage); otherwise its suffix chooses the file format.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np

from ..errors import InputError
from ..params import InputConfig, SelectionConfig
from .cloud import COORDINATE_FIELDS, Cloud
from .clouds import SUPPORTED_SUFFIXES, read_cloud
from .trajectory import Trajectory

if TYPE_CHECKING:  # the selection (scipy, Patchwork++) loads only when a cloud needs it
    from ..selection import Selection

#: File suffixes read as ROS bags (besides directories, which are ROS 2 bag folders).
BAG_SUFFIXES = ('.bag', '.db3', '.mcap')
#: How many distinct class values an error message lists before eliding the rest.
_MAX_LISTED_CLASSES = 20
#: ASPRS LAS class of buildings, mentioned when a cloud holds it but it is not configured.
_ASPRS_BUILDING = 6


def _describe_supported() -> str:
    return (f'supported: {", ".join(SUPPORTED_SUFFIXES)} files and ROS bags '
            f'({", ".join(BAG_SUFFIXES)} or a bag folder with metadata.yaml)')


#: Reads one bag: (path, PointCloud2 topic or None) -> Cloud.
BagReader = Callable[[Path, 'str | None'], Cloud]


def _read_bag(path: Path, topic: str | None, read_bag: BagReader | None) -> Cloud:
    if read_bag is None:
        raise InputError(f'{path} is a ROS bag: bags are read through msg_adapters '
                         '(msg_adapters.bag_io.load_inputs, or the uncertain-facade-map command line)')
    return read_bag(path, topic)


def read_input(path: str | os.PathLike[str], *, topic: str | None = None,
               read_bag: BagReader | None = None) -> Cloud:
    """Read one input: a point cloud file or a ROS bag.

    Args:
        path: a ``.ply``, ``.las``, ``.laz``, ``.pcd`` or ``.npz`` file, a ROS 1 ``.bag``
            file, a ROS 2 ``.db3`` or ``.mcap`` file, or a ROS 2 bag folder with
            ``metadata.yaml``; suffixes are matched case-insensitively.
        topic: PointCloud2 topic of a bag; None for the bag's only PointCloud2 topic.
            Ignored for files.
        read_bag: reader of ROS bags (see :data:`BagReader`); None refuses bags.

    Returns:
        The cloud (map frame, metres) with the input's map origin.

    Raises:
        InputError: the path does not exist, a folder without ``metadata.yaml``, an
            unknown suffix, or the file or bag cannot be read (see
            :func:`~uncertain_facade_map.io.clouds.read_cloud` and
            ``msg_adapters.bag_io.read_bag_cloud``).
    """
    p = Path(path)
    if not p.exists():
        raise InputError(f'no such file: {os.fspath(path)}')
    if p.is_dir():
        if not (p / 'metadata.yaml').is_file():
            raise InputError(f'{os.fspath(path)} is a directory but no ROS 2 bag (no metadata.yaml)')
        return _read_bag(p, topic, read_bag)
    suffix = p.suffix.lower()
    if suffix in BAG_SUFFIXES:
        return _read_bag(p, topic, read_bag)
    if suffix not in SUPPORTED_SUFFIXES:
        raise InputError(f'unsupported input {os.fspath(path)} (suffix {suffix or "none"}); '
                         f'{_describe_supported()}')
    return read_cloud(p)


def load_inputs(paths: Sequence[str | os.PathLike[str]], *, topic: str | None = None,
                read_bag: BagReader | None = None) -> Cloud:
    """Read PLY, LAS/LAZ, PCD, NPZ files and ROS bags and join them into one cloud.

    Each path is read by :func:`read_input` (bags through ``read_bag``). The clouds are
    joined in the order given:

    * Frame: the result is in the map frame of the first input and has its map origin.
      Every other cloud is re-expressed in it, ``x += origin_i[0] - origin_0[0]`` (and
      y, z), computed in float64; the sensor origin fields ``origin_x``, ``origin_y``,
      ``origin_z`` are shifted alike. Coordinate fields become float64 whenever some
      input's origin differs from the first one.
    * Fields: the result has the fields present in *every* input (x, y, z always are),
      in the order of the first input; fields missing from any input are dropped. A
      field whose types differ between inputs gets numpy's promoted type
      (``np.result_type``; e.g. u1 and i4 give i4, f4 and f8 give f8); a field whose
      types cannot be promoted (e.g. sub-arrays of different shapes) is dropped.
    * A single input is returned as read, unchanged.

    Args:
        paths: files and bags to read, at least one (a single path is accepted too).
        topic: PointCloud2 topic to read from every bag; None to take each bag's only
            PointCloud2 topic. Ignored for files.
        read_bag: reader of ROS bags (see :data:`BagReader`); None refuses bags.

    Returns:
        The joined cloud: points of all inputs in input order, packed native structured
        array, map frame of the first input (metres), its map origin.

    Raises:
        InputError: no paths, a missing file, an unknown format, an unreadable file or
            bag, or no point at all in the inputs.
    """
    items = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    if not items:
        raise InputError('no input files given')
    clouds = [read_input(p, topic=topic, read_bag=read_bag) for p in items]
    joined = clouds[0] if len(clouds) == 1 else _join(clouds)
    if len(joined) == 0:
        names = ', '.join(os.fspath(p) for p in items)
        raise InputError(f'no points in {names}')
    return joined


def _join(clouds: list[Cloud]) -> Cloud:
    """Concatenate clouds in the first one's map frame, on their common fields."""
    first = clouds[0]
    origin = first.map_origin
    shifts = [c.map_origin - origin for c in clouds]
    shifted = any(np.any(s != 0) for s in shifts)
    fields: list[tuple[str, np.dtype]] = []
    for name in first.fields:
        if not all(name in c.fields for c in clouds[1:]):
            continue
        types = [c.points.dtype.fields[name][0] for c in clouds]
        if shifted and name in COORDINATE_FIELDS:
            ftype = np.dtype(np.float64)
        elif all(t == types[0] for t in types):
            ftype = types[0]
        else:
            try:
                ftype = np.result_type(*types)
            except TypeError:
                continue
        if ftype.subdtype is None:
            ftype = ftype.newbyteorder('=')
        fields.append((name, ftype))
    points = np.zeros(sum(len(c) for c in clouds), dtype=np.dtype(fields))
    start = 0
    for cloud, shift in zip(clouds, shifts):
        part = points[start:start + len(cloud)]
        for name, _ftype in fields:
            values = cloud.points[name]
            if name in COORDINATE_FIELDS and shift.any():
                axis = COORDINATE_FIELDS.index(name) % 3
                values = values.astype(np.float64) + shift[axis]
            part[name] = values
        start += len(cloud)
    return Cloud(points, origin)


@dataclass(frozen=True, eq=False)
class BuildingPoints:
    """The building points of a cloud, as plain arrays.

    Attributes:
        xyz: (N, 3) float64, metres, map frame.
        building_id: (N,) int64 building ids, or None when the cloud has no
            ``building_id_field``.
        sensor_origins: (N, 3) float64 sensor position at each return, metres, map frame;
            None when the cloud has no ``origin_x``, ``origin_y``, ``origin_z``.
        time: (N,) float64 time of each return, seconds (as stored in the input's
            ``time`` field); None when the cloud has none.
        index: (N,) int64 index of each point in the input cloud.
        map_origin: (3,) float64, metres; georeferenced = ``xyz`` + ``map_origin``.
        selection: what the selection found when the points were selected by
            :mod:`uncertain_facade_map.selection` (a cloud without classes), else None.
    """

    xyz: np.ndarray
    building_id: np.ndarray | None
    sensor_origins: np.ndarray | None
    time: np.ndarray | None
    index: np.ndarray
    map_origin: np.ndarray
    selection: Selection | None = None

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


def _integer_values(cloud: Cloud, name: str, what: str) -> np.ndarray:
    """Field ``name`` as int64, if it holds integers only (integer or bool type, or floats
    with integral finite values).

    Raises:
        InputError: the field is not one-dimensional numeric, or holds a non-integer value.
    """
    values = cloud.points[name]
    kind = values.dtype.kind
    if values.ndim != 1 or kind not in 'biuf':
        raise InputError(f'{what} field {name!r} must hold integers, found type {cloud.points.dtype.fields[name][0]}')
    if kind == 'f':
        bad = ~np.isfinite(values) | (values != np.trunc(values))
        if bad.any():
            example = values[np.flatnonzero(bad)[0]].item()
            raise InputError(f'{what} field {name!r} must hold integers, found {int(bad.sum())} '
                             f'of {len(values)} values that are not, e.g. {example!r}')
    return values.astype(np.int64)


def _listed(values: np.ndarray) -> str:
    """Sorted distinct integers as ``[a, b, ...]``, elided after a few."""
    shown = ', '.join(str(v) for v in values[:_MAX_LISTED_CLASSES].tolist())
    more = f', ... ({len(values)} values)' if len(values) > _MAX_LISTED_CLASSES else ''
    return f'[{shown}{more}]'


def _selects(names: Sequence[str], config: InputConfig, selection: SelectionConfig | None) -> bool:
    """Whether a cloud with fields ``names`` is reduced by the selection rather than by its class."""
    if selection is None or selection.mode == 'off':
        return False
    return selection.mode == 'on' or config.class_field not in names


def select_building_points(cloud: Cloud, config: InputConfig, selection: SelectionConfig | None = None,
                           sensor: Sequence[float] | np.ndarray | None = None,
                           trajectory: Trajectory | None = None) -> BuildingPoints:
    """Keep the points whose class is one of ``config.building_classes``, or the selected ones.

    A cloud without the field ``config.class_field`` (or any cloud, with
    ``selection.mode: on``) is reduced to the points on tall vertical planes by
    :func:`uncertain_facade_map.selection.select_building_points`, given the cloud's sensor
    origins when it has them; with ``selection`` None or ``selection.mode: off`` it is
    taken as all building points. The class field may be of any integer or bool type, or
    float holding integral values (e.g. a PCD label stored as float); values are compared
    as int64.

    Args:
        cloud: the input cloud (map frame, metres).
        config: ``class_field``, ``building_classes`` and ``building_id_field`` are used.
        selection: the selection's parameters; None for none.
        sensor: (3,) the sensor's position (map frame, metres) for a cloud without sensor
            origins (one sweep, or a map scanned from about one place); every point takes
            it as its origin. Ignored when the cloud has origins. None: without origins
            the façades are turned outwards from their buildings' shapes.
        trajectory: the sensor's path, for a cloud without sensor origins but with a
            per-point ``time`` field (seconds, the trajectory's time base): each point's
            origin is the path's position at its time (:mod:`.trajectory`; positions
            georeferenced, the cloud's map origin is subtracted). Ignored when the cloud
            has origins; not together with ``sensor``.

    Returns:
        The building points in input order, with their indices in ``cloud``, the building
        ids (from ``building_id_field``, if the cloud has that field; it must hold
        integers too), sensor origins (the cloud's, else ``sensor``'s) and times when the
        cloud has them.

    Raises:
        InputError: an empty cloud; NaN or infinite coordinates (x, y or z) in any point,
            building or not (the message says how many); a class or building id field that
            is not integer-valued; no building point at all (the message lists the class
            values found and the configured ``building_classes``, or says that the
            selection found no wall); ``sensor`` not three finite numbers; ``trajectory``
            with ``sensor``, for a cloud without a ``time`` field, or with point times
            outside its span.
    """
    n = len(cloud)
    if n == 0:
        raise InputError('the input cloud has no points')
    origins = cloud.sensor_origins
    if sensor is not None and trajectory is not None:
        raise InputError('give the sensor a position or a trajectory, not both')
    if origins is None and trajectory is not None:
        times = cloud.get('time')
        if times is None:
            raise InputError(f'a trajectory gives sensor origins by each point\'s time, but the cloud has no '
                             f'time field (fields: {", ".join(cloud.fields)})')
        origins = trajectory.positions_at(times) - cloud.map_origin
    if origins is None and sensor is not None:
        position = np.asarray(sensor, dtype=np.float64)
        if position.shape != (3,) or not np.isfinite(position).all():
            raise InputError(f'the sensor position must be three finite numbers (x, y, z), got {sensor!r}')
        origins = np.broadcast_to(position, (n, 3))
    finite = np.ones(n, dtype=bool)
    for c in ('x', 'y', 'z'):
        finite &= np.isfinite(cloud.points[c])
    if not finite.all():
        raise InputError(f'{int(n - finite.sum())} of {n} input points have NaN or infinite coordinates')

    found = None
    if _selects(cloud.fields, config, selection):
        from ..selection import select_building_points as select_walls

        found = select_walls(cloud.xyz, origins, selection)
        if not found.mask.any():
            raise InputError(f'no building points: the selection (selection.mode: {selection.mode}) found no wall '
                             f'in {n} points of a cloud without classes ({found.ground.sum()} ground)')
        index = np.flatnonzero(found.mask).astype(np.int64)
    elif config.class_field in cloud.fields:
        classes = _integer_values(cloud, config.class_field, 'class')
        wanted = np.asarray(config.building_classes, dtype=np.int64)
        mask = np.isin(classes, wanted)
        if not mask.any():
            found = np.unique(classes)
            hint = ''
            if _ASPRS_BUILDING in found and _ASPRS_BUILDING not in wanted:
                hint = ('; ASPRS LAS files mark buildings with class 6, '
                        'set input.building_classes: [6]')
            raise InputError(f'no building points: class field {config.class_field!r} holds '
                             f'{_listed(found)}, input.building_classes is '
                             f'{_listed(np.unique(wanted))}{hint}')
        index = np.flatnonzero(mask).astype(np.int64)
    else:
        index = np.arange(n, dtype=np.int64)

    building_id = None
    if config.building_id_field in cloud.fields:
        building_id = _integer_values(cloud, config.building_id_field, 'building id')[index]
    selected = cloud if len(index) == n else cloud.select(index)
    time = selected.get('time')
    return BuildingPoints(
        xyz=selected.xyz,
        building_id=building_id,
        sensor_origins=None if origins is None else np.array(origins[index], dtype=np.float64),
        time=None if time is None else time.astype(np.float64),
        index=index,
        map_origin=cloud.map_origin.copy(),
        selection=found,
    )


@dataclass(frozen=True, eq=False)
class ScanPoints:
    """The building points of one live scan, and what was left out.

    Attributes:
        xyz: (N, 3) float64 building points with finite coordinates, metres, frame of the scan.
        building_id: (N,) int64 building ids, or None.
        sensor_origins: (N, 3) float64 sensor positions, metres, or None.
        nonfinite: number of points skipped for NaN or infinite coordinates.
        not_building: number of finite points of another class, or not selected.
        selection: what the selection found (why it dropped what it dropped, for
            :func:`uncertain_facade_map.selection.selection_warning`) when the scan was
            reduced by it, else None.
    """

    xyz: np.ndarray
    building_id: np.ndarray | None
    sensor_origins: np.ndarray | None
    nonfinite: int
    not_building: int
    selection: Selection | None = None


def select_scan_points(points: np.ndarray, config: InputConfig, selection: SelectionConfig | None = None,
                       sensor_origin: np.ndarray | None = None) -> ScanPoints:
    """Building points of one scan (a PointCloud2 as a structured array), tolerant of gaps.

    Unlike :func:`select_building_points` (whole inputs, where a NaN is an error), a live
    scan may hold NaN or infinite points (no return): they are skipped and counted. A scan
    without building points gives empty arrays. A scan without the class field is reduced
    by the selection as :func:`select_building_points` does, in the scan's own frame. Used
    alike by the node and by offline replay, so both map the same points.

    Args:
        points: (M,) structured array with at least float fields ``x``, ``y``, ``z``;
            ``config.class_field``, ``config.building_id_field`` and ``origin_x``,
            ``origin_y``, ``origin_z`` are used when present.
        config: which class values are building.
        selection: the selection's parameters for scans without classes; None for none
            (such a scan is all building).
        sensor_origin: (3,) sensor position in the scan's frame, metres, for the selection
            when the scan has no origin fields (e.g. zeros for a scan in the sensor's frame);
            None if unknown.

    Returns:
        The building points.

    Raises:
        InputError: no x, y or z field (the message lists the fields), a coordinate or
            class field that is not numeric, or a class or building id field that holds
            non-integer values.
    """
    names = points.dtype.names or ()
    missing = [c for c in ('x', 'y', 'z') if c not in names]
    if missing:
        raise InputError(f'no {", ".join(missing)} field (fields: {", ".join(names) or "none"})')
    for c in ('x', 'y', 'z'):
        if points.dtype[c].kind not in 'iuf' or points.dtype[c].shape:
            raise InputError(f'field {c!r} must be a number, found type {points.dtype[c]}')
    cloud = Cloud(points)
    xyz = np.stack([points[c].astype(np.float64) for c in ('x', 'y', 'z')], axis=1)
    keep = np.isfinite(xyz).all(axis=1)
    nonfinite = int((~keep).sum())
    not_building = 0
    found = None
    origin_fields = all(c in names for c in ('origin_x', 'origin_y', 'origin_z'))
    if _selects(names, config, selection):
        origins = sensor_origin
        if origin_fields:
            origins = np.stack([points[c][keep].astype(np.float64) for c in ('origin_x', 'origin_y', 'origin_z')], 1)
            origins = origins if np.isfinite(origins).all() else sensor_origin
        from ..selection import select_building_points as select_walls

        selected = np.zeros(len(keep), dtype=bool)
        found = select_walls(xyz[keep], origins, selection)
        selected[keep] = found.mask
        not_building = int((keep & ~selected).sum())
        keep = selected
    elif config.class_field in names:
        classes = _integer_values(cloud, config.class_field, 'class')
        building = np.isin(classes, np.asarray(config.building_classes, dtype=np.int64))
        not_building = int((keep & ~building).sum())
        keep &= building
    ids = None
    if config.building_id_field in names:
        ids = _integer_values(cloud, config.building_id_field, 'building id')[keep]
    origins = None
    if origin_fields:
        origins = np.stack([points[c][keep].astype(np.float64) for c in ('origin_x', 'origin_y', 'origin_z')], 1)
        if not np.isfinite(origins).all():
            origins = None
    return ScanPoints(xyz[keep], ids, origins, nonfinite, not_building, found)
