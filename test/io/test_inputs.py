"""Tests of uncertain_facade_map.io.inputs: reading every input format, joining, building points."""

from __future__ import annotations

from pathlib import Path

import hypothesis.extra.numpy as hnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from msg_adapters.bag_io import load_inputs as load_with_bags
from uncertain_facade_map.errors import InputError
from uncertain_facade_map.io.cloud import Cloud
from uncertain_facade_map.io.clouds import write_cloud
from uncertain_facade_map.io.inputs import BuildingPoints, load_inputs, read_input, select_building_points
from uncertain_facade_map.io.las import LAS_SCALE
from uncertain_facade_map.io.npz import write_npz
from uncertain_facade_map.io.pcd import write_pcd
from uncertain_facade_map.io.ply import write_ply
from uncertain_facade_map.io.trajectory import Trajectory
from uncertain_facade_map.params import InputConfig

SETTINGS = settings(max_examples=60, deadline=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

ORIGIN = np.array([2683000.5, 1247000.25, 400.0])
STAMP_NS = 1_700_000_000_123_456_789
SUPPORTED = ('supported: .npz, .ply, .las, .laz, .pcd files and ROS bags '
             '(.bag, .db3, .mcap or a bag folder with metadata.yaml)')


def scene_points(n: int = 200, seed: int = 0) -> np.ndarray:
    """Façade-like points with class, building id, time and sensor origins."""
    rng = np.random.default_rng(seed)
    pts = np.zeros(n, dtype=[('x', 'f8'), ('y', 'f8'), ('z', 'f8'), ('origin_x', 'f8'), ('origin_y', 'f8'),
                             ('origin_z', 'f8'), ('time', 'f8'), ('building_id', 'i4'), ('class', 'u1')])
    pts['x'] = rng.uniform(-50, 50, n)
    pts['y'] = rng.uniform(-50, 50, n)
    pts['z'] = rng.uniform(0, 20, n)
    pts['origin_x'] = rng.uniform(-5, 5, n)
    pts['origin_z'] = 2.0
    pts['time'] = 1.7e9 + np.sort(rng.uniform(0, 60, n))
    pts['class'] = rng.choice([0, 1, 2, 3], n)
    pts['building_id'] = np.where(pts['class'] == 1, rng.integers(0, 5, n), -1)
    return pts


def one_line_error(func, *args, **kwargs) -> str:
    """Call ``func``, expect an InputError with a one-line message, return the message."""
    with pytest.raises(InputError) as err:
        func(*args, **kwargs)
    message = str(err.value)
    assert message and '\n' not in message
    return message


# --------------------------------------------------------------------------------------
# select_building_points

CLASS_TYPES = ['u1', 'i1', 'u2', 'i2', 'u4', 'i4', 'i8', 'f4', 'f8', '?']


@st.composite
def classified(draw: st.DrawFn) -> tuple[Cloud, InputConfig]:
    """A cloud with a random class field (any integer-valued type) and random building_classes."""
    n = draw(st.integers(1, 60))
    ctype = np.dtype(draw(st.sampled_from(CLASS_TYPES)))
    lo = 0 if ctype.kind in 'ub' else -3
    hi = 1 if ctype.kind == 'b' else 8
    extras = draw(st.lists(st.sampled_from(['building_id', 'time', 'origins']), unique=True))
    fields = [('x', 'f8'), ('y', 'f4'), ('z', 'f8'), ('label', ctype)]
    if 'origins' in extras:
        fields += [('origin_x', 'f4'), ('origin_y', 'f8'), ('origin_z', 'f8')]
    if 'building_id' in extras:
        fields.append(('bid', draw(st.sampled_from(['i4', 'u2', 'i8']))))
    if 'time' in extras:
        fields.append(('time', 'f8'))
    points = np.zeros(n, dtype=fields)
    for name, ftype in fields:
        if name == 'label':
            points[name] = draw(hnp.arrays(ctype, n, elements=st.integers(lo, hi)))
        elif name == 'bid':
            points[name] = draw(hnp.arrays(np.dtype(ftype), n, elements=st.integers(0, 1000)))
        else:
            points[name] = draw(hnp.arrays(np.dtype(ftype), n, elements=st.floats(-1e4, 1e4, width=8 * np.dtype(ftype).itemsize)))
    classes = tuple(draw(st.lists(st.integers(-3, 8), max_size=4)))
    config = InputConfig(class_field='label', building_classes=classes, building_id_field='bid')
    return Cloud(points, draw(st.sampled_from([np.zeros(3), ORIGIN]))), config


@SETTINGS
@given(case=classified())
def test_selection_equals_the_reference(case: tuple[Cloud, InputConfig]) -> None:
    cloud, config = case
    labels = [int(v) for v in cloud.points['label']]
    wanted = set(config.building_classes)
    reference = np.array([i for i, v in enumerate(labels) if v in wanted], dtype=np.int64)
    if len(reference) == 0:
        found = sorted(set(labels))
        hint = ('; ASPRS LAS files mark buildings with class 6, set input.building_classes: [6]'
                if 6 in found and 6 not in wanted else '')
        assert one_line_error(select_building_points, cloud, config) == (
            f"no building points: class field 'label' holds {found}, "
            f'input.building_classes is {sorted(wanted)}{hint}')
        return
    selected = select_building_points(cloud, config)
    assert isinstance(selected, BuildingPoints)
    assert selected.index.dtype == np.int64 and np.array_equal(selected.index, reference)
    assert len(selected) == len(reference)
    assert selected.xyz.dtype == np.float64 and selected.xyz.shape == (len(reference), 3)
    assert np.array_equal(selected.xyz, cloud.xyz[reference])
    assert np.array_equal(selected.map_origin, cloud.map_origin)
    if 'bid' in cloud.fields:
        assert selected.building_id.dtype == np.int64
        assert selected.building_id.tolist() == cloud.points['bid'][reference].tolist()
    else:
        assert selected.building_id is None
    if 'origin_x' in cloud.fields:
        assert np.array_equal(selected.sensor_origins, cloud.sensor_origins[reference])
    else:
        assert selected.sensor_origins is None
    if 'time' in cloud.fields:
        assert np.array_equal(selected.time, cloud.points['time'][reference])
    else:
        assert selected.time is None


@SETTINGS
@given(n=st.integers(1, 50), classes=st.lists(st.integers(0, 9), max_size=3).map(tuple))
def test_cloud_without_class_field_is_all_building(n: int, classes: tuple[int, ...]) -> None:
    pts = np.zeros(n, dtype=[('x', 'f4'), ('y', 'f4'), ('z', 'f4'), ('building_id', 'i4')])
    pts['x'] = np.arange(n)
    pts['building_id'] = np.arange(n) % 3
    selected = select_building_points(Cloud(pts, ORIGIN), InputConfig(building_classes=classes))
    assert selected.index.tolist() == list(range(n))
    assert selected.xyz[:, 0].tolist() == list(range(n))
    assert selected.building_id.tolist() == (np.arange(n) % 3).tolist()
    assert selected.sensor_origins is None and selected.time is None
    assert selected.map_origin.tolist() == ORIGIN.tolist()


def test_default_config_on_a_scene() -> None:
    pts = scene_points()
    selected = select_building_points(Cloud(pts, ORIGIN), InputConfig())
    keep = np.flatnonzero(pts['class'] == 1)
    assert selected.index.tolist() == keep.tolist()
    assert selected.building_id.tolist() == pts['building_id'][keep].tolist()
    assert np.array_equal(selected.sensor_origins[:, 0], pts['origin_x'][keep])
    assert np.array_equal(selected.time, pts['time'][keep])


def test_a_sensor_position_is_every_origin_of_a_cloud_without_origins() -> None:
    pts = scene_points()
    bare = pts[['x', 'y', 'z', 'class']]
    selected = select_building_points(Cloud(bare), InputConfig(), sensor=(1.0, -2.0, 1.8))
    assert selected.sensor_origins.shape == (len(selected.index), 3)
    assert (selected.sensor_origins == [1.0, -2.0, 1.8]).all()
    assert select_building_points(Cloud(bare), InputConfig()).sensor_origins is None
    # The cloud's own origins win.
    own = select_building_points(Cloud(pts), InputConfig(), sensor=(1.0, -2.0, 1.8))
    assert np.array_equal(own.sensor_origins[:, 0], pts['origin_x'][own.index])
    for bad in ((1.0, 2.0), (0.0, np.nan, 1.0)):
        assert 'sensor position must be three finite numbers' in one_line_error(
            select_building_points, Cloud(bare), InputConfig(), sensor=bad)


def test_a_trajectory_gives_each_point_the_position_at_its_time() -> None:
    """Positions interpolated at the points' times, in the map frame (the cloud's origin
    subtracted); the cloud's own origins win; a cloud without times and a trajectory with a
    sensor position are refused."""
    pts = scene_points()
    bare = pts[['x', 'y', 'z', 'class', 'time']]
    t0, t1 = pts['time'][0], pts['time'][-1]
    path = Trajectory(np.array([t0, t1]), ORIGIN + np.array([[0.0, 0.0, 2.0], [60.0, 30.0, 2.0]]))
    selected = select_building_points(Cloud(bare, ORIGIN), InputConfig(), trajectory=path)
    share = (pts['time'][selected.index] - t0) / (t1 - t0)
    assert np.allclose(selected.sensor_origins, np.c_[60 * share, 30 * share, np.full(len(share), 2.0)], atol=1e-6)
    own = select_building_points(Cloud(pts, ORIGIN), InputConfig(), trajectory=path)
    assert np.array_equal(own.sensor_origins[:, 0], pts['origin_x'][own.index])
    assert 'has no time field' in one_line_error(
        select_building_points, Cloud(bare[['x', 'y', 'z', 'class']]), InputConfig(), trajectory=path)
    assert 'not both' in one_line_error(select_building_points, Cloud(bare), InputConfig(),
                                        sensor=(0.0, 0.0, 1.0), trajectory=path)
    late = Trajectory(np.array([t0 + 30, t1]), path.position)
    assert 'point times lie outside the trajectory' in one_line_error(
        select_building_points, Cloud(bare), InputConfig(), trajectory=late)


def test_float_class_with_integral_values_is_accepted() -> None:
    pts = np.zeros(4, dtype=[('x', 'f8'), ('y', 'f8'), ('z', 'f8'), ('class', 'f4')])
    pts['class'] = [6.0, 1.0, -0.0, 6.0]
    selected = select_building_points(Cloud(pts), InputConfig(building_classes=(6,)))
    assert selected.index.tolist() == [0, 3]


@pytest.mark.parametrize('dtype, values, message', [
    ('f4', [1.0, 1.5, 2.0], "class field 'class' must hold integers, found 1 of 3 values that are not, e.g. 1.5"),
    ('f8', [np.nan, 1.0, np.inf], "class field 'class' must hold integers, found 2 of 3 values that are not, e.g. nan"),
    ('U3', ['a', 'b', 'c'], "class field 'class' must hold integers, found type <U3"),
])
def test_class_field_that_is_not_integer_valued(dtype: str, values: list, message: str) -> None:
    pts = np.zeros(3, dtype=[('x', 'f8'), ('y', 'f8'), ('z', 'f8'), ('class', dtype)])
    pts['class'] = values
    assert one_line_error(select_building_points, Cloud(pts), InputConfig()) == message


def test_building_id_field_that_is_not_integer_valued() -> None:
    pts = np.zeros(2, dtype=[('x', 'f8'), ('y', 'f8'), ('z', 'f8'), ('building_id', 'f8')])
    pts['building_id'] = [0.5, 1.0]
    assert one_line_error(select_building_points, Cloud(pts), InputConfig()) == (
        "building id field 'building_id' must hold integers, found 1 of 2 values that are not, e.g. 0.5")


def test_empty_cloud_is_refused() -> None:
    empty = Cloud(np.zeros(0, dtype=[('x', 'f8'), ('y', 'f8'), ('z', 'f8')]))
    assert one_line_error(select_building_points, empty, InputConfig()) == 'the input cloud has no points'


def test_nan_and_inf_coordinates_are_counted() -> None:
    pts = scene_points(10)
    pts['x'][2] = np.nan
    pts['z'][2] = np.inf
    pts['y'][7] = -np.inf
    assert one_line_error(select_building_points, Cloud(pts), InputConfig()) == (
        '2 of 10 input points have NaN or infinite coordinates')


def test_no_building_points_lists_classes_and_hints_at_asprs() -> None:
    pts = scene_points(30)
    pts['class'] = np.arange(30) % 3 * 3  # 0, 3, 6
    message = one_line_error(select_building_points, Cloud(pts), InputConfig())
    assert message == ("no building points: class field 'class' holds [0, 3, 6], input.building_classes "
                       'is [1]; ASPRS LAS files mark buildings with class 6, set input.building_classes: [6]')
    pts['class'] = np.arange(30) + 7
    message = one_line_error(select_building_points, Cloud(pts), InputConfig(building_classes=(41, 40, 41)))
    assert message.startswith("no building points: class field 'class' holds [7, 8, 9, ")
    assert message.endswith(', 26, ... (30 values)], input.building_classes is [40, 41]')


# --------------------------------------------------------------------------------------
# load_inputs


def write_every_format(tmp_path: Path, cloud: Cloud) -> dict[str, Path]:
    """The same cloud as PLY, NPZ, LAS, LAZ, PCD and four kinds of bags."""
    from msg_adapters.bag_io import write_bag

    paths = {}
    for suffix in ('ply', 'npz', 'las', 'laz', 'pcd'):
        paths[suffix] = tmp_path / f'cloud.{suffix}'
        write_cloud(paths[suffix], cloud)
    half = len(cloud) // 2
    scans = [(STAMP_NS, cloud.points[:half]), (STAMP_NS + 100_000_000, cloud.points[half:])]
    for storage, name in (('mcap', 'bag_mcap'), ('sqlite3', 'bag_sqlite3'), ('rosbag1', 'ros1.bag')):
        paths[storage] = write_bag(tmp_path / name, scans, storage=storage, map_origin=cloud.map_origin)
    paths['mcap file'] = next(paths['mcap'].glob('*.mcap'))
    paths['db3 file'] = next(paths['sqlite3'].glob('*.db3'))
    return paths


def test_every_format_gives_the_same_points(tmp_path: Path) -> None:
    cloud = Cloud(scene_points(), ORIGIN)
    reference = select_building_points(cloud, InputConfig())
    for kind, path in write_every_format(tmp_path, cloud).items():
        loaded = load_with_bags([path])
        assert loaded.map_origin.tolist() == ORIGIN.tolist(), kind
        tolerance = LAS_SCALE / 2 + 1e-9 if kind in ('las', 'laz') else 0.0
        assert np.all(np.abs(loaded.xyz - cloud.xyz) <= tolerance), kind
        for name in ('class', 'building_id', 'time', 'origin_x', 'origin_y', 'origin_z'):
            assert np.array_equal(loaded.points[name], cloud.points[name]), (kind, name)
        if kind not in ('las', 'laz'):
            assert loaded.same_as(cloud), kind
        selected = select_building_points(loaded, InputConfig())
        assert np.array_equal(selected.index, reference.index), kind
        assert np.array_equal(selected.building_id, reference.building_id), kind
        assert np.array_equal(selected.time, reference.time), kind
        assert np.array_equal(selected.sensor_origins, reference.sensor_origins), kind


def test_bag_topic_is_passed_on(tmp_path: Path) -> None:
    from msg_adapters.bag_io import write_bag

    pts = scene_points(6)
    bag = write_bag(tmp_path / 'b', [(STAMP_NS, pts)], storage='mcap', topic='/lidar/points')
    assert load_with_bags([bag], topic='/lidar/points').same_as(Cloud(pts))
    assert "no sensor_msgs/msg/PointCloud2 topic '/other'" in one_line_error(load_with_bags, [bag], topic='/other')
    # The core alone reads no bag, and says where to read it.
    assert 'bags are read through msg_adapters' in one_line_error(load_inputs, [bag])


def test_joining_inputs_with_different_map_origins(tmp_path: Path) -> None:
    a = scene_points(20, seed=1)
    b = scene_points(30, seed=2)
    a_f4 = np.zeros(20, dtype=[('x', 'f4'), ('y', 'f4'), ('z', 'f4'), ('origin_x', 'f4'), ('origin_y', 'f4'),
                               ('origin_z', 'f4'), ('class', 'u1'), ('intensity', 'u2')])
    for name in a_f4.dtype.names:
        if name != 'intensity':
            a_f4[name] = a[name]
    b_i4 = np.zeros(30, dtype=[('class', 'i4'), ('x', 'f8'), ('y', 'f8'), ('z', 'f8'), ('origin_x', 'f8'),
                               ('origin_y', 'f8'), ('origin_z', 'f8'), ('time', 'f8')])
    for name in b_i4.dtype.names:
        b_i4[name] = b[name]
    origin_b = ORIGIN + [100.5, -20.25, 3.0]
    write_npz(tmp_path / 'a.npz', Cloud(a_f4, ORIGIN))
    write_ply(tmp_path / 'b.ply', Cloud(b_i4, origin_b))
    joined = load_inputs([tmp_path / 'a.npz', tmp_path / 'b.ply'])
    assert joined.map_origin.tolist() == ORIGIN.tolist()
    assert joined.fields == ('x', 'y', 'z', 'origin_x', 'origin_y', 'origin_z', 'class')
    assert joined.points.dtype['x'] == np.float64 and joined.points.dtype['class'] == np.int32
    assert len(joined) == 50
    assert np.array_equal(joined.xyz[:20], Cloud(a_f4).xyz)
    assert np.array_equal(joined.xyz[20:], Cloud(b_i4).xyz + (origin_b - ORIGIN))
    assert np.array_equal(joined.sensor_origins[20:], Cloud(b_i4).sensor_origins + (origin_b - ORIGIN))
    georeferenced = joined.xyz + joined.map_origin
    assert np.allclose(georeferenced[20:], Cloud(b_i4).xyz + origin_b, rtol=0, atol=1e-8)
    assert joined.points['class'].tolist() == a_f4['class'].tolist() + b_i4['class'].tolist()


def test_joining_inputs_with_the_same_origin_keeps_types(tmp_path: Path) -> None:
    pts = np.zeros(5, dtype=[('x', 'f4'), ('y', 'f4'), ('z', 'f4'), ('class', 'u1')])
    pts['x'] = np.arange(5) + 0.1
    write_pcd(tmp_path / 'a.pcd', Cloud(pts, ORIGIN), encoding='ascii')
    write_npz(tmp_path / 'b.npz', Cloud(pts[::-1].copy(), ORIGIN))
    joined = load_inputs([tmp_path / 'a.pcd', str(tmp_path / 'b.npz')])
    assert joined.same_as(Cloud(np.concatenate([pts, pts[::-1]]), ORIGIN))


def test_las_and_pcd_join_on_common_fields(tmp_path: Path) -> None:
    cloud = Cloud(scene_points(40), ORIGIN)
    write_cloud(tmp_path / 'a.laz', cloud)
    write_cloud(tmp_path / 'b.pcd', Cloud(cloud.points, ORIGIN - 1000.0))
    joined = load_inputs([tmp_path / 'a.laz', tmp_path / 'b.pcd'])
    assert set(joined.fields) == set(cloud.fields)
    assert np.all(np.abs(joined.xyz[40:] - (cloud.xyz - 1000.0)) < 1e-9)
    selected = select_building_points(joined, InputConfig())
    keep = np.flatnonzero(cloud.points['class'] == 1)
    assert selected.index.tolist() == keep.tolist() + (keep + 40).tolist()


# --------------------------------------------------------------------------------------
# errors


def test_no_paths() -> None:
    assert one_line_error(load_inputs, []) == 'no input files given'


def test_missing_file(tmp_path: Path) -> None:
    write_npz(tmp_path / 'a.npz', Cloud(scene_points(3)))
    for name in ('missing.ply', 'missing.bag', 'missing_bag_folder'):
        assert one_line_error(load_inputs, [tmp_path / 'a.npz', tmp_path / name]) == (
            f'no such file: {tmp_path / name}')


def test_unknown_format(tmp_path: Path) -> None:
    for name in ('points.txt', 'points', 'points.ply.gz'):
        (tmp_path / name).write_text('1 2 3\n')
        suffix = Path(name).suffix or 'none'
        assert one_line_error(load_inputs, [tmp_path / name]) == (
            f'unsupported input {tmp_path / name} (suffix {suffix}); {SUPPORTED}')


def test_folder_that_is_no_bag(tmp_path: Path) -> None:
    (tmp_path / 'scans').mkdir()
    assert one_line_error(read_input, tmp_path / 'scans') == (
        f'{tmp_path / "scans"} is a directory but no ROS 2 bag (no metadata.yaml)')


def test_empty_inputs(tmp_path: Path) -> None:
    empty = Cloud(np.zeros(0, dtype=[('x', 'f8'), ('y', 'f8'), ('z', 'f8')]))
    write_npz(tmp_path / 'e.npz', empty)
    write_cloud(tmp_path / 'e.las', empty)
    assert one_line_error(load_inputs, [tmp_path / 'e.npz']) == f'no points in {tmp_path / "e.npz"}'
    assert one_line_error(load_inputs, [tmp_path / 'e.npz', tmp_path / 'e.las']) == (
        f'no points in {tmp_path / "e.npz"}, {tmp_path / "e.las"}')


def test_nan_coordinate_from_a_file(tmp_path: Path) -> None:
    pts = scene_points(8)
    pts['y'][3] = np.nan
    write_pcd(tmp_path / 'n.pcd', Cloud(pts), encoding='binary_compressed')
    cloud = load_inputs([tmp_path / 'n.pcd'])
    assert one_line_error(select_building_points, cloud, InputConfig()) == (
        '1 of 8 input points have NaN or infinite coordinates')


def test_no_building_points_in_a_las_file(tmp_path: Path) -> None:
    pts = scene_points(12)
    pts['class'] = [2, 6] * 6
    write_cloud(tmp_path / 'asprs.las', Cloud(pts, ORIGIN))
    cloud = load_inputs([tmp_path / 'asprs.las'])
    assert one_line_error(select_building_points, cloud, InputConfig()) == (
        "no building points: class field 'class' holds [2, 6], input.building_classes is [1]; "
        'ASPRS LAS files mark buildings with class 6, set input.building_classes: [6]')
    assert len(select_building_points(cloud, InputConfig(building_classes=(6,)))) == 6


def test_corrupt_file_and_bag(tmp_path: Path) -> None:
    (tmp_path / 'bad.laz').write_bytes(b'LASF' + bytes(300))
    assert one_line_error(load_inputs, [tmp_path / 'bad.laz']).startswith(
        f'cannot read LAS file {tmp_path / "bad.laz"}: ')
    (tmp_path / 'bad.bag').write_bytes(b'#ROSBAG V2.0\n' + bytes(50))
    assert one_line_error(load_with_bags, [tmp_path / 'bad.bag']).startswith(
        f'cannot read {tmp_path / "bad.bag"} as a ROS 1 or ROS 2 bag: ')


# --------------------------------------------------------------------------------------
# Clouds without classes: the building point selection (uncertain_facade_map.selection)
def street_cloud(with_class: bool = False) -> tuple[Cloud, np.ndarray]:
    """The synthetic unclassified street (support.unclassified_street) as a cloud with sensor
    origins (and a class field of all 1 when asked), and its labels."""
    from support import unclassified_street

    xyz, labels, sensor = unclassified_street(seed=1)
    fields = [('x', 'f8'), ('y', 'f8'), ('z', 'f8'), ('origin_x', 'f8'), ('origin_y', 'f8'), ('origin_z', 'f8')]
    pts = np.zeros(len(xyz), dtype=fields + ([('class', 'u1')] if with_class else []))
    pts['x'], pts['y'], pts['z'] = xyz.T
    pts['origin_x'], pts['origin_y'], pts['origin_z'] = sensor
    if with_class:
        pts['class'] = 1
    return Cloud(pts, ORIGIN), labels


def test_a_cloud_without_classes_is_selected() -> None:
    from support import WALL

    from uncertain_facade_map.params import SelectionConfig
    from uncertain_facade_map.selection import select_building_points as select

    cloud, labels = street_cloud()
    selected = select_building_points(cloud, InputConfig(), SelectionConfig())
    expected = select(cloud.xyz, cloud.sensor_origins).mask
    assert selected.index.tolist() == np.flatnonzero(expected).tolist()
    assert selected.selection is not None and selected.selection.applied and selected.selection.walls == 3
    assert (labels[selected.index] == WALL).mean() >= 0.99 and len(selected) >= 0.97 * (labels == WALL).sum()
    assert np.array_equal(selected.sensor_origins, cloud.sensor_origins[selected.index])
    # No selection given, or mode off: all building, as before.
    for off in (None, SelectionConfig(mode='off')):
        everything = select_building_points(cloud, InputConfig(), off)
        assert len(everything) == len(cloud) and everything.selection is None


def test_the_class_field_wins_in_auto_and_is_ignored_when_on() -> None:
    from uncertain_facade_map.params import SelectionConfig

    cloud, _ = street_cloud(with_class=True)
    by_class = select_building_points(cloud, InputConfig(), SelectionConfig(mode='auto'))
    assert len(by_class) == len(cloud) and by_class.selection is None
    on = select_building_points(cloud, InputConfig(), SelectionConfig(mode='on'))
    plain, _ = street_cloud()
    assert on.index.tolist() == select_building_points(plain, InputConfig(), SelectionConfig()).index.tolist()


def test_a_selection_without_walls_is_a_one_line_error() -> None:
    from uncertain_facade_map.params import SelectionConfig

    rng = np.random.default_rng(0)
    pts = np.zeros(3000, dtype=[('x', 'f8'), ('y', 'f8'), ('z', 'f8')])
    pts['x'], pts['y'] = rng.uniform(-30, 30, (2, 3000))
    pts['z'] = rng.normal(0, 0.02, 3000)
    message = one_line_error(select_building_points, Cloud(pts), InputConfig(), SelectionConfig())
    assert message.startswith('no building points: the selection (selection.mode: auto) found no wall in 3000 points')


def test_scan_points_of_a_scan_without_classes() -> None:
    from support import WALL

    from uncertain_facade_map.io.scans import select_scan_points
    from uncertain_facade_map.params import SelectionConfig
    from uncertain_facade_map.selection import select_building_points as select

    cloud, labels = street_cloud()
    points = cloud.points.copy()
    points['x'][:5] = np.nan  # no returns (ground points): skipped and counted
    finite = np.isfinite(points['x'])
    expected = select(cloud.xyz[finite], cloud.sensor_origins[finite]).mask
    scan = select_scan_points(points, InputConfig(), SelectionConfig())
    assert scan.nonfinite == 5 and scan.not_building == int(finite.sum() - expected.sum())
    assert np.array_equal(scan.xyz, cloud.xyz[finite][expected])
    assert np.array_equal(scan.sensor_origins, cloud.sensor_origins[finite][expected])
    assert (labels[finite][expected] == WALL).mean() >= 0.99
    # What the selection found comes along, for its warning (the node logs it).
    assert scan.selection is not None and scan.selection.kept == len(scan.xyz)
    assert sum(scan.selection.dropped_by.values()) == scan.selection.non_ground - scan.selection.kept
    # Without origin fields the given sensor origin (the node: the scan's own frame) is used.
    plain = points[['x', 'y', 'z']]
    assert np.array_equal(select_scan_points(plain, InputConfig(), SelectionConfig(),
                                             sensor_origin=np.array([0.0, 0.0, 1.8])).xyz, scan.xyz)
    # No selection: all building, as before.
    assert len(select_scan_points(points, InputConfig()).xyz) == finite.sum()
    assert select_scan_points(points, InputConfig()).selection is None


# ----------------------------------------------------------------------------------------
# Absurd coordinates offline (input.max_distance): dropped with a count, or the file refused
# ----------------------------------------------------------------------------------------
def _street_points(n: int = 2000, seed: int = 0) -> np.ndarray:
    """A wall-like cloud of ``n`` float32 points near a map origin, class 1."""
    rng = np.random.default_rng(seed)
    points = np.zeros(n, dtype=[('x', 'f4'), ('y', 'f4'), ('z', 'f4'), ('class', 'u1')])
    points['x'] = rng.uniform(0, 40, n)
    points['y'] = 8.0 + rng.normal(0, 0.02, n)
    points['z'] = rng.uniform(0, 12, n)
    points['class'] = 1
    return points


def test_a_few_absurd_points_are_dropped_and_counted(tmp_path: Path) -> None:
    points = _street_points()
    points['x'][[3, 70, 900]] = np.float32(1e30)
    points['z'][5] = np.float32(-3e12)  # finite, NaN-free, absurd
    write_npz(tmp_path / 'far.npz', Cloud(points))
    said: list[str] = []
    cloud = load_inputs([tmp_path / 'far.npz'], max_distance=100_000.0, warn=said.append)
    assert len(cloud) == len(points) - 4
    assert np.abs(cloud.xyz).max() < 100
    assert said == [f'{tmp_path / "far.npz"}: dropped 4 of 2,000 points farther than 100000 m from the median point '
                    'in x, y or z (input.max_distance)']
    # Without the check the points stay (the caller's choice).
    assert len(load_inputs([tmp_path / 'far.npz'])) == len(points)


def test_a_file_of_mostly_absurd_points_is_refused(tmp_path: Path) -> None:
    points = _street_points()
    points['y'][::10] = np.float32(1e20)  # 10 % absurd, finite
    write_npz(tmp_path / 'absurd.npz', Cloud(points))
    with pytest.raises(InputError, match=r'absurd\.npz: 200 of 2,000 points \(10%\) are NaN or farther than 100000 m '
                                         r'from the median point \(input\.max_distance\).*looks corrupted, not mapped$'):
        load_inputs([tmp_path / 'absurd.npz'], max_distance=100_000.0)


def test_a_file_far_from_any_place_on_earth_is_refused(tmp_path: Path) -> None:
    points = _street_points()
    points['x'] += np.float32(1e12)  # consistent, but no place on Earth
    write_npz(tmp_path / 'space.npz', Cloud(points))
    with pytest.raises(InputError, match='farther than any place on Earth'):
        load_inputs([tmp_path / 'space.npz'], max_distance=100_000.0)


@pytest.mark.parametrize('fmt', ['ply', 'npz', 'pcd'])
def test_byte_swapped_coordinates_are_refused_with_a_hint(tmp_path: Path, fmt: str) -> None:
    points = _street_points()
    for c in ('x', 'y', 'z'):
        points[c] = points[c].byteswap()  # the values a reader gets from data in the other byte order
    path = tmp_path / f'swapped.{fmt}'
    write_cloud(path, Cloud(points))
    with pytest.raises(InputError, match=r"other byte order they would be plausible, so the file's byte order is "
                                         r'wrong: the file looks corrupted, not mapped$'):
        load_inputs([path], max_distance=100_000.0)


def test_build_refuses_absurd_inputs_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The command line: no traceback for 1e30, absurd or byte-swapped inputs (issue 25 item 6)."""
    from uncertain_facade_map_apps.cli import main

    points = _street_points()
    points['y'][::4] = np.float32(1e30)
    write_npz(tmp_path / 'bad.npz', Cloud(points))
    assert main(['build', str(tmp_path / 'bad.npz'), '--out', str(tmp_path / 'map.npz'), '--quiet']) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and 'bad.npz' in err and 'input.max_distance' in err
    assert not (tmp_path / 'map.npz').exists()
