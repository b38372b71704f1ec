"""The reading a live map serves its queries with (issue 37): built by the first query, then
rebuilt in the background only once it is ``node.local_refresh`` old and the map has grown
by ``node.local_growth``; once the map settles, its own, and ``current`` says so."""

import threading
import time

import numpy as np

from uncertain_facade_map.mapping.served import ServedReading
from uncertain_facade_map.params import NodeConfig, QueryConfig
from uncertain_facade_map.pipeline.step7_local_surface import LocalSurface


class Snap:
    """A snapshot: its version, stored points, and the readings built of it."""

    def __init__(self, version: int, stored: int) -> None:
        self.version, self.stored = version, stored
        self.built = 0
        self.gate = threading.Event()
        self.gate.set()

    def local_surface(self, config):
        self.gate.wait(10)
        self.built += 1
        return ('reading', self.version)


class Worker:
    def __init__(self, snap: Snap) -> None:
        self.snapshot, self.settled, self.replacements = snap, False, 0


def after_a_first_query(node: NodeConfig) -> tuple[Snap, Worker, ServedReading]:
    """A map's first snapshot, its worker, and the reading served, built by a first query."""
    first = Snap(1, 1000)
    worker = Worker(first)
    served = ServedReading(worker, QueryConfig(), node)
    served.for_snapshot(first)
    return first, worker, served


def wait_for(condition, timeout: float = 10.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.01)
    return False


def test_the_held_reading_serves_until_it_is_old_and_the_map_has_grown():
    first = Snap(1, 1000)
    worker = Worker(first)
    served = ServedReading(worker, QueryConfig(), NodeConfig(local_refresh=0.2, local_growth=0.05))
    assert served.for_snapshot(first) == ('reading', 1) and first.built == 1  # the first: by the query
    grown = Snap(2, 1040)  # 4 % more: not enough
    worker.snapshot = grown
    time.sleep(0.25)
    assert served.for_snapshot(grown) == ('reading', 1) and grown.built == 0 and not served.current
    more = Snap(3, 1100)  # 10 % more and old enough: built in the background, the held one serves meanwhile
    more.gate.clear()
    worker.snapshot = more
    assert served.for_snapshot(more) == ('reading', 1)
    assert served.for_snapshot(more) == ('reading', 1)  # one build at a time
    more.gate.set()
    assert wait_for(lambda: served.for_snapshot(more) == ('reading', 3))
    assert more.built == 1 and served.builds[0] == 1 and served.current
    # Just built: a newer snapshot waits for the refresh period even when the map grew a lot.
    newer = Snap(4, 5000)
    worker.snapshot = newer
    assert served.for_snapshot(newer) == ('reading', 3) and newer.built == 0


def test_a_small_gain_is_read_after_six_refreshes():
    _, worker, served = after_a_first_query(NodeConfig(local_refresh=0.05, local_growth=0.5))
    same, grown = Snap(2, 1000), Snap(3, 1001)
    worker.snapshot = same
    time.sleep(0.35)
    assert served.for_snapshot(same) == ('reading', 1) and same.built == 0  # nothing stored since: never
    worker.snapshot = grown
    assert served.for_snapshot(grown) == ('reading', 1)
    assert wait_for(lambda: served.for_snapshot(grown) == ('reading', 3))


def test_the_settled_map_gets_its_own_reading_in_the_background():
    _, worker, served = after_a_first_query(NodeConfig(local_refresh=3600.0))
    last = Snap(2, 1001)
    worker.snapshot, worker.settled = last, True
    assert not served.current
    served.refresh()  # nobody asked: built anyway, and current says when it is read
    assert wait_for(lambda: served.current)
    assert served.for_snapshot(last) == ('reading', 2) and last.built == 1


def test_a_new_map_and_refresh_zero_build_at_the_query():
    first, worker, served = after_a_first_query(NodeConfig(local_refresh=5.0))
    loaded = Snap(2, 10)
    worker.snapshot, worker.replacements = loaded, 1  # a load or a reset: the old reading is not this map's
    assert served.for_snapshot(loaded) == ('reading', 2) and loaded.built == 1
    always = ServedReading(worker, QueryConfig(), NodeConfig(local_refresh=0.0))
    assert always.current and always.for_snapshot(first) == ('reading', 1)
    assert ServedReading(worker, QueryConfig(surface='raster'), NodeConfig()).for_snapshot(first) is None


def test_a_reading_without_its_caches_reads_the_same():
    rng = np.random.default_rng(2)
    pts = np.c_[rng.uniform(0, 10, 20_000), 5.0 + rng.normal(0, 0.02, 20_000), rng.uniform(0, 6, 20_000)]
    local = LocalSurface(pts, np.zeros(len(pts), np.int32), np.array([[0.0, -1.0, 0.0]]))
    local.calibrate()
    q = pts[:5000] + rng.normal(0, 0.1, (5000, 3))
    a = local.read(q)
    bare = local.without_caches()
    assert bare._grid is None and bare._tree is None and local._grid is not None
    b = bare.read(q)
    for name in ('facade', 'signed_distance', 'variance', 'noise_variance', 'normal', 'weight'):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
