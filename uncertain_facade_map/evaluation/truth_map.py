"""The ceiling of the occupancy evaluation: the simulator's exact geometry read as a map.

Issue 14: a score means little without the best score reachable under the reference's own
noise. :class:`TruthMethod` answers every voxel from the simulated scene itself, by the
rules our map is read with (:mod:`~uncertain_facade_map.pipeline.step8_occupancy`), so the
gap between our map and it is what the map still gets wrong, and the gap between it and 1
is what no surface map can win (the reference's noise, its grid offsets, rays that pass
under balconies):

- each voxel centre goes to the scene façade whose true surface is nearest along that
  façade's normal, among the façades whose extent holds it from ``band_back`` behind the
  wall plane to ``free_reach`` in front (the same reach as our map's reading); ``s`` is its
  signed distance from the true surface
  (:meth:`~uncertain_facade_map.simulation.scene.Scene.true_depth`, relief, balconies and
  recesses included), positive in front;
- the variance of the surface is 0, the noise variance ``noise_sd^2`` (the simulated
  sensor's range noise), so the ``surface`` reading gives
  ``Phi((h - s)/sd) - Phi((-h - s)/sd)`` and the ``solid`` one ``Phi((r/2 - s)/sd)``;
- a voxel no façade holds gets 0 (surface reading) or 0.5 (solid), as our map.

It needs the scene, so only ``evaluate --scene`` has it; its ``fit`` learns nothing.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..mapping.calibration import scan_voxels
from ..params import MapParams
from ..pipeline.step8_occupancy import FIXED, READINGS, facade_half_depth, fit_plsc
from .baselines.base import OccupancyMethod, check_queries, check_scans

#: How far in front of a façade plane the truth rays start, metres (relief within it).
REACH = 5.0


def true_signed_distance(scene, xyz: np.ndarray, band_back: float, free_reach: float
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance of points from the nearest true façade surface along its normal.

    Args:
        scene: a :class:`~uncertain_facade_map.simulation.scene.Scene`.
        xyz: (K, 3) points, map frame, metres.
        band_back: a façade holds points up to this far behind its wall plane, metres.
        free_reach: and up to this far in front of it, metres.

    Returns:
        ``(s, facade)``: (K,) metres, positive in front of the surface, NaN where no façade
        holds the point; (K,) int scene façade index, -1 where none.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    best = np.full(len(xyz), np.nan)
    which = np.full(len(xyz), -1, dtype=np.int64)
    for f in scene.facades:
        fr = f.frame
        u, v, n = fr.to_facade(xyz).T
        # |s| >= |n| - REACH, so a façade whose plane is farther than that cannot beat the best.
        cand = ((u >= 0) & (u <= fr.length) & (v >= 0) & (v <= fr.height) & (n >= -band_back) & (n <= free_reach)
                & ~(np.abs(n) - REACH > np.abs(best)))
        idx = np.flatnonzero(cand)
        if not len(idx):
            continue
        s = n[idx] - scene.true_depth(f.facade_id, u[idx], v[idx], reach=REACH)
        better = np.isfinite(s) & ~(np.abs(s) >= np.abs(best[idx]))
        best[idx[better]] = s[better]
        which[idx[better]] = f.facade_id
    return best, which


class TruthMethod(OccupancyMethod):
    """The simulated scene's exact geometry as an occupancy map (see the module).

    Args:
        resolution: voxel side, metres.
        scene: the simulated scene the evaluated campaigns come from.
        noise_sd: measurement noise of the reference, metres (the sensor's range noise).
        reading: ``'surface'`` or ``'solid'``, as :class:`~.baselines.facade_gp.FacadeGPMethod`.
        free_reach: how far in front of a wall plane its surface answers, metres.
        occupancy: ``'fixed'`` (the fixed formula) or ``'plsc'`` (its two parameters learnt
            on the mapped scan's own voxels, as our map learns them: a seeded subset of
            50,000 hit voxels against 100,000 of the voxels its rays crossed; nothing need be held
            out, since the truth saw no point).

    Raises:
        InputError: a bad resolution, noise, reading or occupancy.
    """

    name = 'Truth'

    def __init__(self, resolution: float, scene, noise_sd: float = 0.02, reading: str = 'surface',
                 free_reach: float = 50.0, occupancy: str = 'fixed') -> None:
        super().__init__(resolution)
        if not (np.isfinite(noise_sd) and noise_sd > 0):
            raise InputError(f'noise_sd must be a positive number of metres, got {noise_sd!r}')
        if reading not in READINGS:
            raise InputError(f'reading must be one of {", ".join(READINGS)}, got {reading!r}')
        self.scene, self.noise_var, self.reading = scene, float(noise_sd) ** 2, reading
        self.free_reach = float(free_reach)
        if occupancy not in ('plsc', 'fixed'):
            raise InputError(f"occupancy must be 'plsc' or 'fixed', got {occupancy!r}")
        self.occupancy, self._model = occupancy, FIXED
        extra = [w for w, on in (('solid', reading == 'solid'), ('PLSC', occupancy == 'plsc')) if on]
        if extra:
            self.name = f'{TruthMethod.name} ({", ".join(extra)})'
        self._cache: tuple | None = None

    def fit(self, points: np.ndarray, origins: np.ndarray) -> TruthMethod:
        """Nothing to learn but PLSC's two parameters (the inputs are checked as every method's)."""
        points, origins = check_scans(points, origins)
        if self.occupancy == 'plsc':
            labels = scan_voxels(points, origins, self.resolution, max_negatives=100_000, max_positives=50_000)
            s, facade = true_signed_distance(self.scene, labels.centres, MapParams().extraction.band_back,
                                             MapParams().extraction.band_front)
            self._model = fit_plsc(labels.positive, labels.weight, s, np.zeros(len(s)),
                                       np.full(len(s), self.noise_var), self._half_depth(facade))
        return self

    def _answers(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        xyz = check_queries(xyz)
        if self._cache is None or self._cache[0] is not xyz:
            s, facade = true_signed_distance(self.scene, xyz, MapParams().extraction.band_back, self.free_reach)
            self._cache = (xyz, s, facade)
        return self._cache[1], self._cache[2]

    def predict(self, xyz: np.ndarray) -> np.ndarray:
        """(M,) occupancy probability of the voxels centred at (M, 3) ``xyz``."""
        s, facade = self._answers(xyz)
        zero = np.zeros(len(s))
        if self.reading == 'solid':
            return self._model.solid(s, zero, self.noise_var, self.resolution)  # UNKNOWN where no façade
        return self._model.surface(s, zero, self.noise_var, self._half_depth(facade))

    @property
    def plsc_(self):
        """The PLSC parameters learnt in :meth:`fit` (None with the fixed formula)."""
        return self._model if self.occupancy == 'plsc' else None

    def _half_depth(self, facade: np.ndarray) -> np.ndarray:
        normals = np.array([f.frame.n for f in self.scene.facades]).reshape(-1, 3)
        return facade_half_depth(facade, normals, self.resolution)

    def predict_variance(self, xyz: np.ndarray) -> np.ndarray:
        """(M,) 0 where a façade holds the voxel (the truth is exact), +inf elsewhere."""
        s, _ = self._answers(xyz)
        return np.where(np.isfinite(s), 0.0, np.inf)
