"""Tests of msg_adapters.map_messages: poses, query service, façade, grid, marker and diagnostic messages.

Standard messages are rclpy's real classes (with ``ROS_PYTHON_CHECK_FIELDS`` on where it
matters, and serialised by rclpy's C type support); the package's own Facade, FacadeGrid
and FacadeGridArray are stand-ins whose field names are read from ``msg/*.msg``, strict
about the keyword set, and, for the wire format, rosbags classes generated from the same
files.
"""

from __future__ import annotations

import array
import subprocess
import sys
from contextlib import contextmanager
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Iterator

import hypothesis.extra.numpy as hnp
import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from msg_adapters import map_messages as mm
from msg_adapters.map_messages import (
    MARKER_ID_STRIDE,
    MapTypes,
    colour_ramp,
    diagnostic_array,
    facade_grid_array,
    facade_grid_msg,
    facade_msg,
    fill_list_tiles_response,
    fill_query_response,
    matrix_from_quaternion,
    occupancy_grid_msg,
    points_from_request,
    pose_from_frame,
    quaternion_from_matrix,
    rclpy_map_types,
    rigid_from_pose,
    tiles_of_response,
    transform_points,
    triangle_marker_array,
)
from uncertain_facade_map.datatypes import FacadeFrame
from uncertain_facade_map.errors import InputError

SETTINGS = settings(max_examples=60, deadline=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
ROOT = Path(__file__).resolve().parents[2]
# rclpy.serialization imports lark, which imports the deprecated sre_parse.
pytestmark = pytest.mark.filterwarnings("ignore:module 'sre_:DeprecationWarning")
CUSTOM = ('Facade', 'FacadeGrid', 'FacadeGridArray')
STAMP = 1_700_000_000_123_456_789


# --------------------------------------------------------------------------------------
# message classes


def msg_fields(name: str) -> list[str]:
    """Field names of ``msg/<name>.msg`` in order (constants and comments skipped)."""
    names = []
    for line in (ROOT / 'msg' / f'{name}.msg').read_text().splitlines():
        line = line.split('#', 1)[0].strip()
        if not line or '=' in line:
            continue
        names.append(line.split()[1])
    return names


def standin(name: str) -> Any:
    """A strict keyword factory with the fields of ``msg/<name>.msg`` (not a dataclass)."""
    fields = msg_fields(name)

    def make(**kwargs: Any) -> SimpleNamespace:
        assert set(kwargs) == set(fields), (name, set(kwargs) ^ set(fields))
        return SimpleNamespace(**kwargs)

    make.__name__ = name
    return make


def _rclpy_or_skip() -> MapTypes:
    try:
        return rclpy_map_types()
    except ImportError as err:  # pragma: no cover - the project venv has them
        pytest.skip(f'ROS 2 message packages not importable: {err}')


@pytest.fixture(scope='module')
def types() -> MapTypes:
    """rclpy's standard classes plus stand-ins for the package's own messages."""
    t = _rclpy_or_skip()
    for name in CUSTOM:
        setattr(t, name, standin(name))
    return t


@contextmanager
def field_checks(t: Any) -> Iterator[None]:
    """Turn on rclpy's per-field type assertions (ROS_PYTHON_CHECK_FIELDS=1) for ``t``'s classes."""
    with pytest.MonkeyPatch.context() as mp:
        for value in vars(t).values():
            module = sys.modules.get(getattr(value, '__module__', '') or '')
            if module is not None and hasattr(module, 'ros_python_check_fields'):
                mp.setattr(module, 'ros_python_check_fields', '1')
        yield


def rclpy_round_trip(msg: Any) -> Any:
    """Serialise with rclpy's C type support and back (fails on values rclpy cannot take).

    Without rclpy's serialisation (no C extension) the message itself is returned.
    """
    try:
        from rclpy.serialization import deserialize_message, serialize_message
    except ImportError:  # pragma: no cover - the project venv has it
        return msg
    return deserialize_message(serialize_message(msg), type(msg))


@pytest.fixture(scope='module')
def rosbags_types() -> SimpleNamespace:
    """rosbags classes, with Facade, FacadeGrid, FacadeGridArray generated from msg/*.msg."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    defs: dict = {}
    for name in CUSTOM:
        defs.update(get_types_from_msg((ROOT / 'msg' / f'{name}.msg').read_text(),
                                       f'uncertain_facade_map/msg/{name}'))
    store.register(defs)
    names = {'Pose': 'geometry_msgs/msg/Pose', 'Point': 'geometry_msgs/msg/Point',
             'Quaternion': 'geometry_msgs/msg/Quaternion', 'Header': 'std_msgs/msg/Header',
             'Time': 'builtin_interfaces/msg/Time',
             'DiagnosticArray': 'diagnostic_msgs/msg/DiagnosticArray',
             'DiagnosticStatus': 'diagnostic_msgs/msg/DiagnosticStatus',
             'KeyValue': 'diagnostic_msgs/msg/KeyValue',
             **{n: f'uncertain_facade_map/msg/{n}' for n in CUSTOM}}
    return SimpleNamespace(store=store, **{k: store.types[v] for k, v in names.items()})


def rosbags_round_trip(store: Any, msg: Any) -> Any:
    typename = msg.__msgtype__
    return store.deserialize_cdr(store.serialize_cdr(msg, typename), typename)


# --------------------------------------------------------------------------------------
# strategies and fixtures


@st.composite
def rotations(draw: st.DrawFn) -> np.ndarray:
    """Rotation matrices: random axes and angles, including 0, 180 degrees and near them."""
    axis = np.array(draw(st.lists(st.floats(-1, 1), min_size=3, max_size=3)))
    assume(np.linalg.norm(axis) > 1e-3)
    axis /= np.linalg.norm(axis)
    angle = draw(st.one_of(st.floats(0, np.pi), st.sampled_from([0.0, np.pi, np.pi - 1e-9, 1e-9,
                                                                 np.pi / 2])))
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k  # Rodrigues


finite = st.floats(-1e4, 1e4, allow_nan=False, allow_infinity=False)


def make_model(facade_id: int = 3, building: int = 7, shape: tuple[int, int] = (3, 4),
               normal: tuple[float, float, float] = (0.6, -0.8, 0.0)) -> Any:
    """A core FacadeModel built from its parts, with a raster of distinct values."""
    from uncertain_facade_map.datatypes import DepthLayers, FacadeModel, Facets, SurfaceRaster

    frame = FacadeFrame.from_normal(np.array([10.0, -4.0, 0.5]), np.array(normal))
    h, w = shape
    mean = np.arange(h * w, dtype=np.float64).reshape(h, w) * 0.01 - 0.05
    var = 1e-4 * (1 + np.arange(h * w, dtype=np.float64).reshape(h, w))
    source = (np.arange(h * w) % 3).astype(np.int8).reshape(h, w)
    facet = np.zeros((h, w), np.int32)
    raster = SurfaceRaster(np.array([-1.25, 0.5]), 0.25, mean, var, facet, source)
    layers = DepthLayers(np.array([0.7, 0.2, 0.1]), np.array([0.0, -0.2, 1.2]),
                         np.array([0.02, 0.03, 0.1]), 0)
    facets = Facets(np.array([-1.25, 0.5]), 0.25, facet, np.array([0, 1], np.int32))
    return FacadeModel(facade_id=facade_id, building=building, frame=frame,
                       extent=(-1.0, 12.0, 0.0, 9.5), layers=layers, facets=facets,
                       lengthscale2_=np.ones((3, 2)), global_mean_=0.0, global_var_=0.04,
                       noise_var=4e-4, surface=raster, point_index=np.arange(1234))


# --------------------------------------------------------------------------------------
# import hygiene


def test_module_imports_without_rclpy_or_the_model_modules():
    code = ('import sys, msg_adapters.map_messages\n'
            'bad = sorted(m for m in sys.modules if m.split(".")[0] in ("rclpy", "nav_msgs", '
            '"geometry_msgs", "visualization_msgs", "sklearn", "scipy") or m in '
            '("uncertain_facade_map.mapping.facade_map", "uncertain_facade_map.pipeline.step7_queries"))\n'
            'assert not bad, bad\n')
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120,
                            cwd=ROOT)
    assert result.returncode == 0, result.stderr


def test_rclpy_map_types_tolerates_unbuilt_interfaces(monkeypatch):
    t = _rclpy_or_skip()
    for name in ('Pose', 'Point', 'Quaternion', 'Header', 'Time', 'OccupancyGrid', 'MapMetaData',
                 'Marker', 'MarkerArray', 'ColorRGBA', 'DiagnosticArray', 'DiagnosticStatus',
                 'KeyValue'):
        assert getattr(t, name).__name__ == name
    for name in CUSTOM:  # a class once built, None until then; never an exception
        value = getattr(t, name)
        assert value is None or value.__name__ == name
    monkeypatch.setitem(mm.CUSTOM_TYPES, 'Facade', ('no_such_package.msg', 'Facade'))
    fresh = MapTypes(**{k: v for k, v in vars(t).items() if k not in CUSTOM})
    assert fresh.Facade is None
    with pytest.raises(ImportError, match='colcon'):
        facade_msg(make_model(), fresh)
    with pytest.raises(AttributeError):
        fresh.NoSuchType  # noqa: B018


# --------------------------------------------------------------------------------------
# rotations and poses


@given(rotations(), st.lists(finite, min_size=3, max_size=3))
@SETTINGS
def test_frame_pose_rigid_round_trip(types, rotation, origin):
    axes = rotation.T  # rows e_u, e_v, n; the rotation's columns
    pose = pose_from_frame(np.array(origin), axes, types)
    q = np.array([pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w])
    assert abs(np.linalg.norm(q) - 1) < 1e-12 and q[3] >= 0
    r, t = rigid_from_pose(pose)
    np.testing.assert_allclose(r, rotation, atol=1e-9, rtol=0)
    np.testing.assert_array_equal(t, origin)
    # The pose maps façade x, y, z onto e_u, e_v, n.
    np.testing.assert_allclose(r @ np.eye(3), axes.T, atol=1e-9, rtol=0)


@given(st.lists(st.floats(-1, 1), min_size=4, max_size=4), st.floats(1e-3, 1e3))
@SETTINGS
def test_quaternion_matrix_round_trip_up_to_sign(q, scale):
    q = np.array(q)
    assume(np.linalg.norm(q) > 1e-3)
    r = matrix_from_quaternion(q * scale)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)
    back = quaternion_from_matrix(r)
    unit = q / np.linalg.norm(q)
    assert min(np.abs(back - unit).max(), np.abs(back + unit).max()) < 1e-9


def test_real_facade_frames_give_their_axes(types):
    for normal in ([1, 0, 0], [0, -1, 0], [-1, 0, 0], [0.6, 0.8, 0], [0.1, 0.2, 0.3], [-1e-3, -1, 0]):
        frame = FacadeFrame.from_normal(np.array([1.0, 2.0, 3.0]), np.array(normal, float))
        r, t = rigid_from_pose(pose_from_frame(frame.origin, frame.axes, types))
        uvd = np.array([[0.0, 0.0, 0.0], [1.5, -2.0, 0.3], [10.0, 20.0, -1.0]])
        np.testing.assert_allclose(transform_points(uvd, r, t), frame.to_world(uvd), atol=1e-9)


def test_left_handed_or_bad_axes_are_rejected(types):
    with pytest.raises(InputError, match='left-handed'):
        pose_from_frame(np.zeros(3), np.diag([1.0, 1.0, -1.0]), types)
    with pytest.raises(InputError, match='orthonormal'):
        pose_from_frame(np.zeros(3), np.diag([1.0, 2.0, 1.0]), types)
    with pytest.raises(InputError, match='NaN'):
        pose_from_frame(np.array([0.0, np.nan, 0.0]), np.eye(3), types)


@given(rotations(), st.lists(finite, min_size=3, max_size=3), st.floats(0.1, 10))
@SETTINGS
def test_rigid_from_pose_reads_every_pose_and_transform_type(types, rotation, origin, scale):
    from geometry_msgs.msg import (
        Pose,
        PoseStamped,
        PoseWithCovarianceStamped,
        Quaternion,
        Transform,
        TransformStamped,
        Vector3,
    )
    x, y, z, w = quaternion_from_matrix(rotation) * scale  # not normalised on purpose
    quat = Quaternion(x=x, y=y, z=z, w=w)
    pose = Pose(position=types.Point(x=origin[0], y=origin[1], z=origin[2]), orientation=quat)
    transform = Transform(translation=Vector3(x=origin[0], y=origin[1], z=origin[2]), rotation=quat)
    msgs = [pose, PoseStamped(pose=pose), transform, TransformStamped(transform=transform),
            PoseWithCovarianceStamped()]
    msgs[-1].pose.pose = pose
    for msg in msgs:
        r, t = rigid_from_pose(msg)
        np.testing.assert_allclose(r, rotation, atol=1e-9, rtol=0)
        np.testing.assert_array_equal(t, origin)


def test_rigid_from_pose_rejects_degenerate_quaternions():
    from geometry_msgs.msg import Pose, Quaternion, TransformStamped
    pose = Pose(orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=0.0))
    with pytest.raises(InputError, match='zero'):
        rigid_from_pose(pose)
    ts = TransformStamped()
    ts.transform.rotation = Quaternion(x=float('nan'), y=0.0, z=0.0, w=1.0)
    with pytest.raises(InputError, match='NaN'):
        rigid_from_pose(ts)
    ts.transform.rotation = Quaternion(x=0.0, y=0.0, z=0.0, w=float('inf'))
    with pytest.raises(InputError, match='infinite'):
        rigid_from_pose(ts)
    with pytest.raises(InputError, match='not a pose or transform'):
        rigid_from_pose(SimpleNamespace(x=1.0))
    assert isinstance(InputError('x'), ValueError)


@given(hnp.arrays(np.float64, st.tuples(st.integers(0, 30), st.just(3)), elements=finite),
       rotations(), st.lists(finite, min_size=3, max_size=3))
@SETTINGS
def test_transform_points_is_r_x_plus_t(xyz, rotation, t):
    out = transform_points(xyz, rotation, t)
    assert out.shape == xyz.shape
    for p, q in zip(xyz, out):
        np.testing.assert_allclose(q, rotation @ p + t, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(transform_points(out - t, rotation.T, np.zeros(3)), xyz, atol=1e-6)
    with pytest.raises(InputError):
        transform_points(xyz.reshape(-1), rotation, t)


# --------------------------------------------------------------------------------------
# QueryPoints


@given(hnp.arrays(np.float64, st.tuples(st.integers(0, 40), st.just(3)),
                  elements=st.floats(allow_nan=False, allow_infinity=False)))
@SETTINGS
def test_points_from_request_round_trip(types, xyz):
    request = SimpleNamespace(points=[types.Point(x=x, y=y, z=z) for x, y, z in xyz.tolist()])
    out = points_from_request(request, max_points=40)
    assert out.dtype == np.float64 and out.shape == (len(xyz), 3)
    np.testing.assert_array_equal(out, xyz)
    np.testing.assert_array_equal(points_from_request(SimpleNamespace(points=xyz), None), xyz)
    # the flat field, 3 numbers per point (used when points is empty)
    flat = SimpleNamespace(points=[], xyz=array.array('d', xyz.reshape(-1).tolist()))
    np.testing.assert_array_equal(points_from_request(flat, max_points=40), xyz)


def test_points_from_request_flat_errors():
    with pytest.raises(InputError, match='3 numbers per point'):
        points_from_request(SimpleNamespace(points=[], xyz=[1.0, 2.0]), None)
    with pytest.raises(InputError, match='at most 1'):
        points_from_request(SimpleNamespace(points=[], xyz=[0.0] * 6), 1)
    with pytest.raises(InputError, match='NaN'):
        points_from_request(SimpleNamespace(points=[], xyz=[0.0, np.nan, 1.0]), None)


def test_points_from_request_errors(types):
    xyz = np.arange(30, dtype=float).reshape(10, 3)
    xyz[[2, 5, 7], [0, 2, 1]] = [np.nan, np.inf, -np.inf]
    request = SimpleNamespace(points=[types.Point(x=x, y=y, z=z) for x, y, z in xyz.tolist()])
    with pytest.raises(InputError, match=r'3 of 10 query points have NaN or infinite.*first is point 2'):
        points_from_request(request, 100)
    with pytest.raises(InputError, match='10 query points, at most 9'):
        points_from_request(request, 9)
    empty = points_from_request(SimpleNamespace(points=[]), 0)
    assert empty.shape == (0, 3) and empty.dtype == np.float64
    with pytest.raises(InputError, match='x, y and z'):
        points_from_request(SimpleNamespace(points=[SimpleNamespace(x=1.0, y=2.0)]), None)
    with pytest.raises(InputError, match='numbers'):
        points_from_request(SimpleNamespace(points=[SimpleNamespace(x=1.0, y='a', z=0.0)]), None)


def test_fill_query_response_from_point_query():
    from uncertain_facade_map.pipeline.step7_queries import PointQuery
    answers = PointQuery(np.array([0, -1, 4], np.int32), np.array([0.1, np.nan, -0.2]),
                         np.array([1e-4, np.nan, 2e-4]), np.array([4e-4, np.nan, 4e-4]),
                         np.array([0.05, np.nan, -0.3]), np.array([0.2, 0.5, 1.0]),
                         np.array([[0.0, -1.0, 0.0], [np.nan] * 3, [0.6, 0.8, 0.0]]))
    response = fill_query_response(SimpleNamespace(success=False, message='x', normal=None), answers, 'ok')
    assert response.success is True and response.message == 'ok'
    for key, value in answers.as_dict().items():
        got = getattr(response, key)
        assert isinstance(got, array.array) and got.typecode == ('i' if key == 'facade' else 'd')
        np.testing.assert_array_equal(np.array(got), value.reshape(-1))  # normal: 3 numbers per point
    old = fill_query_response(SimpleNamespace(success=False, message='x'), answers)  # a response without normals
    assert not hasattr(old, 'normal') and old.success
    with pytest.raises(InputError, match='normals'):
        fill_query_response(SimpleNamespace(normal=None), dict(answers.as_dict(), normal=np.zeros((3, 2))))
    # a dict, and a dataclass response (rosbags-like) gets numpy arrays
    import dataclasses
    Resp = dataclasses.make_dataclass('Resp', ['success', 'message', *mm.QUERY_FIELDS])
    resp = fill_query_response(Resp(False, '', *[None] * 6), answers.as_dict())
    assert resp.facade.dtype == np.int32 and resp.p_occupied.dtype == np.float64
    with pytest.raises(InputError, match='one length'):
        fill_query_response(SimpleNamespace(), {**answers.as_dict(), 'variance': np.zeros(2)})
    with pytest.raises(InputError, match='lack p_occupied'):
        fill_query_response(SimpleNamespace(), {k: v for k, v in answers.as_dict().items()
                                                if k != 'p_occupied'})


# --------------------------------------------------------------------------------------
# ListTiles


@st.composite
def tile_lists(draw: st.DrawFn) -> tuple[list[str], np.ndarray, list[str], list[bool]]:
    """Tiles as a tiled map lists them: ids, (K, 4) squares (any side, any corner), files, flags."""
    k = draw(st.integers(0, 12))
    index = draw(hnp.arrays(np.int64, (k, 2), elements=st.integers(-10**6, 10**6)))
    side = draw(st.floats(0.5, 500.0))
    ids = [f'tile_{"m" if i < 0 else ""}{abs(i)}_{"m" if j < 0 else ""}{abs(j)}' for i, j in index.tolist()]
    lo = index * side
    bounds = np.hstack([lo, lo + side]).astype(np.float64)
    files = [f'/maps/city/tiles/{t}.npz' for t in ids]
    loaded = draw(st.lists(st.booleans(), min_size=k, max_size=k))
    return ids, bounds, files, loaded


@given(tile_lists())
@SETTINGS
def test_list_tiles_response_round_trip(tiles):
    ids, bounds, files, loaded = tiles
    # a stand-in (array.array), a dataclass (numpy, as rosbags) and rclpy's class, serialised
    stand = fill_list_tiles_response(SimpleNamespace(), ids, bounds, files, loaded, f'{len(ids)} tiles')
    assert stand.success and stand.message == f'{len(ids)} tiles'
    assert isinstance(stand.bounds, array.array) and stand.bounds.typecode == 'd'
    import dataclasses
    Resp = dataclasses.make_dataclass('Resp', ['success', 'message', 'ids', 'bounds', 'files', 'loaded'])
    data = fill_list_tiles_response(Resp(False, '', None, None, None, None), ids, bounds, files, loaded)
    assert data.bounds.dtype == np.float64
    responses = [stand, data]
    try:
        from uncertain_facade_map.srv import ListTiles
    except ImportError:  # pragma: no cover - make venv builds the interfaces
        ListTiles = None
    if ListTiles is not None:
        t = SimpleNamespace(Response=ListTiles.Response)
        with field_checks(t):
            msg = fill_list_tiles_response(ListTiles.Response(), ids, bounds, files, loaded, 'x',
                                           msg_types=rclpy_map_types())
        responses.append(rclpy_round_trip(msg))
    for response in responses:
        out = tiles_of_response(response)
        assert out['ids'] == ids and out['files'] == files
        np.testing.assert_array_equal(out['bounds'], bounds.reshape(-1, 4))
        np.testing.assert_array_equal(out['loaded'], np.array(loaded, dtype=bool).reshape(-1))


def test_list_tiles_response_errors():
    box = np.array([[0.0, 0.0, 50.0, 50.0]])
    with pytest.raises(InputError, match=r'\(K, 4\)'):
        fill_list_tiles_response(SimpleNamespace(), ['tile_0_0'], box[:, :3], ['/a.npz'], [True])
    with pytest.raises(InputError, match='different lengths'):
        fill_list_tiles_response(SimpleNamespace(), ['tile_0_0', 'tile_1_0'], box, ['/a.npz'], [True])
    with pytest.raises(InputError, match='min_x <= max_x'):
        fill_list_tiles_response(SimpleNamespace(), ['tile_0_0'], box[:, [2, 1, 0, 3]], ['/a.npz'], [True])
    with pytest.raises(InputError, match='finite'):
        fill_list_tiles_response(SimpleNamespace(), ['tile_0_0'], box * np.nan, ['/a.npz'], [True])
    with pytest.raises(InputError, match='must be text'):
        fill_list_tiles_response(SimpleNamespace(), [3], box, ['/a.npz'], [True])
    with pytest.raises(InputError, match='4 per tile'):
        tiles_of_response(SimpleNamespace(ids=['a', 'b'], bounds=[0.0] * 4, files=['x', 'y'], loaded=[True, False]))
    with pytest.raises(InputError, match='different lengths'):
        tiles_of_response(SimpleNamespace(ids=['a'], bounds=[0.0] * 4, files=[], loaded=[True]))
    empty = fill_list_tiles_response(SimpleNamespace(), [], [], [], [])
    assert tiles_of_response(empty)['bounds'].shape == (0, 4)


# --------------------------------------------------------------------------------------
# Facade, FacadeGrid, FacadeGridArray


def test_facade_msg_fields(types):
    model = make_model()
    msg = facade_msg(model, types)
    frame = model.frame
    assert msg.facade_id == 3 and msg.building == 7 and msg.main_layer == 0
    assert msg.points == 1234 and msg.facets == 2
    assert isinstance(msg.points, int) and isinstance(msg.facets, int)
    np.testing.assert_allclose(msg.plane[:3], frame.normal)
    assert msg.plane.dtype == np.float64 and msg.plane.shape == (4,)
    on_plane = frame.to_world(np.array([[0.0, 0.0, 0.0], [3.0, 7.0, 0.0], [-2.0, 1.0, 0.0]]))
    np.testing.assert_allclose(on_plane @ msg.plane[:3] + msg.plane[3], 0, atol=1e-12)
    off = frame.to_world(np.array([[1.0, 1.0, 0.4]]))  # 0.4 m outside
    assert off @ msg.plane[:3] + msg.plane[3] == pytest.approx([0.4])
    np.testing.assert_array_equal(msg.extent, [-1.0, 12.0, 0.0, 9.5])
    for name, value in (('layer_weights', [0.7, 0.2, 0.1]), ('layer_means', [0.0, -0.2, 1.2]),
                        ('layer_sigmas', [0.02, 0.03, 0.1])):
        got = getattr(msg, name)
        assert isinstance(got, array.array) and got.typecode == 'd'
        assert list(got) == value
    assert (msg.global_mean, msg.global_variance, msg.noise_variance) == (0.0, 0.04, 4e-4)
    r, t = rigid_from_pose(msg.frame)
    np.testing.assert_allclose(r, frame.axes.T, atol=1e-12)
    np.testing.assert_array_equal(t, frame.origin)


@pytest.mark.parametrize('shape', [(3, 4), (1, 5), (6, 1), (0, 0)])
def test_facade_grid_layout_is_row_major(types, shape):
    model = make_model(shape=shape)
    raster = model.surface
    grid = facade_grid_msg(model, 'map', STAMP, types)
    h, w = shape
    assert (grid.height, grid.width) == (h, w)
    assert (grid.origin_u, grid.origin_v, grid.resolution) == (-1.25, 0.5, 0.25)
    assert grid.header.frame_id == 'map'
    assert (grid.header.stamp.sec, grid.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    assert grid.mean_depth.typecode == 'f' and grid.variance.typecode == 'f' and grid.source.typecode == 'b'
    assert len(grid.mean_depth) == len(grid.variance) == len(grid.source) == h * w
    for row in range(h):
        for col in range(w):
            k = row * w + col
            assert grid.mean_depth[k] == np.float32(raster.mean[row, col])
            assert grid.variance[k] == np.float32(raster.var[row, col])
            assert grid.source[k] == raster.source[row, col]
    # cell (row, col) centre, as SurfaceRaster.centres() orders them
    if h * w:
        centres = raster.centres()
        k = h * w - 1
        assert centres[k, 0] == pytest.approx(grid.origin_u + (k % w + 0.5) * grid.resolution)
        assert centres[k, 1] == pytest.approx(grid.origin_v + (k // w + 0.5) * grid.resolution)


def test_facade_grid_array(types):
    models = [make_model(0, 1, (2, 3)), make_model(1, 1, (4, 2), normal=(-1.0, 0.0, 0.0))]
    msg = facade_grid_array(models, 'map', STAMP, types)
    assert msg.header.frame_id == 'map' and len(msg.grids) == 2
    assert [g.facade_id for g in msg.grids] == [0, 1]
    assert [(g.height, g.width) for g in msg.grids] == [(2, 3), (4, 2)]
    r, _t = rigid_from_pose(msg.grids[1].frame)
    np.testing.assert_allclose(r[:, 2], [-1.0, 0.0, 0.0], atol=1e-12)
    assert facade_grid_array([], 'map', 0, types).grids == []


def test_custom_messages_serialise_with_rosbags_classes(rosbags_types):
    """The wire format: rosbags classes generated from msg/*.msg take what is set (numpy path)."""
    t = rosbags_types
    model = make_model()
    facade = facade_msg(model, t)
    back = rosbags_round_trip(t.store, facade)
    np.testing.assert_array_equal(back.layer_means, [0.0, -0.2, 1.2])
    np.testing.assert_array_equal(back.plane, facade.plane)
    assert back.points == 1234
    grids = facade_grid_array([model, make_model(1, 2, (2, 2))], 'map', STAMP, t)
    back = rosbags_round_trip(t.store, grids)
    assert back.grids[0].mean_depth.dtype == np.float32 and back.grids[0].source.dtype == np.int8
    np.testing.assert_array_equal(back.grids[0].mean_depth, model.surface.mean.astype(np.float32).ravel())
    np.testing.assert_array_equal(back.grids[0].source, model.surface.source.ravel())
    assert back.grids[1].header.stamp.nanosec == 123_456_789
    diag = diagnostic_array('n', 1, 'm', {'a': 1}, 'hw', STAMP, t)
    assert rosbags_round_trip(t.store, diag).status[0].level == 1


# --------------------------------------------------------------------------------------
# OccupancyGrid


def test_occupancy_grid_hand_made(types):
    p = np.array([[0.0, 0.254, 0.5],
                  [np.nan, 0.996, 1.0]])  # 2 rows (y), 3 columns (x)
    with field_checks(types):
        msg = occupancy_grid_msg(p, (1.5, -2.0), 0.2, 'map', STAMP, types, z=0.75)
    assert isinstance(msg.data, array.array) and msg.data.typecode == 'b'
    assert list(msg.data) == [0, 25, 50, -1, 100, 100]  # x fastest, then y
    info = msg.info
    assert (info.width, info.height) == (3, 2)
    assert info.resolution == pytest.approx(0.2)
    assert (info.origin.position.x, info.origin.position.y, info.origin.position.z) == (1.5, -2.0, 0.75)
    o = info.origin.orientation
    assert (o.x, o.y, o.z, o.w) == (0.0, 0.0, 0.0, 1.0)
    assert msg.header.frame_id == 'map' and info.map_load_time.sec == 1_700_000_000
    back = rclpy_round_trip(msg)
    assert list(back.data) == list(msg.data) and back.info.width == 3


@given(hnp.arrays(np.float64, st.tuples(st.integers(0, 12), st.integers(0, 12)),
                  elements=st.one_of(st.floats(0, 1), st.just(np.nan))))
@SETTINGS
def test_occupancy_grid_values(types, p):
    msg = occupancy_grid_msg(p, (0.0, 0.0), 0.5, 'map', 0, types)
    h, w = p.shape
    data = np.array(msg.data, dtype=np.int64)
    assert data.shape == (h * w,) and (msg.info.height, msg.info.width) == (h, w)
    for j in range(h):
        for i in range(w):
            value = data[j * w + i]
            assert value == (-1 if np.isnan(p[j, i]) else round(100 * p[j, i]))
            assert -1 <= value <= 100


def test_occupancy_grid_errors(types):
    for bad in (np.array([[0.5, 1.5]]), np.array([[np.inf]]), np.array([[-0.1]])):
        with pytest.raises(InputError, match='outside'):
            occupancy_grid_msg(bad, (0, 0), 0.1, 'map', 0, types)
    with pytest.raises(InputError, match='H, W'):
        occupancy_grid_msg(np.zeros(4), (0, 0), 0.1, 'map', 0, types)
    with pytest.raises(InputError, match='resolution'):
        occupancy_grid_msg(np.zeros((2, 2)), (0, 0), 0.0, 'map', 0, types)
    with pytest.raises(InputError, match='stamp'):
        occupancy_grid_msg(np.zeros((2, 2)), (0, 0), 0.1, 'map', -1, types)


# --------------------------------------------------------------------------------------
# MarkerArray


@st.composite
def meshes(draw: st.DrawFn) -> tuple:
    n_v = draw(st.integers(1, 30))
    vertices = draw(hnp.arrays(np.float64, (n_v, 3), elements=st.floats(-100, 100)))
    n_t = draw(st.integers(0, 60))
    triangles = draw(hnp.arrays(np.int64, (n_t, 3), elements=st.integers(0, n_v - 1)))
    std = draw(hnp.arrays(np.float64, (n_v,), elements=st.one_of(st.floats(0, 0.5), st.just(np.nan))))
    facade = draw(hnp.arrays(np.int32, (n_v,), elements=st.sampled_from([0, 2, 5, 11])))
    max_vertices = draw(st.sampled_from([3, 6, 9, 30, 60_000]))
    return vertices, triangles, std, facade, max_vertices


def check_markers(msg: Any, vertices, triangles, std, facade, max_vertices, std_max=None) -> None:
    delete_all, *markers = msg.markers
    assert delete_all.action == 3 and delete_all.ns == 'facade_surface'
    ids = [m.id for m in markers]
    assert len(set(ids)) == len(ids)
    assert sum(len(m.points) for m in markers) == 3 * len(triangles)
    per = max(max_vertices // 3, 1) * 3
    tri_facade = facade[triangles[:, 0]] if len(triangles) else np.zeros(0, int)
    by_facade: dict[int, list] = {}
    for m in markers:
        assert m.type == 11 and m.action == 0 and m.frame_locked is False
        assert 0 < len(m.points) <= per and len(m.points) % 3 == 0 and len(m.colors) == len(m.points)
        assert (m.pose.orientation.w, m.scale.x, m.scale.y, m.scale.z) == (1.0, 1.0, 1.0, 1.0)
        f, k = m.id % MARKER_ID_STRIDE, m.id // MARKER_ID_STRIDE
        by_facade.setdefault(f, []).append((k, m))
        rgba = np.array([[c.r, c.g, c.b, c.a] for c in m.colors])
        assert ((rgba >= 0) & (rgba <= 1)).all()
    for f, chunks in by_facade.items():
        chunks.sort(key=lambda km: km[0])
        assert [k for k, _m in chunks] == list(range(len(chunks)))  # ids f, f+S, f+2S, ...
        assert all(len(m.points) == per for _k, m in chunks[:-1])  # only the last one short
        pts = np.array([[p.x, p.y, p.z] for _k, m in chunks for p in m.points])
        expected = vertices[triangles[tri_facade == f].reshape(-1)]  # input order kept
        np.testing.assert_array_equal(pts, expected)
    assert sorted(by_facade) == sorted(set(tri_facade.tolist()))


@given(meshes())
@SETTINGS
def test_triangle_marker_array_properties(types, mesh):
    vertices, triangles, std, facade, max_vertices = mesh
    msg = triangle_marker_array(vertices, triangles, std, facade, 'map', STAMP, types,
                                max_vertices=max_vertices)
    check_markers(msg, vertices, triangles, std, facade, max_vertices)


def test_marker_split_ids_and_colours(types):
    # façade 7: 25 triangles; façade 2: 1 triangle; 10 triangles per marker
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5]])
    std = np.array([0.0, 0.1, 0.2, np.nan])
    facade = np.array([7, 7, 7, 2])
    triangles = np.array([[0, 1, 2]] * 25 + [[3, 0, 1]])
    with field_checks(types):
        msg = triangle_marker_array(vertices, triangles, std, facade, 'map', STAMP, types,
                                    std_max=0.2, max_vertices=30, ns='surf', alpha=0.5)
    assert [m.id for m in msg.markers] == [0, 2, 7, 7 + MARKER_ID_STRIDE, 7 + 2 * MARKER_ID_STRIDE]
    assert [len(m.points) for m in msg.markers] == [0, 3, 30, 30, 15]
    assert all(m.ns == 'surf' and m.header.frame_id == 'map' for m in msg.markers)
    colours = [(c.r, c.g, c.b, c.a) for c in msg.markers[2].colors[:3]]
    ramp = colour_ramp(np.array([0.0, 1.0]), 1.0)
    assert colours[0][:3] == pytest.approx(tuple(ramp[0]), abs=1e-6)
    assert colours[2][:3] == pytest.approx(tuple(ramp[1]), abs=1e-6)
    assert all(c[3] == 0.5 for c in colours)
    grey = msg.markers[1].colors[0]
    assert (grey.r, grey.g, grey.b) == pytest.approx((0.6, 0.6, 0.6))
    back = rclpy_round_trip(msg)
    assert [len(m.points) for m in back.markers] == [0, 3, 30, 30, 15]
    assert back.markers[1].points[0].z == 5.0


def test_marker_default_std_max_is_the_95th_percentile(types):
    std = np.linspace(0.0, 1.0, 101)
    vertices = np.column_stack([np.arange(101.0), np.zeros(101), np.zeros(101)])
    triangles = np.arange(99).reshape(33, 3)  # uses vertices 0..98
    msg = triangle_marker_array(vertices, triangles, std, np.zeros(101, int), 'map', 0, types)
    top = colour_ramp(np.array([1.0]), 1.0)[0]
    colours = np.array([[c.r, c.g, c.b] for c in msg.markers[1].colors])
    p95 = np.percentile(std[:99], 95)
    saturated = std[:99] >= p95 + 1e-3
    assert saturated.any()
    np.testing.assert_allclose(colours[saturated], np.broadcast_to(top, colours[saturated].shape), atol=1e-6)
    assert not np.allclose(colours[std[:99] < 0.9 * p95], top)


def test_marker_errors(types):
    v = np.zeros((3, 3))
    ok = (v, np.array([[0, 1, 2]]), np.zeros(3), np.zeros(3, int))
    with pytest.raises(InputError, match='indices'):
        triangle_marker_array(v, np.array([[0, 1, 3]]), *ok[2:], 'map', 0, types)
    with pytest.raises(InputError, match='façade ids'):
        triangle_marker_array(*ok[:3], np.array([-1, 0, 0]), 'map', 0, types)
    with pytest.raises(InputError, match='NaN'):
        triangle_marker_array(np.full((3, 3), np.nan), *ok[1:], 'map', 0, types)
    with pytest.raises(InputError, match='one value per vertex'):
        triangle_marker_array(v, ok[1], np.zeros(2), ok[3], 'map', 0, types)
    with pytest.raises(InputError, match='std_max'):
        triangle_marker_array(*ok, 'map', 0, types, std_max=0.0)
    only_delete = triangle_marker_array(v, np.zeros((0, 3), int), *ok[2:], 'map', 0, types)
    assert [m.action for m in only_delete.markers] == [3]


def test_triangle_soup_shares_points(types):
    """A soup (every corner its own vertex) gets one Point per distinct position."""
    rng = np.random.default_rng(0)
    base = rng.normal(size=(50, 3))
    tri = rng.integers(0, 50, size=(200, 3))
    soup = base[tri.reshape(-1)]
    msg = triangle_marker_array(soup, np.arange(600).reshape(200, 3), np.zeros(600), np.zeros(600, int),
                                'map', 0, types)
    points = msg.markers[1].points
    assert len({id(p) for p in points}) == len(np.unique(tri))
    np.testing.assert_array_equal([[p.x, p.y, p.z] for p in points], soup)


def test_unique_rows_falls_back_on_hash_collisions(monkeypatch):
    rows = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [1.0, 2.0, 3.0], [-0.0, 0.0, 0.0]])
    first, inverse = mm._unique_rows(rows)
    np.testing.assert_array_equal(rows[first][inverse], rows)
    assert len(first) == 3
    real_argsort = np.argsort

    def colliding(key, *args, **kwargs):  # every key equal: all rows would be one group
        key[:] = 0
        return real_argsort(key, *args, **kwargs)

    monkeypatch.setattr(mm.np, 'argsort', colliding)
    first, inverse = mm._unique_rows(rows)
    np.testing.assert_array_equal(rows[first][inverse], rows)


# --------------------------------------------------------------------------------------
# diagnostics


def test_diagnostic_array(types):
    from diagnostic_msgs.msg import DiagnosticStatus
    values = {'facades': np.int64(21), 'rmse_m': np.float32(0.25), 'ok': True, 'name': 'street',
              'time_s': 0.1 + 0.2}
    with field_checks(types):
        msg = diagnostic_array('facade_mapper: map', 1, 'stale map', values, 'lidar0', STAMP, types)
        msg2 = diagnostic_array('x', DiagnosticStatus.ERROR, '', {}, '', 0, types)
    (status,) = msg.status
    assert status.level == DiagnosticStatus.WARN == b'\x01'
    assert (status.name, status.message, status.hardware_id) == ('facade_mapper: map', 'stale map', 'lidar0')
    assert [(kv.key, kv.value) for kv in status.values] == [
        ('facades', '21'), ('rmse_m', '0.25'), ('ok', 'True'), ('name', 'street'),
        ('time_s', '0.30000000000000004')]
    assert msg.header.stamp.sec == 1_700_000_000
    assert msg2.status[0].level == b'\x02' and msg2.status[0].values == []
    back = rclpy_round_trip(msg)
    assert back.status[0].values[1].value == '0.25' and back.status[0].level == b'\x01'
    # stand-ins without byte constants get an int level
    plain = SimpleNamespace(**vars(types))
    plain.DiagnosticStatus = lambda **kw: SimpleNamespace(**kw)
    assert diagnostic_array('n', 3, '', {}, '', 0, plain).status[0].level == 3
    with pytest.raises(InputError, match='level'):
        diagnostic_array('n', 4, '', {}, '', 0, types)


# --------------------------------------------------------------------------------------
# every standard message rclpy accepts with field checks on


def test_all_standard_messages_pass_rclpy_field_checks(types):
    with field_checks(types):
        with pytest.raises(AssertionError):  # the checks are on: an int is no float64
            types.Point(x=1)
        with pytest.raises(AssertionError):  # and a numpy integer is no uint32
            types.MapMetaData(width=np.int64(3))
        axes = FacadeFrame.from_normal(np.zeros(3), np.array([0, 1.0, 0])).axes
        pose = pose_from_frame(np.array([1.0, 2.0, 3.0]), axes, types)
        grid = occupancy_grid_msg(np.full((4, 5), 0.3), (0, 0), 0.1, 'map', STAMP, types)
        markers = triangle_marker_array(np.eye(3), np.array([[0, 1, 2]]), np.ones(3), np.array([4, 4, 4]),
                                        'map', STAMP, types)
    for msg in (pose, grid, markers):
        rclpy_round_trip(msg)
