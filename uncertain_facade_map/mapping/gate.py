"""The cloud gate: a received cloud waits for its transform, is placed in the map frame,
reduced to its building points and handed to the map worker, in a thread of its own.

The shape of tf2's ``MessageFilter``: clouds wait in arrival order (at most
``node.transform_queue`` of them, each at most ``node.transform_timeout`` s) until the
:class:`~uncertain_facade_map.transforms.TransformBuffer` can place them at their stamp and
their points' times; the first whose transform has not come stops the ones behind it, so
that clouds reach the map in the order they came, as offline replay maps them. Placing and
selecting run in the gate's thread, never in the callback that received the cloud, so that a
node takes clouds in at the sensor's rate however long a selection takes.

What became of each cloud is returned as an :class:`Outcome` (and counted in the
:class:`~.accounts.Accounts` at the same moment, under its lock, so that the accounts add up
while clouds pass).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable

from ..errors import InputError, TransformError
from ..io.scans import Scan, ScanPoints
from ..params import Config
from ..transforms import Placement, TransformBuffer
from .accounts import Accounts
from .worker import Cloud

__all__ = ['POLL_SECONDS', 'CloudGate', 'Outcome']

#: Seconds between the gate's looks at the clouds waiting for their transform.
POLL_SECONDS = 0.01


@dataclass
class _Waiting:
    scan: Scan
    points: int  # width * height of the cloud received
    arrived: float  # time.monotonic()


@dataclass(frozen=True)
class Outcome:
    """What became of one cloud at the gate.

    Attributes:
        kind: 'queued' (handed to the worker), 'dropped' (handed, the worker's queue dropped
            its oldest cloud), 'no_building' (placed, no building point: mapped as nothing),
            'rejected' (its reason in ``why``) or 'no_transform' (gave up waiting).
        scan: the cloud's scan (frame, stamp, points).
        points: points of the cloud received.
        waited: seconds from its arrival to this outcome.
        why: the reason of a rejection, else ''.
        placement: where it was placed (None unless placed).
        found: its building points (None unless selected).
    """

    kind: str
    scan: Scan
    points: int
    waited: float
    why: str = ''
    placement: Placement | None = None
    found: ScanPoints | None = None

    def line(self) -> str:
        """One line of what became of the cloud: its frame, points kept, pose and wait."""
        scan = self.scan
        head = f'cloud at {scan.stamp_ns / 1e9:.3f} s: {self.points:,} points'
        if self.found is None or self.placement is None:
            return f'{head}, {self.kind}: {self.why}'
        pose = 'in the map frame'
        if self.placement.pose is not None:
            t = self.placement.pose.translations[0]
            pose = (f'frame "{scan.frame_id}" at ({t[0]:.2f}, {t[1]:.2f}, {t[2]:.2f}) m'
                    + (f', {len(self.placement.pose.translations)} poses over its points\' times'
                       if not self.placement.pose.single else ''))
        sel = self.found.selection
        kept = (f', the selection kept {sel.kept:,} of {sel.non_ground:,} non-ground points'
                if sel is not None and sel.applied else '')
        return (f'{head}, {len(self.found.xyz):,} building{kept}; {pose}; waited {self.waited:.3f} s'
                + (f' ({self.placement.note})' if self.placement.note else ''))


class CloudGate:
    """Clouds waiting for their transform, then placed, selected and handed to the worker.

    Args:
        transforms: the buffer the poses go into (read here, written by the listener).
        frame_id: the map frame.
        config: the configuration (``input``, ``selection``, ``node.transform_queue``,
            ``node.transform_timeout``, ``node.pose_tolerance``, ``node.max_coordinate``).
        worker: the map worker (``put``).
        accounts: where every outcome is counted.
        on_outcome: called (outside the lock, in the gate's thread) with each outcome.
        on_error: called with an exception that escaped a step (a fault of the code, not of a
            cloud: those are outcomes); the thread goes on. None: counted as a
            ``callback_error`` event.
    """

    def __init__(self, transforms: TransformBuffer, frame_id: str, config: Config, worker: Any, accounts: Accounts,
                 on_outcome: Callable[[Outcome], None] | None = None,
                 on_error: Callable[[Exception], None] | None = None) -> None:
        self.transforms = transforms
        self.frame_id = frame_id
        self._config = config
        self._worker = worker
        self._accounts = accounts
        self._on_outcome = on_outcome
        self._on_error = on_error
        self._waiting: deque[_Waiting] = deque()
        self._outcomes: list[Outcome] = []  # since the last step (written under the accounts' lock)
        self._current: _Waiting | None = None  # the cloud being placed and selected
        self._wake = threading.Event()
        self._stop = False
        self._thread: threading.Thread | None = None

    # -- input ------------------------------------------------------------------------------
    def add(self, scan: Scan, points: int) -> None:
        """Queue a received cloud (``points``: its width x height) to wait for its transform;
        the oldest is given up when more than ``node.transform_queue`` wait. The caller holds
        the accounts' lock (it counted the cloud received under it)."""
        self._waiting.append(_Waiting(scan, points, time.monotonic()))
        limit = self._config.node.transform_queue
        if len(self._waiting) > limit:
            self._give_up(self._waiting.popleft(), f'more than node.transform_queue = {limit} clouds wait for '
                                                   'their transform: the oldest is given up')
        self._wake.set()

    def waiting(self) -> tuple[int, int]:
        """Clouds and points waiting for their transform or being placed (read under the
        accounts' lock)."""
        items = list(self._waiting) + ([self._current] if self._current is not None else [])
        return len(items), sum(item.points for item in items)

    # -- the gate's work ------------------------------------------------------------------------
    def step(self) -> list[Outcome]:
        """Place the waiting clouds in arrival order, hand their building points to the worker,
        give up those that waited ``node.transform_timeout`` s; returns what became of each.

        A cloud is placed and selected without the accounts' lock (the callbacks that count
        clouds in never wait for a selection); it counts as waiting until its outcome is
        counted, under the lock."""
        node, lock = self._config.node, self._accounts.lock
        while True:
            with lock:
                if not self._waiting:
                    break
                head = self._current = self._waiting.popleft()
            final = time.monotonic() - head.arrived >= node.transform_timeout
            placement = found = None
            why, transform = '', False
            try:
                placement = head.scan.place(self.transforms, self.frame_id, node.pose_tolerance, final=final)
                if placement is not None:
                    found = head.scan.building_points(placement, self._config.input, self._config.selection,
                                                      node.max_coordinate)
            except TransformError as exc:
                why, transform = str(exc), True
            except InputError as exc:  # a time field that cannot be read, points beyond the bound
                why = str(exc)
            except Exception as exc:  # noqa: BLE001 - a cloud the code cannot handle is counted, not lost
                self._accounts.event('failed', f'cloud failed: {type(exc).__name__}: {exc}')
                why = f'internal error: {type(exc).__name__}: {exc}'
            with lock:
                self._current = None
                if why and transform:
                    self._give_up(head, why)
                elif why:
                    self._rejected(head, why)
                elif placement is not None and found is not None:
                    self._map(head, placement, found)
                else:  # its transform may still come: it waits at the head
                    self._waiting.appendleft(head)
                    break
        with lock:
            out, self._outcomes = self._outcomes, []
        return out

    def _outcome(self, item: _Waiting, kind: str, why: str = '', placement: Placement | None = None,
                 found: ScanPoints | None = None) -> None:
        self._outcomes.append(Outcome(kind, item.scan, item.points, time.monotonic() - item.arrived, why,
                                      placement, found))

    def _rejected(self, item: _Waiting, why: str, kind: str | None = None) -> None:
        self._accounts.reject(why, item.points, kind)
        self._outcome(item, 'rejected' if kind is None else 'no_transform', why)

    def _give_up(self, item: _Waiting, why: str) -> None:
        """Reject a cloud whose transform never came."""
        scan = item.scan
        self._accounts.counters['clouds_no_transform'] += 1
        self._rejected(item, f'no transform from "{scan.frame_id}" into the map frame "{self.frame_id}" at '
                             f'{scan.stamp_ns / 1e9:.3f} s after {time.monotonic() - item.arrived:.2f} s: {why}',
                       kind='no transform')

    def _map(self, item: _Waiting, placement: Placement, found: ScanPoints) -> None:
        """A placed cloud's building points to the worker (the caller holds the accounts' lock)."""
        accounts = self._accounts
        scan = item.scan
        interval, counters = accounts.interval, accounts.counters
        if placement.note:
            interval['notes'][placement.note] += 1
            accounts.warn(f'a cloud in "{scan.frame_id}" at {scan.stamp_ns / 1e9:.3f} s: {placement.note}',
                          'placement ' + placement.note[:12], period=30.0)
        counters['points_not_building'] += found.not_building
        if found.nonfinite:
            counters['points_nonfinite'] += found.nonfinite
            accounts.warn(f'{found.nonfinite} of {item.points} points with NaN or infinite coordinates skipped',
                          'nonfinite')
        self._selection_note(found)
        interval['points'] += item.points
        interval['building'] += len(found.xyz)
        interval['queued'] += 1
        if not len(found.xyz):
            counters['clouds_no_building'] += 1
            self._outcome(item, 'no_building', placement=placement, found=found)
            return
        if self._worker.put(Cloud(found.xyz, found.building_id, found.sensor_origins, scan.stamp_ns,
                                  arrived=item.arrived)):
            self._outcome(item, 'queued', placement=placement, found=found)
            return
        dropped = self._worker.counters['clouds_dropped']
        interval['dropped'] += 1
        accounts.event('dropped', f'mapping falls behind: {dropped} clouds dropped so far')
        accounts.warn(f'mapping falls behind: dropped the oldest waiting cloud ({dropped} so far; a larger '
                      'node.queue_size or update.batch_points may help)', 'dropped')
        self._outcome(item, 'dropped', placement=placement, found=found)

    def _selection_note(self, found: ScanPoints) -> None:
        """Count what the selection kept of a cloud without classes, and warn when it kept little."""
        from ..selection import selection_warning

        sel = found.selection
        if sel is None or not sel.applied:
            return
        self._accounts.interval['non_ground'] += sel.non_ground
        self._accounts.interval['selected'] += sel.kept
        warning = selection_warning(sel, self._config.selection)
        if warning is not None:
            self._accounts.warn(warning, 'selection share', period=30.0)

    # -- the thread ---------------------------------------------------------------------------
    def start(self) -> CloudGate:
        """Run :meth:`step` in a thread of its own: at once when a cloud arrives, and every
        :data:`POLL_SECONDS` while clouds wait for their transform."""
        self._thread = threading.Thread(target=self._run, name='cloud_gate', daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop:
            self._wake.wait(POLL_SECONDS if self._waiting else 1.0)
            self._wake.clear()
            if self._stop:
                return
            try:
                for outcome in self.step():
                    if self._on_outcome is not None:
                        self._on_outcome(outcome)
            except Exception as exc:  # noqa: BLE001 - the gate must live on, as the callback it replaces did
                if self._on_error is not None:
                    self._on_error(exc)
                else:
                    self._accounts.event('callback_error', f'cloud gate failed: {type(exc).__name__}: {exc}')

    def stop(self, timeout: float = 10.0) -> None:
        """End the thread (the clouds still waiting stay counted as waiting)."""
        self._stop = True
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout)
