"""numpy and core results <-> the ROS messages the façade-mapping node publishes and serves.

Like :mod:`.pointcloud2`, the functions read and set message *attributes* only and never
check message classes: message classes come in through a ``msg_types`` namespace (see
:func:`rclpy_map_types`), so the same code serves rclpy's generated classes, rosbags'
dataclasses and plain stand-ins. Neither rclpy nor the core's modelling modules are
imported when this module loads; façade models are read by their attributes.

Conventions:

* All positions are metres. ``map`` is the frame the façade models live in; a façade
  frame has axes rows ``e_u`` (along the façade, horizontal), ``e_v`` (up the plane) and
  ``n`` (outward normal), see :class:`uncertain_facade_map.datatypes.FacadeFrame`.
* A rigid transform ``(R, t)`` maps child coordinates to parent coordinates:
  ``x_parent = R @ x_child + t``; a ``geometry_msgs/Pose`` of a façade frame in ``map``
  is that transform with ``R = axes.T`` (columns ``e_u, e_v, n``).
* Quaternions are ``(x, y, z, w)`` as in ROS, unit length, and written with ``w >= 0``.
* Stamps are integer nanoseconds since the UNIX epoch, ``0 <= stamp_ns < 2**31 s``.
* Numeric sequence fields (``float64[]``, ``float32[]``, ``int8[]``, ``int32[]``) are set
  in one copy, never element by element: ``array.array`` of the field's type code for
  rclpy (what its generated setters store, and accept with ``ROS_PYTHON_CHECK_FIELDS=1``),
  numpy arrays for dataclass messages (rosbags). A namespace may override this with an
  ``encode_array(values, typecode)`` attribute. Fixed-size arrays (``float64[4]``) are
  always float64 numpy arrays, as both rclpy and rosbags store them.
* Scalar fields get Python ``int``/``float``/``bool``/``str``, never numpy scalars (rclpy
  asserts ``isinstance(value, int)`` for integer fields when field checks are on).

Errors a caller can cause (shapes, NaN, too many points, a degenerate quaternion) raise
:class:`uncertain_facade_map.errors.InputError`, a ``ValueError``.
"""

from __future__ import annotations

import dataclasses
import importlib
import itertools
import operator
from array import array
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any, Iterable, Mapping, Sequence

import numpy as np

from uncertain_facade_map.errors import InputError

if TYPE_CHECKING:  # only for annotations: the core's model module is heavy to import
    from uncertain_facade_map.datatypes import FacadeModel

#: The answer arrays of ``QueryPoints``, with their numpy type and ``array.array`` code.
QUERY_FIELDS: dict[str, tuple[str, str]] = {
    'facade': ('i4', 'i'),
    'mean_depth': ('f8', 'd'),
    'variance': ('f8', 'd'),
    'noise_variance': ('f8', 'd'),
    'signed_distance': ('f8', 'd'),
    'p_occupied': ('f8', 'd'),
}

#: Marker ids of a façade's surface: chunk k of façade f has id ``f + k * MARKER_ID_STRIDE``.
MARKER_ID_STRIDE = 1 << 20
#: Most vertices (3 per triangle) in one TRIANGLE_LIST marker.
MARKER_MAX_VERTICES = 60_000
#: Colour levels of the ramp (colours are quantised to these, then shared).
COLOUR_LEVELS = 256

#: A viridis-like ramp: RGB at 0, 1/8, ..., 1 (samples of matplotlib's viridis).
_RAMP = np.array([
    [0.267004, 0.004874, 0.329415],
    [0.278826, 0.175490, 0.483397],
    [0.229739, 0.322361, 0.545706],
    [0.172719, 0.448791, 0.557885],
    [0.127568, 0.566949, 0.550556],
    [0.157851, 0.683765, 0.501686],
    [0.369214, 0.788888, 0.382914],
    [0.678489, 0.863742, 0.189503],
    [0.993248, 0.906157, 0.143936],
])
#: Colour of vertices whose standard deviation is NaN.
_UNKNOWN_RGB = (0.6, 0.6, 0.6)

#: ``diagnostic_msgs/DiagnosticStatus`` levels.
DIAGNOSTIC_LEVELS = {0: 'OK', 1: 'WARN', 2: 'ERROR', 3: 'STALE'}

_NUMPY_OF_CODE = {'b': np.int8, 'B': np.uint8, 'i': np.int32, 'I': np.uint32, 'f': np.float32,
                  'd': np.float64}


# --------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------


def _encode(msg_types: Any, cls: Any, values: np.ndarray, typecode: str) -> Any:
    """Value of a numeric sequence field of a ``cls`` message.

    Args:
        msg_types: namespace; its ``encode_array(values, typecode)`` is used when present.
        cls: the message class (or factory) the field belongs to.
        values: 1-D array, already of the field's numpy type.
        typecode: ``array.array`` type code of the field ('b', 'i', 'f', 'd', ...).

    Returns:
        ``msg_types.encode_array(values, typecode)`` if given; a numpy array for a dataclass
        message (rosbags); else ``array.array(typecode)`` (rclpy).
    """
    encode = getattr(msg_types, 'encode_array', None) if msg_types is not None else None
    if encode is not None:
        return encode(values, typecode)
    if dataclasses.is_dataclass(cls):
        return np.ascontiguousarray(values, dtype=_NUMPY_OF_CODE[typecode]).reshape(-1)
    return encode_array(values, typecode)


def encode_array(values: np.ndarray, typecode: str) -> array:
    """Copy a numeric array into ``array.array(typecode)`` (rclpy's type for ``T[]``).

    Args:
        values: array of any shape; flattened in C order.
        typecode: 'b' int8, 'B' uint8, 'i' int32, 'I' uint32, 'f' float32, 'd' float64.

    Returns:
        The array, built with one buffer copy.
    """
    out = array(typecode)
    out.frombytes(np.ascontiguousarray(values, dtype=_NUMPY_OF_CODE[typecode]).reshape(-1).view(np.uint8))
    return out


def _time(msg_types: Any, stamp_ns: int) -> Any:
    """``builtin_interfaces/Time`` of integer nanoseconds.

    Raises:
        InputError: the stamp is outside ``0 .. 2**31`` s.
    """
    stamp_ns = int(stamp_ns)
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    if not 0 <= sec < 2**31:
        raise InputError(f'stamp {stamp_ns} ns is outside 0 .. 2**31 s')
    return msg_types.Time(sec=int(sec), nanosec=int(nanosec))


def _header(msg_types: Any, frame_id: str, stamp_ns: int) -> Any:
    """``std_msgs/Header`` with the stamp and frame id."""
    return msg_types.Header(stamp=_time(msg_types, stamp_ns), frame_id=str(frame_id))


def _need(msg_types: Any, name: str) -> Any:
    """``msg_types.<name>``, or a clear ImportError when the class is absent (None)."""
    cls = getattr(msg_types, name, None)
    if cls is None:
        raise ImportError(
            f'message class {name} is not available in msg_types; for the package\'s own '
            f'interfaces (Facade, FacadeGrid, FacadeGridArray) build them with colcon and '
            f'source the workspace')
    return cls


def _vec(values: Any, size: int, what: str) -> np.ndarray:
    """``values`` as a finite float64 vector of ``size`` elements."""
    out = np.asarray(values, dtype=np.float64).reshape(-1)
    if out.shape != (size,):
        raise InputError(f'{what} must have {size} values, got shape {np.shape(values)}')
    if not np.isfinite(out).all():
        raise InputError(f'{what} has NaN or infinite values: {out}')
    return out


# --------------------------------------------------------------------------------------
# rotations and poses
# --------------------------------------------------------------------------------------


def quaternion_from_matrix(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion of a rotation matrix, by Shepperd's method.

    Shepperd's method takes the square root of the largest of ``4 w^2, 4 x^2, 4 y^2,
    4 z^2`` (from the trace and the diagonal), so it stays accurate for every rotation,
    also near 180 degrees where ``w`` vanishes.

    Args:
        rotation: (3, 3) proper rotation matrix (orthonormal within 1e-6, determinant +1).

    Returns:
        (4,) float64 ``(x, y, z, w)``, unit length, ``w >= 0``.

    Raises:
        InputError: wrong shape, NaN or infinite entries, not orthonormal, or a reflection
            (determinant -1, e.g. left-handed façade axes).
    """
    r = np.asarray(rotation, dtype=np.float64)
    if r.shape != (3, 3):
        raise InputError(f'a rotation matrix is (3, 3), got shape {r.shape}')
    if not np.isfinite(r).all():
        raise InputError('rotation matrix has NaN or infinite entries')
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-6):
        raise InputError('rotation matrix is not orthonormal')
    if np.linalg.det(r) <= 0:
        raise InputError('rotation matrix is a reflection (determinant -1): axes are left-handed')
    trace = r[0, 0] + r[1, 1] + r[2, 2]
    diag = (trace, r[0, 0], r[1, 1], r[2, 2])
    k = int(np.argmax(diag))
    if k == 0:
        s = 2.0 * np.sqrt(1.0 + trace)  # s = 4 w
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s]
    elif k == 1:
        s = 2.0 * np.sqrt(max(1.0 + r[0, 0] - r[1, 1] - r[2, 2], 0.0))  # s = 4 x
        q = [0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
    elif k == 2:
        s = 2.0 * np.sqrt(max(1.0 - r[0, 0] + r[1, 1] - r[2, 2], 0.0))  # s = 4 y
        q = [(r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(max(1.0 - r[0, 0] - r[1, 1] + r[2, 2], 0.0))  # s = 4 z
        q = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s, (r[1, 0] - r[0, 1]) / s]
    out = np.array(q)
    out /= np.linalg.norm(out)
    return -out if out[3] < 0 else out


def matrix_from_quaternion(quaternion: Any) -> np.ndarray:
    """Rotation matrix of a quaternion, normalised first.

    Args:
        quaternion: (4,) ``(x, y, z, w)`` of any positive finite length, or an object with
            attributes ``x, y, z, w`` (``geometry_msgs/Quaternion``).

    Returns:
        (3, 3) float64 rotation matrix.

    Raises:
        InputError: NaN or infinite components, or a (near) zero quaternion (norm below
            1e-12), which has no rotation.
    """
    if all(hasattr(quaternion, a) for a in ('x', 'y', 'z', 'w')):
        q = np.array([quaternion.x, quaternion.y, quaternion.z, quaternion.w], dtype=np.float64)
    else:
        q = np.asarray(quaternion, dtype=np.float64).reshape(-1)
        if q.shape != (4,):
            raise InputError(f'a quaternion has 4 components (x, y, z, w), got shape {q.shape}')
    if not np.isfinite(q).all():
        raise InputError(f'quaternion (x, y, z, w) = {tuple(q.tolist())} has NaN or infinite components')
    norm = float(np.linalg.norm(q))
    if norm < 1e-12:
        raise InputError(f'quaternion (x, y, z, w) = {tuple(q.tolist())} is zero: no rotation')
    x, y, z, w = q / norm
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def pose_from_frame(origin: np.ndarray, axes: np.ndarray, msg_types: Any) -> Any:
    """``geometry_msgs/Pose`` of a façade frame in the map frame.

    Args:
        origin: (3,) a point of the façade plane, metres, map frame.
        axes: (3, 3) rows ``e_u, e_v, n`` (orthonormal, right-handed), map frame.
        msg_types: namespace with ``Pose``, ``Point`` and ``Quaternion``.

    Returns:
        Pose with ``position = origin`` and ``orientation`` the quaternion of the rotation
        whose columns are ``e_u, e_v, n`` (façade frame -> map: x -> e_u, y -> e_v,
        z -> n).

    Raises:
        InputError: wrong shapes, NaN, or axes that are not a rotation.
    """
    o = _vec(origin, 3, 'frame origin')
    a = np.asarray(axes, dtype=np.float64)
    if a.shape != (3, 3):
        raise InputError(f'frame axes are (3, 3), got shape {a.shape}')
    x, y, z, w = quaternion_from_matrix(a.T).tolist()
    t = msg_types
    return t.Pose(position=t.Point(x=float(o[0]), y=float(o[1]), z=float(o[2])),
                  orientation=t.Quaternion(x=x, y=y, z=z, w=w))


def _identity_pose(msg_types: Any, xyz: Sequence[float] = (0.0, 0.0, 0.0)) -> Any:
    t = msg_types
    return t.Pose(position=t.Point(x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2])),
                  orientation=t.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))


def rigid_from_pose(msg: Any) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and translation of a pose or transform message.

    Reads, by attributes: ``position``/``orientation`` (Pose), ``translation``/``rotation``
    (Transform), unwrapping ``.pose`` (PoseStamped, PoseWithCovariance[Stamped]) and
    ``.transform`` (TransformStamped) as often as needed.

    Args:
        msg: ``geometry_msgs`` Pose, PoseStamped, Transform, TransformStamped (any
            implementation), or anything with the same attributes.

    Returns:
        ``(R, t)``: (3, 3) rotation of the normalised quaternion and (3,) translation,
        float64, with ``x_parent = R @ x_child + t`` (for a Pose of a façade frame:
        ``R`` has columns ``e_u, e_v, n`` and ``t`` is the origin, metres).

    Raises:
        InputError: the message has none of these attributes, a zero or non-finite
            quaternion, or a non-finite translation.
    """
    obj, found = msg, None
    for _ in range(8):  # deeper than any geometry_msgs nesting
        if hasattr(obj, 'position') and hasattr(obj, 'orientation'):
            found = (obj.position, obj.orientation)
        elif hasattr(obj, 'translation') and hasattr(obj, 'rotation'):
            found = (obj.translation, obj.rotation)
        elif hasattr(obj, 'pose'):
            obj = obj.pose
            continue
        elif hasattr(obj, 'transform'):
            obj = obj.transform
            continue
        break
    if found is None:
        raise InputError(
            f'{type(msg).__name__} is not a pose or transform: it has no position/orientation, '
            f'translation/rotation, .pose or .transform')
    p, q = found
    t = _vec([p.x, p.y, p.z], 3, 'translation')
    return matrix_from_quaternion(q), t


def transform_points(xyz: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Apply a rigid transform to points.

    Args:
        xyz: (N, 3) points in the child frame, metres.
        rotation: (3, 3) rotation R.
        translation: (3,) translation t, metres.

    Returns:
        (N, 3) float64 ``R @ x + t`` for each point, parent frame.

    Raises:
        InputError: wrong shapes.
    """
    p = np.asarray(xyz, dtype=np.float64)
    r = np.asarray(rotation, dtype=np.float64)
    t = np.asarray(translation, dtype=np.float64).reshape(-1)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f'points must be an (N, 3) array, got shape {p.shape}')
    if r.shape != (3, 3) or t.shape != (3,):
        raise InputError(f'a rigid transform is a (3, 3) rotation and a (3,) translation, '
                         f'got {r.shape} and {t.shape}')
    return p @ r.T + t


# --------------------------------------------------------------------------------------
# QueryPoints service
# --------------------------------------------------------------------------------------


_XYZ = operator.attrgetter('x', 'y', 'z')


def points_from_request(request: Any, max_points: int | None) -> np.ndarray:
    """The query points of a ``QueryPoints`` request.

    Reads ``request.points``: a sequence of ``geometry_msgs/Point`` (attributes x, y, z;
    read in C through ``operator.attrgetter`` and ``np.fromiter``, no Python loop body),
    or an (N, 3) numeric array; when it is empty, ``request.xyz`` (if the request has it):
    3 numbers per point, x0, y0, z0, x1, ... (the fast way: no message per point).

    Args:
        request: ``QueryPoints.Request`` or anything with ``points``.
        max_points: most points accepted (the ``service.max_query_points`` parameter);
            None for no limit.

    Returns:
        (N, 3) float64 points, metres, map frame; (0, 3) when there are none.

    Raises:
        InputError: more than ``max_points`` points (checked before reading them),
            non-numeric coordinates, or points with NaN or infinite coordinates (the
            message says how many and the first one's index).
    """
    pts = request.points
    n = len(pts)
    flat_xyz = getattr(request, 'xyz', None) if n == 0 else None
    if flat_xyz is not None and len(flat_xyz):
        if len(flat_xyz) % 3:
            raise InputError(f'query xyz must hold 3 numbers per point, got {len(flat_xyz)} numbers')
        n = len(flat_xyz) // 3
    if max_points is not None and n > int(max_points):
        raise InputError(f'{n} query points, at most {int(max_points)} are accepted per request')
    if n == 0:
        return np.zeros((0, 3), dtype=np.float64)
    if flat_xyz is not None and len(flat_xyz):
        try:
            xyz = np.array(flat_xyz, dtype=np.float64).reshape(n, 3)
        except (TypeError, ValueError) as err:
            raise InputError(f'query point coordinates must be numbers: {err}') from None
    elif isinstance(pts, np.ndarray) and pts.ndim == 2:
        if pts.shape[1] != 3:
            raise InputError(f'query points must be (N, 3), got shape {pts.shape}')
        xyz = np.array(pts, dtype=np.float64)
    else:
        try:
            flat = np.fromiter(itertools.chain.from_iterable(map(_XYZ, pts)), dtype=np.float64,
                               count=3 * n)
        except AttributeError as err:
            raise InputError(f'query points must have x, y and z: {err}') from None
        except (TypeError, ValueError) as err:
            raise InputError(f'query point coordinates must be numbers: {err}') from None
        xyz = flat.reshape(n, 3)
    bad = ~np.isfinite(xyz).all(axis=1)
    if bad.any():
        raise InputError(f'{int(bad.sum())} of {n} query points have NaN or infinite coordinates '
                         f'(the first is point {int(np.argmax(bad))})')
    return xyz


def fill_query_response(response: Any, answers: Any, message: str = '', *,
                        msg_types: Any = None) -> Any:
    """Fill a ``QueryPoints`` response with the answers of the core's point query.

    Args:
        response: ``QueryPoints.Response`` (or anything with its fields); modified in place.
        answers: mapping with (N,) arrays ``facade`` (int, -1 for none), ``mean_depth``
            (metres), ``variance`` (m^2), ``noise_variance`` (m^2), ``signed_distance``
            (metres, positive outside) and ``p_occupied``, and optionally the (N, 3)
            ``normal`` (unit, map frame; written 3 numbers per point), as
            :meth:`uncertain_facade_map.pipeline.step7_queries.PointQuery.as_dict` gives; a ``PointQuery``
            itself is accepted too.
        message: the response's ``message``.
        msg_types: optional namespace whose ``encode_array(values, typecode)`` encodes the
            arrays; without it, ``array.array`` ('i' for int32[], 'd' for float64[]) unless
            ``response`` is a dataclass (then numpy arrays).

    Returns:
        ``response``, with ``success = True``, ``message`` and the arrays set (``normal``
        when the answers and the response have it).

    Raises:
        InputError: a missing answer, arrays of different lengths or not 1-D (``normal``:
            not (N, 3)), or façade ids outside int32.
    """
    if hasattr(answers, 'as_dict'):
        answers = answers.as_dict()
    missing = [k for k in QUERY_FIELDS if k not in answers]
    if missing:
        raise InputError(f'query answers lack {", ".join(missing)}')
    arrays = {k: np.asarray(answers[k]) for k in QUERY_FIELDS}
    shapes = {k: a.shape for k, a in arrays.items()}
    if any(len(s) != 1 for s in shapes.values()) or len({s[0] for s in shapes.values()}) != 1:
        raise InputError(f'query answers must be 1-D arrays of one length, got shapes {shapes}')
    facade = arrays['facade']
    if facade.size and (facade.min() < -2**31 or facade.max() >= 2**31):
        raise InputError('façade ids do not fit int32')
    normal = answers.get('normal')
    if normal is not None:
        normal = np.asarray(normal, dtype=np.float64)
        if normal.shape != (len(facade), 3):
            raise InputError(f'query normals must be ({len(facade)}, 3), got shape {normal.shape}')
    encoder = msg_types if msg_types is not None else SimpleNamespace()
    cls = type(response)
    for key, (dtype, code) in QUERY_FIELDS.items():
        setattr(response, key, _encode(encoder, cls, arrays[key].astype(dtype), code))
    if normal is not None and hasattr(response, 'normal'):
        response.normal = _encode(encoder, cls, normal.reshape(-1), 'd')
    response.success = True
    response.message = str(message)
    return response


def fill_list_tiles_response(response: Any, ids: Sequence[str], bounds: Any, files: Sequence[str],
                             loaded: Sequence[bool], message: str = '', *, msg_types: Any = None) -> Any:
    """Fill a ``ListTiles`` response with the tiles of a tiled map near a position.

    Args:
        response: ``ListTiles.Response`` (or anything with its fields); modified in place.
        ids: (K,) tile ids (``'tile_<ix>_<iy>'``).
        bounds: (K, 4) the tiles' squares, ``min_x, min_y, max_x, max_y``, metres, map frame
            (written 4 numbers per tile).
        files: (K,) the tiles' map files, absolute paths.
        loaded: (K,) whether the node holds each tile loaded.
        message: the response's ``message``.
        msg_types: optional namespace whose ``encode_array(values, typecode)`` encodes
            ``bounds``; without it, ``array.array('d')`` unless ``response`` is a dataclass
            (then a numpy array). ``ids``, ``files`` are lists of ``str``, ``loaded`` of ``bool``.

    Returns:
        ``response``, with ``success = True``.

    Raises:
        InputError: lengths that differ, bounds not (K, 4), not finite or with a min above
            its max, or an id or file that is not text.
    """
    ids, files, loaded = list(ids), list(files), list(loaded)
    box = np.asarray(bounds, dtype=np.float64)
    if box.size == 0 and not ids:
        box = box.reshape(0, 4)
    if box.ndim != 2 or box.shape[1] != 4:
        raise InputError(f'tile bounds must be (K, 4) min_x, min_y, max_x, max_y, got shape {box.shape}')
    if not len(ids) == len(box) == len(files) == len(loaded):
        raise InputError(f'tile lists of different lengths: {len(ids)} ids, {len(box)} bounds, {len(files)} files, '
                         f'{len(loaded)} loaded flags')
    if not np.isfinite(box).all() or (box[:, 2:] < box[:, :2]).any():
        raise InputError('tile bounds must be finite with min_x <= max_x and min_y <= max_y')
    for name, values in (('id', ids), ('file', files)):
        bad = [v for v in values if not isinstance(v, str)]
        if bad:
            raise InputError(f'a tile {name} must be text, got {bad[0]!r}')
    encoder = msg_types if msg_types is not None else SimpleNamespace()
    response.ids = ids
    response.bounds = _encode(encoder, type(response), box.reshape(-1), 'd')
    response.files = files
    response.loaded = [bool(v) for v in loaded]
    response.success = True
    response.message = str(message)
    return response


def tiles_of_response(response: Any) -> dict[str, Any]:
    """The tiles of a ``ListTiles`` response: ``ids`` (list of str), ``bounds`` (K, 4) float64
    (min_x, min_y, max_x, max_y, metres, map frame), ``files`` (list of str) and ``loaded``
    (K,) bool.

    Raises:
        InputError: ``bounds`` not 4 numbers per id, or lists of different lengths.
    """
    ids = [str(v) for v in response.ids]
    box = np.asarray(response.bounds, dtype=np.float64).reshape(-1)
    if box.size != 4 * len(ids):
        raise InputError(f'ListTiles bounds hold {box.size} numbers for {len(ids)} tiles (4 per tile expected)')
    files = [str(v) for v in response.files]
    loaded = np.asarray(list(response.loaded), dtype=bool)
    if not len(files) == len(loaded) == len(ids):
        raise InputError(f'ListTiles lists of different lengths: {len(ids)} ids, {len(files)} files, '
                         f'{len(loaded)} loaded flags')
    return {'ids': ids, 'bounds': box.reshape(-1, 4), 'files': files, 'loaded': loaded}


# --------------------------------------------------------------------------------------
# façade models and rasters
# --------------------------------------------------------------------------------------


def facade_msg(model: FacadeModel, msg_types: Any) -> Any:
    """``uncertain_facade_map/Facade`` of a core façade model.

    Args:
        model: a :class:`uncertain_facade_map.datatypes.FacadeModel` (read by attributes:
            ``facade_id, building, frame.origin, frame.axes, extent, layers.weights_,
            layers.means_, layers.sigmas_, layers.main_, global_mean_, global_var_,
            noise_var, point_index, facets.n_facets``).
        msg_types: namespace with ``Facade``, ``Pose``, ``Point``, ``Quaternion``.

    Returns:
        Facade message: ``frame`` the façade frame's pose in the map frame (see
        :func:`pose_from_frame`); ``plane = (a, b, c, d)`` with ``(a, b, c)`` the unit
        outward normal and ``d = -n . origin`` (so ``n . x + d = 0`` on the plane, metres);
        ``extent = (u_min, u_max, v_min, v_max)``, metres, façade frame; the GMM layers
        (weights, depths mu_k and spreads sigma_k, metres) and main layer; the global prior
        mean (metres) and variance (m^2); the noise variance (m^2); ``points`` = the number
        of the façade's points and ``facets`` = its number of facets.

    Raises:
        ImportError: ``msg_types.Facade`` is missing (interfaces not built).
        InputError: a frame that is not a rotation, or layer arrays of different lengths.
    """
    facade_cls = _need(msg_types, 'Facade')
    frame = model.frame
    origin = _vec(frame.origin, 3, 'frame origin')
    axes = np.asarray(frame.axes, dtype=np.float64)
    normal = axes[2]
    layers = model.layers
    weights = np.asarray(layers.weights_, dtype=np.float64).reshape(-1)
    means = np.asarray(layers.means_, dtype=np.float64).reshape(-1)
    sigmas = np.asarray(layers.sigmas_, dtype=np.float64).reshape(-1)
    if not weights.shape == means.shape == sigmas.shape:
        raise InputError(f'layer weights, means and sigmas differ in length: '
                         f'{weights.size}, {means.size}, {sigmas.size}')
    plane = np.array([normal[0], normal[1], normal[2], -float(normal @ origin)])
    return facade_cls(
        facade_id=int(model.facade_id),
        building=int(model.building),
        frame=pose_from_frame(origin, axes, msg_types),
        plane=plane,
        extent=np.asarray(model.extent, dtype=np.float64).reshape(4).copy(),
        layer_weights=_encode(msg_types, facade_cls, weights, 'd'),
        layer_means=_encode(msg_types, facade_cls, means, 'd'),
        layer_sigmas=_encode(msg_types, facade_cls, sigmas, 'd'),
        main_layer=int(layers.main_),
        global_mean=float(model.global_mean_),
        global_variance=float(model.global_var_),
        noise_variance=float(model.noise_var),
        points=int(len(model.point_index)),
        facets=int(model.facets.n_facets),
    )


def facade_grid_msg(model: FacadeModel, frame_id: str, stamp_ns: int, msg_types: Any) -> Any:
    """``uncertain_facade_map/FacadeGrid`` of a façade model's surface raster.

    Args:
        model: a core ``FacadeModel`` (reads ``facade_id``, ``building``, ``frame`` and
            ``surface``: a ``SurfaceRaster`` with ``origin`` (2,) metres, ``cell`` metres,
            ``mean`` and ``var`` (H, W) metres and m^2, ``source`` (H, W) int8; row = v,
            column = u).
        frame_id: header frame id, the map frame the façade frame is given in.
        stamp_ns: header stamp, nanoseconds.
        msg_types: namespace with ``FacadeGrid``, ``Header``, ``Time``, ``Pose``, ``Point``,
            ``Quaternion``.

    Returns:
        FacadeGrid with ``origin_u, origin_v`` = the raster's lower-left corner,
        ``resolution`` = cell side, ``width = W`` (along u), ``height = H`` (along v), and
        ``mean_depth`` (float32), ``variance`` (float32) and ``source`` (int8) row-major:
        element ``row * W + col`` is cell (row, col), centred at
        ``u = origin_u + (col + 0.5) * resolution``, ``v = origin_v + (row + 0.5) *
        resolution``.

    Raises:
        ImportError: ``msg_types.FacadeGrid`` is missing.
        InputError: raster arrays of different shapes, or a bad stamp.
    """
    grid_cls = _need(msg_types, 'FacadeGrid')
    raster = model.surface
    mean = np.asarray(raster.mean)
    var = np.asarray(raster.var)
    source = np.asarray(raster.source)
    if mean.ndim != 2 or var.shape != mean.shape or source.shape != mean.shape:
        raise InputError(f'raster mean, variance and source must be (H, W) of one shape, got '
                         f'{mean.shape}, {var.shape}, {source.shape}')
    height, width = mean.shape
    origin = _vec(raster.origin, 2, 'raster origin')
    frame = model.frame
    return grid_cls(
        header=_header(msg_types, frame_id, stamp_ns),
        facade_id=int(model.facade_id),
        building=int(model.building),
        frame=pose_from_frame(frame.origin, frame.axes, msg_types),
        origin_u=float(origin[0]),
        origin_v=float(origin[1]),
        resolution=float(raster.cell),
        width=int(width),
        height=int(height),
        mean_depth=_encode(msg_types, grid_cls, mean.astype(np.float32), 'f'),
        variance=_encode(msg_types, grid_cls, var.astype(np.float32), 'f'),
        source=_encode(msg_types, grid_cls, source.astype(np.int8), 'b'),
    )


def facade_grid_array(models: Iterable[FacadeModel], frame_id: str, stamp_ns: int,
                      msg_types: Any) -> Any:
    """``uncertain_facade_map/FacadeGridArray`` of the rasters of all façades.

    Args:
        models: the façade models, in the order the grids are to appear.
        frame_id: header frame id (map frame) of the array and of every grid.
        stamp_ns: header stamp, nanoseconds.
        msg_types: as :func:`facade_grid_msg`, plus ``FacadeGridArray``.

    Returns:
        FacadeGridArray with one :func:`facade_grid_msg` per model.

    Raises:
        ImportError: ``msg_types.FacadeGridArray`` or ``FacadeGrid`` is missing.
        InputError: as :func:`facade_grid_msg`.
    """
    array_cls = _need(msg_types, 'FacadeGridArray')
    grids = [facade_grid_msg(m, frame_id, stamp_ns, msg_types) for m in models]
    return array_cls(header=_header(msg_types, frame_id, stamp_ns), grids=grids)


# --------------------------------------------------------------------------------------
# occupancy grid
# --------------------------------------------------------------------------------------


def occupancy_grid_msg(p: np.ndarray, origin_xy: Sequence[float], resolution: float, frame_id: str,
                       stamp_ns: int, msg_types: Any, z: float = 0.0) -> Any:
    """``nav_msgs/OccupancyGrid`` of a 2D occupancy probability grid.

    Args:
        p: (H, W) occupancy probabilities in [0, 1], NaN where unknown; ``p[j, i]`` is the
            cell whose lower-left corner is ``origin_xy + (i, j) * resolution`` (column i
            along x, row j along y).
        origin_xy: (2,) x, y of the lower-left corner of cell (0, 0), metres, ``frame_id``.
        resolution: cell side, metres, > 0.
        frame_id: header frame id.
        stamp_ns: header stamp and ``info.map_load_time``, nanoseconds.
        msg_types: namespace with ``OccupancyGrid``, ``MapMetaData``, ``Header``, ``Time``,
            ``Pose``, ``Point``, ``Quaternion``.
        z: height of the grid's plane, metres.

    Returns:
        OccupancyGrid with ``info.width = W``, ``info.height = H``, ``info.resolution``,
        ``info.origin`` = pose at ``(x, y, z)`` with identity orientation, and ``data``
        int8 row-major with x fastest (element ``j * W + i`` is ``p[j, i]``):
        ``round(100 p)`` in 0..100 (half to even, like Python's ``round``), -1 for NaN.

    Raises:
        InputError: ``p`` not 2-D, infinite values or values outside [0, 1] (beyond 1e-9),
            a non-positive resolution, or a non-finite origin.
    """
    grid = np.asarray(p, dtype=np.float64)
    if grid.ndim != 2:
        raise InputError(f'occupancy grid must be (H, W), got shape {grid.shape}')
    origin = _vec(origin_xy, 2, 'grid origin')
    if not (np.isfinite(resolution) and resolution > 0):
        raise InputError(f'grid resolution must be positive, got {resolution}')
    if not np.isfinite(z):
        raise InputError(f'grid height z must be finite, got {z}')
    unknown = np.isnan(grid)
    known = grid[~unknown]
    if known.size and not (np.isfinite(known).all() and known.min() >= -1e-9 and known.max() <= 1 + 1e-9):
        bad = int((~np.isfinite(known) | (known < -1e-9) | (known > 1 + 1e-9)).sum())
        raise InputError(f'{bad} occupancy probabilities are infinite or outside [0, 1]')
    data = np.clip(np.rint(np.where(unknown, 0.0, grid) * 100.0), 0, 100).astype(np.int8)
    data[unknown] = -1
    height, width = grid.shape
    t = msg_types
    info = t.MapMetaData(
        map_load_time=_time(t, stamp_ns),
        resolution=float(resolution),
        width=int(width),
        height=int(height),
        origin=_identity_pose(t, (origin[0], origin[1], z)),
    )
    return t.OccupancyGrid(header=_header(t, frame_id, stamp_ns), info=info,
                           data=_encode(t, t.OccupancyGrid, data, 'b'))


# --------------------------------------------------------------------------------------
# surface mesh markers
# --------------------------------------------------------------------------------------


def colour_ramp(values: np.ndarray, vmax: float, vmin: float = 0.0) -> np.ndarray:
    """Viridis-like RGB colours of values between ``vmin`` and ``vmax``.

    Args:
        values: (N,) values; clipped to [vmin, vmax]; NaN gives grey.
        vmax: value of the brightest colour (yellow).
        vmin: value of the darkest colour (dark violet).

    Returns:
        (N, 3) float64 RGB in [0, 1].
    """
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    span = vmax - vmin if vmax > vmin else 1.0
    s = np.clip((v - vmin) / span, 0.0, 1.0)
    nodes = np.linspace(0.0, 1.0, len(_RAMP))
    out = np.stack([np.interp(s, nodes, _RAMP[:, c]) for c in range(3)], axis=1)
    out[np.isnan(v)] = _UNKNOWN_RGB
    return out


def _unique_rows(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct rows of a finite (N, 3) float64 array: ``xyz[first][inverse] == xyz``.

    Rows are grouped by a 64-bit hash of their bytes (one integer sort, much cheaper than
    sorting 24-byte records); if two different rows ever share a hash, the exact but
    slower byte-record ``np.unique`` is used instead.

    Returns:
        ``(first, inverse)``: (U,) index of one occurrence of each distinct row and (N,)
        the distinct row of every row.
    """
    rows = np.ascontiguousarray(xyz, dtype=np.float64)
    bits = rows.view(np.uint64)
    with np.errstate(over='ignore'):
        key = ((bits[:, 0] * np.uint64(0x9E3779B97F4A7C15))
               ^ (bits[:, 1] * np.uint64(0xC2B2AE3D27D4EB4F))
               ^ (bits[:, 2] * np.uint64(0x165667B19E3779F9)))
    order = np.argsort(key)  # unstable sort: any member may represent its group
    sorted_key = key[order]
    new = np.ones(len(key), dtype=bool)
    new[1:] = sorted_key[1:] != sorted_key[:-1]
    first = order[new]
    inverse = np.empty(len(key), dtype=np.int64)
    inverse[order] = np.cumsum(new) - 1
    if not np.array_equal(bits[first][inverse], bits):  # a hash collision: exact fallback
        records = rows.view(np.dtype((np.void, 24))).reshape(-1)
        _keys, first, inverse = np.unique(records, return_index=True, return_inverse=True)
        inverse = inverse.reshape(-1)
    return first, inverse


def _objects(items: Iterable[Any], count: int) -> np.ndarray:
    """1-D object array of ``count`` items (no per-item inspection by numpy)."""
    return np.fromiter(items, dtype=object, count=count)


def triangle_marker_array(vertices: np.ndarray, triangles: np.ndarray, std: np.ndarray,
                          facade: np.ndarray, frame_id: str, stamp_ns: int, msg_types: Any,
                          std_max: float | None = None, ns: str = 'facade_surface',
                          max_vertices: int = MARKER_MAX_VERTICES, alpha: float = 1.0) -> Any:
    """``visualization_msgs/MarkerArray`` of a surface mesh coloured by its uncertainty.

    The array holds a DELETEALL marker first (same ``ns``; RViz then drops the markers of
    an earlier publication, so façades that vanished disappear), then TRIANGLE_LIST
    markers: per façade its triangles in input order, in chunks of at most
    ``max_vertices // 3`` triangles. Marker ids are stable: chunk ``k`` of façade ``f`` has
    id ``f + k * MARKER_ID_STRIDE`` (2**20), so a façade that needs one marker has id
    ``f``; ids are unique while façade ids are below 2**20 and chunks fewer than 2048.

    ``points`` are the triangles' vertex positions in order (3 per triangle) and
    ``colors`` the per-vertex colours of a viridis-like ramp of ``std`` over
    [0, std_max], quantised to :data:`COLOUR_LEVELS` levels (grey for NaN). To keep a
    500 000-triangle mesh fast (an rclpy ``Point`` takes about 3 us to make), one
    ``Point`` object is made per distinct vertex position and one ``ColorRGBA`` per colour
    level, and the markers' lists share them: treat the result as read-only (publishing
    and serialising are unaffected).

    Args:
        vertices: (V, 3) vertex positions, metres, ``frame_id``.
        triangles: (T, 3) vertex indices, counter-clockwise seen from outside.
        std: (V,) standard deviation of the surface at each vertex, metres (NaN: grey).
        facade: (V,) façade id of each vertex, >= 0; a triangle belongs to the façade of
            its first vertex.
        frame_id: header frame id.
        stamp_ns: header stamp, nanoseconds.
        msg_types: namespace with ``MarkerArray``, ``Marker``, ``Header``, ``Time``,
            ``Pose``, ``Point``, ``Quaternion``, ``Vector3``, ``ColorRGBA``. ``Marker`` is
            called with the fields above only and must default the rest (texture, mesh
            file, lifetime, ...), as rclpy's class does; rosbags' Marker, which needs every
            field, is not supported.
        std_max: std of the brightest colour, metres; None for the 95th percentile of the
            finite ``std`` of the vertices the triangles use (1.0 if that is not positive).
        ns: marker namespace.
        max_vertices: most points per marker (rounded down to a multiple of 3, at least 3).
        alpha: opacity of every vertex colour, [0, 1].

    Returns:
        MarkerArray: ``[DELETEALL, façade markers sorted by façade id then chunk]``; every
        marker has identity pose, scale (1, 1, 1), ``frame_locked`` False, lifetime 0
        (forever).

    Raises:
        InputError: wrong shapes, triangle indices outside 0..V-1, non-finite vertices used
            by a triangle, negative or too large façade ids, too many chunks, or a bad
            ``std_max``/``alpha``.
    """
    verts = np.asarray(vertices, dtype=np.float64)
    tri = np.asarray(triangles)
    std = np.asarray(std, dtype=np.float64).reshape(-1)
    fac = np.asarray(facade).reshape(-1)
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise InputError(f'vertices must be (V, 3), got shape {verts.shape}')
    n_v = len(verts)
    if tri.ndim != 2 or tri.shape[1] != 3 or (tri.size and tri.dtype.kind not in 'iu'):
        raise InputError(f'triangles must be (T, 3) integer indices, got {tri.shape} {tri.dtype}')
    if std.shape != (n_v,) or fac.shape != (n_v,):
        raise InputError(f'std and facade must have one value per vertex ({n_v}), got '
                         f'{std.shape} and {fac.shape}')
    if fac.size and fac.dtype.kind not in 'iu':
        raise InputError(f'façade ids must be integers, got {fac.dtype}')
    if not 0.0 <= alpha <= 1.0:
        raise InputError(f'alpha must be in [0, 1], got {alpha}')
    tri = tri.astype(np.int64, copy=False)
    if tri.size and (tri.min() < 0 or tri.max() >= n_v):
        raise InputError(f'triangle indices must be in 0..{n_v - 1}, got {tri.min()}..{tri.max()}')
    per_marker = max(int(max_vertices) // 3, 1)

    t = msg_types
    header = _header(t, frame_id, stamp_ns)
    marker_cls = t.Marker
    triangle_list = int(getattr(marker_cls, 'TRIANGLE_LIST', 11))
    add = int(getattr(marker_cls, 'ADD', 0))
    delete_all = int(getattr(marker_cls, 'DELETEALL', 3))

    def marker(**fields: Any) -> Any:
        return marker_cls(
            header=header, ns=str(ns), type=triangle_list, pose=_identity_pose(t),
            scale=t.Vector3(x=1.0, y=1.0, z=1.0),
            color=t.ColorRGBA(r=1.0, g=1.0, b=1.0, a=float(alpha)), frame_locked=False,
            **fields)

    markers = [marker(id=0, action=delete_all)]
    if not len(tri):
        return t.MarkerArray(markers=markers)

    mask = np.zeros(n_v, dtype=bool)
    mask[tri.reshape(-1)] = True
    used = np.flatnonzero(mask)  # sorted vertices in use (cheaper than np.unique)
    if not np.isfinite(verts[used]).all():
        raise InputError('vertices used by triangles have NaN or infinite coordinates')
    tri_facade = fac[tri[:, 0]].astype(np.int64)
    if tri_facade.min() < 0 or tri_facade.max() >= MARKER_ID_STRIDE:
        raise InputError(f'façade ids of triangles must be in 0..{MARKER_ID_STRIDE - 1}, got '
                         f'{tri_facade.min()}..{tri_facade.max()}')

    if std_max is None:
        finite = std[used][np.isfinite(std[used])]
        std_max = float(np.percentile(finite, 95)) if finite.size else 1.0
        if not std_max > 0:
            std_max = 1.0
    elif not (np.isfinite(std_max) and std_max > 0):
        raise InputError(f'std_max must be positive, got {std_max}')

    # Colour level per vertex: 0..L-1 along the ramp, L for NaN.
    levels = COLOUR_LEVELS
    level = np.full(n_v, levels, dtype=np.int64)
    ok = ~np.isnan(std)
    with np.errstate(over='ignore'):  # a tiny std_max: the ratio overflows to inf, clipped to 1
        level[ok] = np.rint(np.clip(std[ok] / std_max, 0.0, 1.0) * (levels - 1)).astype(np.int64)
    ramp = colour_ramp(np.linspace(0.0, 1.0, levels), 1.0)
    palette_rgb = np.vstack([ramp, _UNKNOWN_RGB]).tolist()
    a = float(alpha)
    palette = _objects((t.ColorRGBA(r=r, g=g, b=b, a=a) for r, g, b in palette_rgb),
                       levels + 1)

    # One Point per distinct position of a used vertex, looked up by vertex index (a
    # triangle soup, whose corners repeat positions, gets no more Points than its mesh).
    first, inverse = _unique_rows(verts[used])
    point_cls = t.Point
    distinct = _objects((point_cls(x=x, y=y, z=z) for x, y, z in verts[used][first].tolist()),
                        len(first))
    point_of = np.empty(n_v, dtype=object)
    point_of[used] = distinct[inverse]

    order = np.argsort(tri_facade, kind='stable')
    sorted_facade = tri_facade[order]
    starts = np.concatenate([[0], np.flatnonzero(sorted_facade[1:] != sorted_facade[:-1]) + 1])
    ids = sorted_facade[starts]
    ends = np.append(starts[1:], len(order))
    for fid, start, end in zip(ids.tolist(), starts.tolist(), ends.tolist()):
        n_chunks = -(-(end - start) // per_marker)
        if fid + (n_chunks - 1) * MARKER_ID_STRIDE >= 2**31:
            raise InputError(f'façade {fid} needs {n_chunks} markers of {per_marker} triangles; '
                             f'marker ids would overflow int32')
        for k in range(n_chunks):
            sel = order[start + k * per_marker:min(start + (k + 1) * per_marker, end)]
            corner = tri[sel].reshape(-1)
            markers.append(marker(
                id=fid + k * MARKER_ID_STRIDE, action=add,
                points=point_of[corner].tolist(),
                colors=palette[level[corner]].tolist()))
    return t.MarkerArray(markers=markers)


# --------------------------------------------------------------------------------------
# diagnostics
# --------------------------------------------------------------------------------------


def _diagnostic_text(value: Any) -> str:
    """A KeyValue value: numpy scalars as Python numbers, floats in shortest form."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, bytes):
        return value.decode('utf-8', 'replace')
    return str(value)


def diagnostic_array(name: str, level: Any, message: str, values: Mapping[str, Any],
                     hardware_id: str, stamp_ns: int, msg_types: Any) -> Any:
    """``diagnostic_msgs/DiagnosticArray`` with one status.

    Args:
        name: status name (e.g. ``'facade_mapper: map'``).
        level: 0 OK, 1 WARN, 2 ERROR, 3 STALE, as an int or as rclpy's one-byte constant
            (``DiagnosticStatus.WARN == b'\\x01'``).
        message: status message.
        values: key -> value; values are written with ``str`` (numpy scalars first turned
            into Python numbers, bytes decoded as UTF-8), in the mapping's order.
        hardware_id: status hardware id.
        stamp_ns: header stamp, nanoseconds; the header frame id is empty.
        msg_types: namespace with ``DiagnosticArray``, ``DiagnosticStatus``, ``KeyValue``,
            ``Header``, ``Time``.

    Returns:
        DiagnosticArray with ``status = [DiagnosticStatus]``. ``level`` is written in the
        type of the class's ``OK`` constant: one byte for rclpy (``octet``), int for rosbags
        and stand-ins.

    Raises:
        InputError: an unknown level.
    """
    t = msg_types
    status_cls = t.DiagnosticStatus
    lvl = int.from_bytes(level, 'little') if isinstance(level, (bytes, bytearray)) else int(level)
    if lvl not in DIAGNOSTIC_LEVELS:
        raise InputError(f'diagnostic level must be one of {DIAGNOSTIC_LEVELS}, got {level!r}')
    lvl_value: Any = bytes([lvl]) if isinstance(getattr(status_cls, 'OK', 0), bytes) else lvl
    pairs = [t.KeyValue(key=str(k), value=_diagnostic_text(v)) for k, v in values.items()]
    status = status_cls(level=lvl_value, name=str(name), message=str(message),
                        hardware_id=str(hardware_id), values=pairs)
    return t.DiagnosticArray(header=_header(t, '', stamp_ns), status=[status])


# --------------------------------------------------------------------------------------
# message-class namespace
# --------------------------------------------------------------------------------------

#: The package's own messages: attribute -> (module, class).
CUSTOM_TYPES: dict[str, tuple[str, str]] = {
    'Facade': ('uncertain_facade_map.msg', 'Facade'),
    'FacadeGrid': ('uncertain_facade_map.msg', 'FacadeGrid'),
    'FacadeGridArray': ('uncertain_facade_map.msg', 'FacadeGridArray'),
}


class MapTypes(SimpleNamespace):
    """A ``msg_types`` namespace whose custom classes are imported on first use.

    Attributes listed in :data:`CUSTOM_TYPES` and not set explicitly are imported when
    first read; a class that does not import (interfaces not built yet) reads as None and
    is tried again on the next read. The functions of this module raise a clear
    ImportError when they need such a missing class.
    """

    def __getattr__(self, name: str) -> Any:
        if name not in CUSTOM_TYPES:
            raise AttributeError(name)
        module, cls = CUSTOM_TYPES[name]
        try:
            value = getattr(importlib.import_module(module), cls)
        except (ImportError, AttributeError):
            return None
        setattr(self, name, value)
        return value


def rclpy_map_types() -> MapTypes:
    """Message classes of rclpy (ROS 2 Python) for the functions of this module.

    The standard message packages are imported here; the package's own messages
    (``uncertain_facade_map.msg``: Facade, FacadeGrid, FacadeGridArray) are imported on
    first use and read as None while they are not built.

    Returns:
        :class:`MapTypes` with ``Pose``, ``PoseStamped``, ``Point``, ``Quaternion``,
        ``Vector3``, ``Transform``, ``TransformStamped``, ``Header``, ``Time``,
        ``OccupancyGrid``, ``MapMetaData``, ``Marker``, ``MarkerArray``, ``ColorRGBA``,
        ``DiagnosticArray``, ``DiagnosticStatus``, ``KeyValue``, ``Facade``,
        ``FacadeGrid``, ``FacadeGridArray`` and ``encode_array`` (:func:`encode_array`,
        ``array.array`` as rclpy stores numeric sequences).

    Raises:
        ImportError: the standard ROS 2 message packages are not installed.
    """
    from builtin_interfaces.msg import Time
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from geometry_msgs.msg import Point, Pose, PoseStamped, Quaternion, Transform, TransformStamped, Vector3
    from nav_msgs.msg import MapMetaData, OccupancyGrid
    from std_msgs.msg import ColorRGBA, Header
    from visualization_msgs.msg import Marker, MarkerArray

    return MapTypes(
        Pose=Pose, PoseStamped=PoseStamped, Point=Point, Quaternion=Quaternion, Vector3=Vector3,
        Transform=Transform, TransformStamped=TransformStamped, Header=Header, Time=Time,
        OccupancyGrid=OccupancyGrid, MapMetaData=MapMetaData, Marker=Marker,
        MarkerArray=MarkerArray, ColorRGBA=ColorRGBA, DiagnosticArray=DiagnosticArray,
        DiagnosticStatus=DiagnosticStatus, KeyValue=KeyValue, encode_array=encode_array,
    )
