"""Occupancy from the uncertain surface (paper, Section IV.C).

"To make the comparison possible, we first transform our abstract surface map to a 3D
occupancy map, where probabilistic least-squares classification is applied and the
occupancy probabilities are obtained through a cumulative Gaussian density function"
(after GPOM and GPmap). The paper leaves the exact form to its reference; the choice here:

A voxel of side ``r`` centred at signed distance ``s`` from the mean surface (positive
outside the building, along the façade normal) is occupied when any of it lies behind the
true surface, i.e. when the surface depth D ~ N(mu, var + noise_var) reaches the voxel's
outer face::

    p_occupied = P(D >= n - r/2) = Phi((r/2 - s) / sqrt(var + noise_var))

so free space in front of the façade tends to 0, voxels holding the surface to about
Phi(r / 2 sigma), and the solid behind it to 1. The noise variance enters because the
map is compared with measured points, which carry it.

:func:`surface_probability` is the other reading, used by the occupancy evaluation
(:mod:`~uncertain_facade_map.evaluation.baselines.facade_gp`): the probability that the voxel *holds the surface*, i.e.
that a measured point of the surface falls inside it, which is the event the evaluation
calls occupied (a voxel holding reference points)::

    p_surface = P(s - h <= D - n <= s + h) = Phi((h - s) / sigma) - Phi((-h - s) / sigma)

with ``h`` the voxel's half extent along the façade normal (``r/2`` for a wall aligned
with the grid, up to ``r sqrt(3)/2`` otherwise: :func:`half_depth`).
"""

from __future__ import annotations

import numpy as np
from scipy.special import ndtr

#: Occupancy of space no façade model covers (unknown, as in OctoMap).
UNKNOWN = 0.5
#: The two readings of an uncertain surface as occupancy in the evaluation: the
#: probability that the voxel holds the surface, or that it lies behind it (solid).
READINGS = ('surface', 'solid')


def occupancy_probability(signed_distance: np.ndarray, variance: np.ndarray, noise_variance: np.ndarray | float,
                          resolution: float) -> np.ndarray:
    """Probability that the voxel centred at each point is occupied.

    Args:
        signed_distance: (N,) distance of the voxel centre to the mean surface along the
            façade normal, metres, positive outside the building; NaN where unknown.
        variance: (N,) surface variance, m^2.
        noise_variance: (N,) or scalar noise variance, m^2.
        resolution: voxel side, metres.

    Returns:
        (N,) probabilities in [0, 1]; :data:`UNKNOWN` where ``signed_distance`` is NaN.
    """
    s = np.asarray(signed_distance, dtype=np.float64)
    sigma = np.sqrt(np.asarray(variance, dtype=np.float64) + noise_variance)
    with np.errstate(invalid='ignore', divide='ignore'):
        p = ndtr((0.5 * resolution - s) / sigma)
    return np.where(np.isfinite(s), p, UNKNOWN)


def half_depth(normal: np.ndarray, resolution: float) -> np.ndarray:
    """Half extent of an axis-aligned voxel along a direction (its support function).

    Args:
        normal: (N, 3) unit normals (or (3,)), map frame.
        resolution: voxel side, metres.

    Returns:
        (N,) (or scalar) ``r/2 (|n_x| + |n_y| + |n_z|)``, metres: ``r/2`` for a normal along
        an axis, ``r/sqrt(2)`` at 45 degrees in a plane.
    """
    return 0.5 * resolution * np.abs(np.asarray(normal, dtype=np.float64)).sum(axis=-1)


def facade_half_depth(facade: np.ndarray, normals: np.ndarray, resolution: float) -> np.ndarray:
    """Half extent of each voxel along the normal of the façade that holds it.

    Args:
        facade: (N,) int index into ``normals`` of each voxel's façade, -1 where none.
        normals: (F, 3) unit outward normal of each façade, map frame.
        resolution: voxel side, metres.

    Returns:
        (N,) :func:`half_depth` of the voxel's façade normal, metres; ``r/2`` where no façade.
    """
    facade = np.asarray(facade)
    h = np.full(len(facade), 0.5 * resolution)
    known = facade >= 0
    if known.any():
        h[known] = half_depth(np.asarray(normals, dtype=np.float64)[facade[known]], resolution)
    return h


def surface_probability(signed_distance: np.ndarray, variance: np.ndarray, noise_variance: np.ndarray | float,
                        half_extent: np.ndarray | float, outside: float = 0.0) -> np.ndarray:
    """Probability that the voxel centred at each point holds the surface (a measured point).

    Args:
        signed_distance: (N,) distance of the voxel centre to the mean surface along the
            façade normal, metres, positive outside the building; NaN where no façade is.
        variance: (N,) surface variance, m^2.
        noise_variance: (N,) or scalar measurement noise variance, m^2.
        half_extent: (N,) or scalar half extent of the voxel along the normal, metres
            (:func:`half_depth`).
        outside: the probability where ``signed_distance`` is NaN (no façade models the
            voxel, so no surface is there: 0 by default).

    Returns:
        (N,) probabilities in [0, 1].
    """
    s = np.asarray(signed_distance, dtype=np.float64)
    sigma = np.sqrt(np.asarray(variance, dtype=np.float64) + noise_variance)
    h = np.asarray(half_extent, dtype=np.float64)
    with np.errstate(invalid='ignore', divide='ignore'):
        p = ndtr((h - s) / sigma) - ndtr((-h - s) / sigma)
    return np.where(np.isfinite(s), np.clip(p, 0.0, 1.0), outside)
