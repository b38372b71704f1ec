"""A tree of timed rigid transforms between named frames, with tf2's BufferCore semantics.

Conventions (those of tf2 and ``geometry_msgs/TransformStamped``):

* An *edge* ``parent -> child`` holds the pose of ``child`` in ``parent``: the transform
  ``(R, t)`` mapping child coordinates into parent coordinates, ``p_parent = R p_child + t``
  (``header.frame_id`` = parent, ``child_frame_id`` = child). Translations are metres,
  rotations unit quaternions ``(x, y, z, w)``.
* Times are integer nanoseconds (UNIX epoch or simulated clock); ``0`` in a lookup means
  "the latest time at which the whole chain is available" (tf2's ``TimePointZero``).
* Each frame has at most one parent, so the frames form a forest. A *dynamic* edge keeps
  timed samples (those within ``cache_time`` of its newest); a *static* edge holds one
  transform valid at every time.
* ``lookup(target, source, t)`` returns the transform taking points in ``source`` to
  ``target`` at time ``t``: it walks both frames up to their lowest common ancestor and
  composes the edges, each dynamic edge interpolated at ``t`` (translation linearly,
  rotation by slerp) between the two samples bracketing ``t``. Outside a dynamic edge's
  samples the lookup fails (:class:`ExtrapolationError`), unless the gap is within
  ``max_extrapolation``, where the nearest sample is held.

Where this differs from tf2 (on purpose):

* A child given a second, different parent is refused (tf2 silently re-parents it); an
  edge added as static and then as dynamic (or the reverse) is refused (tf2 replaces the
  edge's cache); an edge closing a loop is refused at insert (tf2 finds loops at lookup).
* A sample with the stamp of an existing sample replaces it (tf2 keeps both unless they
  are equal; its interpolation then reads one of them).
* ``max_extrapolation`` (default 0, tf2's behaviour) may let lookups hold the first or last
  sample of an edge for a short while.
* Lookups also answer for an interval of times (:meth:`TransformBuffer.can_transform` with
  ``end_ns``) and for many times at once (:meth:`TransformBuffer.lookup_many`).

Errors (all :class:`uncertain_facade_map.errors.TransformError`, an ``InputError``):
:class:`UnknownFrameError`, :class:`ConnectivityError`, :class:`ExtrapolationError` for
lookups; a plain ``TransformError`` for refused transforms.
"""

from __future__ import annotations

import math
import operator
import threading
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from uncertain_facade_map.errors import (
    ConnectivityError,
    ExtrapolationError,
    InputError,
    TransformError,
    UnknownFrameError,
)

from . import rotations as rot

#: A quaternion whose squared norm is further than this from 1 is refused (tf2's rule).
QUATERNION_TOLERANCE = 0.01
#: Deepest chain walked before the tree is declared broken (tf2: MAX_GRAPH_DEPTH = 1000).
MAX_DEPTH = 1000


def _seconds(ns: int) -> str:
    """Nanoseconds as seconds with 3 decimals, for messages."""
    return f'{int(ns) / 1e9:.3f}'


def _norm2(quats: np.ndarray) -> np.ndarray:
    """(K,) squared norms of (K, 4) quaternions (one formula for single and bulk inserts)."""
    with np.errstate(invalid='ignore', over='ignore'):
        return np.einsum('ij,ij->i', quats, quats)


def _strip(name: Any) -> str:
    """Frame name without one leading '/', as tf2 stores it."""
    name = str(name)
    return name[1:] if name.startswith('/') else name


# --------------------------------------------------------------------------------------
# rigid transforms
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Rigid:
    """A rigid transform ``p_out = rotation @ p_in + translation``.

    Attributes:
        rotation: (3, 3) float64 rotation matrix (read-only).
        translation: (3,) float64 translation, metres (read-only).
    """

    rotation: np.ndarray
    translation: np.ndarray

    def __post_init__(self) -> None:
        r = np.array(self.rotation, dtype=np.float64)
        t = np.array(self.translation, dtype=np.float64).reshape(-1)
        if r.shape != (3, 3) or t.shape != (3,):
            raise InputError(f'a rigid transform has a (3, 3) rotation and a (3,) translation, got shapes '
                             f'{r.shape} and {t.shape}')
        r.flags.writeable = False
        t.flags.writeable = False
        object.__setattr__(self, 'rotation', r)
        object.__setattr__(self, 'translation', t)

    @classmethod
    def identity(cls) -> Rigid:
        """The transform that changes nothing."""
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_quaternion(cls, translation: Any, rotation: Any) -> Rigid:
        """From a translation (3,) and a quaternion (4,) ``(x, y, z, w)`` (normalised here)."""
        return cls(rot.to_matrix(np.asarray(rotation, dtype=np.float64)), translation)

    def quaternion(self) -> np.ndarray:
        """(4,) unit quaternion ``(x, y, z, w)`` of the rotation, ``w >= 0``."""
        return rot.from_matrix(self.rotation)

    def matrix(self) -> np.ndarray:
        """(4, 4) homogeneous matrix."""
        out = np.eye(4)
        out[:3, :3] = self.rotation
        out[:3, 3] = self.translation
        return out

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Transform points.

        Args:
            points: (N, 3) or (3,) coordinates in the input frame, metres.

        Returns:
            Same shape, float64, in the output frame.
        """
        p = np.asarray(points, dtype=np.float64)
        return p @ self.rotation.T + self.translation

    def inverse(self) -> Rigid:
        """The transform back: ``a.inverse().apply(a.apply(p)) == p``."""
        rt = self.rotation.T
        return Rigid(rt, -(rt @ self.translation))

    def compose(self, other: Rigid) -> Rigid:
        """``self`` after ``other``: ``a.compose(b).apply(p) == a.apply(b.apply(p))``."""
        return Rigid(self.rotation @ other.rotation, self.rotation @ other.translation + self.translation)


# --------------------------------------------------------------------------------------
# storage of one dynamic edge
# --------------------------------------------------------------------------------------


class _Track:
    """Timed samples of one dynamic edge, sorted by stamp, in growable arrays.

    The valid samples are rows ``lo:hi``; appending in time order is amortised O(1), an
    out-of-order insert shifts the rows after it, pruning moves ``lo``.
    """

    __slots__ = ('stamps', 'xyz', 'quat', 'lo', 'hi')

    def __init__(self, capacity: int = 16) -> None:
        self.stamps = np.zeros(capacity, dtype=np.int64)
        self.xyz = np.zeros((capacity, 3))
        self.quat = np.zeros((capacity, 4))
        self.lo = self.hi = 0

    def __len__(self) -> int:
        return self.hi - self.lo

    def view(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(n,) stamps, (n, 3) translations, (n, 4) quaternions (views, do not modify)."""
        return self.stamps[self.lo:self.hi], self.xyz[self.lo:self.hi], self.quat[self.lo:self.hi]

    @property
    def first(self) -> int:
        return int(self.stamps[self.lo])

    @property
    def last(self) -> int:
        return int(self.stamps[self.hi - 1])

    def _reserve(self, extra: int) -> None:
        """Room for ``extra`` more rows after ``hi``: compact to the front, or grow."""
        n = len(self)
        cap = self.stamps.shape[0]
        if self.hi + extra <= cap:
            return
        if n + extra <= cap // 2:  # enough room once the pruned rows at the front are reused
            new_cap = cap
        else:
            new_cap = max(2 * cap, n + extra)
        stamps = np.zeros(new_cap, dtype=np.int64)
        xyz = np.zeros((new_cap, 3))
        quat = np.zeros((new_cap, 4))
        stamps[:n], xyz[:n], quat[:n] = self.view()
        self.stamps, self.xyz, self.quat = stamps, xyz, quat
        self.lo, self.hi = 0, n

    def insert(self, stamp: int, xyz: np.ndarray, quat: np.ndarray) -> None:
        """Insert one sample in order; a sample with an existing stamp replaces it."""
        if len(self) == 0 or stamp > self.stamps[self.hi - 1]:
            self._reserve(1)
            i = self.hi
            self.hi += 1
        else:
            i = self.lo + int(np.searchsorted(self.stamps[self.lo:self.hi], stamp))
            if self.stamps[i] != stamp:
                if i == self.lo and self.lo > 0:
                    self.lo -= 1
                    i = self.lo
                else:
                    self._reserve(1)
                    i = self.lo + int(np.searchsorted(self.stamps[self.lo:self.hi], stamp))
                    sl, dst = slice(i, self.hi), slice(i + 1, self.hi + 1)
                    self.stamps[dst], self.xyz[dst], self.quat[dst] = (
                        self.stamps[sl].copy(), self.xyz[sl].copy(), self.quat[sl].copy())
                    self.hi += 1
        self.stamps[i], self.xyz[i], self.quat[i] = stamp, xyz, quat

    def merge(self, stamps: np.ndarray, xyz: np.ndarray, quat: np.ndarray) -> None:
        """Insert many samples (any order); on equal stamps the later one (batch order) wins."""
        old_s, old_x, old_q = self.view()
        all_s = np.concatenate([old_s, stamps])
        order = np.argsort(all_s, kind='stable')
        s_sorted = all_s[order]
        keep = np.ones(s_sorted.shape[0], dtype=bool)
        keep[:-1] = s_sorted[1:] != s_sorted[:-1]  # the last of each run of equal stamps
        pick = order[keep]
        n = pick.shape[0]
        cap = max(16, 1 << int(math.ceil(math.log2(n + 1))))
        self.stamps = np.zeros(cap, dtype=np.int64)
        self.xyz = np.zeros((cap, 3))
        self.quat = np.zeros((cap, 4))
        self.stamps[:n] = all_s[pick]
        self.xyz[:n] = np.concatenate([old_x, xyz])[pick]
        self.quat[:n] = np.concatenate([old_q, quat])[pick]
        self.lo, self.hi = 0, n

    def prune(self, keep_ns: int | None, max_samples: int | None = None) -> None:
        """Drop samples older than ``newest - keep_ns`` (tf2's TimeCache::pruneList), and
        the oldest beyond ``max_samples``."""
        if len(self) == 0:
            return
        if keep_ns is not None:
            cutoff = self.last - keep_ns
            self.lo += int(np.searchsorted(self.stamps[self.lo:self.hi], cutoff, side='left'))
        if max_samples is not None and len(self) > max_samples:
            self.lo = self.hi - max_samples


# --------------------------------------------------------------------------------------
# the buffer
# --------------------------------------------------------------------------------------


@dataclass
class _Chain:
    """The edges between two frames: children walked up from each side to the common ancestor."""

    target: str
    source: str
    up_source: list[str] = field(default_factory=list)  # source, parent(source), ... (below common)
    up_target: list[str] = field(default_factory=list)
    common: str = ''

    def edges(self) -> list[str]:
        return self.up_source + self.up_target


class TransformBuffer:
    """Timed transforms between named frames, looked up along the frame tree (tf2 semantics).

    Thread-safe: every method holds the buffer's lock.

    Args:
        cache_time: seconds of history kept per dynamic edge: on every insert, samples
            older than the edge's newest minus ``cache_time`` are dropped (tf2's TimeCache,
            default 10 s). ``math.inf`` keeps everything (offline tools preloading a bag).
        max_extrapolation: seconds a lookup may reach before the first or after the last
            sample of a dynamic edge, answered by holding that sample. tf2: 0 (never).
        max_samples: samples kept per dynamic edge at most, the newest (None: no limit
            besides ``cache_time``); bounds the memory of an edge published very often (1:
            the newest only, which answers its own stamp or, held, ``max_extrapolation``).

    Raises:
        InputError: ``cache_time`` not > 0, ``max_extrapolation`` negative or NaN, or
            ``max_samples`` < 1.
    """

    def __init__(self, cache_time: float = 10.0, max_extrapolation: float = 0.0,
                 max_samples: int | None = None) -> None:
        cache_time = float(cache_time)
        max_extrapolation = float(max_extrapolation)
        if not cache_time > 0:
            raise InputError(f'cache_time must be > 0 s (math.inf keeps all samples), got {cache_time}')
        if not max_extrapolation >= 0:
            raise InputError(f'max_extrapolation must be >= 0 s, got {max_extrapolation}')
        if max_samples is not None and not int(max_samples) >= 1:
            raise InputError(f'max_samples must be >= 1, got {max_samples}')
        self.cache_time = cache_time
        self.max_extrapolation = max_extrapolation
        self.max_samples = None if max_samples is None else int(max_samples)
        self._keep_ns: int | None = None if math.isinf(cache_time) else int(round(cache_time * 1e9))
        self._hold_ns: float = math.inf if math.isinf(max_extrapolation) else int(round(max_extrapolation * 1e9))
        self._lock = threading.RLock()
        self._parent: dict[str, str] = {}
        self._static: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}  # child -> (t, q, R)
        self._tracks: dict[str, _Track] = {}

    # ------------------------------------------------------------------ inserting

    def _names(self, parent: Any, child: Any) -> tuple[str, str]:
        """Stripped names, or TransformError for empty or equal ones."""
        p, c = _strip(parent), _strip(child)
        if not p or not c:
            raise TransformError(f'transform with an empty frame name (parent "{parent}", child "{child}"): '
                                 f'header.frame_id and child_frame_id must both be set')
        if p == c:
            raise TransformError(f'transform from frame "{c}" to itself: the parent and child frames must differ')
        return p, c

    def _tree_check(self, p: str, c: str, static: bool, parents: dict[str, str]) -> None:
        """TransformError if ``p -> c`` breaks the tree or changes the edge's kind."""
        old = parents.get(c)
        if old is not None and old != p:
            raise TransformError(
                f'frame "{c}" already has parent "{old}"; a transform giving it parent "{p}" is refused: '
                f'the frames form a tree, each frame has one parent (to place "{c}" under "{p}", publish '
                f'"{p}" -> "{old}" instead)')
        if old is None:
            frame, depth = p, 0
            while frame in parents and depth <= MAX_DEPTH:
                if frame == c:
                    break
                frame, depth = parents[frame], depth + 1
            if frame == c:
                raise TransformError(f'transform "{p}" -> "{c}" would close a loop: "{c}" is already an ancestor of '
                                     f'"{p}"')
        elif static and c in self._tracks:
            raise TransformError(f'static transform "{p}" -> "{c}" refused: that edge already has dynamic samples '
                                 f'(send it on /tf or on /tf_static, not both)')
        elif not static and c in self._static:
            raise TransformError(f'dynamic transform "{p}" -> "{c}" refused: that edge is static '
                                 f'(send it on /tf or on /tf_static, not both)')

    @staticmethod
    def _stamp(stamp_ns: Any) -> int:
        try:
            stamp = operator.index(stamp_ns)
        except TypeError:
            raise TransformError(f'stamp {stamp_ns!r} is not an integer number of nanoseconds') from None
        if stamp < 0:
            raise TransformError(f'stamp {stamp} ns is negative')
        return int(stamp)

    @staticmethod
    def _values(p: str, c: str, translation: Any, rotation: Any) -> tuple[np.ndarray, np.ndarray]:
        """Finite (3,) translation and normalised (4,) quaternion, or TransformError."""
        try:
            t = np.array(translation, dtype=np.float64).reshape(-1)  # copies: the caller keeps theirs
            q = np.array(rotation, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError) as err:
            raise TransformError(f'transform "{p}" -> "{c}" has non-numeric values: {err}') from None
        if t.shape != (3,) or q.shape != (4,):
            raise TransformError(f'transform "{p}" -> "{c}" needs a translation of 3 values and a quaternion of 4, '
                                 f'got {t.shape[0]} and {q.shape[0]}')
        if not (np.isfinite(t).all() and np.isfinite(q).all()):
            raise TransformError(f'transform "{p}" -> "{c}" has NaN or infinite values: translation {t.tolist()}, '
                                 f'rotation {q.tolist()}')
        norm2 = float(_norm2(q[None])[0])
        if abs(norm2 - 1.0) > QUATERNION_TOLERANCE:
            raise TransformError(f'transform "{p}" -> "{c}" has quaternion (x, y, z, w) = {tuple(q.tolist())} of '
                                 f'squared norm {norm2:.4g}, not within {QUATERNION_TOLERANCE} of 1: not a rotation')
        return t, q / np.sqrt(norm2)

    def set_transform(self, parent: str, child: str, stamp_ns: int, translation: Any, rotation: Any, *,
                      static: bool = False) -> None:
        """Add one transform: the pose of ``child`` in ``parent`` at ``stamp_ns``.

        Args:
            parent: parent frame (``header.frame_id``); a leading '/' is dropped.
            child: child frame (``child_frame_id``); a leading '/' is dropped.
            stamp_ns: integer nanoseconds >= 0 (ignored for static transforms).
            translation: (3,) metres, ``p_parent = R p_child + translation``.
            rotation: (4,) quaternion ``(x, y, z, w)``; squared norm within 0.01 of 1
                (normalised here).
            static: True for a transform valid at every time (``/tf_static``); it replaces
                the edge's previous static transform and is never pruned.

        Raises:
            TransformError: empty names, parent == child, NaN or infinite values, a
                quaternion off unit length, ``child`` already with another parent, a loop,
                a static sample for a dynamic edge or the reverse, a non-integer or negative
                stamp, or a dynamic sample older than the edge's newest minus ``cache_time``
                (tf2's TF_OLD_DATA).
        """
        p, c = self._names(parent, child)
        stamp = self._stamp(stamp_ns)
        t, q = self._values(p, c, translation, rotation)
        with self._lock:
            self._tree_check(p, c, static, self._parent)
            if static:
                self._static[c] = (t, q, rot.to_matrix(q))
            else:
                track = self._tracks.get(c)
                if track is None:
                    track = self._tracks[c] = _Track()
                elif self._keep_ns is not None and len(track) and stamp < track.last - self._keep_ns:
                    raise TransformError(
                        f'transform "{p}" -> "{c}" at {_seconds(stamp)} s is older than the cache keeps '
                        f'({self.cache_time:g} s before the newest sample, {_seconds(track.last)} s): ignored')
                track.insert(stamp, t, q)
                track.prune(self._keep_ns, self.max_samples)
            self._parent[c] = p

    def set_transforms(self, parents: str | Sequence[str], children: str | Sequence[str], stamps_ns: Any,
                       translations: Any, rotations: Any, *, static: bool = False, strict: bool = True,
                       refused: list[str] | None = None) -> int:
        """Add many transforms at once (a bag's /tf): validated in bulk, then merged per edge.

        The end state is that of calling :meth:`set_transform` for the accepted samples in
        time order: on equal stamps of one edge the later sample (in array order) wins; a
        static edge keeps its last transform; samples older than ``cache_time`` before
        their edge's newest are pruned (and counted as accepted, as tf2 accepts then prunes
        them when they come in time order). The tree rules are applied to the edges in the
        order of their first valid sample.

        Args:
            parents, children: (K,) frame names, or one name for all K.
            stamps_ns: (K,) integer nanoseconds >= 0.
            translations: (K, 3) metres.
            rotations: (K, 4) quaternions ``(x, y, z, w)``.
            static: all K are static transforms.
            strict: True (default): raise on the first bad transform and add none.
                False: skip the bad ones and add the rest.
            refused: with ``strict=False``, a list to which ``'index: reason'`` is appended
                for each skipped transform.

        Returns:
            The number of transforms accepted.

        Raises:
            TransformError: (strict) the first bad transform, with its index and why (the
                rules of :meth:`set_transform`); the buffer is then unchanged.
            InputError: arrays of the wrong shapes or lengths, stamps not integers.
        """
        stamps = np.asarray(stamps_ns)
        if stamps.ndim != 1:
            raise InputError(f'stamps_ns must be one-dimensional, got shape {stamps.shape}')
        k = stamps.shape[0]
        if k and stamps.dtype.kind not in 'iu':
            raise InputError(f'stamps_ns must be integer nanoseconds, got {stamps.dtype}')
        stamps = stamps.astype(np.int64, copy=False)
        trans = np.asarray(translations, dtype=np.float64)
        quats = np.asarray(rotations, dtype=np.float64)
        if trans.shape != (k, 3) or quats.shape != (k, 4):
            raise InputError(f'{k} stamps need translations (K, 3) and rotations (K, 4), got shapes {trans.shape} '
                             f'and {quats.shape}')
        one_p, one_c = isinstance(parents, str), isinstance(children, str)
        if one_p and one_c:
            pair_of = [(parents, children)]
            codes = np.zeros(k, dtype=np.int64)
        else:
            ps = [parents] * k if one_p else list(parents)
            cs = [children] * k if one_c else list(children)
            if len(ps) != k or len(cs) != k:
                raise InputError(f'{k} stamps need {k} parents and children, got {len(ps)} and {len(cs)}')
            index: dict[tuple[str, str], int] = {}
            codes = np.fromiter((index.setdefault(pc, len(index)) for pc in zip(ps, cs)), dtype=np.int64, count=k)
            pair_of = list(index)

        # the numbers, vectorised
        finite = np.isfinite(trans).all(axis=1) & np.isfinite(quats).all(axis=1)
        norm2 = _norm2(quats)
        bad_num = ~finite | ~(np.abs(norm2 - 1.0) <= QUATERNION_TOLERANCE) | (stamps < 0)

        with self._lock:
            # the names and the tree, once per distinct pair, in order of first valid sample
            n_pairs = len(pair_of)
            first_ok = np.full(n_pairs, k, dtype=np.int64)
            ok_rows = np.flatnonzero(~bad_num)
            if ok_rows.size:
                seen, where = np.unique(codes[ok_rows], return_index=True)
                first_ok[seen] = ok_rows[where]
            parents_now = dict(self._parent)
            names_of: list[tuple[str, str] | None] = [None] * n_pairs
            error_of: list[str | None] = [None] * n_pairs
            for code in np.argsort(first_ok, kind='stable').tolist():
                try:
                    p, c = self._names(*pair_of[code])
                    if first_ok[code] < k:  # only an edge with a valid sample shapes the tree
                        self._tree_check(p, c, static, parents_now)
                        parents_now[c] = p
                except TransformError as err:
                    error_of[code] = str(err)
                else:
                    names_of[code] = (p, c)
            bad_pair = np.array([e is not None for e in error_of], dtype=bool)
            bad = bad_num | bad_pair[codes]
            if bad.any():
                rows = np.flatnonzero(bad)
                why = lambda i: self._why(i, codes, pair_of, error_of, stamps, trans, quats)  # noqa: E731
                if strict:
                    i = int(rows[0])
                    raise TransformError(f'transform {i} of {k}: {why(i)}')
                if refused is not None:
                    refused.extend(f'{i}: {why(i)}' for i in rows.tolist())
            good = np.flatnonzero(~bad)
            if good.size == 0:
                return 0
            quats_good = quats[good] / np.sqrt(norm2[good])[:, None]
            codes_good = codes[good]
            by_code = np.argsort(codes_good, kind='stable')
            bounds = np.flatnonzero(np.diff(codes_good[by_code])) + 1
            for rows in np.split(by_code, bounds):
                p, c = names_of[int(codes_good[rows[0]])]
                if static:
                    last = rows[-1]
                    q = quats_good[last]
                    self._static[c] = (trans[good[last]].copy(), q, rot.to_matrix(q))
                else:
                    track = self._tracks.get(c)
                    if track is None:
                        track = self._tracks[c] = _Track()
                    track.merge(stamps[good[rows]], trans[good[rows]], quats_good[rows])
                    track.prune(self._keep_ns, self.max_samples)
                self._parent[c] = p
            return int(good.size)

    @staticmethod
    def _why(i: int, codes: np.ndarray, pair_of: list, error_of: list, stamps: np.ndarray, trans: np.ndarray,
             quats: np.ndarray) -> str:
        """Reason transform ``i`` of a batch is refused."""
        err = error_of[codes[i]]
        if err is not None:
            return err
        raw_p, raw_c = pair_of[codes[i]]
        p, c = _strip(raw_p), _strip(raw_c)
        if stamps[i] < 0:
            return f'transform "{p}" -> "{c}" has a negative stamp {int(stamps[i])} ns'
        try:
            TransformBuffer._values(p, c, trans[i], quats[i])
        except TransformError as exc:
            return str(exc)
        return 'refused'  # pragma: no cover - every bad row has a reason above

    # ------------------------------------------------------------------ reading the tree

    def frames(self) -> dict[str, str]:
        """Every edge as ``{child: parent}``."""
        with self._lock:
            return dict(self._parent)

    def _known(self) -> set[str]:
        return set(self._parent) | set(self._parent.values())

    def has_frame(self, name: str) -> bool:
        """Whether a transform names ``name`` (as parent or child; a leading '/' is dropped)."""
        name = _strip(name)
        with self._lock:
            return name in self._parent or name in self._parent.values()

    def time_range(self, child: str) -> tuple[int, int] | None:
        """Oldest and newest kept sample of the dynamic edge above ``child``, nanoseconds.

        Returns:
            ``(first_ns, last_ns)``; None when the edge is static or ``child`` is a root (no
            parent: no time limit).

        Raises:
            UnknownFrameError: no transform names ``child``.
        """
        c = _strip(child)
        with self._lock:
            self._require(c)
            track = self._tracks.get(c)
            if track is None:
                return None
            return track.first, track.last

    def clear(self, *, static: bool = False) -> None:
        """Forget every dynamic edge (tf2's ``clear()``, e.g. after the clock jumped back).

        Args:
            static: also forget the static edges (an empty buffer).
        """
        with self._lock:
            for c in list(self._tracks):
                del self._parent[c]
            self._tracks.clear()
            if static:
                self._parent.clear()
                self._static.clear()

    def __repr__(self) -> str:
        with self._lock:
            head = f'TransformBuffer(cache_time={self.cache_time:g} s, max_extrapolation={self.max_extrapolation:g} s'
            if not self._parent:
                return head + '): no transforms'
            kids: dict[str, list[str]] = {}
            for c, p in self._parent.items():
                kids.setdefault(p, []).append(c)
            roots = sorted(set(kids) - set(self._parent))
            lines: list[str] = []

            def label(c: str) -> str:
                track = self._tracks.get(c)
                if track is None:
                    return f'{c} (static)'
                return f'{c} (dynamic, {len(track)} samples, {_seconds(track.first)}-{_seconds(track.last)} s)'

            def walk(frame: str, text: str, col: int) -> None:
                below = sorted(kids.get(frame, []))
                if not below:
                    lines.append(text)
                for j, c in enumerate(below):
                    # a branch repeats only the frame it leaves from, under its first writing
                    prefix = text if j == 0 else ' ' * col + frame
                    walk(c, f'{prefix} -> {label(c)}', len(prefix) + 4)

            for root in roots:
                walk(root, root, 0)
            return head + f', {len(self._known())} frames):\n  ' + '\n  '.join(lines)

    # ------------------------------------------------------------------ lookups

    def _require(self, frame: str) -> None:
        if frame not in self._parent and frame not in self._parent.values():
            known = tuple(sorted(self._known()))
            listing = ', '.join(known) if known else 'none, no transform is known'
            raise UnknownFrameError(f'frame "{frame}" is unknown: no transform names it (known frames: {listing})',
                                    frame=frame, known=known)

    def _chain(self, target: str, source: str) -> _Chain:
        """The edges joining the frames; raises UnknownFrameError or ConnectivityError."""
        self._require(target)
        self._require(source)
        chain = _Chain(target, source)
        up_source = [source]  # source and its ancestors
        frame = source
        while frame in self._parent:
            frame = self._parent[frame]
            up_source.append(frame)
        on_source = {f: i for i, f in enumerate(up_source)}
        frame = target
        while frame not in on_source:
            if frame not in self._parent:
                root_s, root_t = up_source[-1], frame
                raise ConnectivityError(
                    f'frames "{target}" and "{source}" are not connected: "{target}" is in the tree rooted at '
                    f'"{root_t}", "{source}" in the tree rooted at "{root_s}" (a transform joining the two trees '
                    f'is missing)', target=target, source=source, target_root=root_t, source_root=root_s)
            chain.up_target.append(frame)
            frame = self._parent[frame]
        chain.common = frame
        chain.up_source = up_source[:on_source[frame]]
        return chain

    def _latest(self, chain: _Chain) -> int:
        """Latest time at which every dynamic edge of the chain has data (0 if none)."""
        lasts = [self._tracks[c].last for c in chain.edges() if c in self._tracks]
        return min(lasts) if lasts else 0

    def _hold(self, max_extrapolation: float | None) -> float:
        """Nanoseconds a lookup may hold an edge's first or last sample: the buffer's
        ``max_extrapolation``, or the call's when given (seconds, >= 0)."""
        if max_extrapolation is None:
            return self._hold_ns
        if not max_extrapolation >= 0:
            raise InputError(f'max_extrapolation must be >= 0 s, got {max_extrapolation}')
        return math.inf if math.isinf(max_extrapolation) else int(round(max_extrapolation * 1e9))

    def _coverage(self, chain: _Chain, start: int, end: int, count: Any = None,
                  hold_ns: float | None = None) -> ExtrapolationError | None:
        """Error for the first edge lacking data somewhere in ``[start, end]``, or None.

        An edge that would need data before its oldest sample is reported before one that
        only lacks newer data (the former never resolves). ``hold_ns``: as :meth:`_hold`
        (None: the buffer's).
        """
        hold_ns = self._hold_ns if hold_ns is None else hold_ns
        future: ExtrapolationError | None = None
        for c in chain.edges():
            track = self._tracks.get(c)
            if track is None:
                continue
            first, last = track.first, track.last
            if start < first - hold_ns:
                return self._extrapolation(chain, c, start, first, last, False, count, hold_ns)
            if end > last + hold_ns and future is None:
                future = self._extrapolation(chain, c, end, first, last, True, count, hold_ns)
        return future

    def _extrapolation(self, chain: _Chain, c: str, stamp: int, first: int, last: int, is_future: bool,
                       count: Any, hold_ns: float) -> ExtrapolationError:
        p = self._parent[c]
        gap = stamp - last if is_future else first - stamp
        if is_future:
            where = 'after the newest sample (wait for newer data)'
        else:
            kept = f'; cache_time {self.cache_time:g} s' if self._keep_ns is not None else ''
            where = f'before the oldest kept sample (it will not come{kept})'
        if count is not None:
            mask_n, k = count(first, last, is_future)
            at = f'{mask_n} of {k} times, e.g. {_seconds(stamp)} s'
        else:
            at = f'{_seconds(stamp)} s'
        hold = f', max_extrapolation {hold_ns / 1e9:g} s' if hold_ns else ''
        return ExtrapolationError(
            f'lookup of "{chain.source}" in "{chain.target}" at {at} needs "{c}" in "{p}", whose samples span '
            f'{_seconds(first)}-{_seconds(last)} s: {gap / 1e9:.3f} s {where}{hold}',
            frame=c, parent=p, stamp_ns=stamp, first_ns=first, last_ns=last, future=is_future)

    def _edge(self, c: str, stamp: int) -> Rigid:
        """The edge above ``c`` at one time (inside its coverage)."""
        stat = self._static.get(c)
        if stat is not None:
            return Rigid(stat[2], stat[0])
        s, x, q = self._tracks[c].view()
        n = s.shape[0]
        if n == 1:
            return Rigid(rot.to_matrix(q[0]), x[0])
        i = min(max(int(np.searchsorted(s, stamp, side='right')) - 1, 0), n - 2)
        u = min(max(float(stamp - int(s[i])) / float(int(s[i + 1]) - int(s[i])), 0.0), 1.0)
        xyz = (1.0 - u) * x[i] + u * x[i + 1]
        return Rigid(rot.to_matrix(rot.slerp(q[i], q[i + 1], u)), xyz)

    def latest_common_time(self, target: str, source: str) -> int:
        """The time a lookup at 0 uses: the oldest of the newest samples of the chain's dynamic edges.

        Returns:
            Nanoseconds; 0 when the chain is static (or target == source).

        Raises:
            UnknownFrameError, ConnectivityError.
        """
        target, source = _strip(target), _strip(source)
        if target == source:
            return 0
        with self._lock:
            return self._latest(self._chain(target, source))

    def lookup(self, target: str, source: str, stamp_ns: int, *, max_extrapolation: float | None = None) -> Rigid:
        """The transform taking points in ``source`` to ``target`` at ``stamp_ns``.

        Args:
            target: frame the result maps into (e.g. ``map``).
            source: frame the points are in (e.g. the cloud's ``header.frame_id``).
            stamp_ns: integer nanoseconds; 0 = the latest time the whole chain has data.
            max_extrapolation: seconds, this call's instead of the buffer's (None).

        Returns:
            :class:`Rigid` with ``p_target = rotation @ p_source + translation``. The
            identity when ``target == source`` (also for a frame never seen, as tf2).

        Raises:
            UnknownFrameError: a frame no transform names.
            ConnectivityError: the frames are in two separate trees.
            ExtrapolationError: a dynamic edge of the chain has no data at ``stamp_ns``
                (beyond ``max_extrapolation``).
        """
        target, source = _strip(target), _strip(source)
        if target == source:
            return Rigid.identity()
        stamp = int(stamp_ns)
        with self._lock:
            chain = self._chain(target, source)
            if stamp == 0:
                stamp = self._latest(chain)
            err = self._coverage(chain, stamp, stamp, hold_ns=self._hold(max_extrapolation))
            if err is not None:
                raise err
            from_source = Rigid.identity()
            for c in chain.up_source:
                from_source = self._edge(c, stamp).compose(from_source)
            from_target = Rigid.identity()
            for c in chain.up_target:
                from_target = self._edge(c, stamp).compose(from_target)
            return from_target.inverse().compose(from_source)

    def _edges_at(self, c: str, stamps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rotations (K, 3, 3) or (3, 3) and translations (K, 3) or (3,) of the edge above ``c``."""
        stat = self._static.get(c)
        if stat is not None:
            return stat[2], stat[0]
        s, x, q = self._tracks[c].view()
        n = s.shape[0]
        if n == 1:
            return rot.to_matrix(q[0]), x[0]
        i = np.clip(np.searchsorted(s, stamps, side='right') - 1, 0, n - 2)
        s0, s1 = s[i], s[i + 1]
        u = np.clip((stamps - s0).astype(np.float64) / (s1 - s0).astype(np.float64), 0.0, 1.0)
        xyz = (1.0 - u)[:, None] * x[i] + u[:, None] * x[i + 1]
        return rot.to_matrix(rot.slerp(q[i], q[i + 1], u)), xyz

    def lookup_many(self, target: str, source: str, stamps_ns: Any, *,
                    max_extrapolation: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`lookup` at K times, vectorised (one ``searchsorted`` and one slerp per edge).

        Args:
            target, source: frames as in :meth:`lookup`.
            stamps_ns: (K,) integer nanoseconds, any order; each 0 means the latest common
                time.
            max_extrapolation: seconds, this call's instead of the buffer's (None).

        Returns:
            ``(rotations (K, 3, 3), translations (K, 3))`` float64, with
            ``p_target = rotations[k] @ p_source + translations[k]`` at ``stamps_ns[k]``.

        Raises:
            UnknownFrameError, ConnectivityError: as :meth:`lookup`.
            ExtrapolationError: some time lacks data; it names the earliest (before the
                data) or latest (after it) such time and how many of the K times lack it.
            InputError: stamps not a 1-D integer array.
        """
        stamps = np.asarray(stamps_ns)
        if stamps.ndim != 1 or (stamps.size and stamps.dtype.kind not in 'iu'):
            raise InputError(f'stamps_ns must be a 1-D array of integer nanoseconds, got {stamps.dtype} '
                             f'{stamps.shape}')
        stamps = stamps.astype(np.int64, copy=False)
        k = stamps.shape[0]
        target, source = _strip(target), _strip(source)
        if target == source:
            return np.broadcast_to(np.eye(3), (k, 3, 3)).copy(), np.zeros((k, 3))
        with self._lock:
            chain = self._chain(target, source)
            if k == 0:
                return np.zeros((0, 3, 3)), np.zeros((0, 3))
            zero = stamps == 0
            if zero.any():
                stamps = np.where(zero, self._latest(chain), stamps)
            lo, hi = int(stamps.min()), int(stamps.max())
            hold_ns = self._hold(max_extrapolation)

            def count(first: int, last: int, is_future: bool) -> tuple[int, int]:
                bad = stamps > last + hold_ns if is_future else stamps < first - hold_ns
                return int(np.count_nonzero(bad)), k

            err = self._coverage(chain, lo, hi, count, hold_ns)
            if err is not None:
                raise err
            r_s, t_s = self._compose_up(chain.up_source, stamps)
            r_t, t_t = self._compose_up(chain.up_target, stamps)
            if r_t is None:
                rot, trans = r_s, t_s
            else:
                r_ti = np.swapaxes(r_t, -1, -2)
                rot = r_ti if r_s is None else r_ti @ r_s
                trans = np.einsum('...ij,...j->...i', r_ti, (0.0 if t_s is None else t_s) - t_t)
            # always fresh arrays: a static or one-sample chain would otherwise hand out the buffer's own
            return np.array(np.broadcast_to(rot, (k, 3, 3))), np.array(np.broadcast_to(trans, (k, 3)))

    def _compose_up(self, children: list[str], stamps: np.ndarray) -> tuple[Any, Any]:
        """Rotation and translation from the first child's frame to the last one's parent.

        Returns (None, None) for an empty list (the identity, never multiplied); else
        (3, 3) and (3,) while every edge is static, (K, 3, 3) and (K, 3) otherwise.
        """
        r, t = None, None
        for c in children:
            r_e, t_e = self._edges_at(c, stamps)
            if r is None:
                r, t = r_e, t_e
            else:
                r, t = r_e @ r, np.einsum('...ij,...j->...i', r_e, t) + t_e
        return r, t

    def why_not(self, target: str, source: str, stamp_ns: int, end_ns: int | None = None, *,
                max_extrapolation: float | None = None) -> TransformError | None:
        """Why :meth:`lookup` would fail at ``stamp_ns`` (or somewhere up to ``end_ns``), or None.

        Args:
            target, source: frames as in :meth:`lookup`.
            stamp_ns: integer nanoseconds; 0 = the latest common time (``end_ns`` ignored).
            end_ns: last time of an interval (a sweep's span); every time in
                ``[stamp_ns, end_ns]`` must be answerable.
            max_extrapolation: seconds, this call's instead of the buffer's (None).

        Returns:
            The :class:`UnknownFrameError`, :class:`ConnectivityError` or
            :class:`ExtrapolationError` that the lookup would raise; None if it succeeds.

        Raises:
            InputError: ``end_ns < stamp_ns``.
        """
        target, source = _strip(target), _strip(source)
        start = int(stamp_ns)
        end = start if end_ns is None else int(end_ns)
        if end < start and start != 0:
            raise InputError(f'end {_seconds(end)} s is before start {_seconds(start)} s')
        if target == source:
            return None
        with self._lock:
            try:
                chain = self._chain(target, source)
            except TransformError as err:
                return err
            if start == 0:
                start = end = self._latest(chain)
            return self._coverage(chain, start, end, hold_ns=self._hold(max_extrapolation))

    def can_transform(self, target: str, source: str, stamp_ns: int, end_ns: int | None = None, *,
                      max_extrapolation: float | None = None) -> bool:
        """Whether :meth:`lookup` succeeds at ``stamp_ns`` (and at every time up to ``end_ns``)."""
        return self.why_not(target, source, stamp_ns, end_ns, max_extrapolation=max_extrapolation) is None
