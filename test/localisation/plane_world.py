"""A seeded world of planes with an analytic map query, for the localiser's tests.

Each plane is ``n . x = d`` with an in-plane box (its extent). The *map* of a plane is off
the truth by an error field, constant over square patches of side ``patch`` (a wall's mean
surface is off by the same amount over a patch, as a GP map's is; ``patch`` inf: one error
per whole plane), drawn N(0, ``variance``) per patch; the query answers the signed distance
to the map's plane with that variance, so an estimator that trusts the variance is right on
average over draws of the map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uncertain_facade_map.localisation import se3

BAND_BACK, BAND_FRONT = 1.0, 2.0


@dataclass
class Plane:
    normal: np.ndarray  # (3,) unit, outward
    offset: float  # n . x on the plane
    lo: np.ndarray  # (3,) box of the plane's points (map frame)
    hi: np.ndarray
    variance: float  # map variance, m^2


@dataclass
class Answers:
    facade: np.ndarray
    signed_distance: np.ndarray
    variance: np.ndarray
    noise_variance: np.ndarray
    normal: np.ndarray


def _plane(normal, offset, lo, hi, variance) -> Plane:
    n = np.asarray(normal, float)
    return Plane(n / np.linalg.norm(n), float(offset), np.asarray(lo, float), np.asarray(hi, float), variance)


def street(variance: float = 0.02**2, corridor: bool = False, ground: bool = True) -> list[Plane]:
    """Two long walls at y = +-8 (normals into the street), cross walls at x = +-25 (a
    junction's façades; not in a corridor), the ground (normal up) unless ``ground`` is False."""
    planes = [_plane([0, -1, 0], -8.0, [-40, 8, 0], [40, 8, 12], variance),
              _plane([0, 1, 0], -8.0, [-40, -8, 0], [40, -8, 12], variance)]
    if not corridor:
        planes += [_plane([-1, 0, 0], -25.0, [25, -20, 0], [25, -8.5, 12], variance),
                   _plane([1, 0, 0], -25.0, [-25, 8.5, 0], [-25, 20, 12], variance * 4)]
    if ground:
        planes.append(_plane([0, 0, 1], 0.0, [-40, -8, 0], [40, 8, 0], variance))
    return planes


class World:
    """Planes, one draw of their map errors (seeded), and the analytic query."""

    def __init__(self, planes: list[Plane], seed: int, patch: float = 1.0, noise_variance: float = 0.0) -> None:
        self.planes, self.patch, self.noise_variance = planes, patch, noise_variance
        self.rng = np.random.default_rng(seed)
        self._errors: dict = {}
        self.calls = 0

    def _error(self, k: int, x: np.ndarray) -> np.ndarray:
        """The map error of plane k at points x (constant per patch, drawn on first use)."""
        cells = (np.floor(x / self.patch) if np.isfinite(self.patch) else np.zeros_like(x)).astype(np.int64)
        keys, inverse = np.unique(cells, axis=0, return_inverse=True)
        values = np.empty(len(keys))
        for i, c in enumerate(map(tuple, keys)):
            key = (k, *c)
            if key not in self._errors:
                self._errors[key] = self.rng.normal(0.0, np.sqrt(self.planes[k].variance))
            values[i] = self._errors[key]
        return values[inverse.ravel()]

    def query(self, xyz: np.ndarray) -> Answers:
        self.calls += 1
        n = len(xyz)
        best = np.full(n, np.inf)
        facade = np.full(n, -1)
        sd = np.full(n, np.nan)
        for k, p in enumerate(self.planes):
            d = xyz @ p.normal - p.offset
            inside = np.all((xyz >= p.lo - 0.5 - np.abs(p.normal) * 3) & (xyz <= p.hi + 0.5 + np.abs(p.normal) * 3), 1)
            ok = inside & (d >= -BAND_BACK) & (d <= BAND_FRONT) & (np.abs(d) < best)
            best[ok], facade[ok], sd[ok] = np.abs(d[ok]), k, d[ok]
        on = facade >= 0
        for k in np.unique(facade[on]):
            sel = facade == k
            sd[sel] -= self._error(int(k), xyz[sel] - self.planes[k].normal * sd[sel, None])
        var = np.full(n, np.nan)
        normal = np.full((n, 3), np.nan)
        var[on] = [self.planes[k].variance for k in facade[on]]
        normal[on] = np.array([self.planes[k].normal for k in facade[on]])
        return Answers(facade, sd, var, np.where(on, self.noise_variance, np.nan), normal)

    def scan(self, pose: np.ndarray, n_points: int, sensor_noise: float, reach: float = 30.0,
             clutter: int = 0) -> np.ndarray:
        """(n_points + clutter, 3) points in the sensor frame: drawn on the true planes within
        ``reach`` of the sensor (in proportion to the visible area), with sensor noise along
        the normal; ``clutter`` points floating in the street (no surface)."""
        c = pose[:3, 3]
        boxes = [(np.maximum(p.lo, c - reach), np.minimum(p.hi, c + reach)) for p in self.planes]
        area = np.array([np.prod(np.sort(np.maximum(hi - lo, 0))[1:]) for lo, hi in boxes])
        counts = self.rng.multinomial(n_points, area / area.sum())
        pts = []
        for (lo, hi), p, m in zip(boxes, self.planes, counts):
            x = lo + (hi - lo) * self.rng.random((m, 3))
            x += p.normal * (p.offset - x @ p.normal)[:, None]
            pts.append(x + p.normal * self.rng.normal(0.0, sensor_noise, (m, 1)))
        if clutter:
            pts.append(c + self.rng.uniform([-15, -5, 0.2], [15, 5, 3], (clutter, 3)) - [0, 0, c[2]])
        world = np.concatenate(pts)
        return se3.transform_points(se3.inverse(pose), world)


def perturbed(pose: np.ndarray, rng: np.random.Generator, metres=(0.5, 3.0), degrees=(1.0, 5.0)) -> np.ndarray:
    """``pose`` moved by a random horizontal offset of 0.5-3 m and a random turn of 1-5 degrees
    about a random axis (mostly yaw), as GNSS in a street canyon errs."""
    dist, ang = rng.uniform(*metres), np.deg2rad(rng.uniform(*degrees))
    heading = rng.uniform(0, 2 * np.pi)
    axis = np.array([*rng.normal(0, 0.3, 2), 1.0])
    axis /= np.linalg.norm(axis)
    out = pose.copy()
    out[:3, :3] = se3.so3_exp(axis * ang) @ pose[:3, :3]
    out[:3, 3] += [dist * np.cos(heading), dist * np.sin(heading), rng.normal(0, 0.3)]
    return out
