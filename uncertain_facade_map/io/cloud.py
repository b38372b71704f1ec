"""Point clouds as numpy structured arrays, the record every reader and writer exchanges.

A :class:`Cloud` is a one-dimensional structured array of points plus the map origin.
Coordinates are in the *map frame*: georeferenced coordinates minus ``map_origin``, so that
float32 storage keeps millimetres near the origin while the origin keeps the georeference.

Standard fields (any reader may add others, all are carried through unchanged):

========== ========= ===========================================================
name       dtype     meaning
========== ========= ===========================================================
x, y, z    f8 or f4  point, metres, map frame
origin_x.. same      sensor origin at the time of the return, metres, map frame
time       f8        time of the return, seconds since the UNIX epoch
building_id i4       building the point belongs to, -1 for none or unknown
class      u1        semantic class, see :data:`CLASS_NAMES`
gt_facade  i4        simulator truth: scene-wide façade index hit, -1 for none
gt_outlier u1        simulator truth: 1 for a misclassified (outlier) return
========== ========= ===========================================================
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable, Sequence

import numpy as np

from ..errors import InputError

#: Semantic classes written by the simulator; only ``building`` is mapped by default.
CLASS_NAMES = {0: 'other', 1: 'building', 2: 'ground', 3: 'vegetation', 4: 'vehicle', 5: 'pole'}
CLASS_BUILDING = 1

#: Per-point fields of a simulated cloud, in file order (``xyz_dtype`` replaces ``f8``).
SIMULATED_FIELDS: tuple[tuple[str, str], ...] = (
    ('x', 'f8'), ('y', 'f8'), ('z', 'f8'),
    ('origin_x', 'f8'), ('origin_y', 'f8'), ('origin_z', 'f8'),
    ('time', 'f8'),
    ('building_id', 'i4'),
    ('class', 'u1'),
    ('gt_facade', 'i4'),
    ('gt_outlier', 'u1'),
)

COORDINATE_FIELDS = ('x', 'y', 'z', 'origin_x', 'origin_y', 'origin_z')


def simulated_dtype(xyz_dtype: str = 'f8') -> np.dtype:
    """Return the structured dtype of simulated points.

    Args:
        xyz_dtype: ``'f8'`` or ``'f4'``, the type of the coordinate fields.

    Returns:
        A packed structured dtype with the fields of :data:`SIMULATED_FIELDS`.

    Raises:
        InputError: ``xyz_dtype`` is neither ``'f8'`` nor ``'f4'``.
    """
    if xyz_dtype not in ('f8', 'f4'):
        raise InputError(f"coordinate dtype must be 'f8' or 'f4', not {xyz_dtype!r}")
    return np.dtype([(n, xyz_dtype if n in COORDINATE_FIELDS else t) for n, t in SIMULATED_FIELDS])


@dataclass(frozen=True, eq=False)
class Cloud:
    """Points with per-point fields, in the map frame.

    Attributes:
        points: structured array, shape (N,), with at least the fields x, y, z.
        map_origin: (3,) float64, metres; georeferenced = map frame + map_origin.
    """

    points: np.ndarray
    map_origin: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        pts = self.points
        if not isinstance(pts, np.ndarray) or pts.dtype.names is None:
            raise InputError('a cloud needs a structured array of points')
        if pts.ndim != 1:
            raise InputError(f'a cloud is one-dimensional, got shape {pts.shape}')
        missing = [n for n in ('x', 'y', 'z') if n not in pts.dtype.names]
        if missing:
            raise InputError(f'cloud has no field {", ".join(missing)} (fields: {", ".join(pts.dtype.names)})')
        origin = np.asarray(self.map_origin, dtype=np.float64).reshape(-1)
        if origin.shape != (3,) or not np.all(np.isfinite(origin)):
            raise InputError(f'map origin must be 3 finite numbers, got {self.map_origin!r}')
        object.__setattr__(self, 'map_origin', origin)

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def fields(self) -> tuple[str, ...]:
        """Names of the per-point fields, in storage order."""
        return tuple(self.points.dtype.names)

    @property
    def xyz(self) -> np.ndarray:
        """(N, 3) float64 coordinates, metres, map frame."""
        return self.columns(('x', 'y', 'z'))

    @property
    def sensor_origins(self) -> np.ndarray | None:
        """(N, 3) float64 sensor origins, metres, map frame; None if the cloud has none."""
        names = ('origin_x', 'origin_y', 'origin_z')
        if not all(n in self.fields for n in names):
            return None
        return self.columns(names)

    def columns(self, names: Sequence[str]) -> np.ndarray:
        """Stack fields into an (N, len(names)) float64 array."""
        out = np.empty((len(self), len(names)), dtype=np.float64)
        for i, name in enumerate(names):
            out[:, i] = self.points[name]
        return out

    def get(self, name: str, default: float | int | None = None) -> np.ndarray | None:
        """Return field ``name`` (shape (N,)), or a constant array of ``default``, or None."""
        if name in self.fields:
            return self.points[name]
        if default is None:
            return None
        return np.full(len(self), default)

    def select(self, mask: np.ndarray) -> Cloud:
        """Return the points where ``mask`` (bool (N,) or an index array) holds."""
        return Cloud(self.points[mask], self.map_origin)

    def check_finite(self) -> None:
        """Raise :class:`InputError` if any coordinate is NaN or infinite."""
        for name in ('x', 'y', 'z'):
            bad = ~np.isfinite(self.points[name])
            if bad.any():
                raise InputError(f'{int(bad.sum())} of {len(self)} points have a NaN or infinite {name}')

    def same_as(self, other: Cloud) -> bool:
        """True if both clouds hold the same fields, bytes and map origin."""
        return (
            self.points.dtype == other.points.dtype
            and np.array_equal(self.map_origin, other.map_origin)
            and self.points.tobytes() == other.points.tobytes()
        )

    @staticmethod
    def concatenate(clouds: Iterable[Cloud]) -> Cloud:
        """Join clouds with equal dtypes and map origins into one.

        Raises:
            InputError: no cloud given, or the clouds' fields or origins differ.
        """
        clouds = list(clouds)
        if not clouds:
            raise InputError('nothing to concatenate')
        first = clouds[0]
        for other in clouds[1:]:
            if other.points.dtype != first.points.dtype:
                raise InputError('clouds with different fields cannot be joined')
            if not np.array_equal(other.map_origin, first.map_origin):
                raise InputError('clouds with different map origins cannot be joined')
        return Cloud(np.concatenate([c.points for c in clouds]), first.map_origin)
