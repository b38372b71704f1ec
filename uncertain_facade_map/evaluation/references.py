"""Reference maps for the benchmark: what a map must beat, built from the same mapped points.

Each map answers 3D points as the package's query does (:class:`Answers`: signed distance
to its surface, positive outside, a variance, a noise variance and the occupancy
probability of the voxel centred at the point), so that the benchmark
(:mod:`~uncertain_facade_map.evaluation.benchmark`) scores every map by the same code.

- :class:`LocalPlaneMap`: a plane through the ``k`` (12) nearest mapped points by PCA.
  It is **the same map as** ``../shared/tools/localplane_map.py``, the local-plane map of
  the independent checker ``real_check.py``, so that the benchmark's local-plane row
  agrees with the checker's: the plane through the neighbours' centroid with the normal
  of the smallest eigenvalue of their covariance (divided by ``k``); surface variance =
  that smallest eigenvalue + (mean distance to the neighbours)^2 x 0.05; noise variance
  0.02^2 m^2 added for intervals; occupancy of a voxel of side r at distance s:
  Phi((|s| + r/2) / sd) - Phi((|s| - r/2) / sd), sd = sqrt(variance + noise variance)
  (the probability that the surface crosses the voxel). The one addition: the checker
  leaves the sign of the PCA normal as the eigen-solver gives it; here it is turned
  towards the viewpoint (the neighbours' mean sensor origin, or the sensor), so that the
  signed distance means outside and its bias can be read. RMSE, coverage, NLL, CRPS and
  occupancy do not depend on that sign.
- :class:`FacadePlaneMap`: one plane per façade of a package map, the PCA plane of the
  façade's mapped points (all points the map allocated to it, outliers included), normal
  on the façade's outward side; variance = residual variance of those points about the
  plane (mean squared distance, which holds their noise: the noise variance is 0); the
  points answered are those the package map gives to the façade (its query's rule), the
  occupancy as for the local plane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import norm

from ..errors import InputError
from ..mapping.facade_map import FacadeMap
from ..params import QueryConfig

#: The package map's façade of a point: the rasters' bands alone (the paper's reading).
_RASTER = QueryConfig(surface='raster')

#: Points answered at once by the local-plane map (bounds the (chunk, k, 3) arrays).
_CHUNK = 200_000


@dataclass(frozen=True, eq=False)
class Answers:
    """A map's answers for N points (NaN where it has none).

    Attributes:
        signed_distance: (N,) distance of the point from the map's mean surface along the
            map's normal, metres, positive outside (towards the street).
        variance: (N,) variance of the mean surface there, m^2.
        noise_variance: (N,) variance of a measurement about the surface, m^2.
        p_occupied: (N,) occupancy probability of the voxel centred at the point.
    """

    signed_distance: np.ndarray
    variance: np.ndarray
    noise_variance: np.ndarray
    p_occupied: np.ndarray

    @property
    def answered(self) -> np.ndarray:
        """(N,) bool: the map answered the point (finite distance and variance)."""
        return np.isfinite(self.signed_distance) & np.isfinite(self.variance) & np.isfinite(self.noise_variance)


def surface_band_probability(distance: np.ndarray, sd: np.ndarray, resolution: float) -> np.ndarray:
    """(N,) probability that a surface at ``distance`` (metres, sd ``sd``) crosses a voxel of
    side ``resolution`` centred at the point: Phi((|s| + r/2)/sd) - Phi((|s| - r/2)/sd)."""
    a = np.abs(distance)
    return norm.cdf((a + resolution / 2) / sd) - norm.cdf((a - resolution / 2) / sd)


class LocalPlaneMap:
    """A plane through the ``k`` nearest mapped points (see the module docstring).

    Args:
        points: (M, 3) mapped points, metres, map frame.
        viewpoints: (M, 3) sensor origin of each mapped point, or (3,) one sensor position,
            or None (the normal keeps the eigen-solver's sign).
        k: neighbours per plane (12).
        spread_factor: weight of the squared mean neighbour distance in the variance (0.05).
        noise_sd: measurement noise for intervals, metres (0.02).
    """

    name = 'local plane'

    def __init__(self, points: np.ndarray, viewpoints: np.ndarray | None = None, k: int = 12,
                 spread_factor: float = 0.05, noise_sd: float = 0.02) -> None:
        self.points = np.asarray(points, dtype=np.float64)
        if self.points.ndim != 2 or self.points.shape[1] != 3 or len(self.points) < k:
            raise InputError(f'the local-plane map needs at least {k} (M, 3) points, got shape {self.points.shape}')
        self.viewpoints = None if viewpoints is None else np.asarray(viewpoints, dtype=np.float64)
        self.k, self.spread_factor, self.noise_var = int(k), float(spread_factor), float(noise_sd) ** 2
        self.tree = cKDTree(self.points)

    def planes(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(centroid (N, 3), unit normal (N, 3), smallest eigenvalue (N,), mean neighbour
        distance (N,))`` of the local plane of each of (N, 3) points."""
        dist, idx = self.tree.query(xyz, k=self.k)
        nb = self.points[idx]
        centroid = nb.mean(axis=1)
        rel = nb - centroid[:, None]
        cov = np.einsum('nki,nkj->nij', rel, rel) / self.k
        w, vec = np.linalg.eigh(cov)
        normal = vec[:, :, 0]
        if self.viewpoints is not None:
            view = self.viewpoints if self.viewpoints.ndim == 1 else self.viewpoints[idx].mean(axis=1)
            flip = np.einsum('ni,ni->n', view - centroid, normal) < 0
            normal[flip] *= -1.0
        return centroid, normal, np.maximum(w[:, 0], 0.0), dist.mean(axis=1)

    def query(self, xyz: np.ndarray, resolution: float) -> Answers:
        """Answers for (N, 3) points (every point is answered); ``resolution`` is the voxel side, metres."""
        xyz = np.asarray(xyz, dtype=np.float64)
        n = len(xyz)
        s, var = np.empty(n), np.empty(n)
        for start in range(0, n, _CHUNK):
            part = slice(start, min(start + _CHUNK, n))
            centroid, normal, smallest, spread = self.planes(xyz[part])
            s[part] = np.einsum('ni,ni->n', xyz[part] - centroid, normal)
            var[part] = smallest + spread**2 * self.spread_factor
        noise = np.full(n, self.noise_var)
        return Answers(s, var, noise, surface_band_probability(s, np.sqrt(var + noise), resolution))


class FacadePlaneMap:
    """One PCA plane per façade of a package map (see the module docstring).

    Args:
        fmap: the package's map; its façades' allocated points define the planes.
    """

    name = 'façade plane'

    def __init__(self, fmap: FacadeMap) -> None:
        self.fmap = fmap
        ids, normals, centroids, variances = [], [], [], []
        for f in fmap.facades:
            pts = fmap.points[f.building][f.point_index]
            if len(pts) < 3:
                continue
            centroid = pts.mean(axis=0)
            rel = pts - centroid
            w, vec = np.linalg.eigh(rel.T @ rel / len(pts))
            normal = vec[:, 0] if vec[:, 0] @ f.frame.normal >= 0 else -vec[:, 0]
            ids.append(f.facade_id)
            normals.append(normal)
            centroids.append(centroid)
            variances.append(max(float(w[0]), 0.0))
        self.normal = np.full((len(fmap.facades), 3), np.nan)
        self.centroid = np.full((len(fmap.facades), 3), np.nan)
        self.variance = np.full(len(fmap.facades), np.nan)
        self.normal[ids], self.centroid[ids], self.variance[ids] = normals, centroids, variances

    def query(self, xyz: np.ndarray, resolution: float) -> Answers:
        """Answers for (N, 3) points: NaN where the package map gives the point no façade."""
        xyz = np.asarray(xyz, dtype=np.float64)
        facade = self.fmap.query(xyz, _RASTER, resolution).facade
        s, var = np.full(len(xyz), np.nan), np.full(len(xyz), np.nan)
        on = np.flatnonzero(facade >= 0)
        f = facade[on]
        s[on] = np.einsum('ni,ni->n', xyz[on] - self.centroid[f], self.normal[f])
        var[on] = self.variance[f]
        noise = np.where(np.isfinite(var), 0.0, np.nan)
        with np.errstate(invalid='ignore', divide='ignore'):
            p = surface_band_probability(s, np.sqrt(var), resolution)
        return Answers(s, var, noise, np.where(np.isfinite(p), p, 0.5))
