"""Walls as built rather than as drawn: relief, plaster and glass (:class:`WallRealism`).

A scene with ``walls`` set (the ``*_hard`` scenes, :mod:`.scenes`) differs from its plan in
three ways:

- *Relief*, part of the true surface: every façade bows, leans and undulates by a
  smooth depth field r(u, v) (metres along its outward normal, in its frame) of
  centimetres over metres::

      r(u, v) = bow sin(pi u / L) sin(pi v / H) + lean v + sum_k a_k sin(2 pi u / lu_k + pu_k) sin(2 pi v / lv_k + pv_k)

  with L, H the wall's length and height (u, v clipped to the wall). The whole façade
  moves with it, detail included: a point (u, v, n) of the plan lies at (u, v, n + r(u, v)).
  Rays are intersected with the bent façade exactly up to the curvature of r: a ray
  hitting a façade is cast again against the plan after the inverse bend, linearised at
  its hit, twice (:meth:`FacadeRelief.bend`). :meth:`~.scene.Scene.true_depth` and
  :meth:`~.scene.Scene.true_surface_along` include the relief: it is the truth a map is
  scored against.
- *Plaster*, not part of the truth: a texture of ``plaster`` metres standard deviation on
  a ``plaster_cell`` grid (a few centimetres, below the map's raster), the same in every
  campaign, moves each return along the façade normal. The truth is the wall smoothed
  below the texture's scale, so for a map the plaster is noise (spatially correlated,
  and repeated in every drive).
- *Glass*: window and door recesses are glazed inside a frame of ``frame`` metres. A
  share ``glass_share`` of the shots that reach a pane pass into the room and return
  from ``room_depth`` (min, max) metres further along the ray; they are measurement
  artefacts, outliers with respect to the true surface (``gt_outlier`` = 2), and keep the
  façade's building id as a classifier would give them.

Mixed returns at edges, range- and incidence-dependent noise, quantisation and
registration offsets belong to the sensor (:mod:`.sensor`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError

#: How far (metres along the normal) a hit may lie from a recess back to count as on the pane.
PANE_TOLERANCE = 5e-3


@dataclass(frozen=True)
class WallRealism:
    """How real walls differ from their plans (lengths in metres).

    Attributes:
        bow: (min, max) magnitude of the bow, the depth of the wall's middle over its edges
            (sign random: out or in).
        lean: (min, max) magnitude of the lean, metres per metre of height (sign random).
        waviness: (min, max) amplitude of each of the ``waves`` undulations.
        waves: number of undulations (wavelengths 1.5 to 6 m along and up the wall).
        plaster: standard deviation of the plaster texture.
        plaster_cell: grid step of the plaster texture.
        glass_share: share of the shots at a window pane that return from inside the room.
        room_depth: (min, max) distance behind the pane of a return from the room.
        frame: width of the window frame around the pane (not glass).
    """

    bow: tuple[float, float] = (0.01, 0.04)
    lean: tuple[float, float] = (0.0005, 0.003)
    waviness: tuple[float, float] = (0.001, 0.004)
    waves: int = 2
    plaster: float = 0.002
    plaster_cell: float = 0.02
    glass_share: float = 0.25
    room_depth: tuple[float, float] = (0.5, 5.0)
    frame: float = 0.06

    def __post_init__(self) -> None:
        checks = [
            (0 <= self.bow[0] <= self.bow[1], 'bow must be 0 <= min <= max'),
            (0 <= self.lean[0] <= self.lean[1] < 0.05, 'lean must be 0 <= min <= max < 0.05'),
            (0 <= self.waviness[0] <= self.waviness[1], 'waviness must be 0 <= min <= max'),
            (self.waves >= 0, 'waves must be >= 0'),
            (self.plaster >= 0 and self.plaster_cell > 0, 'plaster must be >= 0 and plaster_cell > 0'),
            (0 <= self.glass_share <= 1, 'glass_share must be in [0, 1]'),
            (0 < self.room_depth[0] <= self.room_depth[1], 'room_depth must be 0 < min <= max'),
            (self.frame >= 0, 'frame must be >= 0'),
        ]
        for ok, message in checks:
            if not ok:
                raise InputError(f'walls: {message}')


@dataclass(frozen=True)
class FacadeRelief:
    """The relief of one façade (see the module docstring for r(u, v)).

    Attributes:
        length: wall length L, metres.
        height: wall height H, metres.
        bow: signed bow, metres.
        lean: signed lean, metres per metre.
        waves: (K, 5) per undulation: amplitude (m), wavelength along u (m), phase along u,
            wavelength along v (m), phase along v (radians).
        texture_seed: seed of the plaster texture.
    """

    length: float
    height: float
    bow: float
    lean: float
    waves: np.ndarray
    texture_seed: int

    @classmethod
    def draw(cls, walls: WallRealism, length: float, height: float, rng: np.random.Generator) -> FacadeRelief:
        """A random relief within the ranges of ``walls``."""
        sign = rng.choice([-1.0, 1.0], size=2)
        bow = float(sign[0] * rng.uniform(*walls.bow))
        lean = float(sign[1] * rng.uniform(*walls.lean))
        k = walls.waves
        waves = np.stack([rng.uniform(*walls.waviness, size=k), rng.uniform(1.5, 6.0, size=k),
                          rng.uniform(0, 2 * np.pi, size=k), rng.uniform(1.5, 6.0, size=k),
                          rng.uniform(0, 2 * np.pi, size=k)], axis=1)
        return cls(length, height, bow, lean, waves, int(rng.integers(2**62)))

    def depth(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The relief and its gradient.

        Args:
            u: (N,) positions along the wall, metres, façade frame.
            v: (N,) heights, metres.

        Returns:
            ``(r, dr/du, dr/dv)``, each (N,): metres, and metres per metre (0 across the
            clipped edges of the wall).
        """
        inside_u = (u > 0) & (u < self.length)
        inside_v = (v > 0) & (v < self.height)
        uc = np.clip(u, 0.0, self.length)
        vc = np.clip(v, 0.0, self.height)
        au, av = np.pi / self.length, np.pi / self.height
        su, sv = np.sin(au * uc), np.sin(av * vc)
        r = self.bow * su * sv + self.lean * vc
        du = self.bow * au * np.cos(au * uc) * sv
        dv = self.bow * av * su * np.cos(av * vc) + self.lean
        for a, lu, pu, lv, pv in self.waves:
            ku, kv = 2 * np.pi / lu, 2 * np.pi / lv
            wu, wv = np.sin(ku * uc + pu), np.sin(kv * vc + pv)
            r = r + a * wu * wv
            du = du + a * ku * np.cos(ku * uc + pu) * wv
            dv = dv + a * kv * wu * np.cos(kv * vc + pv)
        return r, np.where(inside_u, du, 0.0), np.where(inside_v, dv, 0.0)

    def bend(self, uvn_origin: np.ndarray, uvn_direction: np.ndarray, hit_uv: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
        """Rays through the bent façade as rays through its plan, linearised at a hit.

        A point (u, v, n) of the bent façade is the point (u, v, n - r(u, v)) of the plan;
        with r linear around ``hit_uv`` a straight ray stays straight, with the same range
        parameter.

        Args:
            uvn_origin: (N, 3) ray origins in the façade frame, metres.
            uvn_direction: (N, 3) unit directions in the façade frame.
            hit_uv: (N, 2) where to linearise r, metres.

        Returns:
            ``(origin, direction)``: (N, 3) each, in the façade frame, of the rays through
            the plan; the directions are not unit (range t is the same on both).
        """
        r, gu, gv = self.depth(hit_uv[:, 0], hit_uv[:, 1])
        shift = r + gu * (uvn_origin[:, 0] - hit_uv[:, 0]) + gv * (uvn_origin[:, 1] - hit_uv[:, 1])
        origin = uvn_origin.copy()
        origin[:, 2] -= shift
        direction = uvn_direction.copy()
        direction[:, 2] -= gu * uvn_direction[:, 0] + gv * uvn_direction[:, 1]
        return origin, direction

    def plaster(self, u: np.ndarray, v: np.ndarray, sigma: float, cell: float) -> np.ndarray:
        """(N,) the plaster texture at (u, v), metres: value noise of standard deviation
        ``sigma`` on a ``cell`` grid, a fixed function of the façade (same in every campaign)."""
        if sigma == 0:
            return np.zeros(len(u))
        gu, gv = np.asarray(u) / cell, np.asarray(v) / cell
        iu, iv = np.floor(gu).astype(np.int64), np.floor(gv).astype(np.int64)
        fu, fv = gu - iu, gv - iv
        # Uniform node values of standard deviation 1; bilinear interpolation of independent
        # nodes has 2/3 of their standard deviation on average (E[(1-f)^2 + f^2] = 2/3 per axis).
        vals = [_hash_uniform(iu + a, iv + b, self.texture_seed) for a in (0, 1) for b in (0, 1)]
        mixed = ((1 - fu) * (1 - fv) * vals[0] + (1 - fu) * fv * vals[1] + fu * (1 - fv) * vals[2]
                 + fu * fv * vals[3])
        return sigma * 1.5 * np.sqrt(3.0) * (2.0 * mixed - 1.0)


def _hash_uniform(i: np.ndarray, j: np.ndarray, seed: int) -> np.ndarray:
    """Uniform [0, 1) values, a fixed function of integer cells (i, j) and a seed (splitmix64)."""
    with np.errstate(over='ignore'):
        x = (i.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)) ^ (j.astype(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F))
        x ^= np.uint64(seed & 0xFFFFFFFFFFFFFFFF)
        x += np.uint64(0x9E3779B97F4A7C15)
        x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        x ^= x >> np.uint64(31)
    return (x >> np.uint64(11)).astype(np.float64) / float(2**53)


def panes(features: tuple, frame: float) -> np.ndarray:
    """(K, 5) the window panes of a façade: u0, u1, v0, v1 (inside the frame) and the
    depth of the recess back, metres, façade frame."""
    from .scene import Recess

    rows = [(f.u0 + frame, f.u1 - frame, f.v0 + frame, f.v1 - frame, f.depth)
            for f in features if isinstance(f, Recess) and f.u1 - f.u0 > 2 * frame and f.v1 - f.v0 > 2 * frame]
    return np.array(rows, dtype=np.float64).reshape(-1, 5)


def on_pane(uvn_plan: np.ndarray, pane: np.ndarray) -> np.ndarray:
    """(N,) bool: points (u, v, n of the plan, façade frame) on one of the panes."""
    if not len(pane) or not len(uvn_plan):
        return np.zeros(len(uvn_plan), dtype=bool)
    u, v, n = uvn_plan[:, 0:1], uvn_plan[:, 1:2], uvn_plan[:, 2:3]
    hit = ((u >= pane[:, 0]) & (u <= pane[:, 1]) & (v >= pane[:, 2]) & (v <= pane[:, 3])
           & (np.abs(n + pane[:, 4]) < PANE_TOLERANCE))
    return hit.any(axis=1)
