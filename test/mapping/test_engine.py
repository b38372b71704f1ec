"""The map updated in a child process: the same map as in a thread, commands that must
pickle, saves that do not wait for an update, and a child that ends with its parent."""

import functools
import os
import pickle
import signal
import subprocess
import sys
import textwrap
import threading
import time

import numpy as np
import pytest

from uncertain_facade_map.mapping.engine import HelperProcess, Kept, MappingProcessError, ProcessEngine, unkept
from uncertain_facade_map.mapping.facade_map import FacadeMap
from uncertain_facade_map.mapping.worker import Cloud, MapWorker, replace_with
from uncertain_facade_map.params import MapParams, UpdateParams


def wall(n=400, seed=0, u0=0.0):
    rng = np.random.default_rng(seed)
    return np.c_[u0 + rng.uniform(0, 5, n), np.full(n, 10.0) + rng.normal(0, 0.02, n), rng.uniform(0, 5, n)]


def _settle(worker, timeout=120):
    deadline = time.monotonic() + timeout
    while not worker.settled:
        assert time.monotonic() < deadline, 'the worker did not settle'
        time.sleep(0.05)


def test_a_process_builds_the_same_map_as_a_thread_and_the_offline_core():
    params = MapParams(update=UpdateParams(batch_points=1000))
    workers = [MapWorker(FacadeMap(params), queue_size=100, idle_flush=0.3, process=p) for p in (False, True)]
    assert workers[0].process_id is None and workers[1].process_id not in (None, os.getpid())
    offline = FacadeMap(params)
    for i in range(6):
        xyz = wall(400, seed=i, u0=i * 2.0)
        for w in workers:
            w.put(Cloud(xyz, np.zeros(400, np.int64), None, i))
        offline.add_points(xyz, np.zeros(400, np.int64), defer=True)
    for w in workers:
        _settle(w)
    offline.flush()
    for w in workers:
        snap = w.snapshot
        assert snap.points == offline.n_points == 2400 and len(snap.facades) == len(offline.facades) >= 1
        assert snap.stored == offline.n_stored > 0
        # The CPU time of the last update, measured where it ran (the idle flush refits whole).
        assert w.last_update_cpu_seconds > 0.0
        for a, b in zip(snap.facades, offline.facades):
            np.testing.assert_array_equal(a.surface.mean, b.surface.mean)
            np.testing.assert_array_equal(a.surface.var, b.surface.var)
            np.testing.assert_array_equal(a.point_index, b.point_index)
        fmap, version, waiting = w.committed()
        assert fmap.n_points == 2400 and version == snap.version == w.committed_version and waiting == 0
        assert w.accounts()['clouds_mapped'] == 6
        w.stop()


def test_bad_clouds_and_commands_fail_with_the_map_kept():
    errors = []
    worker = MapWorker(FacadeMap(), idle_flush=0, on_error=lambda c, e: errors.append(e), process=True)
    worker.put(Cloud(wall(50)))
    worker.put(Cloud(np.full((5, 3), np.nan)))
    assert worker.wait_idle(60)
    assert len(errors) == 1 and 'NaN' in str(errors[0]) and type(errors[0]).__name__ == 'InputError'
    assert worker.accounts()['clouds_failed'] == 1 and worker.committed()[0].n_pending == 50
    with pytest.raises(MappingProcessError, match='must pickle'):
        worker.call(lambda m: None)
    with pytest.raises(TypeError):
        worker.call(functools.partial(divmod, 1))  # divmod(1, map) raises in the child
    assert worker.committed()[0].n_pending == 50
    version = worker.snapshot.version
    assert worker.call(functools.partial(replace_with, FacadeMap(), 'replaced')) == 'replaced'
    assert worker.snapshot.version == version + 1 and worker.committed()[0].n_pending == 0
    worker.stop()


def test_a_save_gets_the_committed_map_while_the_process_maps():
    params = MapParams(update=UpdateParams(batch_points=1))
    worker = MapWorker(FacadeMap(params), idle_flush=0, process=True)
    worker.put(Cloud(wall(400, seed=1), np.zeros(400, np.int64)))
    assert worker.wait_idle(60)
    version = worker.snapshot.version
    big = np.vstack([wall(20_000, seed=s, u0=5.0 * s) for s in range(2, 26)])  # 480,000 points: an update of ~2 s
    worker.put(Cloud(big, np.zeros(len(big), np.int64)))
    time.sleep(0.5)
    assert worker.accounts()['clouds_waiting'] == 1  # being mapped
    started = time.monotonic()
    fmap, saved_version, waiting = worker.committed()
    assert time.monotonic() - started < 2.0
    assert worker.accounts()['clouds_waiting'] == 1, 'the update ended before the save: make the cloud bigger'
    assert fmap.n_points == 400 and saved_version == version and waiting == 1
    assert worker.wait_idle(120)
    assert worker.committed()[0].n_points == 400 + len(big)
    worker.stop()


def test_a_dead_mapping_process_fails_clouds_with_a_clear_error():
    errors = []
    worker = MapWorker(FacadeMap(), idle_flush=0, on_error=lambda c, e: errors.append(e), process=True)
    os.kill(worker.process_id, signal.SIGKILL)
    time.sleep(0.5)
    worker.put(Cloud(wall(50)))
    assert worker.wait_idle(30)
    assert len(errors) == 1 and isinstance(errors[0], MappingProcessError) and 'ended' in str(errors[0])
    assert worker.accounts()['clouds_failed'] == 1
    worker.stop(5)


def test_the_mapping_process_ends_with_its_parent(tmp_path):
    """A parent killed (SIGKILL) in the middle: its mapping process notices the closed pipes and ends."""
    script = textwrap.dedent('''
        import sys, time
        from uncertain_facade_map.mapping.engine import ProcessEngine
        from uncertain_facade_map.mapping.facade_map import FacadeMap
        engine = ProcessEngine(FacadeMap())
        engine.committed()  # the child is up
        print(engine.pid, flush=True)
        time.sleep(600)
    ''')
    parent = subprocess.Popen([sys.executable, '-c', script], stdout=subprocess.PIPE, text=True,
                              cwd=os.path.dirname(os.path.dirname(os.path.dirname(__file__))))
    child = int(parent.stdout.readline())
    os.kill(child, 0)  # alive
    parent.kill()
    parent.wait(10)
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            os.kill(child, 0)
        except ProcessLookupError:
            break
        time.sleep(0.1)
    else:
        os.kill(child, signal.SIGKILL)
        pytest.fail('the mapping process outlived its parent')


def test_engine_close_is_idempotent_enough():
    engine = ProcessEngine(FacadeMap())
    pid = engine.pid
    engine.close()
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)


def test_a_helper_process_runs_functions_and_starts_again_after_dying():
    helper = HelperProcess('test_helper')
    assert helper.pid is None
    assert helper.call(divmod, 7, 2) == (3, 1)
    with pytest.raises(ZeroDivisionError):
        helper.call(divmod, 1, 0)
    pid = helper.pid
    os.kill(pid, signal.SIGKILL)
    time.sleep(0.3)
    assert helper.call(divmod, 9, 4) == (2, 1) and helper.pid != pid  # started again
    pid = helper.pid
    helper.call(time.sleep, 0.0)
    helper.close()
    assert helper.pid is None
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)


def _size_and_sum(a, scale):
    return len(a), float(a.sum()) * scale


def test_a_kept_argument_crosses_to_the_helper_once_per_object():
    """The node hands its per-point reading (millions of stored points) to every publication:
    the helper keeps it, so only a new reading crosses the process boundary; the answers are
    those of calls with the values themselves, here as there, and again after a restart."""
    helper = HelperProcess('test_helper')
    sent = []
    conn_send = None
    try:
        big, other = np.arange(2_000_000, dtype=np.float64), np.ones(10)
        assert helper.call(_size_and_sum, Kept('a', big, big), 2.0) == _size_and_sum(*unkept((Kept('a', big, big), 2.0)))
        conn_send = helper._conn.send
        helper._conn.send = lambda msg: (sent.append(len(pickle.dumps(msg))), conn_send(msg))[1]
        assert helper.call(_size_and_sum, Kept('a', big, big), 1.0) == (2_000_000, float(big.sum()))
        copy = big.copy()  # equal, but another object: sent
        assert helper.call(_size_and_sum, Kept('a', copy, copy), 1.0) == (2_000_000, float(big.sum()))
        assert helper.call(_size_and_sum, Kept('a', copy, copy), 0.0) == (2_000_000, 0.0)
        assert sent[0] < 10_000 and sent[1] > 16_000_000 and sent[2] < 10_000
        assert unkept((Kept('a', big, other), 1.0))[0] is big  # called here: the object itself, not the copy to send
        os.kill(helper.pid, signal.SIGKILL)
        time.sleep(0.3)
        assert helper.call(_size_and_sum, Kept('a', other, other), 3.0) == (10, 30.0)  # sent again to the new one
    finally:
        helper.close()


def test_closing_a_helper_during_a_call_ends_the_call_with_a_clear_error():
    """The node closes its helper at shutdown, maybe while it computes the published maps:
    the waiting call ends at once with an error that says so, and later calls are refused."""
    helper = HelperProcess('test_helper')
    helper.call(divmod, 1, 1)
    out = {}

    def run():
        try:
            helper.call(time.sleep, 30)
        except MappingProcessError as exc:
            out['error'] = str(exc)

    caller = threading.Thread(target=run)
    caller.start()
    time.sleep(0.5)
    started = time.monotonic()
    helper.close(timeout=1.0)
    caller.join(10)
    assert 'was closed' in out.get('error', '') and time.monotonic() - started < 8
    with pytest.raises(MappingProcessError, match='closed'):
        helper.call(divmod, 1, 1)



def _nap(seconds, _fmap):
    """A command for the mapping process that takes ``seconds``."""
    time.sleep(seconds)


def test_stop_during_a_long_item_kills_the_process_without_reading_its_pipe():
    """stop(timeout) while an item outlasts the timeout: the worker's thread still waits for the
    child's answer on the pipe, so the child is killed at once, not asked to stop (asking read
    the same pipe: the answer arriving meanwhile was garbled, UnpicklingError from stop, seen
    when the streaming bench gave up a rate)."""
    worker = MapWorker(FacadeMap(), idle_flush=0, process=True)
    worker.committed()  # the child is up
    pid = worker.process_id
    failed = []

    def call():
        try:
            worker.call(functools.partial(_nap, 2.5))
        except Exception as exc:  # noqa: BLE001 - what the caller sees
            failed.append(exc)

    caller = threading.Thread(target=call)
    caller.start()
    time.sleep(0.3)
    started = time.monotonic()
    worker.stop(1.0)  # asking the child would wait for the nap's answer (2.5 s) and read it
    assert time.monotonic() - started < 2.0
    caller.join(10)
    assert len(failed) == 1 and isinstance(failed[0], MappingProcessError)
    with pytest.raises(ProcessLookupError):
        for _ in range(50):
            os.kill(pid, 0)
            time.sleep(0.1)


def test_the_parent_holds_the_childs_stored_points_from_appended_rows_only():
    """The stored points come back as the rows each update appended (issue 37: nothing whole
    crosses the process boundary per cloud), and whole after a command replaced the map: the
    parent's copy equals the child's map after clouds of two buildings, a reset and more clouds."""
    from uncertain_facade_map.mapping import engine as eng

    params = MapParams(update=UpdateParams(batch_points=500))
    worker = MapWorker(FacadeMap(params), queue_size=100, idle_flush=0.0, process=True, batching='latency')
    try:
        for i in range(4):
            for b in (0, 1):
                worker.put(Cloud(wall(300, seed=10 * b + i, u0=20.0 * b + i), np.full(300, b, np.int64), None, i))
            worker.wait_idle(120)
        fmap, _, _ = worker.committed()
        held = worker.snapshot.stored_points
        assert sorted(held) == sorted(fmap.points) == [0, 1]
        for b in held:
            np.testing.assert_array_equal(held[b], fmap.points[b])
            assert not held[b].flags.writeable
        worker.call(functools.partial(replace_with, FacadeMap(params), None))
        worker.put(Cloud(wall(300, seed=99, u0=50.0), np.full(300, 5, np.int64), None, 9))
        worker.wait_idle(120)
        fmap, _, _ = worker.committed()
        assert sorted(worker.snapshot.stored_points) == sorted(fmap.points) == [5]
        np.testing.assert_array_equal(worker.snapshot.stored_points[5], fmap.points[5])
    finally:
        worker.stop()
    # The delta of an append carries the new rows only; a replaced array travels whole.
    a = np.zeros((5, 3))
    b = np.vstack([a, np.ones((2, 3))])
    labels, changed = eng._points_delta({0: a}, {0: b}, appended=True)
    assert labels == (0,) and changed[0][0] == 5 and changed[0][1].shape == (2, 3)
    assert eng._points_delta({0: a}, {0: b}, appended=False)[1][0][0] == 0
    np.testing.assert_array_equal(eng._apply_points_delta({0: a}, (labels, changed))[0], b)
