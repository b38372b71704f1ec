"""OctoMap as a baseline occupancy method (the real library, through ``octomap-python``).

Method: A. Hornung, K. M. Wurm, M. Bennewitz, C. Stachniss, W. Burgard, "OctoMap: an
efficient probabilistic 3D mapping framework based on octrees", Autonomous Robots 34(3),
2013. Every ray updates the log-odds of the voxels it passes through (a miss) and of the
voxel holding its end point (a hit), paper Eq. (2)-(3)
``L(n | z_1:t) = L(n | z_1:t-1) + L(n | z_t)``, clamped to ``[l_min, l_max]`` (Eq. 5);
the occupancy of a voxel is ``p = 1 - 1 / (1 + exp(L))``. The ray casting, the log-odds
update, the clamping and the octree are the library's own
(``OcTree.insertPointCloud``); this module only feeds it and reads it back.

Parameters (the library's and the paper's defaults): ``prob_hit`` 0.7, ``prob_miss`` 0.4,
clamping thresholds ``clamp_min`` 0.12 and ``clamp_max`` 0.97, full rays (no maximum
range), octree leaf side = the evaluation's resolution.

What was simplified / chosen here:

- **Grouping of rays into scans.** OctoMap inserts a point cloud with *one* sensor
  origin per scan, and within one ``insertPointCloud`` call each voxel is updated at most
  once (occupied wins over free). Our points come from a moving vehicle with a sensor
  origin per point (per beam, in the simulator). The rays are therefore grouped by their
  origin: the origins are quantised to a cubic grid of side ``origin_quantum`` (default
  5 cm), each cell's rays form one scan, inserted with the mean origin of the cell's rays,
  in the order of their first ray (time order for time-ordered input). A ray's start
  thus moves by at most ``origin_quantum * sqrt(3) / 2`` (4.3 cm at the default); its end
  point (the hit) is exact. On the simulated street this makes about 5 000 scans of about
  220 rays each.
- Points are passed to the library as float32 (its ``point3d``), so map-frame coordinates
  must be local (near the origin), as they are in our clouds; coordinates beyond the
  octree's key range (``resolution * 2^15`` from the origin) raise :class:`InputError`.
- The map is never pruned to the maximum-likelihood map; ``predict`` reads the leaf's
  (or pruned inner node's) probability. A voxel no ray reached (no node) is unknown: 0.5.
- ``predict`` asks the octree once per query point in a Python loop over the binding's
  ``search`` (the binding has no vectorised look-up with probabilities; its
  ``getLabels`` only returns -1/0/1 and loops as well): about 1 M queries in 3-5 s.
"""

from __future__ import annotations

import numpy as np

from ...errors import InputError
from .base import OccupancyMethod, check_queries, check_scans, group_by_origin

#: Half the extent of an OctoMap octree in voxels (16-bit keys centred on 2^15).
_KEY_HALF_RANGE = 1 << 15


def _import_octomap():
    """The ``octomap`` module of the ``octomap-python`` package.

    Raises:
        InputError: the package is not installed (with the install command).
    """
    try:
        import octomap  # noqa: PLC0415 - optional dependency, imported on use
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise InputError('the OctoMap baseline needs the octomap-python package: '
                         '.venv/bin/python -m pip install octomap-python') from err
    return octomap


def _probability(name: str, value: float) -> float:
    value = float(value)
    if not (np.isfinite(value) and 0.0 < value < 1.0):
        raise InputError(f'{name} must be a probability in (0, 1), got {value!r}')
    return value


class OctoMapMethod(OccupancyMethod):
    """OctoMap (Hornung et al. 2013) through the ``octomap-python`` binding.

    Args:
        resolution: octree leaf side, metres (> 0).
        prob_hit: probability of a voxel being occupied given a hit in it (0.5, 1).
        prob_miss: probability of a voxel being occupied given a ray passing it (0, 0.5).
        clamp_min: lower clamping threshold of the occupancy probability, (0, 1).
        clamp_max: upper clamping threshold, (clamp_min, 1).
        origin_quantum: side of the origin cubes grouping rays into scans, metres (> 0);
            see the module docstring.

    Raises:
        InputError: a parameter out of its range.
    """

    name = 'OctoMap'

    def __init__(self, resolution: float, prob_hit: float = 0.7, prob_miss: float = 0.4,
                 clamp_min: float = 0.12, clamp_max: float = 0.97, origin_quantum: float = 0.05) -> None:
        super().__init__(resolution)
        self.prob_hit = _probability('prob_hit', prob_hit)
        self.prob_miss = _probability('prob_miss', prob_miss)
        self.clamp_min = _probability('clamp_min', clamp_min)
        self.clamp_max = _probability('clamp_max', clamp_max)
        if self.prob_hit <= 0.5:
            raise InputError(f'prob_hit must exceed 0.5 (a hit is evidence of occupancy), got {prob_hit!r}')
        if self.prob_miss >= 0.5:
            raise InputError(f'prob_miss must be below 0.5 (a miss is evidence of free space), got {prob_miss!r}')
        if self.clamp_min >= self.clamp_max:
            raise InputError(f'clamp_min ({clamp_min!r}) must be below clamp_max ({clamp_max!r})')
        if not (np.isfinite(origin_quantum) and origin_quantum > 0):
            raise InputError(f'origin_quantum must be a positive number of metres, got {origin_quantum!r}')
        self.origin_quantum = float(origin_quantum)
        self.tree_ = None
        self.n_scans_ = 0

    def _check_range(self, xyz: np.ndarray, what: str) -> None:
        """Raise InputError when (N, 3) ``xyz`` (metres) leave the octree's key range."""
        limit = self.resolution * (_KEY_HALF_RANGE - 1)
        if len(xyz) and np.abs(xyz).max() >= limit:
            raise InputError(f'{what} reach {np.abs(xyz).max():.1f} m from the map origin; an OctoMap octree '
                             f'at {self.resolution} m covers +-{limit:.1f} m: use local map-frame coordinates')

    def fit(self, points: np.ndarray, origins: np.ndarray) -> OctoMapMethod:
        """Insert the rays into a fresh octree.

        Args:
            points: (N, 3) float64 ray end points (hits), map frame, metres.
            origins: (N, 3) float64 sensor origin of each ray, map frame, metres.

        Returns:
            self, with ``tree_`` (the ``octomap.OcTree``) and ``n_scans_`` (the number of
            origin groups inserted).

        Raises:
            InputError: bad shapes, an empty or non-finite input, coordinates outside the
                octree's range, or octomap-python missing.
        """
        points, origins = check_scans(points, origins)
        self._check_range(points, 'points')
        self._check_range(origins, 'sensor origins')
        octomap = _import_octomap()
        tree = octomap.OcTree(self.resolution)
        tree.setProbHit(self.prob_hit)
        tree.setProbMiss(self.prob_miss)
        tree.setClampingThresMin(self.clamp_min)
        tree.setClampingThresMax(self.clamp_max)
        order, starts, mean_origins = group_by_origin(origins, self.origin_quantum)
        sorted_points = np.ascontiguousarray(points[order])
        for g in range(len(mean_origins)):
            scan = sorted_points[starts[g]:starts[g + 1]]
            # Eq. (2)-(5): ray casting, log-odds update and clamping inside the library;
            # inner nodes are updated once at the end (lazy_eval).
            tree.insertPointCloud(scan, np.ascontiguousarray(mean_origins[g]), maxrange=-1.0, lazy_eval=True)
        tree.updateInnerOccupancy()
        self.tree_ = tree
        self.n_scans_ = len(mean_origins)
        return self

    def predict(self, xyz: np.ndarray) -> np.ndarray:
        """Occupancy probability of the voxels centred at ``xyz``.

        Args:
            xyz: (M, 3) float64 voxel centres, map frame, metres.

        Returns:
            (M,) float64: the octree node's probability ``1 - 1 / (1 + exp(L))`` (within
            ``[clamp_min, clamp_max]``), 0.5 where the octree has no node (never observed)
            or the point is outside the octree's range.

        Raises:
            InputError: not fitted, or ``xyz`` not a finite (M, 3) array.
        """
        if self.tree_ is None:
            raise InputError('fit the method before predicting')
        xyz = check_queries(xyz)
        octomap = _import_octomap()
        null = octomap.NullPointerException
        search = self.tree_.search
        out = np.full(len(xyz), 0.5)
        limit = self.resolution * (_KEY_HALF_RANGE - 1)
        inside = np.flatnonzero(np.abs(xyz).max(axis=1) < limit) if len(xyz) else np.empty(0, np.int64)
        for i, p in zip(inside.tolist(), xyz[inside].tolist()):
            try:
                out[i] = search(p).getOccupancy()
            except null:  # no node: the voxel was never observed
                pass
        return out
