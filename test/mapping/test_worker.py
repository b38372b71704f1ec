"""The map worker: clouds in order, the drop policy, commands, idle flush, errors."""

import threading
import time

import numpy as np
import pytest

from uncertain_facade_map.mapping.facade_map import FacadeMap
from uncertain_facade_map.mapping.worker import Cloud, MapWorker, ReplaceMap
from uncertain_facade_map.params import MapParams, UpdateParams


def wall(n=400, seed=0, u0=0.0):
    rng = np.random.default_rng(seed)
    return np.c_[u0 + rng.uniform(0, 5, n), np.full(n, 10.0) + rng.normal(0, 0.02, n), rng.uniform(0, 5, n)]


def test_drop_policy_drops_the_oldest_waiting_cloud():
    gate = threading.Event()
    worker = MapWorker(FacadeMap(), queue_size=2, idle_flush=0)
    started = threading.Event()
    # Block the worker with a command so clouds pile up.
    threading.Thread(target=lambda: worker.call(lambda m: (started.set(), gate.wait(10)), changes=False)).start()
    assert started.wait(5)
    clouds = [Cloud(wall(10, seed=i), None, None, i) for i in range(4)]
    kept = [worker.put(c) for c in clouds]
    assert kept == [True, True, False, False]
    assert worker.counters['clouds_dropped'] == 2 and worker.counters['points_dropped'] == 20
    assert worker.queued == 2
    waiting = [item.stamp_ns for item in worker._queue if isinstance(item, Cloud)]
    assert waiting == [2, 3]  # the newest are kept
    gate.set()
    assert worker.wait_idle(30)
    worker.stop()


def test_the_queue_is_bounded_by_points_too():
    """Small clouds wait through an update while their points fit in queue_points; a cloud
    that would pass it drops the oldest ones until it fits (a cloud larger than the bound
    alone still waits)."""
    gate = threading.Event()
    worker = MapWorker(FacadeMap(), queue_size=1000, idle_flush=0, queue_points=25)
    started = threading.Event()
    threading.Thread(target=lambda: worker.call(lambda m: (started.set(), gate.wait(10)), changes=False)).start()
    assert started.wait(5)
    sizes = [10, 10, 5, 12, 40]
    kept = [worker.put(Cloud(wall(n, seed=i), None, None, i)) for i, n in enumerate(sizes)]
    # 10 + 10 + 5 = 25 fit; 12 drops the oldest (10); 40 alone exceeds 25: all others dropped.
    assert kept == [True, True, True, False, False]
    assert worker.counters['clouds_dropped'] == 4 and worker.counters['points_dropped'] == 10 + 10 + 5 + 12
    assert [item.stamp_ns for item in worker._queue if isinstance(item, Cloud)] == [4]
    gate.set()
    assert worker.wait_idle(30)
    assert worker.counters['clouds_mapped'] + worker.counters['clouds_failed'] == 1
    worker.stop()
    with pytest.raises(ValueError, match='queue_points'):
        MapWorker(FacadeMap(), queue_points=0)


def test_clouds_are_mapped_in_order_and_flushed_when_idle():
    params = MapParams(update=UpdateParams(batch_points=1000))
    worker = MapWorker(FacadeMap(params), queue_size=100, idle_flush=0.3)
    offline = FacadeMap(params)
    for i in range(6):
        xyz = wall(400, seed=i, u0=i * 2.0)
        worker.put(Cloud(xyz, np.zeros(400, np.int64), None, i))
        offline.add_points(xyz, np.zeros(400, np.int64), defer=True)
    deadline = time.monotonic() + 60
    while not worker.settled:
        assert time.monotonic() < deadline
        time.sleep(0.05)
    offline.flush()
    snap = worker.snapshot
    assert snap.points == offline.n_points == 2400 and len(snap.facades) == len(offline.facades) >= 1
    for a, b in zip(snap.facades, offline.facades):
        np.testing.assert_array_equal(a.surface.mean, b.surface.mean)
        np.testing.assert_array_equal(a.surface.var, b.surface.var)
    assert worker.counters['clouds_mapped'] == 6
    worker.stop()


def test_a_bad_cloud_is_reported_and_the_map_kept():
    errors = []
    worker = MapWorker(FacadeMap(), idle_flush=0, on_error=lambda c, e: errors.append(str(e)))
    worker.put(Cloud(np.full((5, 3), np.nan)))
    worker.put(Cloud(wall(50)))
    assert worker.wait_idle(30)
    assert len(errors) == 1 and 'NaN' in errors[0]
    assert worker.counters['clouds_failed'] == 1 and worker.counters['clouds_mapped'] == 1
    worker.stop()


def test_commands_run_after_queued_clouds_and_may_replace_the_map():
    worker = MapWorker(FacadeMap(), idle_flush=0)
    worker.put(Cloud(wall(50)))
    assert worker.call(lambda m: m.n_points + m.n_pending, changes=False) == 50
    version = worker.snapshot.version
    worker.call(lambda m: ReplaceMap(FacadeMap(), 'x'))
    assert worker.snapshot.points == 0 and worker.snapshot.version == version + 1
    with pytest.raises(ZeroDivisionError):
        worker.call(lambda m: 1 / 0)
    worker.stop()
    with pytest.raises(RuntimeError):
        worker.call(lambda m: None)


def test_snapshots_are_read_only():
    """The node's query callbacks read the worker's snapshots while it maps: a write into one
    of their arrays raises instead of changing the map under a reader."""
    worker = MapWorker(FacadeMap(MapParams(update=UpdateParams(batch_points=1000))), queue_size=10, idle_flush=0)
    worker.put(Cloud(wall(3000), None, None, 1))
    assert worker.wait_idle(60)
    snap = worker.snapshot
    worker.stop()
    assert snap.facades
    f = snap.facades[0]
    arrays = {'map_origin': snap.map_origin, 'surface.mean': f.surface.mean, 'surface.var': f.surface.var,
              'surface.facet': f.surface.facet, 'surface.source': f.surface.source, 'surface.origin': f.surface.origin,
              'facets.facet': f.facets.facet, 'layers.means_': f.layers.means_, 'frame.axes': f.frame.axes,
              'lengthscale2_': f.lengthscale2_, 'point_index': f.point_index, 'anchor': f.anchor}
    for name, array in arrays.items():
        with pytest.raises(ValueError, match='read-only'):
            array.flat[0] = array.flat[0]
        assert not array.flags.writeable, name


def test_map_scans_selects_in_scans_without_classes():
    """Replay (and the node, which calls the same select_scan_points) maps the selected points
    of scans without a class field, and all of them without a selection."""
    from support import unclassified_street

    from uncertain_facade_map.io.scans import select_scan_points
    from uncertain_facade_map.mapping.worker import map_scans
    from uncertain_facade_map.params import InputConfig, SelectionConfig

    xyz, _, _ = unclassified_street(seed=2)
    scan = np.zeros(len(xyz), dtype=[('x', 'f4'), ('y', 'f4'), ('z', 'f4')])
    scan['x'], scan['y'], scan['z'] = xyz.T
    selected = len(select_scan_points(scan, InputConfig(), SelectionConfig()).xyz)
    fmap = FacadeMap()
    summary = map_scans(fmap, [scan], InputConfig(), selection=SelectionConfig())
    assert summary.points == len(xyz) and summary.building_points == selected < 0.45 * len(xyz)
    assert summary.facades == 3


def test_an_update_that_fails_half_way_leaves_the_map_as_it_was(monkeypatch):
    """A linear-algebra failure inside the update of a building, after the points were
    stored: the map goes back to what it was, the cloud counts as failed, and the next
    clouds build the same map as if the bad one had never come."""
    from uncertain_facade_map.mapping import facade_map as fm

    params = MapParams(update=UpdateParams(batch_points=1))
    errors = []
    worker = MapWorker(FacadeMap(params), idle_flush=0, on_error=lambda c, e: errors.append(e))
    offline = FacadeMap(params)
    first = wall(400, seed=1)
    worker.put(Cloud(first, np.zeros(400, np.int64)))
    offline.add_points(first, np.zeros(400, np.int64), defer=True)
    assert worker.wait_idle(30)
    before = worker.snapshot

    real = fm.FacadeMap._update_building

    def broken(self, b, first_index, *rest):
        real(self, b, first_index, *rest)
        raise np.linalg.LinAlgError('Matrix is not positive definite')

    monkeypatch.setattr(fm.FacadeMap, '_update_building', broken)
    worker.put(Cloud(wall(300, seed=2, u0=3.0), np.zeros(300, np.int64)))
    assert worker.wait_idle(30)
    monkeypatch.setattr(fm.FacadeMap, '_update_building', real)
    assert len(errors) == 1 and isinstance(errors[0], np.linalg.LinAlgError)
    accounts = worker.accounts()
    assert accounts['clouds_failed'] == 1 and accounts['points_failed'] == 300
    assert worker.snapshot.version == before.version
    fmap, version, waiting = worker.committed()
    assert fmap.n_points == offline.n_points == 400 and version == before.version and waiting == 0

    last = wall(400, seed=3, u0=1.0)
    worker.put(Cloud(last, np.zeros(400, np.int64)))
    offline.add_points(last, np.zeros(400, np.int64), defer=True)
    assert worker.wait_idle(30)
    snap = worker.snapshot
    assert snap.points == offline.n_points == 800 and len(snap.facades) == len(offline.facades)
    for a, b in zip(snap.facades, offline.facades):
        np.testing.assert_array_equal(a.surface.mean, b.surface.mean)
    worker.stop()


def test_accounts_add_up_at_any_moment_and_latency_is_measured():
    """Clouds in = mapped + dropped + failed + waiting (and points alike), read while the
    worker is blocked, after drops, failures and held-back clouds; a held-back cloud gets
    its latency when the batch update maps it."""
    params = MapParams(update=UpdateParams(batch_points=600))
    worker = MapWorker(FacadeMap(params), queue_size=3, idle_flush=0)
    gate, started = threading.Event(), threading.Event()
    threading.Thread(target=lambda: worker.call(lambda m: (started.set(), gate.wait(10)), changes=False)).start()
    assert started.wait(5)

    def balanced():
        a = worker.accounts()
        for kind in ('clouds', 'points'):
            assert a[f'{kind}_in'] == sum(a[f'{kind}_{k}'] for k in ('mapped', 'dropped', 'failed', 'waiting')), a
        return a

    sizes = [200, 50, 300, 250, 400]
    for i, n in enumerate(sizes):
        worker.put(Cloud(wall(n, seed=i, u0=i), np.zeros(n, np.int64)))
    worker.put(Cloud(np.full((7, 3), np.nan)))
    a = balanced()
    assert a['clouds_waiting'] == 3 and a['clouds_dropped'] == 3 and a['points_in'] == sum(sizes) + 7
    gate.set()
    assert worker.wait_idle(30)
    a = balanced()
    assert a['clouds_failed'] == 1 and a['points_failed'] == 7 and a['clouds_mapped'] == 2
    assert a['points_mapped'] == 650 and a['points_pending'] == 0  # 250 + 400 >= 600: one update
    assert len(worker.latencies) == 2 and all(t >= 0 for t in worker.latencies)
    worker.stop()


def test_a_failed_idle_flush_is_reported_and_the_map_kept(monkeypatch):
    """Nobody waits for the idle flush: its failure goes to on_flush_error and is counted;
    the map keeps the points held back, as before the flush."""
    from uncertain_facade_map.mapping import facade_map as fm

    def broken(self, consolidate=True):
        self.pending = []
        raise np.linalg.LinAlgError('Matrix is not positive definite')

    monkeypatch.setattr(fm.FacadeMap, 'flush', broken)
    errors = []
    params = MapParams(update=UpdateParams(batch_points=10_000))
    worker = MapWorker(FacadeMap(params), idle_flush=0.2, on_flush_error=errors.append)
    worker.put(Cloud(wall(300), np.zeros(300, np.int64)))
    deadline = time.monotonic() + 30
    while not errors:
        assert time.monotonic() < deadline, 'the idle flush never ran'
        time.sleep(0.05)
    assert isinstance(errors[0], np.linalg.LinAlgError)
    assert worker.counters['flushes_failed'] >= 1
    assert worker.committed()[0].n_pending == 300 and worker.snapshot.points == 0
    worker.stop()


def test_latency_batching_maps_a_lone_cloud_at_once_and_fixed_batching_holds_it_back():
    """node.batching (issue 37): with 'latency' a cloud that nothing waits behind is mapped
    in its own update (queryable at once), with 'fixed' its points wait for
    update.batch_points; both maps hold the same points once flushed."""
    import numpy as np

    from uncertain_facade_map.mapping.facade_map import FacadeMap
    from uncertain_facade_map.mapping.worker import Cloud, MapWorker
    from uncertain_facade_map.params import MapParams, UpdateParams

    params = MapParams(update=UpdateParams(batch_points=100_000))
    rng = np.random.default_rng(3)
    xyz = np.c_[rng.uniform(0, 6, 900), np.full(900, 10.0) + rng.normal(0, 0.02, 900), rng.uniform(0, 6, 900)]
    maps = {}
    for batching in ('latency', 'fixed'):
        worker = MapWorker(FacadeMap(params), queue_size=10, idle_flush=0.0, batching=batching)
        try:
            worker.put(Cloud(xyz, np.zeros(900, np.int64), None, 1))
            assert worker.wait_idle(60)
            snap = worker.snapshot
            if batching == 'latency':
                assert snap.stored == 900 and worker.pending_points == 0 and len(worker.latencies) == 1
            else:
                assert snap.stored == 0 and worker.pending_points == 900 and not worker.latencies
            worker.call(lambda m: m.flush())
            maps[batching] = worker.committed()[0]
        finally:
            worker.stop()
    np.testing.assert_array_equal(maps['latency'].points[0], maps['fixed'].points[0])
    import pytest
    with pytest.raises(ValueError, match='batching'):
        MapWorker(FacadeMap(params), batching='soon')


def test_latency_batching_stores_clouds_at_once_and_models_them_while_none_waits():
    """node.batching 'latency' (issue 37, two tiers): every cloud is stored in the first item
    after its arrival, with the clouds that came meanwhile (its latency ends there), and the
    façades are modelled after, in pieces while no cloud waits; the settled map has modelled
    every stored point and holds the points the clouds give offline."""
    import time

    import numpy as np

    from uncertain_facade_map.mapping import worker as wk
    from uncertain_facade_map.mapping.facade_map import FacadeMap
    from uncertain_facade_map.params import MapParams, UpdateParams

    params = MapParams(update=UpdateParams(batch_points=2000, step_points=300))
    rng = np.random.default_rng(1)
    clouds = [np.c_[rng.uniform(0, 8, 600), np.full(600, 10.0) + rng.normal(0, 0.01, 600), rng.uniform(0, 6, 600)]
              for _ in range(8)]
    seen = []
    w = wk.MapWorker(FacadeMap(params), queue_size=20, idle_flush=0.2, batching='latency',
                     on_change=lambda snap: seen.append((snap.stored, len(snap.facades))))
    try:
        for i, xyz in enumerate(clouds):
            w.put(wk.Cloud(xyz, np.zeros(600, np.int64), None, i + 1))
        deadline = time.monotonic() + 120
        while not w.settled and time.monotonic() < deadline:
            time.sleep(0.05)
        assert w.settled
        acc = w.accounts()
        assert acc['clouds_mapped'] == 8 and acc['points_unmodelled'] == 0 and len(w.latencies) == 8
        fmap = w.committed()[0]
    finally:
        w.stop()
    assert any(facades == 0 and stored > 0 for stored, facades in seen)  # stored before modelled
    assert len(fmap.facades) == 1 and fmap.n_unmodelled == 0
    offline = FacadeMap(params)
    for xyz in clouds:
        offline.add_points(xyz, np.zeros(600, np.int64))
    np.testing.assert_array_equal(fmap.points[0], offline.points[0])
