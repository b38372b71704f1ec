"""The local frame of a façade: 2.5D coordinates (u, v) on the plane and depth d along the normal.

Paper, Section IV.B: "The building façades obtained from the RANSAC are firstly
transformed individually to the local frame of their main planes, where a map point is a
2.5-dimensional point P = {x, d}, with the location x in R^2 on the plane and the depth
value d in the direction of the plane normal (derived by the PCA using all façade points)."

Axes: ``normal`` points out of the building (towards the street); ``e_u`` is horizontal
in the plane; ``e_v = normal x e_u`` points up the plane (straight up for a vertical
façade). All coordinates are metres; world points are in the map frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError

_UP = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True, eq=False)
class FacadeFrame:
    """Orthonormal façade frame.

    Attributes:
        origin: (3,) a point of the plane, metres, map frame.
        axes: (3, 3) rows e_u, e_v, normal (unit, right-handed), map frame.
    """

    origin: np.ndarray
    axes: np.ndarray

    def __post_init__(self) -> None:
        origin = np.asarray(self.origin, dtype=np.float64).reshape(3)
        axes = np.asarray(self.axes, dtype=np.float64).reshape(3, 3)
        if not np.allclose(axes @ axes.T, np.eye(3), atol=1e-9):
            raise InputError('façade axes must be orthonormal')
        object.__setattr__(self, 'origin', origin)
        object.__setattr__(self, 'axes', axes)

    @classmethod
    def from_normal(cls, origin: np.ndarray, normal: np.ndarray) -> FacadeFrame:
        """Frame with the given outward normal, ``e_u`` horizontal, ``e_v`` up the plane.

        Args:
            origin: (3,) point of the plane, metres.
            normal: (3,) outward normal (need not be unit length; must not be vertical).

        Raises:
            InputError: the normal is (nearly) vertical, i.e. the plane is a roof or floor.
        """
        n = np.asarray(normal, dtype=np.float64)
        n = n / np.linalg.norm(n)
        e_u = np.cross(_UP, n)
        norm = np.linalg.norm(e_u)
        if norm < 1e-6:
            raise InputError('a façade plane cannot be horizontal')
        e_u /= norm
        e_v = np.cross(n, e_u)
        return cls(origin, np.stack([e_u, e_v, n]))

    @property
    def normal(self) -> np.ndarray:
        """(3,) outward unit normal."""
        return self.axes[2]

    def to_local(self, xyz: np.ndarray) -> np.ndarray:
        """(N, 3) map-frame points -> (N, 3) façade coordinates (u, v, d), metres."""
        return (np.asarray(xyz, dtype=np.float64) - self.origin) @ self.axes.T

    def to_world(self, uvd: np.ndarray) -> np.ndarray:
        """(N, 3) façade coordinates (u, v, d) -> (N, 3) map-frame points, metres."""
        return np.asarray(uvd, dtype=np.float64) @ self.axes + self.origin

    def directions_to_local(self, vectors: np.ndarray) -> np.ndarray:
        """(N, 3) map-frame directions (e.g. normals) -> (N, 3) in façade axes."""
        return np.asarray(vectors, dtype=np.float64) @ self.axes.T

    def as_array(self) -> np.ndarray:
        """(4, 3) float64: origin then the three axes (for map files)."""
        return np.vstack([self.origin, self.axes])

    @classmethod
    def from_array(cls, array: np.ndarray) -> FacadeFrame:
        """Inverse of :meth:`as_array`."""
        array = np.asarray(array, dtype=np.float64)
        if array.shape != (4, 3):
            raise InputError(f'a façade frame is a (4, 3) array, got {array.shape}')
        return cls(array[0], array[1:])
