"""uncertain_facade_map.io.av2 on a small Argoverse 2 log written here (feather files, known truth).

The log: two sweeps of float16 ego-frame points, an upper lidar 1.5 m above the ego origin
(no rotation) and a lower one rolled by 90 degrees about x, ego poses with
exact translations and yaws of 0 and 90 degrees; every expected value is worked out by hand.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.io.av2 import (
    LIDAR_DTYPE,
    REFERENCE_DTYPE,
    lidar_clouds,
    map_origin_of,
    read_av2_log,
    reference_clouds,
    rotation_matrices,
)

pa = pytest.importorskip('pyarrow')
feather = pytest.importorskip('pyarrow.feather')

S0, S1 = 1_000_000_000_000, 1_100_000_000_000  # sweep stamps, ns
YAW90 = [0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)]  # x, y, z, w
ROLL90 = [np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5)]  # 90 degrees about x: lidar (x, y, z) is ego (x, -z, y)
#: Ego-frame points (exact in float16) and their lasers: two of the upper lidar, two of the lower.
EGO = np.array([[10.0, 0.0, 1.5], [0.0, 4.0, 2.5], [6.0, -2.0, 0.25], [1.0, 1.0, 1.0]])
LASERS = np.array([3, 31, 32, 63], np.uint8)


def pose_row(t, q):
    return dict(tx_m=t[0], ty_m=t[1], tz_m=t[2], qx=q[0], qy=q[1], qz=q[2], qw=q[3])


def write_log(root: Path, *, poses=None, lidars=('up_lidar', 'down_lidar'), drop_column=None) -> Path:
    (root / 'sensors' / 'lidar').mkdir(parents=True)
    (root / 'calibration').mkdir()
    for k, stamp in enumerate((S0, S1)):
        columns = {'x': EGO[:, 0] + k, 'y': EGO[:, 1], 'z': EGO[:, 2]}
        table = {c: pa.array(v.astype(np.float16)) for c, v in columns.items()}
        table.update(intensity=pa.array(np.array([10, 20, 30, 40], np.uint8) + k),
                     laser_number=pa.array(LASERS), offset_ns=pa.array(np.array([0, 1000, 2000, 3000], np.int32)))
        table.pop(drop_column, None)
        feather.write_feather(pa.table(table), str(root / 'sensors' / 'lidar' / f'{stamp}.feather'))
    rows = poses or [(S0 - 50_000_000, [100.0, 200.0, 10.0], [0, 0, 0, 1]), (S0, [1000.4, 2000.6, 50.2], [0, 0, 0, 1]),
                     (S1, [1002.0, 2000.0, 50.0], YAW90), (S1 + 40_000_000, [1003.0, 2000.0, 50.0], YAW90)]
    records = [dict(timestamp_ns=s, **pose_row(t, q)) for s, t, q in rows[::-1]]  # stored out of order
    feather.write_feather(pa.table({k: [r[k] for r in records] for k in records[0]}),
                          str(root / 'city_SE3_egovehicle.feather'))
    mounts = {'up_lidar': ([0.0, 0.0, 1.5], [0, 0, 0, 1]), 'down_lidar': ([1.0, 0.0, 1.0], ROLL90),
              'ring_front_center': ([1.6, 0.0, 1.4], YAW90)}
    names = [n for n in mounts if n in lidars or not n.endswith('lidar')]
    calib = {'sensor_name': names}
    for key in ('tx_m', 'ty_m', 'tz_m', 'qx', 'qy', 'qz', 'qw'):
        calib[key] = [pose_row(*mounts[n])[key] for n in names]
    feather.write_feather(pa.table(calib), str(root / 'calibration' / 'egovehicle_SE3_sensor.feather'))
    return root


@pytest.fixture
def log(tmp_path):
    return read_av2_log(write_log(tmp_path / 'log'))


def test_read(log):
    assert [s.stamp_ns for s in log.sweeps] == [S0, S1]
    np.testing.assert_array_equal(log.sweeps[1].xyz, EGO + [1, 0, 0])
    assert log.sweeps[0].xyz.dtype == np.float64
    assert log.sweeps[1].intensity.tolist() == [11, 21, 31, 41]
    assert log.sweeps[0].laser_number.tolist() == LASERS.tolist()
    assert log.sweeps[0].offset_ns.tolist() == [0, 1000, 2000, 3000] and log.sweeps[0].offset_ns.dtype == np.int64
    assert log.poses.stamps_ns.tolist() == [S0 - 50_000_000, S0, S1, S1 + 40_000_000]
    assert log.poses.translations[1].tolist() == [1000.4, 2000.6, 50.2]
    np.testing.assert_array_equal(log.poses.quaternions[2], YAW90)
    assert sorted(log.extrinsics) == ['down_lidar', 'ring_front_center', 'up_lidar']
    assert log.extrinsics['down_lidar'].translation.tolist() == [1.0, 0.0, 1.0]
    assert log.extrinsics['down_lidar'].quaternion.tolist() == ROLL90
    assert len(read_av2_log(log.path, max_sweeps=1).sweeps) == 1
    assert map_origin_of(log).tolist() == [1000.0, 2001.0, 50.0]  # rounded to metres


def test_lidar_clouds(log):
    clouds = lidar_clouds(log, log.sweeps[0])
    assert list(clouds) == ['up_lidar', 'down_lidar']
    up, down = clouds['up_lidar'], clouds['down_lidar']
    assert up.dtype == down.dtype == LIDAR_DTYPE
    # Up: 1.5 m lower in its own frame. Down, rolled 90 degrees about x at (1, 0, 1): (x-1, z-1, -y).
    np.testing.assert_array_equal(np.stack([up[c] for c in 'xyz'], 1), [[10.0, 0.0, 0.0], [0.0, 4.0, 1.0]])
    np.testing.assert_allclose(np.stack([down[c] for c in 'xyz'], 1), [[5.0, -0.75, 2.0], [0.0, 0.0, -1.0]],
                               atol=1e-6)
    assert up['ring'].tolist() == [3, 31] and down['ring'].tolist() == [0, 31]
    assert up['intensity'].tolist() == [10.0, 20.0] and down['intensity'].tolist() == [30.0, 40.0]


def test_reference_clouds(log):
    ref = reference_clouds(log)
    assert [s for s, _ in ref] == [S0, S1]
    for _s, points in ref:
        assert points.dtype == REFERENCE_DTYPE
    origin = np.array([1000.0, 2001.0, 50.0])
    # Sweep 0: no rotation, ego at (1000.4, 2000.6, 50.2).
    p0 = ref[0][1]
    np.testing.assert_allclose(np.stack([p0[c] for c in 'xyz'], 1), EGO + [1000.4, 2000.6, 50.2] - origin, atol=1e-6)
    sensors = np.stack([p0['origin_' + c] for c in 'xyz'], 1)
    np.testing.assert_allclose(sensors, np.array([[0, 0, 1.5]] * 2 + [[1, 0, 1]] * 2) + [0.4, -0.4, 0.2], atol=1e-9)
    # Sweep 1: yaw 90 degrees, (x, y, z) -> (-y, x, z), ego at (1002, 2000, 50).
    p1 = ref[1][1]
    ego = EGO + [1, 0, 0]
    turned = np.stack([-ego[:, 1], ego[:, 0], ego[:, 2]], 1)
    np.testing.assert_allclose(np.stack([p1[c] for c in 'xyz'], 1), turned + [2.0, -1.0, 0.0], atol=1e-6)
    np.testing.assert_allclose([p1['origin_' + c][3] for c in 'xyz'], [2.0, 0.0, 1.0], atol=1e-9)
    assert p1['ring'].tolist() == [3, 31, 0, 31]
    # Another map origin moves everything by the difference.
    moved = reference_clouds(log, origin + [1.0, -2.0, 0.5])[1][1]
    assert np.allclose(moved['y'], p1['y'] + 2.0) and np.allclose(moved['origin_z'], p1['origin_z'] - 0.5)


def test_pose_interpolation(log):
    t, q = log.poses.at(S1)  # a recorded stamp: the recorded pose
    assert t.tolist() == [1002.0, 2000.0, 50.0] and q.tolist() == YAW90
    t, q = log.poses.at((S0 + S1) // 2)  # halfway: the mean translation, yaw 45 degrees
    np.testing.assert_allclose(t, [1001.2, 2000.3, 50.1])
    np.testing.assert_allclose(q, [0, 0, np.sin(np.pi / 8), np.cos(np.pi / 8)], atol=1e-12)
    t, q = log.poses.at(S0 + (S1 - S0) // 4)
    np.testing.assert_allclose(q, [0, 0, np.sin(np.pi / 16), np.cos(np.pi / 16)], atol=1e-12)
    with pytest.raises(InputError, match='no ego pose around'):
        log.poses.at(S1 + 50_000_000)


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-1, 1, allow_nan=False), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 1e-3))
def test_rotation_matrices_equal_scipys(q):
    from scipy.spatial.transform import Rotation

    np.testing.assert_allclose(rotation_matrices(np.array(q)), Rotation.from_quat(q).as_matrix(), atol=1e-12)
    assert rotation_matrices(np.array([q, q])).shape == (2, 3, 3)


def test_errors(tmp_path, monkeypatch):
    with pytest.raises(InputError, match='not a folder'):
        read_av2_log(tmp_path / 'nowhere')
    (tmp_path / 'empty').mkdir()
    with pytest.raises(InputError, match='no lidar sweep'):
        read_av2_log(tmp_path / 'empty')
    with pytest.raises(InputError, match=r"lacks the column\(s\) offset_ns"):
        read_av2_log(write_log(tmp_path / 'no_offset', drop_column='offset_ns'))
    with pytest.raises(InputError, match='two with one stamp'):
        read_av2_log(write_log(tmp_path / 'twice', poses=[(S0, [0, 0, 0], [0, 0, 0, 1])] * 2))
    log = read_av2_log(write_log(tmp_path / 'one_lidar', lidars=('up_lidar',)))
    with pytest.raises(InputError, match='no extrinsic of down_lidar'):
        lidar_clouds(log, log.sweeps[0])
    broken = write_log(tmp_path / 'broken')
    (broken / 'city_SE3_egovehicle.feather').write_bytes(b'not arrow')
    with pytest.raises(InputError, match='cannot read .* as a feather file'):
        read_av2_log(broken)
    (broken / 'city_SE3_egovehicle.feather').unlink()
    with pytest.raises(InputError, match='city_SE3_egovehicle.feather not found'):
        read_av2_log(broken)
    monkeypatch.setitem(sys.modules, 'pyarrow.feather', None)
    with pytest.raises(InputError, match='needs pyarrow'):
        read_av2_log(write_log(tmp_path / 'fine'))


def test_a_log_without_calibration_takes_the_documented_lidar_layout(tmp_path):
    import shutil

    from uncertain_facade_map.io.av2 import DOCUMENTED_LIDARS

    root = write_log(tmp_path / 'sample')
    shutil.rmtree(root / 'calibration')
    log = read_av2_log(root)
    assert sorted(log.extrinsics) == ['down_lidar', 'up_lidar']
    for name, (t, q) in DOCUMENTED_LIDARS.items():
        assert log.extrinsics[name].translation.tolist() == list(t)
        assert log.extrinsics[name].quaternion.tolist() == list(q)
    assert len(log.warnings) == 1 and 'no calibration/ folder' in log.warnings[0]
    # av2-api's example: the upper lidar upright, the lower one upside down (z flipped).
    up, down = (rotation_matrices(np.array(DOCUMENTED_LIDARS[n][1])) for n in ('up_lidar', 'down_lidar'))
    assert up[2, 2] > 0.999 and down[2, 2] < -0.999
    # The clouds are placed by it: each lidar's points back in the ego frame exactly.
    clouds = lidar_clouds(log, log.sweeps[0])
    ref = reference_clouds(log)[0][1]
    assert len(clouds['up_lidar']) + len(clouds['down_lidar']) == len(ref)
    # A calibration folder without its file is an error, as before: the user meant to give one.
    (root / 'calibration').mkdir()
    with pytest.raises(InputError, match='egovehicle_SE3_sensor.feather not found'):
        read_av2_log(root)
    assert read_av2_log(write_log(tmp_path / 'calibrated')).warnings == ()
