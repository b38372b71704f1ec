"""The tile grid: squares of side ``side`` of the map frame's x, y plane, from its origin.

Tile ``(ix, iy)`` is the half-open square ``[ix side, (ix + 1) side) x [iy side, (iy + 1) side)``
(metres, map frame). :meth:`TileGrid.index` and :meth:`TileGrid.bounds` agree to the last
bit: a point's index is that of the square whose bounds, as :meth:`TileGrid.bounds` computes
them, hold it (``floor(x / side)`` corrected where its rounding disagrees with
``ix * side``).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from ..errors import InputError

__all__ = ['TileGrid', 'tile_id', 'parse_tile_id', 'tile_file']

_ID = re.compile(r'^tile_(m?)(\d+)_(m?)(\d+)$')


@dataclass(frozen=True)
class TileGrid:
    """Square tiles of the map frame's x, y plane.

    Attributes:
        side: side of a tile, metres (finite, > 0).
    """

    side: float

    def __post_init__(self) -> None:
        try:
            side = float(self.side)
        except (TypeError, ValueError):
            raise InputError(f'tile side must be a number of metres, got {self.side!r}') from None
        if not (math.isfinite(side) and side > 0):
            raise InputError(f'tile side must be a finite number of metres > 0, got {self.side!r}')
        object.__setattr__(self, 'side', side)

    def index(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) int64 tile indices ``(ix, iy)`` of (N, 2) map-frame x, y (metres; extra
        columns, e.g. z, are ignored; a single (2,) point gives (1, 2)).

        Raises:
            InputError: not an (N, >= 2) array, or NaN / infinite coordinates.
        """
        xy = np.asarray(xy, dtype=np.float64)
        if xy.ndim == 1:
            xy = xy[None]
        if xy.ndim != 2 or xy.shape[1] < 2:
            raise InputError(f'tile index needs (N, 2) x, y coordinates, got shape {xy.shape}')
        xy = xy[:, :2]
        if not np.isfinite(xy).all():
            raise InputError('tile index needs finite x, y coordinates (NaN or infinite found)')
        s = self.side
        idx = np.floor(xy / s)
        # The square's bounds are computed as idx * side: where the division's rounding puts
        # a point on the other side of a boundary, follow the bounds.
        idx -= xy < idx * s
        idx += xy >= (idx + 1) * s
        return idx.astype(np.int64)

    def bounds(self, ix: int, iy: int) -> tuple[float, float, float, float]:
        """``(min_x, min_y, max_x, max_y)`` of tile ``(ix, iy)``'s square, metres, map frame
        (min inclusive, max exclusive)."""
        s = self.side
        ix, iy = float(int(ix)), float(int(iy))
        return (ix * s, iy * s, (ix + 1.0) * s, (iy + 1.0) * s)


def _part(i: int) -> str:
    return f'm{-i}' if i < 0 else str(i)


def tile_id(ix: int, iy: int) -> str:
    """The id of tile ``(ix, iy)``: ``tile_{ix}_{iy}``, a negative index written ``m`` and its
    magnitude (``tile_m3_12``), so that ids are file names."""
    return f'tile_{_part(int(ix))}_{_part(int(iy))}'


def parse_tile_id(text: str) -> tuple[int, int]:
    """``(ix, iy)`` of a tile id (inverse of :func:`tile_id`).

    Raises:
        InputError: not a tile id.
    """
    m = _ID.match(str(text))
    if m is None:
        raise InputError(f'not a tile id: {text!r} (expected tile_IX_IY, negatives as m3)')
    ix, iy = int(m.group(2)), int(m.group(4))
    if (m.group(1) and ix == 0) or (m.group(3) and iy == 0):
        raise InputError(f'not a tile id: {text!r} (m0 is written 0)')
    return (-ix if m.group(1) else ix), (-iy if m.group(3) else iy)


def tile_file(tile: str) -> str:
    """The file of tile ``tile`` relative to the map's folder: ``tiles/<id>.npz``."""
    return f'tiles/{tile}.npz'
