"""Occupancy mapping methods of the evaluation, behind one small interface
(:class:`~.base.OccupancyMethod`: ``fit(points, origins)``, ``predict(xyz)``).

:data:`METHODS` maps each method's command-line name to ``module:class``; modules are
imported only when a method is asked for (:func:`make_method`).
"""

from __future__ import annotations

import importlib

from ...errors import InputError
from .base import OccupancyMethod

#: Command-line name -> "module:class" (relative to this package).
METHODS = {
    'ours': 'facade_gp:FacadeGPMethod',
    'ours-raster': 'facade_gp:FacadeGPRasterMethod',
    'ours-fixed': 'facade_gp:FacadeGPFixedMethod',
    'ours-free': 'facade_gp:FacadeGPFreeSpaceMethod',
    'ours-solid': 'facade_gp:FacadeGPSolidMethod',
    'octomap': 'octomap_map:OctoMapMethod',
    'bgk': 'bgk_octomap:BGKOctoMapMethod',
    'gpom': 'gpom:FastGPOMMethod',
    'hilbert': 'hilbert_map:LARDHilbertMapMethod',
    'gpis': 'gpis_map:GPISMapMethod',
    'gpis-solid': 'gpis_map:GPISMapSolidMethod',
}


def make_method(name: str, resolution: float) -> OccupancyMethod:
    """A fresh method by its command-line name, for one resolution.

    Raises:
        InputError: an unknown name or a bad resolution.
    """
    if name not in METHODS:
        raise InputError(f'unknown method {name!r}; choose from {", ".join(METHODS)}')
    module, cls = METHODS[name].split(':')
    return getattr(importlib.import_module(f'.{module}', __name__), cls)(resolution)
