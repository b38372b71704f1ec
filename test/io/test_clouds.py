"""Tests of uncertain_facade_map.io.clouds: the format chosen by the suffix, and clean errors for every format."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from cloud_support import SETTINGS, one_line_error, raw_clouds, xyz_points
from hypothesis import given, settings
from hypothesis import strategies as st

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.io.cloud import Cloud, simulated_dtype
from uncertain_facade_map.io.clouds import read_cloud, write_cloud
from uncertain_facade_map.io.las import LAS_SCALE, read_las
from uncertain_facade_map.io.npz import read_npz, write_npz
from uncertain_facade_map.io.pcd import read_pcd, write_pcd
from uncertain_facade_map.io.ply import read_ply, write_ply

# --------------------------------------------------------------------------------------
# round trips


@settings(SETTINGS, max_examples=30)
@given(cloud=raw_clouds())
def test_binary_formats_keep_every_bit_pattern(tmp_path: Path, cloud: Cloud) -> None:
    for name in ('c.ply', 'c.npz'):
        write_cloud(tmp_path / name, cloud)
        assert read_cloud(tmp_path / name).same_as(cloud), name


def test_simulated_cloud_round_trips_through_every_format(tmp_path: Path) -> None:
    pts = np.zeros(50, dtype=simulated_dtype('f4'))
    rng = np.random.default_rng(1)
    for name in pts.dtype.names:
        pts[name] = rng.integers(0, 5, 50)
    pts['x'] = rng.normal(size=50)
    cloud = Cloud(pts, [2683000.0, 1247000.0, 400.0])
    for name in ('a.ply', 'a.npz', 'A.PLY', 'A.NPZ'):
        write_cloud(tmp_path / name, cloud)
        assert read_cloud(tmp_path / name).same_as(cloud)


def test_empty_cloud(tmp_path: Path) -> None:
    cloud = Cloud(xyz_points(0))
    for name in ('e.ply', 'e.npz'):
        write_cloud(tmp_path / name, cloud)
        assert read_cloud(tmp_path / name).same_as(cloud)
    write_ply(tmp_path / 'e.ply', cloud, binary=False)
    assert read_cloud(tmp_path / 'e.ply').same_as(cloud)


def test_simulated_cloud_through_las_laz_and_pcd(tmp_path: Path) -> None:
    pts = np.zeros(50, dtype=simulated_dtype('f4'))
    rng = np.random.default_rng(1)
    for name in pts.dtype.names:
        pts[name] = rng.integers(0, 5, 50)
    pts['x'] = rng.normal(size=50)
    cloud = Cloud(pts, [2683000.0, 1247000.0, 400.0])
    for name in ('a.pcd', 'A.PCD'):
        write_cloud(tmp_path / name, cloud)
        assert read_cloud(tmp_path / name).same_as(cloud)
    for name in ('a.las', 'a.laz', 'A.LAS'):
        write_cloud(tmp_path / name, cloud)
        back = read_cloud(tmp_path / name)
        assert np.all(np.abs(back.xyz - cloud.xyz) <= LAS_SCALE / 2 + 1e-9)
        for field in cloud.fields[3:]:
            assert np.array_equal(back.points[field], cloud.points[field]), field


# --------------------------------------------------------------------------------------
# errors


@pytest.mark.parametrize('reader', [read_cloud, read_ply, read_npz])
@pytest.mark.parametrize('name', ['missing.ply', 'missing.npz'])
def test_missing_file(tmp_path: Path, reader, name: str) -> None:
    assert one_line_error(reader, tmp_path / name).startswith('no such file: ')


def test_directory_is_not_a_file(tmp_path: Path) -> None:
    (tmp_path / 'd.ply').mkdir()
    assert 'not a file' in one_line_error(read_cloud, tmp_path / 'd.ply')


@pytest.mark.parametrize('name', ['c.xyz', 'c', 'c.ply.gz', 'c.txt', 'c.las.gz'])
def test_unknown_suffix(tmp_path: Path, name: str) -> None:
    (tmp_path / name).write_bytes(b'x')
    for message in (one_line_error(read_cloud, tmp_path / name),
                    one_line_error(write_cloud, tmp_path / name, Cloud(xyz_points()))):
        assert 'unsupported file type' in message and '.npz' in message and '.ply' in message
        assert '.las' in message and '.laz' in message and '.pcd' in message


@settings(SETTINGS, max_examples=60)
@given(data=st.data())
def test_damaged_files_raise_only_input_errors(tmp_path: Path, data: st.DataObject) -> None:
    """Random truncation and byte damage: a cloud or an InputError, never anything else."""
    suffix = data.draw(st.sampled_from(['.ply', '.ply-ascii', '.npz', '.npz-z']))
    pts = np.zeros(8, dtype=simulated_dtype('f4'))
    cloud = Cloud(pts, [1.0, 2.0, 3.0])
    path = tmp_path / ('d' + suffix[:4])
    if suffix == '.ply-ascii':
        write_ply(path, cloud, binary=False)
    elif suffix == '.npz-z':
        write_npz(path, cloud, compress=True)
    else:
        write_cloud(path, cloud)
    raw = bytearray(path.read_bytes())
    cut = data.draw(st.integers(0, len(raw)))
    raw = raw[:cut]
    for _ in range(data.draw(st.integers(0, 4))):
        if raw:
            raw[data.draw(st.integers(0, len(raw) - 1))] = data.draw(st.integers(0, 255))
    path.write_bytes(bytes(raw))
    try:
        back = read_cloud(path)
    except InputError as err:
        assert '\n' not in str(err)
    else:
        assert isinstance(back, Cloud)


def test_unwritable_path(tmp_path: Path) -> None:
    cloud = Cloud(xyz_points())
    for name in ('no/such/dir/c.ply', 'no/such/dir/c.npz'):
        assert 'cannot write' in one_line_error(write_cloud, tmp_path / name, cloud)


@settings(SETTINGS, max_examples=60)
@given(data=st.data())
def test_damaged_las_and_pcd_raise_only_input_errors(tmp_path: Path, data: st.DataObject) -> None:
    """Random truncation and byte damage (LAZ: truncation only, see read_las on lazrs)."""
    kind = data.draw(st.sampled_from(['las', 'laz', 'ascii', 'binary', 'binary_compressed']))
    pts = np.zeros(8, dtype=simulated_dtype('f4'))
    pts['x'] = np.arange(8)
    cloud = Cloud(pts, [1.0, 2.0, 3.0])
    path = tmp_path / ('d.' + (kind if kind in ('las', 'laz') else 'pcd'))
    if kind in ('las', 'laz'):
        write_cloud(path, cloud)
    else:
        write_pcd(path, cloud, encoding=kind)
    raw = bytearray(path.read_bytes())
    raw = raw[:data.draw(st.integers(0, len(raw)))]
    if kind != 'laz':
        for _ in range(data.draw(st.integers(0, 4))):
            if raw:
                raw[data.draw(st.integers(0, len(raw) - 1))] = data.draw(st.integers(0, 255))
    path.write_bytes(bytes(raw))
    try:
        back = read_cloud(path)
    except InputError as err:
        assert '\n' not in str(err)
    else:
        assert isinstance(back, Cloud)


@pytest.mark.parametrize('reader', [read_cloud, read_las, read_pcd])
@pytest.mark.parametrize('name', ['missing.las', 'missing.laz', 'missing.pcd'])
def test_missing_las_and_pcd(tmp_path: Path, reader, name: str) -> None:
    assert one_line_error(reader, tmp_path / name) == f'no such file: {tmp_path / name}'


def test_unwritable_las_and_pcd(tmp_path: Path) -> None:
    cloud = Cloud(xyz_points())
    for name in ('no/such/dir/c.las', 'no/such/dir/c.laz', 'no/such/dir/c.pcd'):
        assert 'cannot write' in one_line_error(write_cloud, tmp_path / name, cloud)
