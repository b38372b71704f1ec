"""``build --tiles`` on COPC input (``.copc.laz``, issue 29): a COPC file written by copclib (the
`small` campaign in an octree of depth 4, every field carried: class, building ids, sensor origins,
time, ground truth) builds, with ``--bounds`` cutting both of its buildings, the same tiles bit for
bit as the same points in a plain LAS file; the bounded read decompresses only the octree nodes that
meet the bounds (23 of 159, 18,445 of 34,921 points); without ``--bounds`` the COPC file is read as an
ordinary LAZ file, to the same tiles as the LAS; bounds that meet no node give the one-line error;
bounds reaching past the file's int32 coordinates read the points within them.

The tiled build depends on the order of the points, and laspy's COPC query returns its nodes' points
in file order, so the plain LAS holds the points in the COPC file's order. About 8 s (four in-process
builds of two tiles)."""

from __future__ import annotations

import copy
import hashlib
import json
from pathlib import Path

import copclib
import laspy
import laspy.copc as laspy_copc
import numpy as np
import pytest

from uncertain_facade_map.io.cloud import Cloud
from uncertain_facade_map.io.las import iter_las, read_las, write_las
from uncertain_facade_map.tiling.manifest import read_manifest
from uncertain_facade_map_apps.cli import main

#: Octree depth of the written COPC file: leaves of 8 m for the small scene's 128 m.
DEPTH = 4
#: --bounds, map frame (the scene's building 0 spans x 0..18 m, building 1 x 22..40 m, y 7..15 m;
#: its points x -44..83 m, y -41..37 m): both buildings cut.
BOUNDS_MAP = (10.0, 0.0, 30.0, 20.0)


def _inside(points: np.ndarray, closed: bool = False) -> np.ndarray:
    """(N,) bool: which points lie in BOUNDS_MAP (x, y map frame; half-open as the router, or closed)."""
    x, y = points['x'], points['y']
    if closed:
        return (x >= BOUNDS_MAP[0]) & (x <= BOUNDS_MAP[2]) & (y >= BOUNDS_MAP[1]) & (y <= BOUNDS_MAP[3])
    return (x >= BOUNDS_MAP[0]) & (x < BOUNDS_MAP[2]) & (y >= BOUNDS_MAP[1]) & (y < BOUNDS_MAP[3])


def write_copc(path: Path, cloud: Cloud, folder: Path) -> tuple[np.ndarray, list[tuple[tuple[int, ...], np.ndarray]]]:
    """Write ``cloud`` as a COPC file with copclib: the point records of :func:`write_las` (LAS 1.4
    format 6, scale 0.1 mm, offset = map origin, every other field in extra bytes) in an octree of
    :data:`DEPTH` levels (each level keeps the first point of each of its cells, the leaves the rest),
whose root cube starts at the header's minimum with the longest side of the points' box, so that
the cube of the COPC info (centre and half-size, which laspy reads) and copclib's node boxes (from
the header) agree.

    copclib's Python binding cannot name or type extra-bytes fields (its ``EbVlr(n)`` makes n unnamed
    bytes), so the extra-bytes description is read by copclib from a LAZ file that laspy writes with
    the same header (with the WKT bit, which copclib requires for format 6).

    Returns:
        The cloud's point indices in the file's order, and per node (in file order) its key
        (depth, x, y, z) and its point indices.
    """
    write_las(folder / 'records.las', cloud)
    las = laspy.read(folder / 'records.las')
    header = copy.deepcopy(las.header)
    header.global_encoding.wkt = True
    laspy.LasData(header).write(folder / 'template.laz', laz_backend=laspy.LazBackend.Lazrs)
    extra_bytes = copclib.LazReader(str(folder / 'template.laz')).laz_config.extra_bytes_vlr
    records = las.points.array
    scales, offsets = np.asarray(las.header.scales), np.asarray(las.header.offsets)
    xyz = np.stack([records['X'], records['Y'], records['Z']], 1) * scales + offsets
    low, high = xyz.min(0), xyz.max(0)
    half = (high - low).max() / 2  # the root cube from the header's minimum (copclib's node boxes too)
    centre = low + half
    cells = 2 ** DEPTH
    cell = np.clip(np.floor((xyz - low) / (2 * half) * cells).astype(np.int64), 0, cells - 1)
    level = np.full(len(xyz), DEPTH)
    left = np.arange(len(xyz))
    for depth in range(DEPTH):  # the first point of each cell of this level stays here
        _, first = np.unique(cell[left] >> (DEPTH - depth), axis=0, return_index=True)
        level[left[first]] = depth
        left = np.delete(left, first)

    config = copclib.CopcConfigWriter(6, copclib.Vector3(*scales), copclib.Vector3(*offsets), '', extra_bytes)
    config.las_header.min = copclib.Vector3(*low)
    config.las_header.max = copclib.Vector3(*high)
    config.copc_info.center_x, config.copc_info.center_y, config.copc_info.center_z = centre
    config.copc_info.halfsize = half
    config.copc_info.spacing = 2 * half / cells
    writer = copclib.FileWriter(str(path), config)
    nodes = []
    for depth in range(DEPTH + 1):
        members = np.flatnonzero(level == depth)
        keys, which = np.unique(cell[members] >> (DEPTH - depth), axis=0, return_inverse=True)
        for k, key in enumerate(keys):
            index = members[which.ravel() == k]
            writer.AddNode(copclib.VoxelKey(depth, *map(int, key)),
                           copclib.VectorChar(np.frombuffer(records[index].tobytes(), dtype=np.int8)))
            nodes.append(((depth, *map(int, key)), index))
    writer.Close()
    return np.concatenate([index for _, index in nodes]), nodes


def _hashes(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted((folder / 'tiles').glob('*.npz'))}


def _build(source: Path, out: Path, bounds: str | None) -> dict:
    args = ['build', str(source), '--tiles', str(out), '--side', '20', '--quiet']
    assert main(args + ([] if bounds is None else ['--bounds', bounds])) == 0
    return json.loads((out / 'build.json').read_text())


@pytest.fixture(scope='module')
def campaign(scenes, tmp_path_factory):
    """The COPC file, the plain LAS of the same points in the same order, the points, the nodes."""
    folder = tmp_path_factory.mktemp('copc')
    cloud = scenes.campaign('small', 0)
    order, nodes = write_copc(folder / 'drive.copc.laz', cloud, folder)
    ordered = Cloud(cloud.points[order], cloud.map_origin)
    write_las(folder / 'drive.las', ordered)
    return folder, ordered, nodes


@pytest.fixture(scope='module')
def bounded(campaign):
    """Both files built with --bounds; the octree nodes laspy decompressed for the COPC file."""
    folder, cloud, _ = campaign
    origin = cloud.map_origin
    bounds = ','.join(f'{v + origin[i % 2]:.3f}' for i, v in enumerate(BOUNDS_MAP))
    read_nodes = []
    load = laspy_copc.load_octree_for_query

    def spy(*args, **kwargs):
        found = load(*args, **kwargs)
        read_nodes.extend(((n.key.level, n.key.x, n.key.y, n.key.z), n.point_count) for n in found)
        return found

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(laspy_copc, 'load_octree_for_query', spy)
        report_copc = _build(folder / 'drive.copc.laz', folder / 'copc_bounded', bounds)
    report_las = _build(folder / 'drive.las', folder / 'las_bounded', bounds)
    return report_copc, report_las, read_nodes


def test_the_copc_file_carries_every_field(campaign):
    folder, cloud, nodes = campaign
    copc, las = read_las(folder / 'drive.copc.laz'), read_las(folder / 'drive.las')
    assert len(nodes) > 100 and max(key[0] for key, _ in nodes) == DEPTH
    assert copc.map_origin.tolist() == las.map_origin.tolist() == cloud.map_origin.tolist()
    assert copc.fields == las.fields
    for name in ('class', 'building_id', 'origin_x', 'origin_y', 'origin_z', 'time', 'gt_facade'):
        assert name in copc.fields
    assert copc.points.tobytes() == las.points.tobytes()
    assert copclib.FileReader(str(folder / 'drive.copc.laz')).ValidateSpatialBounds()  # each point in its node
    with laspy_copc.CopcReader.open(str(folder / 'drive.copc.laz')) as reader:
        assert reader.header.point_count == len(cloud)


def test_a_bounded_copc_build_equals_the_las_build(campaign, bounded):
    folder, cloud, _ = campaign
    report_copc, report_las, _ = bounded
    hashes = _hashes(folder / 'copc_bounded')
    assert hashes and hashes == _hashes(folder / 'las_bounded')
    copc, las = read_manifest(folder / 'copc_bounded'), read_manifest(folder / 'las_bounded')
    assert copc.tiles == las.tiles
    assert copc.occupancy == las.occupancy is not None
    assert sorted(copc.building_tiles) == [0, 1]  # both cut by the bounds
    pts = cloud.points
    inside = (pts['class'] == 1) & _inside(pts)
    assert report_copc['building_points'] == report_las['building_points'] == int(inside.sum())
    assert int(inside.sum()) < int((pts['class'] == 1).sum())


def test_a_bounded_copc_build_reads_only_the_nodes_meeting_the_bounds(campaign, bounded):
    folder, cloud, nodes = campaign
    report_copc, report_las, read_nodes = bounded
    with laspy_copc.CopcReader.open(str(folder / 'drive.copc.laz')) as reader:
        info = reader.copc_info
        low, side = info.center - info.halfsize, 2 * info.halfsize
    meets = {}
    for key, index in nodes:  # the node's cube (map frame) against the bounds, in x and y
        size = side / 2 ** key[0]
        x0, y0 = low[0] + key[1] * size - cloud.map_origin[0], low[1] + key[2] * size - cloud.map_origin[1]
        meets[key] = (x0 <= BOUNDS_MAP[2] and x0 + size >= BOUNDS_MAP[0] and
                      y0 <= BOUNDS_MAP[3] and y0 + size >= BOUNDS_MAP[1], len(index))
    read = dict(read_nodes)
    assert len(read) == len(read_nodes)  # each node once
    assert set(read) == {key for key, (meet, _) in meets.items() if meet}
    assert all(read[key] == meets[key][1] for key in read)
    decompressed = sum(read.values())
    assert len(read) < len(nodes) / 4 and decompressed < 0.6 * len(cloud)  # 23 of 159 nodes, 18,445 points
    # Read: the points of those nodes within the bounds (laspy's closed test), the plain LAS whole.
    assert report_copc['input_points'] == int(_inside(cloud.points, closed=True).sum()) < decompressed
    assert report_las['input_points'] == len(cloud)


def test_an_unbounded_copc_build_equals_the_las_build(campaign):
    folder, _, _ = campaign
    report_copc = _build(folder / 'drive.copc.laz', folder / 'copc_whole', None)
    report_las = _build(folder / 'drive.las', folder / 'las_whole', None)
    assert report_copc['input_points'] == report_las['input_points']
    hashes = _hashes(folder / 'copc_whole')
    assert len(hashes) >= 2 and hashes == _hashes(folder / 'las_whole')
    assert read_manifest(folder / 'copc_whole').tiles == read_manifest(folder / 'las_whole').tiles


def test_bounds_that_meet_no_node_of_the_copc_file(campaign, capsys):
    folder, cloud, _ = campaign
    far = ','.join(f'{v + cloud.map_origin[i % 2]:.3f}' for i, v in enumerate((500.0, 500.0, 600.0, 600.0)))
    args = ['build', str(folder / 'drive.copc.laz'), '--tiles', str(folder / 'far'), '--bounds', far, '--quiet']
    assert main(args) == 2
    assert 'no building points in the inputs within --bounds' in capsys.readouterr().err


def test_bounds_past_the_files_integer_range(campaign):
    folder, cloud, _ = campaign
    path = folder / 'drive.copc.laz'
    # 0.1 mm quanta in int32 reach 214 km from the offset: laspy's query alone overflowed, and read nothing.
    parts = list(iter_las(path, bounds=(0.0, 0.0, 1e7, 1e7)))
    assert [len(p) for p in parts] == [len(cloud)]
    assert parts[0].points.tobytes() == read_las(path).points.tobytes()
    parts = list(iter_las(path, bounds=(cloud.map_origin[0], 0.0, 1e7, 1e7)))
    assert len(parts[0]) == int((cloud.points['x'] >= 0).sum())
    assert [len(p) for p in iter_las(path, bounds=(1e9, 1e9, 1e9 + 1, 1e9 + 1))] == [0]  # past it: nothing
