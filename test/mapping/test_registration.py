"""Scan-to-scan disagreement (pose and registration noise) in the map's variance.

Seeded walls with a known rigid offset between scans: the estimate
(:func:`~uncertain_facade_map.mapping.calibration.scan_disagreement`) recovers the mean
square offset along the normal; without an offset it stays near 0; and with it in the
variance, later scans' points fall in the 95 % interval 93-97 % of the time (local and
raster reading). The real AV2 sweeps (two lidars of one car as two scans) are checked when
``../shared`` is there: there the term overshoots with the local reading (0.990).
About 8 s in all (3 s without the real sweeps).
"""

import functools
import importlib.util
import json
import sys
import zipfile

import numpy as np
import pytest
from support import REPO

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.io.map_file import load_map, save_map
from uncertain_facade_map.mapping.calibration import registration_variance, scan_disagreement
from uncertain_facade_map.mapping.engine import view_of
from uncertain_facade_map.mapping.facade_map import FacadeMap, build_map
from uncertain_facade_map.params import MapParams, QueryConfig, UpdateParams
from uncertain_facade_map.pipeline.step7_local_surface import for_query
from uncertain_facade_map.pipeline.step7_queries import query_map, query_points

SENSOR = np.array([8.0, 0.0, 1.8])


def _wall(rng, n, shift=0.0, yaw=0.0, sd=0.01):
    """(n, 3) points of a 20 m x 10 m wall in the plane x = 0 (normal x) with noise ``sd``,
    turned by ``yaw`` (rad) about the vertical through the origin and moved ``shift`` along x."""
    p = np.c_[rng.normal(0.0, sd, n), rng.uniform(-10.0, 10.0, n), rng.uniform(0.0, 10.0, n)]
    c, s = np.cos(yaw), np.sin(yaw)
    return p @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T + [shift, 0.0, 0.0]


def _mean_square_offset(shift, yaw):
    """Mean square offset along x of the moved wall over y in [-10, 10]: (shift - sin(yaw) y)^2."""
    y = np.linspace(-10.0, 10.0, 10_001)
    return float(np.mean((shift - np.sin(yaw) * y) ** 2))


@pytest.mark.parametrize('shift, yaw_deg', [(0.03, 0.0), (0.03, 0.2), (0.10, 0.0)])
def test_offset_between_two_scans_is_recovered(shift, yaw_deg):
    rng = np.random.default_rng(1)
    a, b = _wall(rng, 20_000), _wall(rng, 20_000, shift, np.deg2rad(yaw_deg))
    truth = _mean_square_offset(shift, np.deg2rad(yaw_deg))
    # The second scan against the first's stored points, and both as two scans of one call.
    later = scan_disagreement(b, np.zeros(len(b), np.int64), a, rng=np.random.default_rng(0))
    both = scan_disagreement(np.vstack([a, b]), np.repeat([0, 1], len(a)), np.empty((0, 3)),
                             rng=np.random.default_rng(0))
    for sums in (later, both):
        # Most sampled points count: those whose other-scan neighbours lie around them on a
        # patch (measured 1,751-1,784 of 2,000; 1,900 and more before the tests of spread and
        # of the point lying among them, which the random walls' edges and gaps fail).
        assert sums[0] >= 1700
        # The excess over the local reading's calibrated variance, which covers a little
        # more than the wall's own noise (measured: 2.78-2.84 cm for 3 cm, 3.48-3.50 cm
        # for 3.61 cm, 9.82-9.85 cm for 10 cm).
        assert np.sqrt(registration_variance(sums, 0.3)) == pytest.approx(np.sqrt(truth), rel=0.1)


def test_no_offset_gives_about_zero():
    rng = np.random.default_rng(2)
    a, b = _wall(rng, 20_000), _wall(rng, 20_000)
    var = registration_variance(scan_disagreement(b, np.zeros(len(b), np.int64), a), 0.3)
    assert var < 0.005 ** 2  # below a 5 mm standard deviation (the noise is 1 cm)


def test_no_overlap_and_bounds():
    rng = np.random.default_rng(3)
    a = _wall(rng, 5000)
    far = a + [0.0, 100.0, 0.0]
    assert not scan_disagreement(far, np.zeros(len(far), np.int64), a).any()  # nothing seen twice
    assert not scan_disagreement(a, np.zeros(len(a), np.int64), np.empty((0, 3))).any()  # one scan only
    assert not scan_disagreement(a, np.zeros(len(a), np.int64), a, max_points=0).any()
    assert registration_variance(np.array([50.0, 1.0, 0.0]), 0.3) == 0.0  # too few points compared
    assert registration_variance(np.array([500.0, 500.0, 0.0]), 0.3) == pytest.approx(0.09)  # bounded
    assert registration_variance(np.array([500.0, 0.0, 1.0]), 0.3) == 0.0  # never negative


def test_later_scans_fall_in_the_95_interval():
    """Twenty later scans, each moved by a Gaussian offset (3 cm along the normal, 0.05 degree
    yaw), against a map of a first scan: the map alone covers about 60 % of their points
    (the issue's real drive: 52-63 %); with the learnt variance, 93-97 %, with the local
    reading (the default) and the raster alike."""
    rng = np.random.default_rng(0)
    a = _wall(rng, 8000)
    fmap = build_map(a, np.zeros(len(a), np.int64), np.tile(SENSOR, (len(a), 1)))
    later = [_wall(rng, 2000, rng.normal(0.0, 0.03), np.deg2rad(rng.normal(0.0, 0.05))) for _ in range(20)]
    sums = sum(scan_disagreement(c, np.zeros(len(c), np.int64), fmap.points[0], rng=np.random.default_rng(i))
               for i, c in enumerate(later))
    var = registration_variance(sums, 0.3)
    assert np.sqrt(var) == pytest.approx(0.03, abs=0.005)
    ex = fmap.params.extraction
    for reading in ('local', 'raster'):  # local: 0.575 and 0.944; raster: 0.602 and 0.944
        config = QueryConfig(surface=reading)
        local = for_query(fmap.facades, fmap.points, config)
        coverage = []
        for v in (0.0, var):
            hits = []
            for c in later:
                q = query_map(fmap.facades, fmap.points, c, 0.1, ex.band_back, ex.band_front, fmap.occupancy_, config,
                              local, v)
                ok = q.facade >= 0
                hits.append(np.abs(q.signed_distance[ok]) <= 1.96 * np.sqrt(q.variance[ok] + q.noise_variance[ok]))
            coverage.append(np.mean(np.concatenate(hits)))
        assert coverage[0] < 0.7
        assert 0.93 <= coverage[1] <= 0.97


@functools.cache
def _two_scan_map(defer: bool, params: MapParams | None = None) -> FacadeMap:
    """A wall scanned twice, 4 cm apart along its normal (cached: the tests only read it)."""
    rng = np.random.default_rng(4)
    fmap = FacadeMap(params or MapParams(update=UpdateParams(batch_points=100_000)))
    for shift in (0.0, 0.04):
        x = _wall(rng, 6000, shift)
        fmap.add_points(x, np.zeros(len(x), np.int64), np.tile(SENSOR, (len(x), 1)), defer=defer)
    fmap.flush()
    return fmap


@pytest.mark.parametrize('defer', [False, True])
def test_the_map_learns_it_call_by_call(defer):
    """Each call is a scan, held back (live mapping) or not; the view carries the term."""
    fmap = _two_scan_map(defer)
    assert np.sqrt(fmap.registration_var_) == pytest.approx(0.04, abs=0.006)
    assert view_of(fmap).registration_var == fmap.registration_var_
    off = _two_scan_map(defer, MapParams(update=UpdateParams(registration_points=0)))
    assert off.registration_var_ == 0.0 and not off.registration_sums_.any()


def test_scan_labels_in_one_call():
    rng = np.random.default_rng(5)
    x = np.vstack([_wall(rng, 6000), _wall(rng, 6000, 0.04)])
    scan = np.repeat([7, 9], 6000)
    fmap = build_map(x, np.zeros(len(x), np.int64), np.tile(SENSOR, (len(x), 1)), scan=scan)
    assert np.sqrt(fmap.registration_var_) == pytest.approx(0.04, abs=0.006)
    assert build_map(x, np.zeros(len(x), np.int64)).registration_var_ < 0.01 ** 2  # one scan: no cross term
    with pytest.raises(InputError, match='not with defer'):
        FacadeMap().add_points(x, scan=scan, defer=True)
    with pytest.raises(InputError, match='integer labels'):
        FacadeMap().add_points(x, scan=scan[:10])


def test_query_adds_it_to_answered_points():
    fmap = _two_scan_map(False)
    ex = fmap.params.extraction
    pts = np.array([[0.0, 0.0, 5.0], [0.05, 3.0, 2.0], [50.0, 50.0, 50.0]])
    plain = query_points(fmap.facades, pts, 0.1, ex.band_back, ex.band_front, fmap.occupancy_)
    wider = fmap.query(pts, QueryConfig(surface='raster'), 0.1, event='solid')  # the map's own term
    assert np.allclose(wider.variance[:2], plain.variance[:2] + fmap.registration_var_)
    assert np.isnan(wider.variance[2]) and wider.facade[2] == -1  # unanswered stays so
    assert np.array_equal(wider.signed_distance[:2], plain.signed_distance[:2])


def test_map_file_keeps_it_and_old_files_load_with_zero(tmp_path):
    fmap = _two_scan_map(False)
    back = load_map(save_map(fmap, tmp_path / 'm.npz'))
    assert back.registration_var_ == fmap.registration_var_ > 0
    assert np.array_equal(back.registration_sums_, fmap.registration_sums_)
    # The same file as version 3 wrote it: no registration, nor its parameters.
    path = tmp_path / 'old.npz'
    with np.load(tmp_path / 'm.npz', allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays['meta']))
    meta['version'] = 3
    del meta['registration']
    for name in ('registration_points', 'registration_max_std'):
        del meta['params']['update'][name]
    arrays['meta'] = np.array(json.dumps(meta))
    with open(path, 'wb') as fh:
        np.savez(fh, **arrays)
    assert zipfile.is_zipfile(path)
    old = load_map(path)
    assert old.registration_var_ == 0.0 and not old.registration_sums_.any()
    assert old.params.update.registration_points == 0  # goes on as it was built


def test_pending_scans_survive_a_save(tmp_path):
    rng = np.random.default_rng(6)
    fmap = FacadeMap(MapParams(update=UpdateParams(batch_points=100_000)))
    for shift in (0.0, 0.04):
        x = _wall(rng, 3000, shift)
        fmap.add_points(x, np.zeros(len(x), np.int64), np.tile(SENSOR, (len(x), 1)), defer=True)
    back = load_map(save_map(fmap, tmp_path / 'p.npz'))
    assert [len(p[0]) for p in back.pending] == [3000, 3000]
    fmap.flush()
    back.flush()
    assert back.registration_var_ == fmap.registration_var_ > 0


SHARED = REPO.parent / 'shared'
REAL = SHARED / 'data' / 'real'
CHECKER = SHARED / 'tools' / 'real_check.py'


@pytest.mark.skipif(not (CHECKER.exists() and (REAL / 'av2_7fab_sweep1.ply').exists()),
                    reason='the real sweeps (../shared/data/real) are not here')
def test_real_av2_two_lidars_then_the_next_sweep():
    """AV2 sweep 0's wall points (the checker's wall pick), its up lidar (rings 0-31) and
    down lidar (32-63) as two scans (1.73 cm between them beyond the local reading); sweep
    1's wall points against that map, 95 % coverage with the default (local) reading: 0.936
    without the term, 0.978 with it: ABOVE the 93-97 % aimed at (0.903 and 0.990 before
    issue 39). Sweep 1 repeats both
    lidars (its points' nearest stored points are 57 % of the same lidar), so it does not
    miss the map by the offset between the lidars, which the map's leave-one-out calibration
    on the mixed points already holds in part. The raster reading: 0.943 without, 0.952
    with."""
    from plyfile import PlyData

    spec = importlib.util.spec_from_file_location('real_check', CHECKER)
    rc = importlib.util.module_from_spec(spec)
    sys.modules.setdefault('real_check', rc)
    spec.loader.exec_module(rc)

    def walls(name):
        xyz, origins = rc.read_ply(str(REAL / name))
        ring = np.asarray(PlyData.read(str(REAL / name))['vertex']['ring'])
        wall = np.zeros(len(xyz), bool)
        for _, _, piece, _ in rc.walls(xyz, origins.mean(0), np.random.default_rng(3)):
            wall |= piece
        return xyz[wall], origins[wall], ring[wall]

    xyz, origins, ring = walls('av2_7fab_sweep0.ply')
    later, _, _ = walls('av2_7fab_sweep1.ply')
    fmap = build_map(xyz, None, origins, scan=(ring >= 32).astype(np.int64))
    ex = fmap.params.extraction
    sd = np.sqrt(fmap.registration_var_)
    assert 0.015 <= sd <= 0.025  # 1.73 cm
    local = for_query(fmap.facades, fmap.points, QueryConfig())
    coverage = {}
    for reading in ('local', 'raster'):
        for v in (0.0, fmap.registration_var_):
            q = query_map(fmap.facades, fmap.points, later, 0.1, ex.band_back, ex.band_front, fmap.occupancy_,
                          QueryConfig(surface=reading), local if reading == 'local' else None, v)
            ok = q.facade >= 0
            coverage[reading, v > 0] = np.mean(np.abs(q.signed_distance[ok])
                                               <= 1.96 * np.sqrt(q.variance[ok] + q.noise_variance[ok]))
    # Measured 0.936: the local planes' scatter floored at a quarter of the façade's noise
    # variance (issue 39: float16 coordinates put neighbours exactly on a plane); 0.890 before.
    assert 0.925 <= coverage['local', False] <= 0.95
    # Measured 0.978 (0.990 until issue 39: the points of sweep 1 up to query.local_reach from
    # the stored points are now answered, and cover less): the term still overshoots here.
    assert 0.975 <= coverage['local', True] <= 0.995
    assert 0.93 <= coverage['raster', False] < coverage['raster', True] <= 0.97


def test_dense_scans_are_read_at_the_maps_storage_density():
    """A car lidar's scans are far denser than the map stores them: the other scans are read
    as the map would store them (at most store_per_voxel per store_voxel), and the offset is
    recovered as from scans of about that density (measured: 2.77 cm for 5x denser scans
    thinned to 4 per 0.2 m voxel, 2.82 cm from the sparse scans, 2.63 cm unthinned)."""
    def offset(n, **store):
        rng = np.random.default_rng(4)
        a, b = _wall(rng, n), _wall(rng, n, 0.03)
        sums = scan_disagreement(np.vstack([a, b]), np.repeat([0, 1], n), np.empty((0, 3)),
                                 rng=np.random.default_rng(0), **store)
        assert sums[0] >= 1700  # measured 1,839 thinned (see above)
        return np.sqrt(registration_variance(sums, 0.3))

    thinned = offset(100_000, store_voxel=0.2, store_per_voxel=4)
    assert thinned == pytest.approx(0.03, rel=0.1)
    assert thinned == pytest.approx(offset(20_000), rel=0.05)
