"""The map as the localiser's ``query``: answers with surface normals.

:func:`map_query` wraps :meth:`FacadeMap.query <uncertain_facade_map.mapping.facade_map.FacadeMap.query>`
(or a ``MapSnapshot``'s): when the answer has no ``normal`` yet (``PointQuery`` before issue 28's
item 1), each answered point gets its façade's plane normal (map frame, outward), NaN where
``facade == -1``.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import numpy as np

__all__ = ['WithNormals', 'map_query']


@dataclasses.dataclass(frozen=True)
class WithNormals:
    """A map's answers (N,) with (N, 3) ``normal`` added (the attributes of ``PointQuery``)."""

    facade: np.ndarray
    signed_distance: np.ndarray
    variance: np.ndarray
    noise_variance: np.ndarray
    normal: np.ndarray


def map_query(source: Any, config: Any = None, resolution: float | None = None) -> Callable[[np.ndarray], Any]:
    """``query(xyz)`` for :func:`~uncertain_facade_map.localisation.localise` from a map.

    Args:
        source: a ``FacadeMap`` or ``MapSnapshot`` (anything with ``query(xyz, config,
            resolution)`` and ``facades`` whose ``frame.normal`` is the outward plane normal).
        config: the ``query`` settings (``QueryConfig``; default: the defaults).
        resolution: voxel side of ``p_occupied`` (unused by the localiser; default the config's).
    """
    normals = np.array([f.frame.normal for f in source.facades], dtype=np.float64).reshape(-1, 3)

    def query(xyz: np.ndarray) -> Any:
        ans = source.query(xyz, config, resolution)
        if getattr(ans, 'normal', None) is not None:
            return ans
        facade = np.asarray(ans.facade)
        normal = np.full((len(facade), 3), np.nan)
        on = facade >= 0
        normal[on] = normals[facade[on]]
        return WithNormals(facade, ans.signed_distance, ans.variance, ans.noise_variance, normal)

    return query
