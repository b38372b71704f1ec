"""Our map (GMM layers + local GPs) behind the evaluation's interface.

``fit`` builds the façade map from the points in one go (:func:`~uncertain_facade_map.mapping.facade_map.build_map`,
buildings clustered from the points: the interface carries no building ids); ``predict``
turns the uncertain surface into occupancy (paper Section IV.C: "probabilistic
least-squares classification ... occupancy probabilities obtained through a cumulative
Gaussian density function"; the exact form is left to the paper's reference).

Two readings of the same map (:mod:`~uncertain_facade_map.pipeline.step8_occupancy`), with D ~ N(mean depth, var + noise var)
the surface depth and s the voxel centre's signed distance from the mean surface:

- ``surface`` (the default, :class:`FacadeGPMethod`): the probability that the voxel holds
  the surface, ``Phi((h - s)/sigma) - Phi((-h - s)/sigma)``, ``h`` the voxel's half extent
  along the façade normal. This is the event the evaluation scores as occupied (a voxel
  holding reference points), so it is the one compared with the baselines.
- ``solid`` (:class:`FacadeGPSolidMethod`): the probability that any of the voxel lies
  behind the surface, ``Phi((r/2 - s)/sigma)``, which is what the node publishes
  (:func:`~uncertain_facade_map.pipeline.step8_occupancy.occupancy_probability`): the building taken as solid behind its
  façades. The report shows it beside the other, as a sensitivity of the comparison.

Each reading is taken with the paper's PLSC (the default: the two parameters learnt from
the mapped points alone by :meth:`~uncertain_facade_map.mapping.facade_map.FacadeMap.calibrate_occupancy`,
as the command line's ``build`` and the node learn them) or with the fixed formula
(``occupancy='fixed'``, :class:`FacadeGPFixedMethod`: scale 1, spread 0).

For the evaluation a voxel belongs to a façade from ``band_back`` behind its plane to
``free_reach`` in front of it (the queries' ``band_front`` is 2 m, for points near the
wall): everything in front of a mapped wall, within its extent, is free space by the
model. A voxel no façade covers holds no modelled surface: 0 in the ``surface`` reading
(the map claims to hold every building surface it observed) and unknown, 0.5, in the
``solid`` one (as the node publishes it). The variance is the surface variance of the GP
(m^2), the quantity the paper's "accurate inference" threshold (0.01) applies to; +inf
where no façade covers the voxel, so such voxels never count as accurately inferred.
"""

from __future__ import annotations

import numpy as np

from ...errors import InputError
from ...mapping.calibration import surface_terms
from ...mapping.facade_map import FacadeMap, build_map
from ...params import MapParams, QueryConfig
from ...pipeline.step7_queries import query_points
from ...pipeline.step8_occupancy import FIXED, READINGS, carve
from ...voxels import pack_keys, voxel_index
from .base import OccupancyMethod, check_queries, check_scans

#: The last map built (``key``, ``map``) and its PLSC parameters by resolution (``plsc``):
#: the readings of one map (:class:`FacadeGPMethod` and its subclasses, asked one after the
#: other by the evaluation) and its resolutions build it once and calibrate it once per resolution.
_SHARED: dict = {}


class FacadeGPMethod(OccupancyMethod):
    """The package's façade map as an occupancy method.

    Args:
        resolution: voxel side, metres.
        params: modelling parameters (default: the configuration's defaults).
        free_reach: voxels up to this far in front of a façade plane take its surface,
            metres.
        reading: ``'surface'`` (p that the voxel holds the surface) or ``'solid'`` (p that
            it lies behind the surface, as the node publishes).
        occupancy: ``'plsc'`` (parameters learnt from the mapped points at this resolution)
            or ``'fixed'``.
        surface: ``'local'`` (the queries' default: the stored points read per point where
            they are dense, the rasters elsewhere) or ``'raster'`` (the paper's reading alone).

    Raises:
        InputError: a bad resolution, ``free_reach``, ``reading`` or ``occupancy``.
    """

    name = 'Ours'
    reading_default = 'surface'
    occupancy_default = 'plsc'
    surface_default = 'local'

    def __init__(self, resolution: float, params: MapParams | None = None, free_reach: float = 50.0,
                 reading: str | None = None, occupancy: str | None = None, surface: str | None = None) -> None:
        super().__init__(resolution)
        if not (np.isfinite(free_reach) and free_reach > 0):
            raise InputError(f'free_reach must be a positive number of metres, got {free_reach!r}')
        reading = self.reading_default if reading is None else reading
        if reading not in READINGS:
            raise InputError(f'reading must be one of {", ".join(READINGS)}, got {reading!r}')
        occupancy = self.occupancy_default if occupancy is None else occupancy
        if occupancy not in ('plsc', 'fixed'):
            raise InputError(f"occupancy must be 'plsc' or 'fixed', got {occupancy!r}")
        self.occupancy = occupancy
        self.query = QueryConfig(surface=self.surface_default if surface is None else surface)
        self.params = params or MapParams()
        self.free_reach = float(free_reach)
        self.reading = reading
        self.map_: FacadeMap | None = None
        self._query = None

    def fit(self, points: np.ndarray, origins: np.ndarray) -> FacadeGPMethod:
        """Build the map from (N, 3) points with their (N, 3) sensor origins (map frame,
        metres) and learn its PLSC parameters at this resolution. The readings of one map
        share it: a fit on the same arrays and parameters as the last one takes that map
        (:data:`_SHARED`; its PLSC parameters too at a resolution already learnt), so only
        the first pays for the build and the first at each resolution for the calibration."""
        points, origins = check_scans(points, origins)
        key = (id(points), id(origins), points.shape, float(points.sum()), float(origins.sum()), self.params)
        if _SHARED.get('key') != key:
            _SHARED.clear()
            _SHARED.update(key=key, map=build_map(points, None, origins, self.params), plsc={})
        fmap = _SHARED['map']
        if self.resolution not in _SHARED['plsc']:
            _SHARED['plsc'][self.resolution] = fmap.calibrate_occupancy(self.resolution)
        fmap.occupancy_ = _SHARED['plsc'][self.resolution]
        self.local_ = fmap.local_surface(self.query)  # the map keeps it for the other readings
        self.map_ = fmap
        self._query = None
        return self

    def _answers(self, xyz: np.ndarray):
        if self.map_ is None:
            raise InputError('fit the method before predicting')
        xyz = check_queries(xyz)
        if self._query is None or self._query[0] is not xyz:
            ex = self.params.extraction
            self._query = (xyz, query_points(self.map_.facades, xyz, self.resolution, ex.band_back, self.free_reach,
                                             local=self.local_, registration_var=self.map_.registration_var_))
        return self._query[1]

    def predict(self, xyz: np.ndarray) -> np.ndarray:
        """(M,) occupancy probability of the voxels centred at (M, 3) ``xyz`` (map frame,
        metres), in the method's reading."""
        answers = self._answers(xyz)
        model = self.map_.occupancy_ if self.occupancy == 'plsc' else FIXED
        noise, h = surface_terms(self.map_.facades, answers, self.resolution)
        if self.reading == 'solid':
            return model.solid(answers.signed_distance, answers.variance, noise, self.resolution)
        return model.surface(answers.signed_distance, answers.variance, noise, h)

    @property
    def plsc_(self):
        """The PLSC parameters learnt in :meth:`fit` (None with the fixed formula)."""
        return self.map_.occupancy_ if self.occupancy == 'plsc' and self.map_ is not None else None

    def predict_variance(self, xyz: np.ndarray) -> np.ndarray:
        """(M,) surface variance at ``xyz``, m^2; +inf where no façade covers the voxel."""
        var = self._answers(xyz).variance
        return np.where(np.isfinite(var), var, np.inf)

    def diagnostics(self, xyz: np.ndarray) -> dict[str, np.ndarray]:
        """``signed_distance``: (M,) of each voxel centre from the mean surface along the
        façade normal, metres, positive in front; NaN where no façade covers it."""
        return {'signed_distance': self._answers(xyz).signed_distance}


class FacadeGPSolidMethod(FacadeGPMethod):
    """:class:`FacadeGPMethod` in the ``solid`` reading (the node's occupancy)."""

    name = 'Ours (solid)'
    reading_default = 'solid'


class FacadeGPRasterMethod(FacadeGPMethod):
    """:class:`FacadeGPMethod` read from the façade rasters alone: the paper's method, kept
    visible beside the per-point reading that departs from it (issue 26)."""

    name = 'Ours (raster, paper)'
    surface_default = 'raster'


class FacadeGPFixedMethod(FacadeGPMethod):
    """:class:`FacadeGPMethod` with the fixed formula instead of the learnt PLSC."""

    name = 'Ours (fixed)'
    occupancy_default = 'fixed'


class FacadeGPFreeSpaceMethod(FacadeGPMethod):
    """:class:`FacadeGPMethod` with the mapped rays' free space (an extension beyond the
    paper, issue 14): a voxel's learnt PLSC occupancy loses ``carve_`` log-odds per mapped
    ray through it (:func:`~uncertain_facade_map.pipeline.step8_occupancy.carve`), unless
    it holds a mapped point; the rays are the map's stored points' and the weight is
    learnt from them alone (:meth:`~uncertain_facade_map.mapping.facade_map.FacadeMap.calibrate_free_space`)."""

    name = 'Ours + free space'

    def fit(self, points: np.ndarray, origins: np.ndarray) -> FacadeGPFreeSpaceMethod:
        """Build the map, learn PLSC and the carving weight from (N, 3) points and their
        (N, 3) sensor origins (map frame, metres)."""
        super().fit(points, origins)
        self.carve_ = self.map_.calibrate_free_space(self.resolution)
        return self

    def predict(self, xyz: np.ndarray) -> np.ndarray:
        """(M,) carved occupancy of the voxels centred at (M, 3) ``xyz``."""
        p = super().predict(xyz)
        keys = pack_keys(voxel_index(check_queries(xyz), self.resolution))
        return carve(p, self.map_.ray_crossings(keys, self.resolution), self.carve_)
