"""Map products against synthetic scenes with known truth.

Scene ``corner``: one building, built end to end by ``build_map`` from noisy points (2 cm
along the normal): wall A on the plane y = 10.03 facing -y (x 0..8, z 0..6) with a block
0.5 m out (a balcony front at y = 9.53, x 3..5, z 3..4.5), and wall B on x = 8.02 facing
+x (y 10.03..16), meeting A at a corner. Scene ``tilted``: one hand-made façade whose
normal is off every map axis and off the horizontal (also: exactly along -y, and at 45
degrees between x and y), with a 0.3 m step, to check the voxel enumeration against brute
force in general and in special positions.
"""

from dataclasses import replace

import numpy as np
import pytest

import uncertain_facade_map.mapping.products as products
from uncertain_facade_map.datatypes import ExtractedFacade, FacadeFrame
from uncertain_facade_map.errors import InputError
from uncertain_facade_map.mapping.facade_map import build_map
from uncertain_facade_map.mapping.products import height_band_grid, surface_grid, surface_mesh, voxel_occupancy
from uncertain_facade_map.params import MapParams
from uncertain_facade_map.pipeline.step6_surface import fit_facade
from uncertain_facade_map.pipeline.step7_queries import query_points, surface_at

WALL_Y, SIDE_X = 10.03, 8.02
BLOCK = dict(x0=3.0, x1=5.0, z0=3.0, z1=4.5, out=0.5)
BAND = (1.0, 2.0)  # band_back, band_front: the ExtractionParams defaults


def _corner_points(rng):
    """Noisy points of walls A and B and the block front, with sensor origins."""
    density = 600  # points per m^2
    # Wall A without the part the block hides, and the block's front.
    xa = rng.uniform(0, SIDE_X, 8 * 6 * density)
    za = rng.uniform(0, 6, len(xa))
    hidden = (xa > BLOCK['x0']) & (xa < BLOCK['x1']) & (za > BLOCK['z0']) & (za < BLOCK['z1'])
    ya = np.where(hidden, WALL_Y - BLOCK['out'], WALL_Y)
    a = np.c_[xa, ya + rng.normal(0, 0.02, len(xa)), za]
    oa = np.c_[xa, np.full(len(xa), 4.0), np.full(len(xa), 2.5)]
    yb = rng.uniform(WALL_Y, 16.0, 6 * 6 * density)
    zb = rng.uniform(0, 6, len(yb))
    b = np.c_[SIDE_X + rng.normal(0, 0.02, len(yb)), yb, zb]
    ob = np.c_[np.full(len(yb), 13.0), yb, np.full(len(yb), 2.5)]
    return np.vstack([a, b]), np.vstack([oa, ob])


@pytest.fixture(scope='module')
def corner():
    xyz, origins = _corner_points(np.random.default_rng(1))
    fmap = build_map(xyz, np.zeros(len(xyz), np.int64), origins, MapParams())
    assert len(fmap.facades) == 2
    wall = next(f for f in fmap.facades if f.frame.normal[1] < -0.99)
    side = next(f for f in fmap.facades if f.frame.normal[0] > 0.99)
    return fmap.facades, wall, side


@pytest.fixture(scope='module', params=[(0.35, -0.8, 0.3), (0.0, -1.0, 0.0), (1.0, -1.0, 0.0)],
                ids=['oblique', 'axis-aligned', 'diagonal'])
def tilted(request):
    rng = np.random.default_rng(2)
    uv = rng.uniform(0, 4, (12000, 2))
    truth = np.where(uv[:, 0] > 2.0, 0.3, 0.0)
    d = truth + rng.normal(0, 0.02, len(uv))
    frame = FacadeFrame.from_normal(np.array([3.1, -2.2, 0.4]), np.array(request.param))
    extracted = ExtractedFacade(frame, np.arange(len(uv)), np.c_[uv, d], np.ones(len(uv)), (0, 4, 0, 4))
    return [fit_facade(extracted, MapParams(), rng)]


def _away_from_details(xyz, pad=0.3):
    """Wall A points clear of the block, the corner and the wall's edges."""
    x, z = xyz[:, 0], xyz[:, 2]
    block = ((x > BLOCK['x0'] - pad) & (x < BLOCK['x1'] + pad) & (z > BLOCK['z0'] - pad) & (z < BLOCK['z1'] + pad))
    return (x > pad) & (x < SIDE_X - pad) & (z > pad) & (z < 6 - pad) & ~block


# --------------------------------------------------------------------------- surface grid


def test_surface_grid_lies_on_the_true_plane(corner):
    facades, wall, _ = corner
    grid = surface_grid(facades)
    on_a = (grid.facade == wall.facade_id)
    clear = on_a & _away_from_details(grid.xyz)
    err = grid.xyz[clear, 1] - WALL_Y
    assert clear.sum() > 3000
    assert np.sqrt(np.mean(err**2)) < 0.015 and np.abs(err).max() < 0.05, (np.sqrt(np.mean(err**2)), np.abs(err).max())
    x, z = grid.xyz[:, 0], grid.xyz[:, 2]
    front = on_a & (x > BLOCK['x0'] + 0.3) & (x < BLOCK['x1'] - 0.3) & (z > BLOCK['z0'] + 0.3) & (z < BLOCK['z1'] - 0.3)
    assert front.sum() > 50
    np.testing.assert_allclose(grid.xyz[front, 1], WALL_Y - BLOCK['out'], atol=0.05)
    # One point per facet cell, with the raster's own standard deviation, in raster order.
    for f in facades:
        mine = grid.facade == f.facade_id
        on = f.surface.facet >= 0
        assert mine.sum() == on.sum()
        np.testing.assert_array_equal(grid.std[mine], np.sqrt(f.surface.var[on]))
        np.testing.assert_array_equal(grid.facet[mine], f.surface.facet[on])
        local = f.frame.to_local(grid.xyz[mine])
        np.testing.assert_allclose(local[:, :2], f.surface.centres()[on.ravel()], atol=1e-9)
        np.testing.assert_allclose(local[:, 2], f.surface.mean[on], atol=1e-9)
    assert grid.xyz.dtype == np.float64 and grid.facade.dtype == np.int32 and grid.std.shape == (len(grid),)


def test_surface_grid_steps(corner):
    facades, wall, _ = corner
    fine = surface_grid(facades, 0.1)
    coarse = surface_grid(facades, 0.2)  # a multiple of the cell: every other cell centre
    assert 0.2 < len(coarse) / len(fine) < 0.3
    assert {tuple(p) for p in coarse.xyz} <= {tuple(p) for p in fine.xyz}
    odd = surface_grid(facades, 0.15)  # between cell centres: interpolated
    assert 0.3 < len(odd) / len(fine) < 0.6
    clear = (odd.facade == wall.facade_id) & _away_from_details(odd.xyz)
    assert np.abs(odd.xyz[clear, 1] - WALL_Y).max() < 0.05
    for f in facades:
        mine = odd.facade == f.facade_id
        local = f.frame.to_local(odd.xyz[mine])
        # (u, v) back from the map frame differ by rounding, which moves a bilinear blend a
        # little; a node exactly halfway between cells across a facet edge may fall to
        # either cell, so it must match surface_at on one side or the other.
        err_mean = np.full(len(local), np.inf)
        err_std = np.full(len(local), np.inf)
        for du, dv in ((0, 0), (1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (-1, -1), (1, -1), (-1, 1)):
            mean, var = surface_at(f.surface, local[:, :2] + 1e-7 * np.array([du, dv]))
            err_mean = np.minimum(err_mean, np.abs(local[:, 2] - mean))
            err_std = np.minimum(err_std, np.abs(odd.std[mine] - np.sqrt(var)))
        assert err_mean.max() < 1e-6 and err_std.max() < 1e-6
    for bad in (0.0, -0.1, np.nan, np.inf):
        with pytest.raises(InputError, match='step'):
            surface_grid(facades, bad)
    with pytest.raises(InputError, match='max_points'):
        surface_grid(facades, 0.01, max_points=10_000)
    empty = surface_grid([], 0.1)
    assert empty.xyz.shape == (0, 3) and empty.std.shape == (0,)


# --------------------------------------------------------------------------- mesh


@pytest.mark.parametrize('step', [None, 0.2])
def test_mesh_faces_outwards_and_keeps_steps_open(corner, step):
    facades, wall, _ = corner
    mesh = surface_mesh(facades, step)
    grid = surface_grid(facades, step)
    tri = mesh.triangles
    assert tri.dtype == np.int32 and tri.min() >= 0 and tri.max() < len(mesh.vertices)
    assert len(tri) > 1.5 * len(mesh.vertices) * 0.9
    # Every vertex is a grid node (the same numbers), and every vertex is used.
    assert {tuple(p) for p in mesh.vertices} <= {tuple(p) for p in grid.xyz}
    assert np.array_equal(np.unique(tri), np.arange(len(mesh.vertices)))
    # A triangle's three vertices share façade and facet: no triangle spans two facets.
    for attr in (mesh.facade, mesh.facet):
        assert np.all(attr[tri[:, 0]] == attr[tri[:, 1]]) and np.all(attr[tri[:, 0]] == attr[tri[:, 2]])
    assert len(np.unique(mesh.facet[mesh.facade == wall.facade_id])) >= 2  # wall and block front
    # Right-hand normals point outwards, along the façade normal.
    a, b, c = (mesh.vertices[tri[:, k]] for k in range(3))
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    outward = np.stack([f.frame.normal for f in facades])[mesh.facade[tri[:, 0]]]
    cos = np.sum(n * outward, axis=1)
    assert cos.min() > 0, cos.min()
    assert np.median(cos) > 0.99
    # No long sloped triangles across the 0.5 m depth step of the block.
    s = step or 0.1
    edges = np.linalg.norm(np.concatenate([b - a, c - b, a - c]), axis=1)
    assert edges.max() < s * np.sqrt(2) + 0.15, edges.max()
    assert mesh.triangle_points().shape == (3 * len(tri), 3)
    node_std = {tuple(p): v for p, v in zip(grid.xyz, grid.std)}
    np.testing.assert_array_equal(mesh.std, [node_std[tuple(p)] for p in mesh.vertices])


def test_mesh_of_a_left_handed_frame_still_faces_outwards(corner):
    _, wall, _ = corner
    e_u, e_v, n = wall.frame.axes
    mirrored = replace(wall, frame=FacadeFrame(wall.frame.origin, np.stack([-e_u, e_v, n])))
    mesh = surface_mesh([mirrored])
    a, b, c = (mesh.vertices[mesh.triangles[:, k]] for k in range(3))
    assert len(a) > 1000 and np.all(np.cross(b - a, c - a) @ n > 0)


# --------------------------------------------------------------------------- voxels


def _brute_shell(facades, resolution, shell, band=BAND):
    """Every voxel of the bounding box tested against the definition, then the query's verdict."""
    boxes = []
    for f in facades:
        r = f.surface
        h, w = r.mean.shape
        on = r.facet >= 0
        d = (r.mean[on].min() - shell, r.mean[on].max() + shell)
        boxes.append(f.frame.to_world(np.array([[u, v, dd] for u in (r.origin[0], r.origin[0] + w * r.cell)
                                                 for v in (r.origin[1], r.origin[1] + h * r.cell) for dd in d])))
    boxes = np.vstack(boxes)
    lo = np.floor(boxes.min(axis=0) / resolution).astype(int) - 1
    hi = np.ceil(boxes.max(axis=0) / resolution).astype(int) + 1
    idx = np.stack(np.meshgrid(*[np.arange(a, b) for a, b in zip(lo, hi)], indexing='ij'), -1).reshape(-1, 3)
    centres = (idx + 0.5) * resolution
    keep = np.zeros(len(idx), bool)
    per_facade = []
    for f in facades:
        r = f.surface
        h, w = r.mean.shape
        local = f.frame.to_local(centres)
        col = np.floor((local[:, 0] - r.origin[0]) / r.cell).astype(int)
        row = np.floor((local[:, 1] - r.origin[1]) / r.cell).astype(int)
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        ok = np.zeros(len(idx), bool)
        ok[inside] = r.facet[row[inside], col[inside]] >= 0
        mean, _ = surface_at(r, local[ok, :2])
        ok[ok] = np.abs(local[ok, 2] - mean) <= shell
        per_facade.append(ok)
        keep |= ok
    res = query_points(facades, centres[keep], resolution, *band)
    known = res.facade >= 0
    return idx[keep][known], [set(map(tuple, idx[ok])) for ok in per_facade]


def test_voxels_match_the_definition_and_the_query(corner):
    facades, _, _ = corner
    vox = voxel_occupancy(facades, 0.2, 0.3)
    truth, per_facade = _brute_shell(facades, 0.2, 0.3)
    assert len(vox) > 1000
    assert set(map(tuple, vox.index)) == set(map(tuple, truth))
    assert len(np.unique(vox.index, axis=0)) == len(vox), 'a voxel is listed twice'
    # Voxels near the corner are in both façades' shells, and listed once.
    assert len(per_facade[0] & per_facade[1]) > 10
    np.testing.assert_array_equal(vox.centres, (vox.index + 0.5) * 0.2)
    res = query_points(facades, vox.centres, 0.2, *BAND)
    np.testing.assert_array_equal(vox.p_occupied, res.p_occupied)
    np.testing.assert_array_equal(vox.facade, res.facade)


@pytest.mark.parametrize('resolution, shell', [(0.1, 0.3), (0.07, 0.1), (0.25, 0.4), (0.05, 0.02)])
def test_voxels_of_a_tilted_facade_match_brute_force(tilted, resolution, shell):
    vox = voxel_occupancy(tilted, resolution, shell)
    truth, _ = _brute_shell(tilted, resolution, shell)
    assert len(truth) > 100
    assert set(map(tuple, vox.index)) == set(map(tuple, truth))
    assert len(vox) == len(truth)


def test_voxel_probabilities_against_the_true_wall(corner):
    facades, wall, _ = corner
    vox = voxel_occupancy(facades, 0.1, 0.3)
    np.testing.assert_array_equal(vox.p_occupied, query_points(facades, vox.centres, 0.1, *BAND).p_occupied)
    assert len(np.unique(vox.index, axis=0)) == len(vox)
    c = vox.centres
    clear = _away_from_details(c) & (c[:, 0] < SIDE_X - 1.0) & (np.abs(c[:, 1] - WALL_Y) < 0.5)
    s = WALL_Y - c[:, 1]  # true signed distance, positive outside (towards -y)
    behind = clear & (s < -0.1)
    front = clear & (s > 0.2)
    assert behind.sum() > 1000 and front.sum() > 1000
    assert vox.p_occupied[behind].min() > 0.9, vox.p_occupied[behind].min()
    assert vox.p_occupied[front].max() < 0.1, vox.p_occupied[front].max()
    # The shell: voxels reach about 0.3 m either side of the wall, no further.
    assert s[clear].min() > -0.36 and s[clear].max() < 0.36
    assert s[clear].min() < -0.25 and s[clear].max() > 0.25


def test_voxel_batches_change_nothing(corner, monkeypatch):
    facades, _, _ = corner
    whole = voxel_occupancy(facades, 0.1, 0.3)
    monkeypatch.setattr(products, '_BATCH', 997)
    batched = voxel_occupancy(facades, 0.1, 0.3)
    np.testing.assert_array_equal(batched.index, whole.index)
    np.testing.assert_array_equal(batched.p_occupied, whole.p_occupied)
    np.testing.assert_array_equal(batched.facade, whole.facade)


def test_voxel_limits_and_bad_input(corner):
    facades, _, _ = corner
    n = len(voxel_occupancy(facades, 0.2, 0.3))
    with pytest.raises(InputError, match=r'max_voxels.*coarsen the resolution 0.2 m by a factor of') as err:
        voxel_occupancy(facades, 0.2, 0.3, max_voxels=n - 1)
    assert f'{n:,}' in str(err.value)
    with pytest.raises(InputError, match='estimated.*max_voxels'):
        voxel_occupancy(facades, 0.01, 0.3)
    assert len(voxel_occupancy(facades, 0.2, 0.3, max_voxels=n)) == n
    for kwargs in ({'resolution': 0.0}, {'resolution': np.nan}, {'shell': -0.1}, {'band_back': -1.0}):
        with pytest.raises(InputError):
            voxel_occupancy(facades, **{'resolution': 0.2, 'shell': 0.3, **kwargs})
    empty = voxel_occupancy([], 0.1, 0.3)
    assert empty.centres.shape == (0, 3) and empty.p_occupied.shape == (0,)


# --------------------------------------------------------------------------- 2D grid


def test_height_band_grid(corner):
    facades, _, _ = corner
    r, margin = 0.1, 1.0
    grid = height_band_grid(facades, r, 0.5, 2.0, margin=margin)
    h, w = grid.p.shape
    with pytest.MonkeyPatch.context() as patch:  # batches of columns change nothing
        patch.setattr(products, '_BATCH', 997)
        np.testing.assert_array_equal(height_band_grid(facades, r, 0.5, 2.0, margin=margin).p, grid.p)
    # Origin on the voxel lattice; the grid covers every façade's query box plus the margin.
    np.testing.assert_allclose(grid.origin / r, np.round(grid.origin / r), atol=1e-9)
    x, y = grid.cell_centres()
    assert x.shape == (w,) and y.shape == (h,)
    np.testing.assert_allclose(np.diff(x), r) and np.testing.assert_allclose(x[0], grid.origin[0] + r / 2)
    assert grid.origin[0] <= -1.0 - margin + 0.01  # wall A's raster starts 1 m before its first point
    assert grid.origin[1] <= WALL_Y - BAND[1] - margin + 1e-9
    assert grid.origin[0] + w * r >= SIDE_X + BAND[1] + margin - 1e-9
    assert grid.origin[1] + h * r >= 16.0 + margin - 1e-9
    known = np.isfinite(grid.p)
    assert np.all((grid.p[known] >= 0) & (grid.p[known] <= 1))
    assert not known[0].any() and not known[-1].any() and not known[:, 0].any() and not known[:, -1].any()
    # The row holding the wall line is occupied, the rows in front free, behind occupied.
    cols = (x > 0.5) & (x < SIDE_X - 0.5)
    wall_row = int(np.floor(WALL_Y / r)) - int(round(grid.origin[1] / r))
    assert y[wall_row] - r / 2 <= WALL_Y < y[wall_row] + r / 2
    assert grid.p[wall_row, cols].min() > 0.5, grid.p[wall_row, cols].min()
    # (Clear of the last metre before the corner: see test_height_band_grid_air_at_the_corner.)
    clear = cols & (x < SIDE_X - 1.2)
    front = (y > WALL_Y - 1.9) & (y < WALL_Y - 0.15)
    assert grid.p[np.ix_(front, clear)].max() < 0.1
    behind = (y > WALL_Y + 0.1) & (y < WALL_Y + 0.9)
    assert grid.p[np.ix_(behind, clear)].min() > 0.9
    # Far from any façade (over 2 m in front of wall A, away from wall B): unknown.
    far = y < WALL_Y - 2.1
    assert np.isnan(grid.p[np.ix_(far, (x > 0.5) & (x < 6.0))]).all()
    # A cell is the largest known query probability over the band's voxel layers.
    rng = np.random.default_rng(3)
    rows, cols_ = np.nonzero(known)
    pick = rng.choice(len(rows), 40, replace=False)
    layers = (np.arange(5, 20) + 0.5) * r
    for i, j in zip(rows[pick], cols_[pick]):
        res = query_points(facades, np.c_[np.full(15, x[j]), np.full(15, y[i]), layers], r, *BAND)
        assert grid.p[i, j] == res.p_occupied[res.facade >= 0].max()
    values = grid.occupancy_values()
    assert values.dtype == np.int8 and values.shape == (h * w,)
    assert np.all(values[~known.ravel()] == -1)
    assert values.reshape(h, w)[wall_row, cols].min() > 50


def test_height_band_grid_bad_input(corner):
    facades, _, _ = corner
    with pytest.raises(InputError, match='z_min < z_max'):
        height_band_grid(facades, 0.1, 2.0, 2.0)
    with pytest.raises(InputError, match='resolution'):
        height_band_grid(facades, 0.0, 0.5, 2.0)
    with pytest.raises(InputError, match='max_cells.*coarsen'):
        height_band_grid(facades, 0.1, 0.5, 2.0, max_cells=1000)
    with pytest.raises(InputError, match='max_samples.*coarsen'):
        height_band_grid(facades, 0.1, 0.5, 2.0, max_samples=1000)
    empty = height_band_grid([], 0.1, 0.5, 2.0)
    assert empty.p.shape == (0, 0)


def test_height_band_grid_coarsens_to_its_limits(corner):
    """With coarsen, a grid over either limit is the one at the first doubled resolution
    within both; coarsen cannot reach a limit no grid meets."""
    facades, _, _ = corner
    for limits in ({'max_cells': 1000}, {'max_samples': 1000}):
        grid = height_band_grid(facades, 0.1, 0.5, 2.0, coarsen=True, **limits)
        assert grid.resolution > 0.1 and np.log2(grid.resolution / 0.1) % 1 == 0
        np.testing.assert_array_equal(grid.p, height_band_grid(facades, grid.resolution, 0.5, 2.0, **limits).p)
        with pytest.raises(InputError):
            height_band_grid(facades, grid.resolution / 2, 0.5, 2.0, **limits)
    with pytest.raises(InputError, match='max_cells'):
        height_band_grid(facades, 0.1, 0.5, 2.0, max_cells=1, coarsen=True)


def test_height_band_grid_air_at_the_corner(corner):
    facades, _, _ = corner
    grid = height_band_grid(facades, 0.1, 0.5, 2.0)
    x, y = grid.cell_centres()
    # Air in the corner, more than a voxel from either wall (the cells touching wall B hold its surface).
    air = np.ix_((y > WALL_Y - 0.9) & (y < WALL_Y - 0.15), (x > SIDE_X - 0.9) & (x < SIDE_X - 0.2))
    assert np.nanmax(grid.p[air]) < 0.1
