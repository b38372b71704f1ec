"""GP training points: the points the depth layers do not explain (paper, Section III.C, eqs. 7 and 8).

"Points that are not close enough to the corresponding GMM component, or whose normal
vectors deviate from the façade normal, are used as training points for the GPs." A point
of layer k is a training point if ``|d - mu_k| > 1.96 sigma_k`` (eq. 7) or if its normal's
component along the façade normal is below ``cos(alpha_z)`` (eq. 8).
"""

from __future__ import annotations

import numpy as np

from ..datatypes import DepthLayers
from ..params import GPParams
from ._gp_kernels import capped_draw
from .step4_gp_blocks import block_codes


def select_training(depth: np.ndarray, normal_cos: np.ndarray, layer: np.ndarray, layers: DepthLayers,
                    gp: GPParams) -> np.ndarray:
    """GP training points: not explained by their facet's layer (paper eqs. 7 and 8).

    Args:
        depth: (N,) depths, metres.
        normal_cos: (N,) |cos| of the angle between point normal and façade normal.
        layer: (N,) layer of the facet each point lies in.
        layers: the GMM.
        gp: thresholds (inlier_sigmas, alpha_z_deg).

    Returns:
        (N,) bool, True for training points: |d - mu_k| > 1.96 sigma_k or n_z < cos(alpha_z).
        For a layer wider than ``max_planar_sigma`` (EM also fits components to slopes,
        round bays and to a wall merged with shallow recesses), sigma_k in the first test is
        replaced by ``max_planar_sigma``: only the points that a plane of that spread
        explains are left to the layer, the rest go to the GP.
    """
    spread = np.minimum(layers.sigmas_[layer], gp.max_planar_sigma)
    far = np.abs(depth - layers.means_[layer]) > gp.inlier_sigmas * spread
    tilted = normal_cos < np.cos(np.deg2rad(gp.alpha_z_deg))
    return far | tilted


def _thin_planar(uv: np.ndarray, facet: np.ndarray, candidates: np.ndarray, origin: np.ndarray,
                 sizes: np.ndarray, per_block: int, rng: np.random.Generator) -> np.ndarray:
    """Pick at most ``per_block`` of the candidate points in every block (a random draw)."""
    idx = np.flatnonzero(candidates)
    if per_block <= 0 or not len(idx):
        return np.zeros(len(uv), dtype=bool)
    codes = block_codes(uv[idx], facet[idx], origin, sizes)
    # Per block, the per_block candidates of smallest random key: what sorting by (block,
    # key) and keeping each block's first per_block picks, without sorting all candidates.
    out = np.zeros(len(uv), dtype=bool)
    out[idx[capped_draw(codes, rng.random(len(idx)), per_block)]] = True
    return out
