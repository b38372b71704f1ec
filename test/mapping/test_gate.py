"""The cloud gate: clouds wait for their transform in arrival order, are placed, reduced to
their building points and handed to the worker; every cloud has one outcome and the
accounts add up while clouds pass."""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from uncertain_facade_map.io.scans import Scan
from uncertain_facade_map.mapping.accounts import Accounts
from uncertain_facade_map.mapping.gate import CloudGate
from uncertain_facade_map.params import Config, NodeConfig

SECOND = 1_000_000_000


class _Worker:
    """The worker's side the gate uses: ``put`` (``room`` clouds, then drops) and counters."""

    def __init__(self, room: int = 100) -> None:
        self.clouds: list = []
        self.room = room
        self.counters = {'clouds_dropped': 0}

    def put(self, cloud) -> bool:
        self.clouds.append(cloud)
        if len(self.clouds) > self.room:
            self.clouds.pop(0)
            self.counters['clouds_dropped'] += 1
            return False
        return True

    def accounts(self) -> dict:
        n = len(self.clouds)
        return {'clouds_mapped': n, 'clouds_dropped': self.counters['clouds_dropped'], 'clouds_failed': 0,
                'clouds_waiting': 0, 'points_mapped': sum(len(c.xyz) for c in self.clouds), 'points_dropped': 0,
                'points_failed': 0, 'points_waiting': 0, 'points_pending': 0, 'points_unmodelled': 0, 'flushes': 0}


def _scan(frame: str, stamp_ns: int, n: int = 200, building: bool = True, seed: int = 0) -> Scan:
    rng = np.random.default_rng(seed)
    dtype = np.dtype([('x', np.float32), ('y', np.float32), ('z', np.float32), ('class', np.uint8)])
    points = np.zeros(n, dtype)
    points['x'] = 10.0
    points['y'] = rng.uniform(-5, 5, n)
    points['z'] = rng.uniform(0, 10, n)
    points['class'] = 6 if building else 0
    config = Config()
    return Scan.of(points, frame, stamp_ns, dataclasses.replace(config.input, time_field=''))


def _gate(worker: _Worker, **node: float) -> tuple[CloudGate, Accounts, list]:
    from uncertain_facade_map.transforms import TransformBuffer

    config = Config()
    config = dataclasses.replace(config, node=dataclasses.replace(NodeConfig(), **node),
                                 input=dataclasses.replace(config.input, building_classes=(6,)))
    accounts = Accounts(lambda text: None)
    outcomes: list = []
    gate = CloudGate(TransformBuffer(), config.input.frame_id, config, worker, accounts, outcomes.append)
    return gate, accounts, outcomes


def _add(gate: CloudGate, accounts: Accounts, scan: Scan) -> None:
    with accounts.lock:
        accounts.received(scan.frame_id, scan.stamp_ns, len(scan.points))
        gate.add(scan, len(scan.points))


def _wait_until(condition, deadline: float) -> None:
    """Poll ``condition()`` every 10 ms until it holds or ``time.monotonic()`` passes ``deadline``."""
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.01)


def _balance(accounts: Accounts, worker: _Worker, gate: CloudGate) -> int:
    v = accounts.values(worker, gate)
    return v['clouds_received'] - (v['clouds_mapped'] + v['clouds_dropped'] + v['clouds_rejected']
                                   + v['clouds_failed'] + v['clouds_waiting'])


def test_clouds_wait_for_their_transform_and_keep_their_order():
    """Three clouds of 'lidar' arrive before its poses: none passes, all wait (counted as
    waiting); once the poses come all three reach the worker in arrival order, moved by the
    pose (x + 1 m), and the accounts add up at every step."""
    worker = _Worker()
    gate, accounts, _ = _gate(worker, transform_timeout=5.0)
    scans = [_scan('lidar', (10 + k) * SECOND, seed=k) for k in range(3)]
    for scan in scans:
        _add(gate, accounts, scan)
    assert gate.step() == [] and gate.waiting() == (3, 600)
    assert _balance(accounts, worker, gate) == 0
    for t in (9, 14):
        gate.transforms.set_transform('map', 'lidar', t * SECOND, [1.0, 0, 0], [0, 0, 0, 1])
    outcomes = gate.step()
    assert [o.kind for o in outcomes] == ['queued'] * 3
    assert [c.stamp_ns for c in worker.clouds] == [s.stamp_ns for s in scans]
    assert np.allclose(worker.clouds[0].xyz[:, 0], 11.0)
    assert gate.waiting() == (0, 0) and _balance(accounts, worker, gate) == 0
    assert all(o.line().startswith('cloud at 1') for o in outcomes)


def test_a_cloud_without_its_transform_is_given_up_after_the_timeout():
    """A cloud of a frame no pose ever names is rejected as 'no transform' after
    node.transform_timeout s, and the cloud behind it (in the map frame) then passes."""
    worker = _Worker()
    gate, accounts, _ = _gate(worker, transform_timeout=0.05)
    _add(gate, accounts, _scan('nowhere', 5 * SECOND))
    _add(gate, accounts, _scan('map', 6 * SECOND))
    assert gate.step() == []  # the first waits; the second waits behind it
    time.sleep(0.06)
    outcomes = gate.step()
    assert [o.kind for o in outcomes] == ['no_transform', 'queued']
    assert 'no transform from "nowhere"' in outcomes[0].why
    assert accounts.counters['clouds_no_transform'] == 1 and accounts.counters['clouds_rejected'] == 1
    assert _balance(accounts, worker, gate) == 0


def test_outcomes_of_every_kind_add_up():
    """Building clouds queued, one dropped by a full worker, one without building points,
    one beyond the queue's bound given up: one outcome each, and the accounts add up."""
    worker = _Worker(room=2)
    gate, accounts, _ = _gate(worker, transform_queue=3)
    for k in range(3):
        _add(gate, accounts, _scan('map', k * SECOND, seed=k))
    _add(gate, accounts, _scan('map', 4 * SECOND, building=False))  # the 4th: the oldest waiting is given up
    kinds = [o.kind for o in gate.step()]
    assert kinds == ['no_transform', 'queued', 'queued', 'no_building']
    _add(gate, accounts, _scan('map', 5 * SECOND))
    assert [o.kind for o in gate.step()] == ['dropped']
    assert accounts.counters['clouds_no_building'] == 1
    assert _balance(accounts, worker, gate) == 0


def test_the_thread_hands_clouds_on_without_a_step_call():
    """Started, the gate's own thread passes a cloud in the map frame to the worker at once."""
    worker = _Worker()
    gate, accounts, outcomes = _gate(worker)
    gate.start()
    try:
        _add(gate, accounts, _scan('map', SECOND))
        _wait_until(lambda: outcomes, time.monotonic() + 5)
    finally:
        gate.stop()
    assert [o.kind for o in outcomes] == ['queued'] and len(worker.clouds) == 1


def test_a_cloud_is_counted_in_while_another_is_selected():
    """A selection that takes 0.5 s does not hold up the count of the next cloud in (the
    callback takes the accounts' lock; the gate selects without it), and the accounts add up
    meanwhile: the cloud being selected counts as waiting."""
    worker = _Worker()
    gate, accounts, outcomes = _gate(worker)
    slow = _scan('map', SECOND)
    select = slow.building_points

    def building_points(*args, **kwargs):
        time.sleep(0.5)
        return select(*args, **kwargs)

    slow.building_points = building_points
    gate.start()
    try:
        _add(gate, accounts, slow)
        time.sleep(0.1)  # the gate is selecting now
        started = time.perf_counter()
        _add(gate, accounts, _scan('map', 2 * SECOND))
        took = time.perf_counter() - started
        assert gate.waiting()[0] == 2 and _balance(accounts, worker, gate) == 0
        _wait_until(lambda: len(outcomes) >= 2, time.monotonic() + 5)
    finally:
        gate.stop()
    assert took < 0.1
    assert [o.kind for o in outcomes] == ['queued', 'queued']
    assert [c.stamp_ns for c in worker.clouds] == [SECOND, 2 * SECOND]


def test_a_fault_in_a_step_is_reported_and_the_gate_goes_on():
    """An exception that escapes a step (a fault of the code: here the worker's put raises
    once) goes to on_error, and the gate's thread maps the next cloud (before the split the
    callback doing this work was guarded; a thread that died would stop the mapping unseen)."""
    worker = _Worker()
    put, faults = worker.put, []

    def put_once_failing(cloud):
        worker.put = put
        raise RuntimeError('put failed')

    worker.put = put_once_failing
    gate, accounts, outcomes = _gate(worker)
    gate._on_error = faults.append
    gate.start()
    try:
        _add(gate, accounts, _scan('map', SECOND))
        deadline = time.monotonic() + 5
        _wait_until(lambda: faults, deadline)
        _add(gate, accounts, _scan('map', 2 * SECOND))
        _wait_until(lambda: outcomes, deadline)
    finally:
        gate.stop()
    assert [str(f) for f in faults] == ['put failed']
    assert [o.kind for o in outcomes] == ['queued'] and worker.clouds[-1].stamp_ns == 2 * SECOND
