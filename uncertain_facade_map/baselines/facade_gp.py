"""Our map (GMM layers + local GPs) behind the evaluation's interface.

``fit`` builds the façade map from the points in one go (:func:`~..facade_map.build_map`,
buildings clustered from the points: the interface carries no building ids);
``predict`` turns the uncertain surface into occupancy (:mod:`..occupancy`, paper
Section IV.C): a voxel centred at signed distance s from the mean surface has
p = Phi((r/2 - s) / sqrt(var + noise_var)).

For the evaluation a voxel belongs to a façade from ``band_back`` behind its plane to
``free_reach`` in front of it (the queries' ``band_front`` is 2 m, for points near the
wall): everything in front of a mapped wall, within its extent, is free space by the
model, which is what the surface map says about it. Voxels no façade covers are unknown
(0.5). The variance is the surface variance of the GP (m^2), the quantity the paper's
"accurate inference" threshold (0.01) applies to.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..facade_map import FacadeMap, MapParams, build_map
from ..queries import query_points
from .base import OccupancyMethod, check_queries, check_scans


class FacadeGPMethod(OccupancyMethod):
    """The package's façade map as an occupancy method.

    Args:
        resolution: voxel side, metres.
        params: modelling parameters (default: the configuration's defaults).
        free_reach: voxels up to this far in front of a façade plane take its surface,
            metres.
    """

    name = 'Ours'

    def __init__(self, resolution: float, params: MapParams | None = None, free_reach: float = 50.0) -> None:
        super().__init__(resolution)
        if not (np.isfinite(free_reach) and free_reach > 0):
            raise InputError(f'free_reach must be a positive number of metres, got {free_reach!r}')
        self.params = params or MapParams()
        self.free_reach = float(free_reach)
        self.map_: FacadeMap | None = None
        self._query = None

    def fit(self, points: np.ndarray, origins: np.ndarray) -> FacadeGPMethod:
        """Build the map from (N, 3) points with their (N, 3) sensor origins (map frame, metres)."""
        points, origins = check_scans(points, origins)
        self.map_ = build_map(points, None, origins, self.params)
        self._query = None
        return self

    def _answers(self, xyz: np.ndarray):
        if self.map_ is None:
            raise InputError('fit the method before predicting')
        xyz = check_queries(xyz)
        if self._query is None or self._query[0] is not xyz:
            ex = self.params.extraction
            self._query = (xyz, query_points(self.map_.facades, xyz, self.resolution, ex.band_back, self.free_reach))
        return self._query[1]

    def predict(self, xyz: np.ndarray) -> np.ndarray:
        """(M,) occupancy probability of the voxels centred at (M, 3) ``xyz``."""
        return self._answers(xyz).p_occupied

    def predict_variance(self, xyz: np.ndarray) -> np.ndarray:
        """(M,) surface variance at ``xyz``, m^2; +inf where no façade covers the voxel."""
        var = self._answers(xyz).variance
        return np.where(np.isfinite(var), var, np.inf)
