"""What happened to every cloud and pose a live mapper received: counters that add up, the
recent drops, rejections and failures, and the line a log tells every few seconds.

One :class:`Accounts` per live mapper (the ``facade_mapper`` node's): the cloud gate
(:class:`~.gate.CloudGate`) counts under :attr:`Accounts.lock` while it places and selects,
the pose listener under a lock of its own (a pose must never wait for a cloud's selection),
and :meth:`Accounts.values` reads everything at one moment, so that ``clouds_received =
clouds_mapped + clouds_dropped + clouds_rejected + clouds_failed + clouds_waiting`` holds
whenever /diagnostics is read.
"""

from __future__ import annotations

import threading
import time
from collections import Counter, deque
from typing import Any, Callable

import numpy as np

__all__ = ['WARN_EVENTS', 'Accounts']

#: Kinds of event that make the diagnostic level WARN while they are recent.
WARN_EVENTS = ('dropped', 'rejected', 'failed', 'callback_error')
#: Gaps between stamps kept per frame to find the sensor's period.
_PERIODS = 50


def _new_interval() -> dict[str, Any]:
    return {'in': 0, 'queued': 0, 'rejected': Counter(), 'dropped': 0, 'non_ground': 0, 'selected': 0,
            'notes': Counter(), 'points': 0, 'building': 0}


def _percentile(values: Any, q: float, scale: float = 1.0, digits: int = 3) -> float:
    values = np.asarray(list(values), dtype=np.float64)
    return round(scale * float(np.percentile(values, q)), digits) if len(values) else 0.0


class Accounts:
    """Counters of a live mapper's input, its recent events and throttled warnings.

    Args:
        warning: logs a warning line (the node's logger); :meth:`warn` throttles it per kind.
    """

    def __init__(self, warning: Callable[[str], None]) -> None:
        self._warning = warning
        self.counters = {'clouds_received': 0, 'points_received': 0, 'clouds_rejected': 0, 'points_rejected': 0,
                         'clouds_no_building': 0, 'points_nonfinite': 0, 'points_not_building': 0,
                         'clouds_missed_estimate': 0, 'queries': 0, 'queries_failed': 0,
                         'saves': 0, 'callback_errors': 0, 'clouds_no_transform': 0}
        self.pose_counters = {'poses_rejected': 0, 'transforms_received': 0}
        #: Held while a cloud is counted, placed and selected (and while the counts are read).
        self.lock = threading.Lock()
        self._pose_lock = threading.Lock()
        self.events: deque[tuple[float, str, str]] = deque(maxlen=1000)  # (monotonic, kind, text)
        self.interval = _new_interval()  # what the next summary line tells
        self.query_seconds: deque[float] = deque(maxlen=200)  # time in the node of the latest queries
        self._last_stamp: dict[str, tuple[int, deque[int]]] = {}  # frame -> (last stamp, recent periods)
        self._warned: dict[str, float] = {}
        self._summary: tuple[int, int] = (-1, 0)  # (map version, clouds mapped) at the last summary line

    # -- events ---------------------------------------------------------------------------
    def warn(self, text: str, key: str, period: float = 5.0) -> None:
        """Log a warning, at most once per ``period`` seconds for each kind ``key``."""
        now = time.monotonic()
        if now - self._warned.get(key, -1e9) >= period:
            self._warned[key] = now
            self._warning(text)

    def event(self, kind: str, text: str) -> None:
        """Remember a drop, rejection or failure (``kind`` one of :data:`WARN_EVENTS`) for the
        diagnostics' recent window."""
        self.events.append((time.monotonic(), kind, text))
        if kind == 'callback_error':
            with self.lock:
                self.counters['callback_errors'] += 1

    def count(self, name: str, n: int = 1) -> None:
        """Add ``n`` to a counter (``queries``, ``saves``...)."""
        with self.lock:
            self.counters[name] += n

    def recent(self, window: float) -> list[tuple[float, str, str]]:
        """The events of the last ``window`` seconds, oldest first."""
        now = time.monotonic()
        return [e for e in list(self.events) if now - e[0] <= window]

    # -- clouds (the caller holds :attr:`lock`) ----------------------------------------------
    def received(self, frame: str, stamp_ns: int, points: int) -> int:
        """Count a cloud received; returns the clouds estimated lost just before it (:meth:`count_gap`)."""
        self.counters['clouds_received'] += 1
        self.counters['points_received'] += points
        self.interval['in'] += 1
        return self.count_gap(frame, stamp_ns)

    def reject(self, why: str, points: int, kind: str | None = None) -> None:
        """Count a refused cloud of ``points`` points; ``kind`` names the reason in the summary
        line (default: the reason's first words)."""
        self.counters['clouds_rejected'] += 1
        self.counters['points_rejected'] += points
        self.interval['rejected'][kind or why.split(':')[0][:40]] += 1
        self.event('rejected', f'cloud rejected: {why}')
        self.warn(f'cloud rejected: {why}', kind or why.split(':')[0][:30])

    def count_gap(self, frame: str, stamp: int) -> int:
        """Estimate clouds lost before they reached the mapper from the gaps between stamps
        (a gap of k typical periods means k - 1 lost); returns the clouds this gap lost. The
        typical period is the 10th percentile of the last 50 gaps: when most clouds are lost
        the median gap is itself a gap, the short ones are still the sensor's period."""
        last, periods = self._last_stamp.get(frame, (None, deque(maxlen=_PERIODS)))
        missed = 0
        if last is not None and stamp > last:
            gap = stamp - last
            if len(periods) >= 5:
                typical = float(np.percentile(periods, 10))
                if typical > 0 and gap > 1.5 * typical:
                    missed = int(round(gap / typical)) - 1
                    self.counters['clouds_missed_estimate'] += missed
            periods.append(gap)
        if last is None or stamp > last:
            self._last_stamp[frame] = (stamp, periods)
        return missed

    # -- poses ------------------------------------------------------------------------------
    def pose_received(self) -> None:
        with self._pose_lock:
            self.pose_counters['transforms_received'] += 1

    def reject_pose(self, source: str, why: str) -> None:
        with self._pose_lock:
            self.pose_counters['poses_rejected'] += 1
        self.event('rejected', f'{source} rejected: {why}')
        self.warn(f'{source} rejected: {why}', f'pose {source} {why[:20]}')

    # -- reading ------------------------------------------------------------------------------
    def values(self, worker: Any, gate: Any) -> dict[str, Any]:
        """Clouds and points received, mapped, dropped, rejected, failed and waiting, read at
        one moment so that they add up (``received = mapped + dropped + rejected + failed +
        waiting``, for points also ``+ not_building + nonfinite``).

        Args:
            worker: the map worker (``accounts()``).
            gate: the cloud gate (``waiting()``: clouds and points waiting for a transform).
        """
        with self.lock:
            c = dict(self.counters)
            w = worker.accounts()
            waiting, waiting_points = gate.waiting()
        with self._pose_lock:
            poses = dict(self.pose_counters)
        return {
            'clouds_received': c['clouds_received'], 'clouds_mapped': w['clouds_mapped'] + c['clouds_no_building'],
            'clouds_dropped': w['clouds_dropped'], 'clouds_rejected': c['clouds_rejected'],
            'clouds_failed': w['clouds_failed'], 'clouds_waiting': w['clouds_waiting'] + waiting,
            'clouds_waiting_transform': waiting, 'clouds_no_transform': c['clouds_no_transform'],
            'clouds_missed_estimate': c['clouds_missed_estimate'],
            'points_received': c['points_received'], 'points_mapped': w['points_mapped'],
            'points_not_building': c['points_not_building'], 'points_nonfinite': c['points_nonfinite'],
            'points_dropped': w['points_dropped'], 'points_rejected': c['points_rejected'],
            'points_failed': w['points_failed'],
            'points_waiting': w['points_waiting'] + waiting_points,
            'points_pending': w['points_pending'], 'points_unmodelled': w['points_unmodelled'],
            'poses_rejected': poses['poses_rejected'],
            'transforms_received': poses['transforms_received'],
            'flushes': w['flushes'], 'queries': c['queries'], 'queries_failed': c['queries_failed'],
            'saves': c['saves'], 'callback_errors': c['callback_errors'],
        }

    def diagnostics(self, worker: Any, gate: Any, reading: Any, window: float) -> tuple[dict[str, Any], int, str]:
        """The values /diagnostics publishes of the live map (:meth:`values`, the map's size,
        update time, latency, the reading and the recent window), its level (0 OK, 1 WARN: a
        drop, rejection or failure in the last ``window`` s) and its message."""
        reading.refresh()
        snap = worker.snapshot
        recent = self.recent(window)
        latencies = list(worker.latencies)
        values = self.values(worker, gate)
        values.update({
            'map_points': snap.points, 'map_points_stored': snap.stored,
            'map_mb': round(snap.map_bytes / 2**20, 1), 'buildings': snap.buildings, 'facades': len(snap.facades),
            'map_version': snap.version, 'settled': worker.settled and reading.current,
            'reading_builds': reading.builds[0], 'reading_build_seconds': round(reading.builds[1], 2),
            'last_update_seconds': round(worker.last_update_seconds, 4),
            'last_update_cpu_seconds': round(worker.last_update_cpu_seconds, 4),
            'latency_seconds': round(float(latencies[-1]), 3) if latencies else 0.0,
            'latency_p50_seconds': _percentile(latencies, 50),
            'latency_p95_seconds': _percentile(latencies, 95),
            'latency_max_seconds': round(float(max(latencies)), 3) if latencies else 0.0,
            'mapper_busy_share': round(worker.busy_share(), 3),
            'query_p95_ms': _percentile(self.query_seconds, 95, 1e3, 1),
            'mapping_pid': worker.process_id or 0,
            'recent_window_seconds': window,
            **{f'recent_{kind}': sum(1 for _, k, _ in recent if k == kind) for kind in WARN_EVENTS},
            'last_error': recent[-1][2] if recent else '',
            'last_error_age_seconds': round(time.monotonic() - recent[-1][0], 1) if recent else -1,
        })
        message = ('mapping' if not recent else
                   f'{len(recent)} drops, rejections or failures in the last {window:g} s (see values)')
        return values, 1 if recent else 0, message

    def summary(self, worker: Any, gate: Any, period: float) -> str | None:
        """The line of what happened since the last one (None when nothing did): clouds in,
        queued (placed and handed to the mapper), mapped (taken into the map), waiting,
        dropped, rejected and why, the selection's share, the map's size."""
        with self.lock:
            interval, self.interval = self.interval, _new_interval()
            waiting = gate.waiting()[0]
        snap = worker.snapshot
        mapped = worker.counters['clouds_mapped'] + self.counters['clouds_no_building']  # as /diagnostics
        version, before = self._summary
        if not interval['in'] and not interval['queued'] and not interval['rejected'] \
                and snap.version == version and mapped == before:
            return None
        self._summary = (snap.version, mapped)
        rejected = sum(interval['rejected'].values())
        why = '; '.join(f'{n} {kind}' for kind, n in interval['rejected'].most_common(3))
        parts = [f'last {period:g} s: {interval["in"]} clouds in, {interval["queued"]} queued, '
                 f'{mapped - before} mapped',
                 f'{waiting} waiting for a transform', f'{interval["dropped"]} dropped',
                 f'{rejected} rejected' + (f' ({why})' if why else '')]
        if interval['non_ground']:
            parts.append(f'the selection kept {interval["selected"] / interval["non_ground"]:.0%} of the non-ground '
                         'points')
        elif interval['points']:
            parts.append(f'{interval["building"] / interval["points"]:.0%} of the points building')
        parts.append(f'map: {snap.buildings} buildings, {len(snap.facades)} façades, {snap.points:,} points')
        return ', '.join(parts)

    def start_summary(self, worker: Any) -> None:
        """The map as the first summary line will compare it (the node's start)."""
        self._summary = (worker.snapshot.version, 0)
