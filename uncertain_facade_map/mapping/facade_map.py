"""The whole map: buildings, their façades, and each façade's uncertain surface.

The orchestrator only sees arrays. Per building it extracts façades
(:mod:`~uncertain_facade_map.pipeline.step1_facades`); per façade it runs the rest of the
pipeline (:mod:`~uncertain_facade_map.pipeline.step6_surface`: depth layers and facets,
training points by eqs. 7 and 8, length scales, local GPs in blocks, outliers) onto a
raster. Queries (:mod:`~uncertain_facade_map.pipeline.step7_queries`) read the rasters.

The surface of a façade is d(x) = g(x) + f(x) (paper eq. 2): g = mu_k of the facet's
layer, f the facet's local GP. Where no facet covers a location, the global GP prior
holds: the main layer's mean with the variance of all the façade's depths.

**Incremental mapping** (:meth:`FacadeMap.add_points`): new points go to the façade whose
depth band and grown plane extent hold them (:func:`~uncertain_facade_map.pipeline.step1_facades.assign_to_facades`,
the extraction's own rule); the rest wait in the building's pool, where RANSAC runs again
once the pool has grown enough. A façade's frame and its block grid's anchor never move,
so cells and blocks keep their identity. A façade whose points have grown by
``refit_growth`` since its last whole fit is fitted whole again (layers, length scales,
every block) while that fit had fewer than ``refit_max_points`` points; otherwise only
the blocks whose extended block received a new training point, and the cells whose facet
changed, are recomputed (:func:`update_facade`), so the cost of an update follows the new
data, and :meth:`FacadeMap.flush` fits whole what was updated block by block (the idle
flush of live mapping, the end of a replay). Whole refits of small façades at geometric
steps cost a bounded multiple of ``refit_max_points`` per façade in all.

**Live mapping in two tiers** (:meth:`FacadeMap.store_points`, :meth:`FacadeMap.model_step`):
a cloud is stored at once, at a cost that follows the cloud (labelled, thinned, appended; no
normal, no façade); the per-point reading answers from the stored points from then on. Model
steps then do the rest in bounded pieces: one building's stored points (their normals, seen
from both sides once :data:`MODEL_LAG` later clouds have come, then allocation and the
façade updates), one scan of the comparison, one building's pool. Stored in one go and then
modelled, a drive gives the map :meth:`add_points` builds from it in one batch, bit for bit.

**Copies for free** (:meth:`FacadeMap.clone`): an array the map holds is never written
again; an update replaces it (and the frozen façade models) by new ones. A clone copies
only the containers, so it is cheap, stays as it was while the original maps on, and can
be saved from another thread or put back when an update fails (the live worker does both).

**Bounded memory** (:meth:`FacadeMap._thin`): a building stores at most
``update.store_per_voxel`` points per cubic voxel of side ``update.store_voxel`` (map
frame), the first to arrive, and with ``update.store_spacing`` > 0 none within that
distance of a stored point; a new point that is not stored is counted
(:attr:`FacadeMap.thinned`) and goes no further. Driving the same street again therefore
stops growing the stored points, the per-building arrays, the façades' point indices and
the work of an update once the voxels are full; with the spacing, from the second pass on
(it samples the walls near the same spots). The rule depends only on
the order of the points, not on how they are cut into calls, so the live map (many calls)
and the offline build (one call) store the same points.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from ..datatypes import ExtractedFacade, FacadeFrame, FacadeModel
from ..errors import InputError
from ..params import MapParams, QueryConfig
from ..pipeline.step1_facades import (
    STOREY_OFFSET,
    _final_frame,
    _plane_box,
    _point_normals,
    assign_to_facades,
    building_cells,
    check_building_ids,
    extract_facades,
    side_by_side,
    split_buildings,
)
from ..pipeline.step4_gp_blocks import in_sorted
from ..pipeline.step6_surface import _extent, fit_facade, update_facade
from ..pipeline.step7_local_surface import LocalSurface, for_query
from ..pipeline.step7_queries import PointQuery, query_map
from ..pipeline.step8_occupancy import FIXED, PLSC
from ..threads import one_blas_thread
from ..voxels import near_keys, wrapped_keys
from ._storage_kernel import store, voxel_groups
from .calibration import (
    HeldOut,
    Settings,
    fit_free_space,
    fit_occupancy,
    hold_out,
    ray_step,
    registration_variance,
    scan_disagreement,
    scans_to_compare,
)

#: Points of the other buildings at most that turn the normals of a wall without sensor origins.
_CONTEXT_POINTS = 20_000
#: A full update comes at the latest after this many batches (``update.batch_points``) of
#: received points, however few were stored (a parked car's scans: the comparison's queue
#: stays bounded).
FULL_AFTER_RECEIVED = 10
#: Points of a cloud stored by :meth:`FacadeMap.store_points` that wait for the scan
#: comparison at most (a seeded draw; it reads a few hundred of each scan against the others).
REGISTRATION_SCAN_POINTS = 8000
#: Clouds stored by :meth:`FacadeMap.store_points` whose points wait for later ones before a
#: model step models them (their normals then see the points around them on both sides, not
#: only those stored before them), unless :meth:`FacadeMap.flush` models everything.
MODEL_LAG = 3
#: A building's stored points are modelled once ``update.step_points`` of them wait (a whole
#: piece: an update solves again every block near a new training point and reads the whole
#: façade, so small pieces cost nearly as much as large ones: one lap of the simulated street
#: kept up cloud by cloud cost 66 CPU s with pieces from 5,000 points, 30 s from 20,000) ...
MODEL_MAX_WAIT = 100
#: Calls of :meth:`FacadeMap.store_points` a due full round (the scan comparison, then the
#: pools: RANSAC for new façades) waits behind ready pieces of stored points at most; then,
#: while clouds keep coming, the round's pieces take every other model step. Without it a
#: drive that never pauses never had its full round, and no new façade until it stopped (the
#: simulated residential drive replayed for 2 minutes: 4 of 48 façades the whole time).
ROUND_MAX_WAIT = 10


@dataclass(frozen=True, eq=False)
class _FacadePoints:
    """A façade's points as its last update read them (:meth:`FacadeMap._extracted_for_update`).

    Attributes:
        frame, relief, layers: the façade's, when they were read (identity tells a whole
            refit, which changes them).
        index: (N,) sorted building indices of the points.
        uvd: (N, 3) their (u, v, d) in ``frame``, metres.
        cos: (N,) |cos| of the angle between each point's normal and the façade normal.
        depth: (N,) depth from the relief, ``d - relief(u, v)``, metres.
        labels: (N,) int64 most responsible layer of each depth.
    """

    frame: FacadeFrame
    relief: object
    layers: object
    index: np.ndarray
    uvd: np.ndarray
    cos: np.ndarray
    depth: np.ndarray
    labels: np.ndarray


@dataclass(eq=False)
class FacadeMap:
    """Façade models of all buildings, built incrementally from building points.

    Attributes:
        params: modelling parameters.
        map_origin: (3,) georeference of the map frame, metres.
        facades: all façade models; ``facades[i].facade_id == i``; ids never change.
        points: per building label, the building's points (N, 3), metres, map frame.
        sensor_origins: per building label, (N, 3) sensor origins or None.
        normals: per building label, (N, 3) unit point normals (sign arbitrary).
        pool_checked: per building label, the number of unallocated points at the last
            RANSAC run on them.
        last_update: what the last :meth:`add_points` did: ``buildings``, ``facades_new``,
            ``facades_refitted`` (whole), ``facades_updated`` (blocks only),
            ``updated_cells``, ``seconds`` and ``registration_seconds`` (of those, comparing the
            new scans with the stored points).
        pending: points held back by ``add_points(..., defer=True)``, in arrival order:
            (xyz, building_id or None, sensor_origins or None) per call.
        thinned: per building label, the number of its points counted but not stored
            (their voxel of ``update.store_voxel`` already held ``update.store_per_voxel``).
        occupancy_: the occupancy's PLSC parameters learnt from the map's own scans
            (:meth:`calibrate_occupancy`), or the fixed formula's.
        occupancy_stored_: points stored at the last calibration (0: never calibrated).
        registration_sums_: (3,) running sums of how far each new scan's points lie off the
            other scans' local reading (:func:`~uncertain_facade_map.mapping.calibration.scan_disagreement`):
            points compared, their squared signed distances and the reading's predicted
            variances (m^2).
        registration_var_: the variance of scan-to-scan disagreement (pose and registration
            noise) learnt from those sums, m^2, added to every answer's variance
            (:func:`~uncertain_facade_map.mapping.calibration.registration_variance`; 0 until
            enough overlap between scans was seen, or with ``update.registration_points`` 0).
            One value for the whole map: registration errors belong to scans, not buildings.
    """

    params: MapParams = field(default_factory=MapParams)
    map_origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    facades: list[FacadeModel] = field(default_factory=list)
    points: dict[int, np.ndarray] = field(default_factory=dict)
    sensor_origins: dict[int, np.ndarray | None] = field(default_factory=dict)
    normals: dict[int, np.ndarray] = field(default_factory=dict)
    pool_checked: dict[int, int] = field(default_factory=dict)
    last_update: dict = field(default_factory=dict)
    pending: list[tuple[np.ndarray, np.ndarray | None, np.ndarray | None]] = field(default_factory=list)
    thinned: dict[int, int] = field(default_factory=dict)
    occupancy_: PLSC = FIXED
    occupancy_stored_: int = 0
    registration_sums_: np.ndarray = field(default_factory=lambda: np.zeros(3))
    registration_var_: float = 0.0
    #: Scans held for the next comparison (:meth:`_learn_registration`): (xyz (N, 3), scan
    #: labels (N,)) per update, compared together once ``update.batch_points`` of them wait
    #: (or at :meth:`flush`), against the stored points as they stood before the first of them.
    _registration_queue: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list, init=False, repr=False)
    #: The stored points (per building label, the arrays, shared) before the queued scans came.
    _registration_base: dict[int, np.ndarray] | None = field(default=None, init=False, repr=False)
    #: Building points mapped before the queued scans (the seed of the comparison's draw).
    _registration_mapped: int = field(default=0, init=False, repr=False)
    #: Points stored since the last full update (see ``map_now`` in :meth:`add_points`).
    _since_full: int = field(default=0, init=False, repr=False)
    #: Points received (stored or not) since the last full update.
    _received_since_full: int = field(default=0, init=False, repr=False)
    #: Buildings that received points since their pool was last looked at (in a full update).
    _unchecked: set[int] = field(default_factory=set, init=False, repr=False)
    #: Per building label, (lo (3,), hi (3,)) bounds of its stored points, metres, map frame.
    _bounds: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict, init=False, repr=False)
    #: Per building label, its occupied storage voxels: (V,) sorted int64 keys and (V,) int32
    #: counts of stored points (rebuilt from ``points`` when missing, e.g. after loading).
    _voxels: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict, init=False, repr=False)
    #: Per façade id, what an update reads of each of its points and that does not change
    #: while its frame, relief and layers stay (:class:`_FacadePoints`): computed for the new
    #: points only (rebuilt when missing, e.g. after loading, or after a whole refit).
    _facade_points: dict[int, _FacadePoints] = field(default_factory=dict, init=False, repr=False)
    #: Per building label, the first of its stored rows that :meth:`store_points` stored and no
    #: model step has allocated yet (in the order the buildings received them).
    _unmodelled: dict[int, int] = field(default_factory=dict, init=False, repr=False)
    #: Per building label, its number of stored rows before each of the latest
    #: :data:`MODEL_LAG` calls of :meth:`store_points` (oldest first): :meth:`model_step`
    #: leaves the rows those calls stored for later.
    _recent: list[dict[int, int]] = field(default_factory=list, init=False, repr=False)
    #: Calls of :meth:`store_points` so far, and per building the count when its oldest
    #: unmodelled row was stored.
    _stores: int = field(default=0, init=False, repr=False)
    _unmodelled_since: dict[int, int] = field(default_factory=dict, init=False, repr=False)
    #: Buildings whose pools a started full round still has to look at (:meth:`model_step`).
    _pools_due: list[int] = field(default_factory=list, init=False, repr=False)
    #: ``_stores`` when a full round became due behind ready pieces (None: not waiting), when
    #: the round under way started, and whether the round took the last contested step.
    _round_due_since: int | None = field(default=None, init=False, repr=False)
    _round_started: int = field(default=0, init=False, repr=False)
    _round_turn: bool = field(default=False, init=False, repr=False)
    #: The scan comparison under way in pieces (:meth:`_start_registration`), or None.
    _registration_round: tuple | None = field(default=None, init=False, repr=False)

    def add_points(self, xyz: np.ndarray, building_id: np.ndarray | None = None,
                   sensor_origins: np.ndarray | None = None,
                   progress: Callable[[int, int], None] | None = None, defer: bool = False,
                   scan: np.ndarray | None = None, map_now: bool = False) -> list[int]:
        """Add building points and update the façades they touch.

        Args:
            xyz: (N, 3) building points, metres, map frame.
            building_id: (N,) building labels (negative: none), or None to cluster; points
                without a label join the mapped building whose cells they touch, or form
                new buildings.
            sensor_origins: (N, 3) sensor origins, or None.
            progress: called with (buildings updated, buildings to update) after each one.
            defer: hold the points back (:attr:`pending`) until ``update.batch_points``
                points are pending, then map them all in one update (live mapping; see
                :meth:`flush`). The map then depends only on the sequence of calls, not
                on their timing. Each call held back is one scan. The occupancy's PLSC
                parameters are not learnt here (it builds a second map): :meth:`flush`
                learns them when the stored points have doubled.
            scan: (N,) int scan label of each point when the call holds several scans
                (e.g. the two lidars of a car), or None: the call is one scan. Each scan's
                points are compared with the other scans' and the stored points where they
                overlap (:attr:`registration_var_`). Not with ``defer`` (a call is a scan).
            map_now: with ``defer``, map the points held back now, however few (live mapping
                when nothing waits behind this cloud: its points are queryable at once; under
                load the batches grow with the backlog, up to ``update.batch_points``). Such
                an update allocates the points to the façades and updates those; once
                ``update.batch_points`` points have been stored since the last full update
                (points landing in full voxels are not: new information, not the sensor's
                rate, sets the pace; at the latest after :data:`FULL_AFTER_RECEIVED` batches
                received), or at :meth:`flush`, an update is a full one: it also looks for new façades in
                the buildings' pools (RANSAC) and compares the scans with the stored points
                (:attr:`registration_var_`). So new façades are extracted from as many
                points as with fixed batches (small pools give partial walls that stay
                façades of their own), and the comparison's cost follows the points, not
                the number of updates; the points of a wall with no façade yet are stored,
                and the per-point reading answers there.

        Returns:
            The labels of the buildings updated (none while points are held back).

        Raises:
            InputError: empty input, wrong shapes or non-finite coordinates (checked
                before anything changes).
        """
        xyz, building_id, sensor_origins = self._checked(xyz, building_id, sensor_origins)
        if scan is not None:
            scan = np.asarray(scan)
            if defer:
                raise InputError('scan labels go with one add_points call holding several scans, not with defer '
                                 '(each deferred call is one scan)')
            if scan.shape != (len(xyz),) or not np.issubdtype(scan.dtype, np.integer):
                raise InputError(f'scan must be (N,) integer labels for the {len(xyz)} points, got {scan.dtype} '
                                 f'{scan.shape}')
        if defer:
            self.pending.append((xyz, building_id, sensor_origins))
            if self.n_pending < self.params.update.batch_points and not map_now:
                return []
            # A full update once update.batch_points points have come since the last one (_add_points).
            return self._map_pending(progress, compare=False)
        if self.pending:
            self.pending.append((xyz, building_id, sensor_origins))
            return self._map_pending(progress, scan)
        return self._add(xyz, building_id, sensor_origins, progress, scan)

    # -- the two tiers of live mapping -----------------------------------------------------
    def store_points(self, xyz: np.ndarray, building_id: np.ndarray | None = None,
                     sensor_origins: np.ndarray | None = None) -> list[int]:
        """Store a cloud's building points at once and leave their modelling to
        :meth:`model_step` (live mapping's first tier: the points are in :attr:`points`, and
        the per-point reading answers from them, as soon as this returns).

        The points are labelled, thinned and appended (with their normals) exactly as
        :meth:`add_points` does, and queued for the scan comparison as one scan. Their cost
        follows the cloud, not the map: no façade is touched.

        Args:
            xyz: (N, 3) building points, metres, map frame.
            building_id: (N,) building labels (negative: none), or None to cluster.
            sensor_origins: (N, 3) sensor origins, or None.

        Returns:
            The labels of the buildings that stored points.

        Raises:
            InputError: empty input, wrong shapes or non-finite coordinates (checked
                before anything changes).
        """
        xyz, building_id, sensor_origins = self._checked(xyz, building_id, sensor_origins)
        if self.pending:  # points held back by add_points(defer=True) come first
            self._map_pending(compare=False)
        with one_blas_thread():
            # A bounded draw of the cloud waits for the comparison (its pieces then cost a
            # bounded time however far the second tier lags).
            cap = REGISTRATION_SCAN_POINTS
            sample = xyz if len(xyz) <= cap else \
                xyz[np.sort(np.random.default_rng([self.params.seed, self.n_points]).choice(len(xyz), cap, False))]
            self._queue_registration(sample, None)
            labels = self._labels(xyz, building_id)
            stored, thinned = [], 0
            self._recent = [*self._recent[-(MODEL_LAG - 1):], {b: len(p) for b, p in self.points.items()}] \
                if MODEL_LAG > 0 else []
            for b in (int(v) for v in np.unique(labels)):
                sel = np.flatnonzero(labels == b)
                keep = sel[self._thin(b, xyz[sel])]
                thinned += len(sel) - len(keep)
                if len(keep) or b not in self.points:
                    first = self._append(b, xyz[keep], None if sensor_origins is None else sensor_origins[keep],
                                         with_normals=False)
                    if len(keep):
                        self._unmodelled.setdefault(b, first)
                        self._unmodelled_since.setdefault(b, self._stores)
                        stored.append(b)
            self._stores += 1
        self._since_full += len(xyz) - thinned
        self._received_since_full += len(xyz)
        return stored

    @property
    def unmodelled_rows(self) -> dict[int, int]:
        """Per building label, its first stored row not modelled yet (:meth:`store_points`)."""
        return dict(self._unmodelled)

    @unmodelled_rows.setter
    def unmodelled_rows(self, rows: dict[int, int]) -> None:
        for b, first in rows.items():
            if b not in self.points or not 0 <= first <= len(self.points[b]):
                raise InputError(f'unmodelled rows of building {b}: {first} is not a row of its '
                                 f'{len(self.points.get(b, ()))} stored points')
        self._unmodelled = {b: first for b, first in rows.items() if first < len(self.points[b])}

    @property
    def n_unmodelled(self) -> int:
        """Stored points no model step has allocated yet (:meth:`store_points`)."""
        return int(sum(len(self.points[b]) - first for b, first in self._unmodelled.items()))

    def _model_limit(self, b: int) -> int:
        """Building ``b``'s rows a model step may model now: those stored before the latest
        :data:`MODEL_LAG` calls of :meth:`store_points`."""
        if not self._recent:
            return len(self.points[b])
        return self._recent[0].get(b, 0)

    def _next_to_model(self) -> int | None:
        """The building whose stored rows a model step models next (the oldest waiting whose
        rows before the limit number ``update.step_points``, or have waited
        :data:`MODEL_MAX_WAIT` clouds), or None."""
        for b, first in self._unmodelled.items():
            ready = self._model_limit(b) - first
            if ready > 0 and (ready >= self.params.update.step_points
                              or self._stores - self._unmodelled_since.get(b, self._stores) >= MODEL_MAX_WAIT):
                return b
        return None

    @property
    def needs_model(self) -> bool:
        """Whether :meth:`model_step` has work now: stored points to model (but those of the
        latest :data:`MODEL_LAG` clouds), or a full round due (``update.batch_points`` stored,
        or :data:`FULL_AFTER_RECEIVED` batches received, since the last one) or under way."""
        return bool(self._next_to_model() is not None or self._pools_due or self._registration_round is not None
                    or self._round_due())

    def _round_due(self) -> bool:
        """Whether a full round is due (``update.batch_points`` stored, or
        :data:`FULL_AFTER_RECEIVED` batches received, since the last one) and has work."""
        batch = self.params.update.batch_points
        due = self._since_full >= batch or self._received_since_full >= FULL_AFTER_RECEIVED * batch
        return bool(due and (self._unchecked or self._registration_queue))

    def _round_first(self) -> bool:
        """Whether the next model step goes to the full round rather than to a ready piece of
        stored points: pieces first (a drive stored before it is modelled is modelled as
        before), unless clouds keep coming: a due round then waits :data:`ROUND_MAX_WAIT`
        stores at most, and a round under way takes every other step while stores come."""
        if self._registration_round is not None or self._pools_due:
            self._round_turn = not self._round_turn
            return self._round_turn and self._stores > self._round_started
        if not self._round_due():
            self._round_due_since = None
            return False
        if self._round_due_since is None:
            self._round_due_since = self._stores
        return self._stores - self._round_due_since >= ROUND_MAX_WAIT

    def model_step(self, max_points: int | None = None) -> list[int]:
        """One bounded piece of live mapping's second tier, so that a cloud waiting to be
        stored waits for one piece at most: the oldest building's stored points not modelled
        yet (at most ``max_points`` of them, in arrival order) allocated to its façades and
        those updated, as :meth:`add_points` updates them; once they are all modelled and a
        full round is due, the scan comparison (one piece), then the pools of the buildings
        that received points, one building a piece (RANSAC for new façades). While clouds
        keep coming the round does not wait for the pieces to run out (:meth:`_round_first`).

        Returns:
            The labels of the buildings updated (empty when there was nothing to do).
        """
        t0 = time.perf_counter()
        with one_blas_thread():
            b = self._next_to_model() if self._recent else next(iter(self._unmodelled), None)
            if b is not None and self._round_first():
                b = None  # the full round's turn (see _round_first)
            if b is not None:
                first = self._unmodelled[b]
                n = len(self.points[b])
                end = min(n, self._model_limit(b))
                if max_points is not None:
                    end = min(end, first + max(int(max_points), 1))
                del self._unmodelled[b]
                since = self._unmodelled_since.pop(b, self._stores)
                if end < n:  # the rest waits behind the other buildings
                    self._unmodelled[b] = end
                    self._unmodelled_since[b] = since
                self.last_update = _update_record([b])
                self._ensure_normals(b, first, end)
                self._update_building(b, first, False, end)
                self._unchecked.add(b)
                done = [b]
            elif self._registration_round is not None:
                started = time.perf_counter()
                self._registration_piece()
                self.last_update = _update_record([], time.perf_counter() - started)
                done = []
            elif self._pools_due:
                b = self._pools_due.pop(0)
                self.last_update = _update_record([b])
                if b in self.points:  # its modelled rows (those of the latest clouds may wait)
                    n = self._unmodelled.get(b, len(self.points[b]))
                    self._update_building(b, n, True, n)
                done = [b]
            elif self.needs_model:  # a full round: compare the scans, then the pools, a piece each
                self._round_due_since, self._round_started = None, self._stores
                started = time.perf_counter()
                self._start_registration()
                self.last_update = _update_record([], time.perf_counter() - started)
                self._pools_due, self._unchecked = sorted(self._unchecked), set()
                self._since_full = self._received_since_full = 0
                done = []
            else:
                return []
        self.last_update['seconds'] = time.perf_counter() - t0
        return done

    def _model_all(self) -> None:
        """Model every stored point :meth:`store_points` left and finish a full round under
        way (before anything that reads every point's façade: an update of held-back
        points, a flush)."""
        self._recent = []  # everything now, the latest clouds too
        while self._unmodelled or self._pools_due or self._registration_round is not None:
            self.model_step()

    def clone(self) -> FacadeMap:
        """A copy that later updates of either map do not change (the containers are copied,
        the arrays and frozen models shared: the map never writes an array it holds)."""
        new = copy.copy(self)
        for name, value in vars(self).items():
            if isinstance(value, (dict, list, set)):
                setattr(new, name, copy.copy(value))
        return new

    def calibrate_occupancy(self, resolution: float = 0.1, progress: Callable[[str], None] | None = None) -> PLSC:
        """Learn the occupancy's PLSC parameters from the stored points and their rays
        (:mod:`~uncertain_facade_map.mapping.calibration`: a map of a sample of them, some
        voxels held out; seeded by ``params.seed``) and keep them in :attr:`occupancy_`.

        Args:
            resolution: voxel side of the labels, metres (the parameters serve every
                resolution: the scale is relative to the voxel, the spread is the surface's).
            progress: called with a line of text when done.

        Raises:
            InputError: a building without sensor origins (no rays to learn free space from).
        """
        if not self.points:
            return self.occupancy_
        held = self._held_out(resolution)
        if held is not None:
            with one_blas_thread():
                self.occupancy_ = fit_occupancy(held[0], held[1].facades, self.params, seed=self.params.seed,
                                                progress=progress)
        else:
            self.occupancy_ = FIXED
        self.occupancy_stored_ = self.n_stored
        return self.occupancy_

    def _held_out(self, resolution: float) -> tuple[HeldOut, FacadeMap] | None:
        """The calibration's sample of the stored points and the map of its mapped part
        (:func:`held_out_map`), kept until the stored points or the resolution change: the
        occupancy and the free-space weight learn from the same one."""
        xyz, origins, ids = self._stored_rays()
        state = ((), tuple(self.points.items()))
        cache = self.__dict__.get('_held_out_cache')
        if cache is None or cache[1] != resolution or not _same_state(cache[0], state):
            with one_blas_thread():
                held = held_out_map(xyz, origins, ids, self.params, resolution, seed=self.params.seed)
            cache = (state, resolution, held)
            self.__dict__['_held_out_cache'] = cache
        return cache[2]

    def _stored_rays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(N, 3) stored points, (N, 3) their sensor origins and (N,) building labels.

        Raises:
            InputError: a building without sensor origins.
        """
        if not self._has_rays:
            raise InputError('the occupancy calibration needs the sensor origin of every point '
                             '(its free space comes from the rays)')
        labels = sorted(self.points)
        xyz = np.vstack([self.points[b] for b in labels]) if labels else np.empty((0, 3))
        origins = np.vstack([self.sensor_origins[b] for b in labels]) if labels else np.empty((0, 3))
        ids = np.repeat(np.asarray(labels, dtype=np.int64), [len(self.points[b]) for b in labels])
        return xyz, origins, ids

    @property
    def _has_rays(self) -> bool:
        """Every building's stored points have their sensor origins."""
        return all(self.sensor_origins.get(b) is not None for b in self.points)

    def calibrate_free_space(self, resolution: float = 0.1) -> float:
        """The free-space extension's weight (beyond the paper), learnt from the stored
        points and their rays with :attr:`occupancy_`
        (:func:`~uncertain_facade_map.mapping.calibration.fit_free_space`, on the sample
        :meth:`calibrate_occupancy` learnt from)."""
        if not self.points:
            return 0.0
        held = self._held_out(resolution)
        if held is None:
            return 0.0
        return fit_free_space(held[0], held[1].facades, self.occupancy_, self.params, seed=self.params.seed)

    def ray_crossings(self, keys: np.ndarray, resolution: float) -> np.ndarray:
        """(K,) number of stored rays (every ``calibration.ray_step``-th) through each voxel
        of (K,) packed ``keys`` (:func:`~uncertain_facade_map.voxels.ray_crossings`), 0 for
        a voxel holding a stored point."""
        from ..voxels import pack_keys, ray_crossings, voxel_index

        xyz, origins, _ = self._stored_rays()
        step = ray_step(len(xyz))
        crossings = ray_crossings(xyz[::step], origins[::step], resolution, keys)
        crossings[np.isin(keys, pack_keys(voxel_index(xyz, resolution)))] = 0  # a hit outweighs passing rays
        return crossings

    def calibrate_when_grown(self, growth: float = 1.0, min_points: int = 20_000) -> bool:
        """Calibrate (:meth:`calibrate_occupancy`) once the stored points have grown by
        ``growth`` times those of the last calibration (at :meth:`flush`: the cost, a map of
        at most 200,000 points, calibration's ``max_points``, is spent at each doubling),
        with at least ``min_points`` stored and sensor origins for all; True when it did."""
        if not self._calibration_due(growth, min_points):
            return False
        self.calibrate_occupancy()
        self.__dict__.pop('_held_out_cache', None)  # live mapping learns no free-space weight: the sample's map goes
        return True

    def _calibration_due(self, growth: float = 1.0, min_points: int = 20_000) -> bool:
        n = self.n_stored
        return n >= max(min_points, (1.0 + growth) * self.occupancy_stored_) and self._has_rays

    @property
    def needs_consolidation(self) -> bool:
        """Whether a façade was updated block by block since its last whole fit (what
        :meth:`flush` fits whole, besides mapping the points held back)."""
        return any(f.fitted_points != len(f.point_index) for f in self.facades)

    @property
    def needs_full_update(self) -> bool:
        """Whether pools or scans wait for a full update (:meth:`add_points` with
        ``map_now``): buildings whose pool was not looked at since they received points, or
        scans not compared yet; :meth:`flush` does both."""
        return bool(self._unchecked or self._registration_queue or self._unmodelled or self._pools_due
                    or self._registration_round is not None)

    @property
    def n_pending(self) -> int:
        """Number of points held back."""
        return int(sum(len(p[0]) for p in self.pending))

    def _map_pending(self, progress: Callable[[int, int], None] | None = None,
                     last_scan: np.ndarray | None = None, compare: bool = True) -> list[int]:
        """Map the points held back, each call one scan (the last one's points labelled
        ``last_scan`` if given); ``compare``: compare the scans waiting for it with the stored
        points now (:meth:`_learn_registration`), else once enough have come."""
        parts, self.pending = self.pending, []
        if not parts:
            return []
        scan = np.repeat(np.arange(len(parts), dtype=np.int64), [len(p[0]) for p in parts])
        if last_scan is not None:
            _, local = np.unique(last_scan, return_inverse=True)
            scan[len(scan) - len(last_scan):] = len(parts) - 1 + local.reshape(-1)
        xyz = np.vstack([p[0] for p in parts])
        ids = None
        if any(p[1] is not None for p in parts):
            ids = np.concatenate([p[1] if p[1] is not None else np.full(len(p[0]), -1, np.int64) for p in parts])
        origins = None if any(p[2] is None for p in parts) else np.vstack([p[2] for p in parts])
        return self._add(xyz, ids, origins, progress, scan, compare)

    def flush(self, consolidate: bool = True) -> list[int]:
        """Map the points held back, then (``consolidate``) fit whole every façade that
        was only updated block by block since its last whole fit, so that the map is as
        good as one built in one go from the same points.

        Then (``consolidate``) the occupancy's PLSC parameters are learnt again if the stored
        points have doubled (:meth:`calibrate_when_grown`): live mapping learns them here, when
        the input pauses (the worker's idle flush), not in its updates.

        Returns:
            The ids of the façades fitted whole.
        """
        with one_blas_thread():
            self._map_pending()
            self._model_all()
            self._learn_registration()
            if self._unchecked:
                self.last_update = _update_record(sorted(self._unchecked))
                self._check_pools()
            self._since_full = self._received_since_full = 0
            done = []
            if consolidate:
                done = self._consolidate()
                self.calibrate_when_grown()
        return done

    def _allocate(self, xyz: np.ndarray, facade_ids: list[int]) -> np.ndarray:
        """(N,) id of the façade among ``facade_ids`` that takes each of the points (N, 3)
        (metres, map frame) by the extraction's rule (:func:`assign_to_facades`), -1 for none."""
        which, _ = assign_to_facades(xyz, [self.facades[i] for i in facade_ids], self.params.extraction)
        return np.where(which >= 0, np.asarray(facade_ids)[np.maximum(which, 0)], -1)

    def _consolidate(self) -> list[int]:
        """Allocate every building's points to its façades again, by the extraction's rule
        (:func:`assign_to_facades` over all the building's façades at once), and fit whole
        every façade whose points changed or that was updated block by block.

        Incremental allocation gives a new point to the façades that exist when it arrives:
        near a corner, the points of a side wall found later stay in the main façade's band;
        the extraction of one batch would have given them to the side wall. Returns the ids
        of the façades fitted whole."""
        done = []
        for b in sorted({f.building for f in self.facades}):
            mine = [f.facade_id for f in self.facades if f.building == b]
            owner = self._allocate(self.points[b], mine)
            for fid in mine:
                f = self.facades[fid]
                index = np.flatnonzero(owner == fid)
                same = len(index) == len(f.point_index) and np.array_equal(index, f.point_index)
                if len(index) >= 10 and (not same or f.fitted_points != len(index)):
                    self._refit_whole(b, fid, index, f.plane_extent)
                    done.append(fid)
        return sorted(done)

    def _checked(self, xyz: np.ndarray, building_id: np.ndarray | None, sensor_origins: np.ndarray | None
                 ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        xyz = np.asarray(xyz, dtype=np.float64)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise InputError(f'points must be an (N, 3) array, got shape {xyz.shape}')
        if not len(xyz):
            raise InputError('no building points to map')
        if not np.isfinite(xyz).all():
            raise InputError(f'{int((~np.isfinite(xyz)).any(axis=1).sum())} points have NaN or infinite coordinates')
        if sensor_origins is not None:
            sensor_origins = np.asarray(sensor_origins, dtype=np.float64)
            if sensor_origins.shape != xyz.shape:
                raise InputError(f'sensor_origins must have the shape of the points {xyz.shape}, '
                                 f'got {sensor_origins.shape}')
        if building_id is not None:
            building_id = check_building_ids(building_id, len(xyz))
        return xyz, building_id, sensor_origins

    def _add(self, xyz: np.ndarray, building_id: np.ndarray | None, sensor_origins: np.ndarray | None,
             progress: Callable[[int, int], None] | None, scan: np.ndarray | None = None,
             compare: bool = True) -> list[int]:
        # Small matrices only: BLAS in one thread (uncertain_facade_map.threads).
        with one_blas_thread():
            return self._add_points(xyz, building_id, sensor_origins, progress, scan, compare)

    def _add_points(self, xyz: np.ndarray, building_id: np.ndarray | None, sensor_origins: np.ndarray | None,
                    progress: Callable[[int, int], None] | None, scan: np.ndarray | None = None,
                    compare: bool = True) -> list[int]:
        t0 = time.perf_counter()
        self._model_all()
        self._queue_registration(xyz, scan)
        labels = self._labels(xyz, building_id)
        self.last_update = _update_record([])
        changed = [int(b) for b in np.unique(labels)]
        # Every building's points first: without sensor origins the others' points turn a
        # building's walls (``_context``), whichever building comes first.
        firsts = {}
        thinned = 0
        for b in changed:
            sel = np.flatnonzero(labels == b)
            sel = sel[self._thin(b, xyz[sel])]
            thinned += int((labels == b).sum()) - len(sel)
            if len(sel) or b not in self.points:
                firsts[b] = self._append(b, xyz[sel], None if sensor_origins is None else sensor_origins[sel])
        self.last_update['thinned'] = thinned
        # A batch's worth of stored points (update.batch_points) since the last full round
        # (new information: a car lidar's points mostly land in full voxels and are never
        # stored), FULL_AFTER_RECEIVED batches received, or a full update asked for: compare
        # the scans, and look for new façades in the pools.
        batch = self.params.update.batch_points
        self._since_full += len(xyz) - thinned
        self._received_since_full += len(xyz)
        full = compare or self._since_full >= batch or self._received_since_full >= FULL_AFTER_RECEIVED * batch
        if full:
            started = time.perf_counter()
            self._learn_registration()  # against the stored points of before the scans queued
            self.last_update['registration_seconds'] = time.perf_counter() - started
            self._since_full = self._received_since_full = 0
        for done, b in enumerate(changed, 1):
            if b in firsts:  # nothing to do for a building whose new points were all thinned
                self._update_building(b, firsts[b], full)
                if not full:
                    self._unchecked.add(b)
            if progress is not None:
                progress(done, len(changed))
        if full:
            self._check_pools(set(firsts))
        self.last_update['buildings'] = changed
        self.last_update['seconds'] = time.perf_counter() - t0
        return changed

    def _queue_registration(self, xyz: np.ndarray, scan: np.ndarray | None) -> None:
        """Hold new points (N, 3) and their (N,) scan labels (None: one scan) for the next
        comparison with the stored points (:meth:`_learn_registration`), before they are
        thinned or stored; the first held keeps the stored points as they stand."""
        if self.params.update.registration_points <= 0:
            return
        if not self._registration_queue:
            self._registration_base = dict(self.points)  # the arrays are never written: shared
            self._registration_mapped = self.n_points
        first = 1 + max((int(q[1].max()) for q in self._registration_queue), default=-1)
        labels = np.zeros(len(xyz), np.int64) if scan is None else \
            np.unique(np.asarray(scan), return_inverse=True)[1].reshape(-1).astype(np.int64)
        self._registration_queue.append((xyz, labels + first))

    def _learn_registration(self) -> None:
        """Compare the scans held back (:meth:`_queue_registration`), scan by scan, with the
        other scans' and the stored points of before them, and update :attr:`registration_var_`.

        Only the buildings whose stored points meet the new points' bounds (grown by 2 m) take
        part, so its cost follows the new points and the walls they meet, not the map."""
        self._start_registration()
        while self._registration_round is not None:
            self._registration_piece()

    def _start_registration(self) -> None:
        """Begin the comparison of the scans held back in pieces (:meth:`model_step`): the
        scans drawn, the stored points of before them near the new points gathered once."""
        queue, self._registration_queue = self._registration_queue, []
        base, self._registration_base = self._registration_base or {}, None
        up = self.params.update
        self._registration_round = None
        if up.registration_points <= 0 or not queue:
            return
        xyz = queue[0][0] if len(queue) == 1 else np.vstack([q[0] for q in queue])
        labels = queue[0][1] if len(queue) == 1 else np.concatenate([q[1] for q in queue])
        lo, hi = xyz.min(axis=0) - 2.0, xyz.max(axis=0) + 2.0
        near = [p for b, p in base.items() if len(p) and self._meets(b, p, lo, hi)]
        earlier = np.vstack(near) if near else np.empty((0, 3))
        # The draw as before the queue: seeded by the points mapped before them and their number.
        rng = np.random.default_rng([self.params.seed, self._registration_mapped, len(xyz)])
        scans, per_scan = scans_to_compare(labels, len(earlier), up.registration_points, rng)
        if len(scans):
            self._registration_round = (xyz, labels, earlier, rng, tuple(int(v) for v in scans), per_scan)

    def _registration_piece(self) -> None:
        """Compare one scan of the comparison under way (:meth:`_start_registration`)."""
        xyz, labels, earlier, rng, todo, per_scan = self._registration_round
        scan = todo[0]
        self._registration_round = (xyz, labels, earlier, rng, todo[1:], per_scan) if len(todo) > 1 else None
        up, reading = self.params.update, QueryConfig()
        found = scan_disagreement(xyz, labels, earlier, reading.local_neighbours, up.registration_points, rng,
                                  reading.local_inner, up.store_voxel, up.store_per_voxel,
                                  store_spacing=up.store_spacing, scans=np.array([scan]), per_scan=per_scan)
        if found[0]:
            self.registration_sums_ = self.registration_sums_ + found
            self.registration_var_ = registration_variance(self.registration_sums_, up.registration_max_std)

    def _meets(self, b: int, pts: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bool:
        """Whether building ``b``'s points ``pts`` (stored now or earlier: the stored points
        only grow, so the bounds of those stored now hold them) may lie within the box [lo,
        hi] (3,), metres, map frame."""
        held = self._bounds.get(b)
        if held is None:
            held = (pts.min(axis=0), pts.max(axis=0))
            if self.points.get(b) is pts:
                self._bounds[b] = held
        return bool(np.all(held[0] <= hi) and np.all(held[1] >= lo))

    def _labels(self, xyz: np.ndarray, building_id: np.ndarray | None) -> np.ndarray:
        """Building label of each new point: its id, else the clustered building it touches
        (:func:`~uncertain_facade_map.pipeline.step1_facades.split_buildings` with the
        mapped buildings' cells)."""
        return split_buildings(xyz, building_id, self.params.extraction.building_cell, self._cells)

    @property
    def _cells(self) -> dict[int, np.ndarray]:
        """Per building, the sorted keys of its occupied clustering cells
        (:func:`~uncertain_facade_map.pipeline.step1_facades.building_cells`; cached)."""
        cache = self.__dict__.setdefault('_cell_cache', {})
        cell = self.params.extraction.building_cell
        for b, pts in self.points.items():
            keys, n = cache.get(b, (np.empty(0, np.int64), 0))
            if n != len(pts):
                # Points are only appended: the cells of the new ones join the cached cells.
                cache[b] = (np.union1d(keys, building_cells(pts[n:], cell)), len(pts))
        return {b: keys for b, (keys, _) in cache.items() if b in self.points}

    def _voxel_keys(self, xyz: np.ndarray) -> np.ndarray:
        """(N,) int64 keys of the storage voxels (side ``update.store_voxel``) of (N, 3) points,
        metres, map frame (:func:`~uncertain_facade_map.voxels.wrapped_keys`: they repeat only
        2^21 voxels apart, further than the points of one building lie)."""
        return wrapped_keys(xyz, self.params.update.store_voxel)

    def _voxel_index(self, b: int) -> tuple[np.ndarray, np.ndarray]:
        """Building ``b``'s (V,) sorted voxel keys and (V,) int32 counts of stored points."""
        if b not in self._voxels:
            pts = self.points.get(b)
            if pts is None or not len(pts):
                self._voxels[b] = (np.empty(0, np.int64), np.empty(0, np.int32))
            else:
                keys, counts = np.unique(self._voxel_keys(pts), return_counts=True)
                self._voxels[b] = (keys, counts.astype(np.int32))
        return self._voxels[b]

    def _thin(self, b: int, xyz: np.ndarray) -> np.ndarray:
        """(N,) bool over building ``b``'s new (N, 3) points (metres, map frame, arrival
        order): stored, because its voxel holds fewer than ``update.store_per_voxel`` stored
        points and no stored point lies within ``update.store_spacing`` of it (both counting
        the new points stored before it). Records the stored ones in the voxel index and
        counts the others in :attr:`thinned`. Costs O(N log N + V + S) for the building's V
        voxels and the S stored points within the new points' bounds."""
        up = self.params.update
        xyz = np.ascontiguousarray(xyz, dtype=np.float64)
        keys = self._voxel_keys(xyz)
        uk, group, order = voxel_groups(keys)
        vk, vc = self._voxel_index(b)
        pos = np.searchsorted(vk, uk)
        found = np.zeros(len(uk), dtype=bool)
        if len(vk):
            found = vk[np.minimum(pos, len(vk) - 1)] == uk
        have = np.zeros(len(uk), dtype=np.int64)
        have[found] = vc[pos[found]]
        held = np.empty((0, 3))
        pts = self.points.get(b)
        if up.store_spacing > 0 and pts is not None and len(pts) and len(xyz):
            lo, hi = xyz.min(axis=0) - up.store_spacing, xyz.max(axis=0) + up.store_spacing
            held = np.ascontiguousarray(pts[np.all((pts >= lo) & (pts <= hi), axis=1)])
        keep = store(xyz, group, order, have, up.store_per_voxel, held, up.store_spacing)
        added = np.bincount(group, weights=keep, minlength=len(uk)).astype(np.int32)
        vc = vc.copy()  # the index may be shared with a copy of the map
        vc[pos[found]] += added[found]
        new = ~found & (added > 0)
        self._voxels[b] = (np.insert(vk, pos[new], uk[new]), np.insert(vc, pos[new], added[new]))
        dropped = int(len(keys) - keep.sum())
        if dropped:
            self.thinned[b] = self.thinned.get(b, 0) + dropped
        return keep

    def _append(self, b: int, xyz: np.ndarray, origins: np.ndarray | None, with_normals: bool = True) -> int:
        """Append a building's new points (and their normals; ``with_normals`` False: NaN rows,
        estimated when they are modelled, :meth:`_ensure_normals`); returns the first new index."""
        old = self.points.get(b)
        first = 0 if old is None else len(old)
        pts = xyz if old is None else np.vstack([old, xyz])
        self.points[b] = pts
        if len(xyz):  # the bounds grow with the new points (those of the old taken once if missing)
            lo, hi = xyz.min(axis=0), xyz.max(axis=0)
            if old is not None and len(old):
                held = self._bounds.get(b) or (old.min(axis=0), old.max(axis=0))
                lo, hi = np.minimum(held[0], lo), np.maximum(held[1], hi)
            self._bounds[b] = (lo, hi)
        old_so = self.sensor_origins.get(b)
        self.sensor_origins[b] = origins if old is None else (None if origins is None or old_so is None
                                                              else np.vstack([old_so, origins]))
        held = self.normals.get(b)
        normals = np.full((len(xyz), 3), np.nan)
        self.normals[b] = normals if held is None else np.vstack([held, normals])
        if with_normals:
            self._ensure_normals(b, first, len(pts))
        return first

    def _ensure_normals(self, b: int, first: int, end: int) -> None:
        """Estimate the normals of building ``b``'s rows in [first, end) that have none yet
        (stored by :meth:`store_points`), from its stored points near them: those stored
        before *and after* them (a normal estimated when a point is stored sees only the
        points stored before it, a one-sided neighbourhood at the edge of what the sensor has
        seen so far, and tilts: the simulated street's façades scored 2.25 cm so, 1.76 cm with
        the normals of the map built in one go). Neighbours are sought as :meth:`_append`
        seeks them, in the cells of side ``update.normal_reach`` around the rows."""
        held = self.normals[b]
        need = first + np.flatnonzero(np.isnan(held[first:end, 0]))
        if not len(need):
            return
        pts = self.points[b]
        new = pts[need]
        reach = self.params.update.normal_reach
        lo, hi = new.min(axis=0) - reach, new.max(axis=0) + reach
        near = np.flatnonzero(np.all((pts >= lo) & (pts <= hi), axis=1))  # holds every row of need
        near = near[in_sorted(wrapped_keys(pts[near], reach), near_keys(new, reach))]
        normals = held.copy()  # the map never writes an array it holds
        if len(near) >= 3:
            local = pts[near]
            k = self.params.extraction.normal_neighbours
            normals[need] = _point_normals(local - local.mean(axis=0), min(k, len(local)),
                                           np.searchsorted(near, need))
        else:
            normals[need] = [0.0, 0.0, 1.0]
        self.normals[b] = normals

    def facade_of_points(self, building: int) -> np.ndarray:
        """(N,) int64 façade id of each of a building's points, -1 for none."""
        out = np.full(len(self.points[building]), -1, dtype=np.int64)
        for f in self.facades:
            if f.building == building:
                out[f.point_index] = f.facade_id
        return out

    def _extracted(self, b: int, index: np.ndarray, frame: FacadeFrame,
                   plane_extent: tuple[float, float, float, float]) -> ExtractedFacade:
        uvd = frame.to_local(self.points[b][index])
        cos = np.minimum(np.abs(self.normals[b][index] @ frame.normal), 1.0)
        return ExtractedFacade(frame, index, uvd, cos, _extent(uvd[:, :2]), plane_extent)

    def _extracted_for_update(self, b: int, index: np.ndarray, model: FacadeModel,
                              plane_extent: tuple[float, float, float, float]
                              ) -> tuple[ExtractedFacade, np.ndarray, np.ndarray]:
        """:meth:`_extracted` of façade ``model``'s points ``index`` (sorted building indices)
        in its frame, with (N,) their depths from its relief (metres) and (N,) their layers:
        read from :attr:`_facade_points` for the points it holds, computed for the others (the
        same values, point by point: the stored points, their normals, the frame, relief and
        layers do not change between whole fits)."""
        frame, pts = model.frame, self.points[b]
        held = self._facade_points.get(model.facade_id)
        if held is not None and not (held.frame is frame and held.relief is model.relief
                                     and held.layers is model.layers):
            held = None
        n = len(index)
        have = np.zeros(n, dtype=bool)
        pos = np.zeros(n, dtype=np.int64)
        if held is not None and len(held.index):
            pos = np.minimum(np.searchsorted(held.index, index), len(held.index) - 1)
            have = held.index[pos] == index
        uvd, cos = np.empty((n, 3)), np.empty(n)
        depth, labels = np.empty(n), np.empty(n, dtype=np.int64)
        if have.any():
            at = pos[have]
            uvd[have], cos[have], depth[have], labels[have] = held.uvd[at], held.cos[at], held.depth[at], held.labels[at]
        todo = np.flatnonzero(~have)
        if len(todo):
            rows = index[todo]
            uvd[todo] = frame.to_local(pts[rows])
            cos[todo] = np.minimum(np.abs(self.normals[b][rows] @ frame.normal), 1.0)
            depth[todo] = uvd[todo, 2] - model.relief.at(uvd[todo, :2])
            labels[todo] = model.layers.predict(depth[todo])
        self._facade_points[model.facade_id] = _FacadePoints(frame, model.relief, model.layers, index, uvd, cos,
                                                             depth, labels)
        return ExtractedFacade(frame, index, uvd, cos, _extent(uvd[:, :2]), plane_extent), depth, labels

    def _context(self, b: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """(C, 3) points of the other buildings (at most ``_CONTEXT_POINTS``, a random draw),
        metres, map frame, and (C,) int64 their buildings: they turn the normals of walls
        without sensor origins."""
        others = [(o, p) for o, p in self.points.items() if o != b]
        if not others:
            return np.empty((0, 3)), np.empty(0, dtype=np.int64)
        starts = np.cumsum([0] + [len(p) for _, p in others])
        if starts[-1] <= _CONTEXT_POINTS:
            return (np.concatenate([p for _, p in others]),
                    np.concatenate([np.full(len(p), o, dtype=np.int64) for o, p in others]))
        # The draw's rows gathered from each building (not a copy of all their points).
        pick = rng.choice(int(starts[-1]), _CONTEXT_POINTS, replace=False)
        part = np.searchsorted(starts, pick, side='right') - 1
        out = np.empty((_CONTEXT_POINTS, 3))
        labels = np.empty(_CONTEXT_POINTS, dtype=np.int64)
        for k, (o, p) in enumerate(others):
            mine = part == k
            out[mine] = p[pick[mine] - starts[k]]
            labels[mine] = o
        return out, labels

    def _walls(self, b: int) -> list[tuple[FacadeFrame, np.ndarray]]:
        """The building's façades as (frame, (K, 3) stored points within ``ransac_threshold``
        of the plane, metres, map frame): a sloped façade extracted later faces like the
        wall it adjoins."""
        out = []
        thr = self.params.extraction.ransac_threshold
        for f in self.facades:
            if f.building == b:
                xyz = self.points[b][f.point_index]
                out.append((f.frame, xyz[np.abs(f.frame.to_local(xyz)[:, 2]) <= thr]))
        return out

    def _check_pools(self, done: set[int] = frozenset()) -> None:
        """Look for new façades in the pools of the buildings that received points in
        updates that were not full ones (``map_now``), but for those in ``done``."""
        todo, self._unchecked = sorted(self._unchecked - done), set()
        for b in todo:
            if b in self.points:
                self._update_building(b, len(self.points[b]), True)

    def _update_building(self, b: int, first: int, extract: bool = True, end: int | None = None) -> None:
        """Allocate a building's points from ``first`` on, extract new façades from its pool
        (``extract``: in a full update, see :meth:`add_points`), and update the façades that
        received points. ``end``: the rows from it on are not there yet (stored, not modelled:
        :meth:`model_step`); None: all rows."""
        ex, params = self.params.extraction, self.params
        pts = self.points[b]
        if end is not None and end < len(pts):
            pts = pts[:end]
        n = len(pts)
        owner = self.facade_of_points(b)[:n]
        mine = [f.facade_id for f in self.facades if f.building == b]
        if mine and first < n:
            owner[first:] = self._allocate(pts[first:], mine)
        grown: dict[int, tuple[float, float, float, float]] = {}
        pool = np.flatnonzero(owner < 0)
        checked = self.pool_checked.get(b, 0)
        step = max(ex.min_facade_points, params.update.extraction_growth * checked)
        if extract and len(pool) >= ex.min_facade_points and len(pool) >= checked + step:
            rng = np.random.default_rng([params.seed, b, n])
            so = self.sensor_origins.get(b)
            context, labels = (None, None) if so is not None else self._context(b, rng)
            extracted, _ = extract_facades(pts[pool], ex, sensor_origins=None if so is None else so[pool], rng=rng,
                                           context=context, context_labels=labels,
                                           walls=() if so is not None else self._walls(b), normals=self.normals[b][pool])
            for e in extracted:
                index = pool[e.index]
                target = self._coplanar(b, e, index)
                if target is None:
                    fid = len(self.facades)
                    model = fit_facade(self._extracted(b, index, e.frame, e.plane_extent), params,
                                       self._rng(b, fid, len(index)), fid, b)
                    self.facades.append(model)
                    owner[index] = fid
                    self.last_update['facades_new'].append(fid)
                    continue
                t = self.facades[target]
                d = t.frame.to_local(pts[index])[:, 2]
                fits = (d >= -ex.band_back) & (d <= ex.band_front)
                owner[index[fits]] = target
                grown[target] = _union(grown.get(target, t.plane_extent), _extent(_plane_corners_in(e, t.frame)))
            self.pool_checked[b] = int((owner < 0).sum())
        new_ids = set(self.last_update['facades_new'])
        for fid in sorted(set(np.unique(owner[first:][owner[first:] >= 0]).tolist()) | set(grown)):
            if fid in new_ids:
                continue
            model = self.facades[fid]
            index = np.flatnonzero(owner == fid)
            fresh = ~in_sorted(index, model.point_index)  # both sorted building indices
            if not fresh.any():
                continue
            # The wall's extent grows with the new points on the plane.
            plane = grown.get(fid, model.plane_extent)
            uvd_new = model.frame.to_local(pts[index[fresh]])
            on_plane = uvd_new[np.abs(uvd_new[:, 2]) <= ex.ransac_threshold]
            if len(on_plane) >= 3:
                plane = _union(plane, _plane_box(on_plane))
            up = params.update
            if model.fitted_points < up.refit_max_points and len(index) >= (1.0 + up.refit_growth) * model.fitted_points:
                updated = self._refit_whole(b, fid, index, plane)
            else:
                rng = self._rng(b, fid, len(index))
                extracted, depth, labels = self._extracted_for_update(b, index, model, plane)
                updated = update_facade(model, extracted, fresh, params, rng, depth=depth, labels=labels)
                self.facades[fid] = updated
            key = 'facades_refitted' if updated.fitted_points == len(index) else 'facades_updated'
            self.last_update[key].append(fid)
            self.last_update['updated_cells'] += int(updated.stats.get('updated_cells', updated.surface.mean.size))

    def _rng(self, b: int, fid: int, n: int) -> np.random.Generator:
        """The draws of fitting façade ``fid`` of building ``b`` on ``n`` points: seeded by the
        façade's ordinal within its building (0 for the building's first façade), not its id in
        the map, so that a building's façades do not depend on which other buildings the map
        holds (a tile of a tiled map, or the whole city, builds them bit for bit alike)."""
        ordinal = sum(1 for f in self.facades[:fid] if f.building == b)
        return np.random.default_rng([self.params.seed, b, ordinal, n])

    def _refit_whole(self, b: int, fid: int, index: np.ndarray, plane: tuple[float, float, float, float]
                     ) -> FacadeModel:
        """Fit façade ``fid`` whole on the points ``index``, its frame estimated again (the
        first came from a part of the wall, and a small tilt smears the depth layers)."""
        ex, pts, model = self.params.extraction, self.points[b], self.facades[fid]
        rng = self._rng(b, fid, len(index))
        frame = _final_frame(pts[index], self.normals[b][index], model.frame, ex) or model.frame
        uvd = frame.to_local(pts[index])
        wall = uvd[np.abs(uvd[:, 2]) <= ex.ransac_threshold]
        if len(wall) >= 3:
            plane = _plane_box(wall)
        elif frame is not model.frame:
            frame, plane = model.frame, plane
        updated = fit_facade(self._extracted(b, index, frame, plane), self.params, rng, fid, b)
        self.facades[fid] = updated
        return updated

    def _coplanar(self, b: int, e: ExtractedFacade, index: np.ndarray) -> int | None:
        """Id of the building's façade that a newly extracted one continues (the merge rule
        of the extraction: parallel within ``merge_angle_deg``, closer than ``merge_offset``
        along the normal and in u), or None. Only a façade whose allocation band holds the
        new plane (``-band_back <= d <= band_front``) can take it: a recess deeper than
        that (a set-back entrance) would join and then lose all its points to no façade.
        Nor does one a storey's setback away (``STOREY_OFFSET``) that occupies its own part
        of the wall (:func:`side_by_side`; upper storeys over a set-back ground floor): as
        in the extraction, it is a façade of its own. ``index``: e's points among the
        building's."""
        ex = self.params.extraction
        cos_max = np.cos(np.deg2rad(ex.merge_angle_deg))
        best = None
        pts = self.points[b]
        for f in self.facades:
            if f.building != b or float(e.frame.normal @ f.frame.normal) < cos_max:
                continue
            box = _plane_corners_in(e, f.frame)
            d = float(f.frame.to_local(e.frame.origin[None])[0, 2])
            gap = max(f.plane_extent[0] - box[:, 0].max(), box[:, 0].min() - f.plane_extent[1], 0.0)
            if not (abs(d) < ex.merge_offset and -ex.band_back <= d <= ex.band_front and gap <= ex.merge_offset):
                continue
            if abs(d) >= STOREY_OFFSET:
                mine = f.frame.to_local(pts[index[np.abs(e.uvd[:, 2]) <= ex.ransac_threshold]])
                theirs = f.frame.to_local(pts[f.point_index])
                if side_by_side(mine[:, :2], theirs[np.abs(theirs[:, 2]) <= ex.ransac_threshold, :2]):
                    continue
            if best is None or len(f.point_index) > len(self.facades[best].point_index):
                best = f.facade_id
        return best

    def rejected(self, building: int) -> np.ndarray:
        """(N,) bool over a building's points: on no façade, or removed by the outlier test."""
        n = len(self.points[building])
        on_facade = np.zeros(n, dtype=bool)
        removed = np.zeros(n, dtype=bool)
        for f in self.facades:
            if f.building == building:
                on_facade[f.point_index] = True
                removed[f.outlier_index] = True
        return removed | ~on_facade

    @property
    def buildings(self) -> list[int]:
        """Labels of the mapped buildings."""
        return sorted(self.points)

    @property
    def n_points(self) -> int:
        """Number of building points mapped: stored plus thinned (counted, not stored)."""
        return self.n_stored + self.n_thinned

    @property
    def n_stored(self) -> int:
        """Number of building points stored (see ``update.store_voxel``)."""
        return int(sum(len(p) for p in self.points.values()))

    @property
    def n_thinned(self) -> int:
        """Number of building points counted but not stored (their voxel was full)."""
        return int(sum(self.thinned.values()))

    def query(self, xyz: np.ndarray, config: QueryConfig | None = None, resolution: float | None = None,
              event: str | None = None) -> PointQuery:
        """Answer the 3D point query for (N, 3) points (metres, map frame) from this map:
        :func:`~uncertain_facade_map.pipeline.step7_queries.query_map` with the map's own
        façades, stored points, depth bands (``extraction.band_back`` / ``band_front``),
        learnt occupancy (:attr:`occupancy_`) and :attr:`registration_var_`.

        Args:
            xyz: (N, 3) points, metres, map frame.
            config: the query settings (``query.*``; default: the defaults, as the node's).
            resolution: voxel side of the occupancy probability, metres (default:
                ``config.resolution``).
            event: what ``p_occupied`` is the probability of, 'surface' or 'solid'
                (default: ``config.occupancy_event``).

        Raises:
            InputError: bad points, resolution or event.
        """
        config, resolution = query_settings(config, resolution, event)
        ex = self.params.extraction
        return query_map(self.facades, self.points, xyz, resolution, ex.band_back, ex.band_front, self.occupancy_,
                         config, self.local_surface(config), self.registration_var_)

    def local_surface(self, config: QueryConfig | None = None) -> LocalSurface | None:
        """The stored points read per point as queries with ``config`` read them
        (:func:`~uncertain_facade_map.pipeline.step7_local_surface.for_query`; None for
        ``query.surface`` 'raster'), kept until the map changes: the cache holds the façade
        models and stored arrays it was built from, and the map replaces, never writes, what it
        holds, so an identity check per query tells whether it still stands."""
        config = QueryConfig() if config is None else config
        state = (tuple(self.facades), tuple(self.points.items()))
        cache = self.__dict__.get('_local_cache')
        if cache is None or not _same_state(cache[0], state):
            cache = (state, {})
            self.__dict__['_local_cache'] = cache
        key = reading_key(config)
        if key not in cache[1]:
            cache[1][key] = for_query(self.facades, self.points, config)
        return cache[1][key]


def query_settings(config: QueryConfig | None, resolution: float | None, event: str | None
                   ) -> tuple[QueryConfig, float]:
    """The query settings with ``event`` (if given) in them, and the resolution (default:
    the settings')."""
    config = QueryConfig() if config is None else config
    if event is not None and event != config.occupancy_event:
        config = replace(config, occupancy_event=event)
    return config, config.resolution if resolution is None else resolution


def reading_key(config: QueryConfig) -> tuple:
    """The settings a local surface depends on (:func:`~uncertain_facade_map.pipeline.step7_local_surface.for_query`)."""
    return config.surface, config.local_neighbours, config.local_radius, config.local_inner


def _same_state(a: tuple, b: tuple) -> bool:
    """Whether two ``(façade models, (label, points) pairs)`` states hold the same objects."""
    return (len(a[0]) == len(b[0]) and len(a[1]) == len(b[1]) and all(x is y for x, y in zip(a[0], b[0]))
            and all(x[0] == y[0] and x[1] is y[1] for x, y in zip(a[1], b[1])))


def _update_record(buildings: list[int], registration_seconds: float = 0.0) -> dict:
    """A fresh :attr:`FacadeMap.last_update` (the lists filled as the update goes)."""
    return {'buildings': buildings, 'facades_new': [], 'facades_refitted': [], 'facades_updated': [],
            'updated_cells': 0, 'registration_seconds': registration_seconds}


def _plane_corners_in(e: ExtractedFacade, frame: FacadeFrame) -> np.ndarray:
    """(4, 2) (u, v) in ``frame`` of the corners of ``e``'s wall extent (on its plane)."""
    b = e.plane_extent
    corners = np.array([[b[i], b[j], 0.0] for i in (0, 1) for j in (2, 3)])
    return frame.to_local(e.frame.to_world(corners))[:, :2]


def _union(a: tuple[float, float, float, float], b: tuple[float, float, float, float]
           ) -> tuple[float, float, float, float]:
    return (min(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), max(a[3], b[3]))


def stored_mask(xyz: np.ndarray, params: MapParams) -> np.ndarray:
    """(N,) bool: which of one building's (N, 3) points (metres, map frame, in arrival
    order) a map with ``params`` stores, the others being thinned (``update.store_voxel``,
    ``update.store_per_voxel``, ``update.store_spacing``)."""
    return FacadeMap(params)._thin(0, np.asarray(xyz, dtype=np.float64))


def build_map(xyz: np.ndarray, building_id: np.ndarray | None = None, sensor_origins: np.ndarray | None = None,
              params: MapParams | None = None, map_origin: np.ndarray | None = None,
              progress: Callable[[int, int], None] | None = None, scan: np.ndarray | None = None) -> FacadeMap:
    """Build a map from building points in one go (see :meth:`FacadeMap.add_points`)."""
    fmap = FacadeMap(params or MapParams(), np.zeros(3) if map_origin is None else np.asarray(map_origin, float))
    fmap.add_points(xyz, building_id, sensor_origins, progress, scan=scan)
    return fmap


def held_out_map(xyz: np.ndarray, sensor_origins: np.ndarray, building_id: np.ndarray | None, params: MapParams,
                 resolution: float, settings: Settings | None = None, seed: int = 0
                 ) -> tuple[HeldOut, FacadeMap] | None:
    """The calibration's sample of (N, 3) mapped points (metres, map frame) with their (N, 3)
    sensor origins and (N,) building labels or None, a share of its hit voxels held out
    (:func:`~uncertain_facade_map.mapping.calibration.hold_out`), and the map of the rest;
    None: too few points to map."""
    held = hold_out(xyz, sensor_origins, building_id, params, resolution, settings or Settings(), seed)
    if held is None:
        return None
    m = held.mapped
    return held, build_map(held.xyz[m], None if held.ids is None else held.ids[m], held.origins[m], params)


def calibrate_occupancy(xyz: np.ndarray, sensor_origins: np.ndarray, params: MapParams | None = None,
                        building_id: np.ndarray | None = None, resolution: float = 0.1, seed: int = 0,
                        progress: Callable[[str], None] | None = None, **settings) -> PLSC:
    """Learn the occupancy's PLSC parameters from (N, 3) mapped points and their (N, 3) sensor
    origins (metres, map frame) alone (:mod:`~uncertain_facade_map.mapping.calibration`).

    Args:
        xyz: (N, 3) mapped building points.
        sensor_origins: (N, 3) the sensor origin of each point.
        params: the map's parameters (default: the defaults).
        building_id: (N,) building labels, or None to cluster.
        resolution: voxel side of the labels, metres.
        seed: seed of every draw.
        progress: called with a line of text when done.
        settings: :class:`~uncertain_facade_map.mapping.calibration.Settings` (holdout,
            max_points, region, max_rays, max_negatives, reach, band_front).

    Returns:
        The fitted parameters; :data:`~uncertain_facade_map.pipeline.step8_occupancy.FIXED`
        when the sample holds too few points or labelled voxels near a façade.

    Raises:
        InputError: bad shapes, non-finite values or settings out of range.
    """
    params = params or MapParams()
    settings = Settings(**settings)
    held = held_out_map(xyz, sensor_origins, building_id, params, resolution, settings, seed)
    return FIXED if held is None else fit_occupancy(held[0], held[1].facades, params, settings, seed, progress)
