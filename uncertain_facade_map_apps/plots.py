"""Figures of a façade map, after the paper's figures of the mapping stages.

Per façade (:func:`plot_facade`), one PNG with six panels in the façade frame (u along
the wall, v up, metres, equal aspect):

(a) the façade's points coloured by their GMM depth layer (``layers.predict`` of the
    depth; paper Fig. 3a),
(b) the GP training points (paper eqs. 7 and 8, recomputed from the points and the model
    as :func:`~uncertain_facade_map.pipeline.step6_surface.fit_facade` selects them; Fig. 3b) over the other points, and
    the training points the chi-squared test removed as outliers,
(c) the partition into local GP blocks (paper eq. 9; Fig. 3c): every facet's block grid,
    anchored at ``model.anchor``, block sides from its layer's length scales; blocks are
    shaded in four tones of their layer's colour (no two neighbours alike), facets are
    outlined,
(d) the mean surface depth d(x) on the model's raster (Fig. 3e),
(e) its standard deviation sqrt(var) (Fig. 3d), on a log scale,
(f) the depth histogram with the GMM components pi_k N(d | mu_k, sigma_k^2), their sum
    and the main layer (paper Fig. 4).

For the whole map (:func:`plot_overview`), one PNG: a top view (x, y, map frame) and a 3D
view of every façade's mean surface, coloured by its standard deviation on one scale for
the map, with the façade ids at their centres. The top view draws, per raster column of a
façade, the median standard deviation of the column; the 3D view draws the raster cells.
Both keep to the extent of the façade's points (the raster's margin beyond them, where
the global prior holds, is left out; holes in the data are drawn).

:func:`plot_benchmark` draws a run of ``uncertain-facade-map benchmark``: residuals on the
façades and calibration curves.

:func:`plot_map` writes both kinds into a folder (``uncertain-facade-map plot MAP --out
DIR``). A map without façades is not an error: it gives the overview alone, its building
points from above with a note saying that there are no façades.

Scatter panels draw at most ``max_points`` points each, a seeded random subset (the
figures are reproducible), so a street of a million points plots in about 1.5 s per
façade. matplotlib is imported only inside the functions, and figures are drawn on
matplotlib's Agg canvas without pyplot: nothing needs a display, and the process's pyplot
backend is left alone.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from uncertain_facade_map.datatypes import SOURCE_GP, FacadeModel, SurfaceRaster
from uncertain_facade_map.errors import InputError
from uncertain_facade_map.mapping.facade_map import FacadeMap
from uncertain_facade_map.params import GPParams
from uncertain_facade_map.pipeline.step3_training import select_training
from uncertain_facade_map.pipeline.step4_gp_blocks import block_codes, block_size

#: Points drawn per scatter panel at most (a seeded random subset beyond).
MAX_POINTS = 50_000
#: Resolution of the PNG files, dots per inch: default and accepted range.
DEFAULT_DPI = 100
DPI_RANGE = (10, 1200)
#: Colours of the depth layers (K <= 10).
LAYER_COLOURS = ('#1f77b4', '#ff7f0e', '#2ca02c', '#d62728', '#9467bd', '#8c564b', '#e377c2', '#7f7f7f',
                 '#bcbd22', '#17becf')
#: Share of white mixed into a block's layer colour, by the parity of its block indices.
_BLOCK_TINTS = np.array([0.0, 0.45, 0.25, 0.65])


def _figure(width: float, height: float, layout: str | None = 'constrained'):
    """A matplotlib Figure on the Agg canvas (no pyplot, no display)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout=layout)
    FigureCanvasAgg(fig)
    return fig


def _layer_colour(k: int) -> str:
    return LAYER_COLOURS[k % len(LAYER_COLOURS)]


def _sample(n: int, k: int, rng: np.random.Generator) -> np.ndarray:
    """Sorted indices of at most ``k`` of ``n`` items (all if n <= k)."""
    if n <= k:
        return np.arange(n)
    return np.sort(rng.choice(n, k, replace=False))


def surface_extent(surface: SurfaceRaster) -> tuple[float, float, float, float]:
    """(u_min, u_max, v_min, v_max) of a surface raster's cells, metres (imshow's extent).

    Args:
        surface: the raster.

    Returns:
        The raster's outer edges in the façade frame.
    """
    h, w = surface.mean.shape
    return (float(surface.origin[0]), float(surface.origin[0] + w * surface.cell),
            float(surface.origin[1]), float(surface.origin[1] + h * surface.cell))


def std_norm(std: np.ndarray):
    """Colour scale of standard deviations: logarithmic from the 1st to the 99.5th
    percentile (std spans centimetres where scanned to decimetres where the prior holds).

    Args:
        std: standard deviations, metres (any shape; non-finite values ignored).

    Returns:
        A matplotlib ``LogNorm``.
    """
    from matplotlib.colors import LogNorm

    finite = std[np.isfinite(std) & (std > 0)]
    if not len(finite):
        return LogNorm(1e-3, 1.0)
    lo, hi = np.percentile(finite, [1.0, 99.5])
    lo = max(float(lo), 1e-4)
    hi = max(float(hi), lo * 1.5)
    return LogNorm(lo, hi)


def draw_surface(ax, model: FacadeModel, quantity: str = 'mean', vmin: float | None = None,
                 vmax: float | None = None, unit: str = 'm', colorbar: bool = True, cax=None):
    """Draw a façade's mean surface depth or its standard deviation as an image.

    Args:
        ax: matplotlib Axes.
        model: the façade.
        quantity: ``'mean'`` (depth d, coolwarm) or ``'std'`` (sqrt of the variance,
            viridis; log scale unless ``vmin``/``vmax`` are given).
        vmin: lower end of the colour scale (default: robust from the data).
        vmax: upper end of the colour scale (default: robust from the data).
        unit: ``'m'`` or ``'cm'``, for the values and the colour bar.
        colorbar: add a colour bar labelled with the quantity and unit.
        cax: Axes for the colour bar (default: space taken from ``ax``).

    Returns:
        The AxesImage.

    Raises:
        InputError: unknown quantity or unit.
    """
    scale = {'m': 1.0, 'cm': 100.0}.get(unit)
    if scale is None:
        raise InputError(f'unit must be m or cm, got {unit!r}')
    s = model.surface
    if quantity == 'mean':
        values, cmap, label = s.mean * scale, 'coolwarm', f'mean depth d ({unit}, + out of the wall)'
        if vmin is None or vmax is None:
            lo, hi = np.percentile(values, [1.0, 99.0])
            lo, hi = (lo - 0.05 * scale, hi + 0.05 * scale) if hi - lo < 0.1 * scale else (lo, hi)
            vmin, vmax = (lo if vmin is None else vmin), (hi if vmax is None else vmax)
        kwargs = {'vmin': vmin, 'vmax': vmax}
    elif quantity == 'std':
        values, cmap, label = np.sqrt(np.maximum(s.var, 0.0)) * scale, 'viridis', f'standard deviation ({unit})'
        kwargs = {'vmin': vmin, 'vmax': vmax} if vmin is not None and vmax is not None else {'norm': std_norm(values)}
    else:
        raise InputError(f'quantity must be mean or std, got {quantity!r}')
    im = ax.imshow(values, origin='lower', extent=surface_extent(s), cmap=cmap, interpolation='nearest', **kwargs)
    _facade_axes(ax)
    if colorbar:
        ax.figure.colorbar(im, ax=None if cax is not None else ax, cax=cax, label=label,
                           extend='both' if quantity == 'mean' else 'max')
    return im


def _facade_axes(ax) -> None:
    ax.set_aspect('equal')
    ax.set_xlabel('u (m)')
    ax.set_ylabel('v (m)')


def facade_arrays(fmap: FacadeMap, model: FacadeModel) -> tuple[np.ndarray, np.ndarray]:
    """A façade's points in its frame and their normals' alignment with it.

    Args:
        fmap: the map holding the façade's building points and normals.
        model: the façade.

    Returns:
        ``(uvd, normal_cos)``: (M, 3) façade coordinates (u, v, d), metres, in the order
        of ``model.point_index``; (M,) |cos| of the angle between each point's normal and
        the façade normal (1 where the map holds no normals).

    Raises:
        InputError: the map has no points for the façade's building, or the façade's point
            indices do not fit them (a damaged map).
    """
    pts = fmap.points.get(model.building)
    if pts is None:
        raise InputError(f'façade {model.facade_id}: the map holds no points of its building {model.building}')
    index = np.asarray(model.point_index, dtype=np.int64)
    if len(index) and (index.min() < 0 or index.max() >= len(pts)):
        raise InputError(f'façade {model.facade_id}: point indices beyond its building\'s {len(pts)} points '
                         '(damaged map)')
    uvd = model.frame.to_local(pts[index])
    normals = fmap.normals.get(model.building)
    if normals is None or len(normals) != len(pts):
        cos = np.ones(len(index))
    else:
        cos = np.minimum(np.abs(normals[index] @ model.frame.normal), 1.0)
    return uvd, cos


def training_points(model: FacadeModel, uvd: np.ndarray, normal_cos: np.ndarray, gp: GPParams) -> np.ndarray:
    """The GP training points of a façade, as :func:`~uncertain_facade_map.pipeline.step6_surface.fit_facade` selects them.

    Args:
        model: the façade.
        uvd: (M, 3) its points (u, v, d), metres, façade frame (d from the plane).
        normal_cos: (M,) |cos| between point normals and the façade normal.
        gp: the map's GP parameters (thresholds of eqs. 7 and 8).

    Returns:
        (M,) bool: on a facet and not explained by the facet's layer (paper eqs. 7, 8),
        with depths taken from the wall's relief as in the fit.
    """
    facet = model.facets.facet_at(uvd[:, :2])
    has_facet = facet >= 0
    if not model.facets.n_facets:
        return np.zeros(len(uvd), dtype=bool)
    layer = np.where(has_facet, model.facets.layer_of_facet[np.maximum(facet, 0)], model.layers.main_)
    depth = uvd[:, 2] - model.relief.at(uvd[:, :2])
    return select_training(depth, normal_cos, layer, model.layers, gp) & has_facet


def block_layout(model: FacadeModel, c_min: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The local GP blocks over a façade's surface raster (paper eq. 9).

    Args:
        model: the façade.
        c_min: covariance threshold that sets the block size (``GPParams.c_min``).

    Returns:
        ``(code, parity, sizes)``: (H, W) int64 block code of each raster cell (-1 where
        no facet is), (H, W) int8 parity 2 (i_u mod 2) + (i_v mod 2) of its block's indices
        (-1 where no facet is), and (F, 2) block sides per facet, metres.
    """
    s = model.surface
    shape = s.facet.shape
    code = np.full(shape, -1, dtype=np.int64)
    parity = np.full(shape, -1, dtype=np.int8)
    if not model.facets.n_facets:
        return code, parity, np.empty((0, 2))
    sizes = block_size(model.lengthscale2_[model.facets.layer_of_facet], c_min)
    facet = s.facet.ravel()
    inside = facet >= 0
    centres = s.centres()[inside]
    anchor = np.asarray(model.anchor, dtype=np.float64)
    code.ravel()[inside] = block_codes(centres, facet[inside], anchor, sizes)
    b = np.floor((centres - anchor) / sizes[facet[inside]]).astype(np.int64)
    parity.ravel()[inside] = 2 * (b[:, 0] % 2) + (b[:, 1] % 2)
    return code, parity, sizes


def _edges(labels: np.ndarray, origin: np.ndarray, cell: float) -> np.ndarray:
    """(S, 2, 2) segments along the cell edges where ``labels`` changes (and around the
    labelled cells at the raster's border), metres."""
    padded = np.pad(labels, 1, constant_values=-1)
    segs = []
    rows, cols = np.nonzero(padded[:, 1:] != padded[:, :-1])  # vertical edges
    keep = (rows >= 1) & (rows <= labels.shape[0])
    rows, cols = rows[keep] - 1, cols[keep]
    x = origin[0] + cols * cell
    y = origin[1] + rows * cell
    segs.append(np.stack([np.stack([x, y], 1), np.stack([x, y + cell], 1)], 1))
    rows, cols = np.nonzero(padded[1:, :] != padded[:-1, :])  # horizontal edges
    keep = (cols >= 1) & (cols <= labels.shape[1])
    rows, cols = rows[keep], cols[keep] - 1
    x = origin[0] + cols * cell
    y = origin[1] + rows * cell
    segs.append(np.stack([np.stack([x, y], 1), np.stack([x + cell, y], 1)], 1))
    return np.concatenate(segs)


def _marker_size(n: int, extent: tuple[float, float, float, float], panel_width: float) -> float:
    """Marker diameter (points) so that ``n`` points over ``extent`` roughly touch."""
    area = max((extent[1] - extent[0]) * (extent[3] - extent[2]), 1e-6)
    spacing = np.sqrt(0.6 * area / max(n, 1))  # metres, façades are not full
    per_metre = 72.0 * panel_width / max(extent[1] - extent[0], 1e-6)
    return float(np.clip(spacing * per_metre, 0.6, 4.0))


#: Layout of a façade figure, inches: margins of a panel (left for the v axis, right for a
#: legend or colour bar, top for the title, bottom for the u axis) and the figure's title.
_LEFT, _RIGHT, _TOP, _BOTTOM, _TITLE = 0.7, 2.55, 0.35, 0.5, 0.45


def _facade_layout(width_m: float, height_m: float):
    """Figure, six panel Axes (a-f), colour-bar Axes of (d) and (e), and the panel width
    (inches) for a façade raster of ``width_m`` x ``height_m`` metres: 3 rows x 2 columns,
    the map panels sized to the façade's aspect."""
    aspect = height_m / max(width_m, 1e-6)
    pw = float(np.clip(0.15 * width_m, 5.5, 10.0))
    ph = pw * aspect
    if ph > 7.0:  # a tall façade: narrower panels
        ph = 7.0
        pw = ph / aspect
    elif ph < 1.8:  # a long low one: the axes keep their aspect inside a taller box
        ph = 1.8
    cw, ch = _LEFT + pw + _RIGHT, _TOP + ph + _BOTTOM
    fw, fh = 2 * cw, 3 * ch + _TITLE
    fig = _figure(fw, fh, layout=None)
    axes, caxes = [], []
    for row in range(3):
        for col in range(2):
            x0 = col * cw + _LEFT
            y0 = fh - _TITLE - (row + 1) * ch + _BOTTOM
            if (row, col) == (2, 1):  # the histogram: no equal aspect, room for its legend inside
                axes.append(fig.add_axes((x0 / fw, y0 / fh, (pw + _RIGHT - 0.3) / fw, ph / fh)))
                continue
            axes.append(fig.add_axes((x0 / fw, y0 / fh, pw / fw, ph / fh)))
            if (row, col) in ((1, 1), (2, 0)):
                caxes.append(fig.add_axes(((x0 + pw + 0.12) / fw, y0 / fh, 0.14 / fw, ph / fh)))
    return fig, axes, caxes, pw


def plot_facade(model: FacadeModel, uvd: np.ndarray, normal_cos: np.ndarray, path: str | Path,
                gp: GPParams | None = None, dpi: int = DEFAULT_DPI, max_points: int = MAX_POINTS,
                seed: int = 0) -> Path:
    """Draw one façade's six panels (points by layer, training points, GP blocks, mean,
    standard deviation, GMM histogram) into a PNG file.

    Args:
        model: the façade.
        uvd: (M, 3) its points (u, v, d), metres, façade frame, in the order of
            ``model.point_index`` (see :func:`facade_arrays`).
        normal_cos: (M,) |cos| between point normals and the façade normal.
        path: PNG file to write.
        gp: the map's GP parameters (training-point thresholds, c_min); default GPParams().
        dpi: resolution, dots per inch.
        max_points: at most this many points per scatter panel (a seeded random subset).
        seed: seed of the subsets (combined with the façade id).

    Returns:
        The path written.

    Raises:
        InputError: ``uvd`` and ``normal_cos`` do not match the model's points.
        OSError: the file cannot be written.
    """
    from matplotlib.collections import LineCollection
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    gp = gp or GPParams()
    uvd = np.asarray(uvd, dtype=np.float64)
    normal_cos = np.asarray(normal_cos, dtype=np.float64)
    n = len(model.point_index)
    if uvd.shape != (n, 3) or normal_cos.shape != (n,):
        raise InputError(f'façade {model.facade_id}: expected ({n}, 3) points and ({n},) normal cosines, '
                         f'got {uvd.shape} and {normal_cos.shape}')
    rng = np.random.default_rng([seed, model.facade_id])
    layers, s = model.layers, model.surface
    extent = surface_extent(s)
    width_m, height_m = extent[1] - extent[0], extent[3] - extent[2]
    fig, (ax_a, ax_b, ax_c, ax_d, ax_e, ax_f), (cax_d, cax_e), panel_w = _facade_layout(width_m, height_m)
    k_layers = layers.n_layers
    point_layer = layers.predict(uvd[:, 2]) if n else np.empty(0, np.int64)
    training = training_points(model, uvd, normal_cos, gp) if n else np.empty(0, bool)
    outlier = np.isin(model.point_index, model.outlier_index)
    legend_kw = {'loc': 'upper left', 'bbox_to_anchor': (1.02, 1.0), 'fontsize': 7, 'frameon': False,
                 'borderaxespad': 0.0, 'handlelength': 1.2}

    # (a) points by GMM layer.
    shown = _sample(n, max_points, rng)
    ms = _marker_size(len(shown), model.extent, panel_w)
    for k in range(k_layers):
        sel = shown[point_layer[shown] == k]
        main = ' main' if k == layers.main_ else ''
        ax_a.plot(uvd[sel, 0], uvd[sel, 1], ls='', marker='o', ms=ms, mew=0, color=_layer_colour(k),
                  label=f'layer {k}{main}: μ {layers.means_[k]:+.2f} m, σ {layers.sigmas_[k] * 100:.1f} cm, '
                        f'π {layers.weights_[k]:.2f}')
    ax_a.set_title(f'(a) {n:,} points by GMM depth layer ({k_layers} layers)', fontsize=10)
    ax_a.legend(markerscale=max(3.0 / ms, 1.0), **legend_kw)

    # (b) GP training points, outliers removed.
    plain = np.flatnonzero(~training & ~outlier)
    train_kept = np.flatnonzero(training & ~outlier)
    removed = np.flatnonzero(outlier)
    part = [plain[_sample(len(plain), max_points, rng)], train_kept[_sample(len(train_kept), max_points, rng)],
            removed[_sample(len(removed), max_points, rng)]]
    ax_b.plot(uvd[part[0], 0], uvd[part[0], 1], ls='', marker='o', ms=ms, mew=0, color='#c8c8c8',
              label=f'explained by the layers ({len(plain):,})')
    ax_b.plot(uvd[part[1], 0], uvd[part[1], 1], ls='', marker='o', ms=max(ms, 1.0), mew=0, color='#d62728',
              label=f'GP training points ({len(train_kept):,})')
    ms_out = float(np.clip(1.5 * _marker_size(len(part[2]), model.extent, panel_w), 1.5, 4.0))
    ax_b.plot(uvd[part[2], 0], uvd[part[2], 1], ls='', marker='x', ms=ms_out, mew=0.5, color='#08306b',
              label=f'removed as outliers ({len(removed):,})')
    ax_b.set_title(f'(b) GP training points: |d - μ_k| > {gp.inlier_sigmas:g} σ_k or normal > '
                   f'{gp.alpha_z_deg:g}°', fontsize=10)
    ax_b.legend(markerscale=max(3.0 / ms, 1.0), **legend_kw)

    # (c) partition into local GP blocks over the facets.
    code, parity, sizes = block_layout(model, gp.c_min)
    rgba = np.ones(code.shape + (4,))
    rgba[..., 3] = 0.0
    inside = code >= 0
    if inside.any():
        from matplotlib.colors import to_rgb

        base = np.array([to_rgb(_layer_colour(k)) for k in range(k_layers)])
        cell_layer = model.facets.layer_of_facet[s.facet[inside]]
        tint = _BLOCK_TINTS[parity[inside]][:, None]
        rgba[inside, :3] = base[cell_layer] * (1 - tint) + tint
        rgba[inside, 3] = 1.0
    ax_c.imshow(rgba, origin='lower', extent=extent, interpolation='nearest')
    if inside.any():
        ax_c.add_collection(LineCollection(_edges(s.facet, s.origin, s.cell), colors='k', linewidths=0.5))
    n_blocks = len(np.unique(code[inside]))
    handles = []
    for k in range(k_layers):
        facets_k = np.flatnonzero(model.facets.layer_of_facet == k)
        if len(facets_k):
            side = sizes[facets_k[0]]
            handles.append(Patch(color=_layer_colour(k), label=f'layer {k}: {len(facets_k)} facets, blocks '
                                                               f'{side[0]:.2f} × {side[1]:.2f} m'))
    handles.append(Line2D([], [], color='k', lw=0.5, label='facet outline'))
    ax_c.legend(handles=handles, **legend_kw)
    ax_c.set_title(f'(c) partition into local GPs: {n_blocks:,} blocks in {model.facets.n_facets} facets',
                   fontsize=10)

    # (d), (e) mean surface and its standard deviation.
    draw_surface(ax_d, model, 'mean', cax=cax_d)
    ax_d.set_title('(d) mean surface depth d(x) = g(x) + f(x)', fontsize=10)
    draw_surface(ax_e, model, 'std', cax=cax_e)
    observed = s.source == SOURCE_GP
    median = f', median {np.median(np.sqrt(s.var[observed])) * 100:.1f} cm where observed' if observed.any() else ''
    ax_e.set_title(f'(e) standard deviation of the surface{median}', fontsize=10)
    for ax in (ax_a, ax_b, ax_c, ax_d, ax_e):
        _facade_axes(ax)
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
        ax.set_adjustable('datalim')  # fill the panel: a long façade gets more v around it

    # (f) depth histogram with the GMM.
    depth = uvd[:, 2]
    spread = 3.0 * layers.sigmas_
    lo = min(np.percentile(depth, 0.1) if n else 0.0, float((layers.means_ - spread).min()))
    hi = max(np.percentile(depth, 99.9) if n else 0.0, float((layers.means_ + spread).max()))
    bins = int(np.clip((hi - lo) / 0.01, 20, 400))
    hist_top = 0.0
    if n:
        density, _, _ = ax_f.hist(depth, bins=bins, range=(lo, hi), density=True, histtype='stepfilled',
                                  color='#d0d0d0', label='depths (histogram)')
        hist_top = float(density.max())
    x = np.linspace(lo, hi, 1500)
    comps = layers.weights_[:, None] * np.exp(-0.5 * ((x[None, :] - layers.means_[:, None]) / layers.sigmas_[:, None])
                                               ** 2) / (np.sqrt(2 * np.pi) * layers.sigmas_[:, None])
    for k in range(k_layers):
        ax_f.plot(x, comps[k], color=_layer_colour(k), lw=1.2, label='π_k N(d | μ_k, σ_k²)' if k == 0 else None)
    ax_f.plot(x, comps.sum(axis=0), 'k--', lw=0.9, label='GMM p(d)')
    ax_f.axvline(layers.means_[layers.main_], color=_layer_colour(layers.main_), ls=':', lw=1.2)
    ax_f.annotate(f'main layer {layers.main_}', (layers.means_[layers.main_], 0.97),
                  xycoords=('data', 'axes fraction'), ha='left', va='top', fontsize=8, xytext=(3, 0),
                  textcoords='offset points')
    ax_f.set_yscale('log')
    top = max(float(comps.sum(axis=0).max()), hist_top, 1e-3)
    ax_f.set_ylim(top * 1e-4, top * 2.0)
    ax_f.set_xlim(lo, hi)
    ax_f.set_xlabel('depth d (m, + out of the wall)')
    ax_f.set_ylabel('density (1/m, log)')
    ax_f.set_title(f'(f) depth histogram and GMM ({k_layers} components)', fontsize=10)
    ax_f.legend(fontsize=7, loc='upper right', bbox_to_anchor=(1.0, 0.9))

    nrm = model.frame.normal
    fig.suptitle(f'façade {model.facade_id} (building {model.building}): {n:,} points, '
                 f'{width_m:.0f} m × {height_m:.0f} m raster, normal ({nrm[0]:+.2f}, {nrm[1]:+.2f}, {nrm[2]:+.2f})',
                 fontsize=12)
    return _save(fig, path, dpi)


def _overview_cells(model: FacadeModel) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A façade's raster cells within its points' extent: (c,) u of the columns, (r,) v of
    the rows, (r, c) mean depth and (r, c) standard deviation, metres."""
    s = model.surface
    h, w = s.mean.shape
    cu = s.origin[0] + (np.arange(w) + 0.5) * s.cell
    cv = s.origin[1] + (np.arange(h) + 0.5) * s.cell
    cols = np.flatnonzero((cu >= model.extent[0]) & (cu <= model.extent[1]))
    rows = np.flatnonzero((cv >= model.extent[2]) & (cv <= model.extent[3]))
    if not len(cols) or not len(rows):  # a raster thinner than a cell: take its middle
        cols, rows = np.array([w // 2]), np.array([h // 2])
    mean = s.mean[np.ix_(rows, cols)]
    std = np.sqrt(np.maximum(s.var[np.ix_(rows, cols)], 0.0))
    return cu[cols], cv[rows], mean, std


def _centre(model: FacadeModel, v: float | None = None) -> np.ndarray:
    """(3,) map-frame point at the middle of a façade's points' extent (at height ``v``)."""
    e = model.extent
    return model.frame.to_world(np.array([[0.5 * (e[0] + e[1]), 0.5 * (e[2] + e[3]) if v is None else v,
                                           model.global_mean_]]))[0]


def plot_overview(fmap: FacadeMap, path: str | Path, dpi: int = DEFAULT_DPI, max_points: int = MAX_POINTS,
                  seed: int = 0) -> Path:
    """Draw the whole map from above and in 3D, coloured by the surface's standard
    deviation (one colour scale), façade ids at their centres.

    A map without façades gives its building points from above and a note saying so.

    Args:
        fmap: the map.
        path: PNG file to write.
        dpi: resolution, dots per inch.
        max_points: at most this many points per scatter (a seeded random subset).
        seed: seed of the subsets.

    Returns:
        The path written.

    Raises:
        OSError: the file cannot be written.
    """
    from matplotlib.cm import ScalarMappable

    rng = np.random.default_rng([seed, 1 << 20])
    pts = np.vstack([fmap.points[b] for b in fmap.buildings]) if fmap.points else np.empty((0, 3))
    context = pts[_sample(len(pts), max_points, rng)]
    cells = [_overview_cells(f) for f in fmap.facades]
    # Top view: per raster column of each façade, its median std at the column's median depth.
    col_xyz, col_std, cell_xyz, cell_std = [], [], [], []
    for f, (cu, cv, mean, std) in zip(fmap.facades, cells):
        col_xyz.append(f.frame.to_world(np.stack([cu, np.full(len(cu), np.median(cv)), np.median(mean, axis=0)], 1)))
        col_std.append(np.median(std, axis=0))
        uu, vv = np.meshgrid(cu, cv)
        cell_xyz.append(f.frame.to_world(np.stack([uu.ravel(), vv.ravel(), mean.ravel()], 1)))
        cell_std.append(std.ravel())
    every = np.vstack(cell_xyz + [context]) if cells or len(context) else np.zeros((1, 3))
    lo, hi = every.min(axis=0), every.max(axis=0)
    span = np.maximum(hi - lo, 1.0)
    width, left, right = 12.5, 0.8, 1.6
    top_h = float(np.clip(width * span[1] / span[0], 2.5, 9.0))
    low_h = 7.0 if cells else 0.0
    fw, fh = left + width + right, top_h + low_h + 1.2
    fig = _figure(fw, fh, layout=None)
    ax_top = fig.add_axes((left / fw, (low_h + 0.6) / fh, width / fw, top_h / fh))
    ax_top.plot(context[:, 0], context[:, 1], ls='', marker='o', ms=0.6 if cells else 1.5, mew=0,
                color='#d0d0d0' if cells else '#808080', zorder=1)
    ax_top.set_aspect('equal', adjustable='datalim')
    ax_top.set_xlabel('x (m)')
    ax_top.set_ylabel('y (m)')
    if not cells:
        ax_top.text(0.5, 0.5, 'no façades in this map', transform=ax_top.transAxes, ha='center', va='center',
                    fontsize=14, bbox={'facecolor': 'white', 'edgecolor': '0.5'})
        ax_top.set_title(f'map from above: {len(fmap.buildings)} buildings, {fmap.n_points:,} points (grey), '
                         'no façades', fontsize=11)
        return _save(fig, path, dpi)

    col_xyz, col_std = np.vstack(col_xyz), np.concatenate(col_std)
    all_xyz, all_std = np.vstack(cell_xyz), np.concatenate(cell_std)
    norm, cmap = std_norm(all_std), 'viridis'
    order = np.argsort(col_std)  # the most uncertain drawn last, on top
    ax_top.scatter(col_xyz[order, 0], col_xyz[order, 1], c=col_std[order], norm=norm, cmap=cmap, s=5, lw=0,
                   zorder=2)
    for f in fmap.facades:
        centre = _centre(f)
        ax_top.annotate(str(f.facade_id), centre[:2], ha='center', va='center', fontsize=7, zorder=3,
                        bbox={'boxstyle': 'round,pad=0.15', 'facecolor': 'white', 'edgecolor': '0.5', 'lw': 0.5,
                              'alpha': 0.85})
    ax_top.set_title(f'map from above: {len(fmap.facades)} façades of {len(fmap.buildings)} buildings, '
                     f'{fmap.n_points:,} points (grey); colour: median standard deviation of each raster column',
                     fontsize=11)
    cax = fig.add_axes(((left + width + 0.3) / fw, (low_h + 0.6) / fh, 0.18 / fw, top_h / fh))
    fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), cax=cax, label='standard deviation (m)', extend='max')

    # 3D: raster cells of every façade, a random subset.
    ax_3d = fig.add_axes((0.0, 0.0, (left + width) / fw, (low_h + 0.2) / fh), projection='3d')
    keep = _sample(len(all_xyz), max_points, rng)
    ax_3d.scatter(all_xyz[keep, 0], all_xyz[keep, 1], all_xyz[keep, 2], c=all_std[keep], norm=norm, cmap=cmap,
                  s=3.0, lw=0, depthshade=False)
    for f in fmap.facades:
        top = _centre(f, f.extent[3])
        ax_3d.text(top[0], top[1], top[2] + 1.0, str(f.facade_id), fontsize=8, ha='center')
    ax_3d.set_box_aspect((span[0], span[1], span[2]), zoom=1.3)
    ax_3d.set_proj_type('ortho')
    ax_3d.set_xlim(lo[0], lo[0] + span[0])
    ax_3d.set_ylim(lo[1], lo[1] + span[1])
    ax_3d.set_zlim(lo[2], lo[2] + span[2])
    ax_3d.view_init(elev=40, azim=-65)
    ax_3d.set_xlabel('x (m)')
    ax_3d.set_ylabel('y (m)')
    ax_3d.set_zlabel('z (m)')
    ax_3d.text2D(0.5, 0.95, f'mean surfaces in 3D, coloured by standard deviation ({len(keep):,} raster cells '
                            'within the scanned extents)', transform=ax_3d.transAxes, ha='center', fontsize=11)
    return _save(fig, path, dpi)


def _save(fig, path: str | Path, dpi: int) -> Path:
    """Write a figure as PNG (light compression: fast, files somewhat larger)."""
    path = Path(path)
    fig.savefig(path, dpi=dpi, pil_kwargs={'compress_level': 3})
    return path


def output_folder(out: str | Path) -> Path:
    """The folder to write figures to, created if its parent exists.

    Args:
        out: folder path.

    Returns:
        The folder.

    Raises:
        InputError: neither the folder nor its parent exists, it is not a folder, or it is
            not writable.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f'output folder {out} is a file')
    if not out.exists():
        if not out.parent.is_dir():
            raise InputError(f'output folder {out} does not exist, nor does its parent {out.parent}')
        try:
            out.mkdir()
        except OSError as exc:
            raise InputError(f'cannot create output folder {out}: {exc.strerror or exc}') from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise InputError(f'output folder {out} is not writable')
    return out


def select_facades(fmap: FacadeMap, facades: Sequence[int] | None = None) -> list[int]:
    """The ids of the façades to draw, checked.

    Args:
        fmap: the map.
        facades: façade ids (repeats are drawn once); None for all.

    Returns:
        The ids, in the order given, without repeats.

    Raises:
        InputError: an id names no façade of the map.
    """
    known = {f.facade_id for f in fmap.facades}
    ids = sorted(known) if facades is None else [int(i) for i in facades]
    unknown = [i for i in dict.fromkeys(ids) if i not in known]
    if unknown:
        have = f'façades 0 to {max(known)}' if known else 'no façades'
        raise InputError(f'no façade {", ".join(map(str, unknown))} in the map (it has {have})')
    return list(dict.fromkeys(ids))


def plot_map(fmap: FacadeMap, out: str | Path, facades: Sequence[int] | None = None, dpi: int = DEFAULT_DPI,
             max_points: int = MAX_POINTS, seed: int = 0,
             progress: Callable[[int, int], None] | None = None) -> list[Path]:
    """Write ``facade_<id>.png`` for the chosen façades and ``overview.png`` for the map.

    Args:
        fmap: the map.
        out: output folder (created if its parent exists).
        facades: ids of the façades to draw; None for all.
        dpi: resolution, dots per inch.
        max_points: at most this many points per scatter panel.
        seed: seed of the point subsets.
        progress: called with (façades done, façades to draw) after each one.

    Returns:
        The paths written: the façades' in the order asked, then the overview.

    Raises:
        InputError: unknown façade ids, a bad dpi or max_points, an unusable output folder,
            or a damaged map.
        OSError: a file cannot be written.
    """
    if isinstance(dpi, bool) or not isinstance(dpi, (int, np.integer)) or not DPI_RANGE[0] <= dpi <= DPI_RANGE[1]:
        raise InputError(f'dpi must be an integer from {DPI_RANGE[0]} to {DPI_RANGE[1]}, got {dpi!r}')
    if isinstance(max_points, bool) or not isinstance(max_points, (int, np.integer)) or max_points < 1:
        raise InputError(f'max_points must be a positive integer, got {max_points!r}')
    ids = select_facades(fmap, facades)
    known = {f.facade_id: f for f in fmap.facades}
    out = output_folder(out)
    written = []
    for done, fid in enumerate(ids, 1):
        model = known[fid]
        uvd, cos = facade_arrays(fmap, model)
        written.append(plot_facade(model, uvd, cos, out / f'facade_{fid}.png', fmap.params.gp, dpi, max_points,
                                   seed))
        if progress is not None:
            progress(done, len(ids))
    written.append(plot_overview(fmap, out / 'overview.png', dpi, max_points, seed))
    return written


#: Colour of each map in the benchmark's calibration panels.
BENCHMARK_COLOURS = {'this package': '#1f77b4', 'local plane': '#ff7f0e', 'façade plane': '#2ca02c'}
#: Façades drawn at most in the benchmark figure (those with the most scored points).
BENCHMARK_FACADES = 4


def plot_benchmark(results: Sequence, path: str | Path, dpi: int = DEFAULT_DPI, residual_range: float = 0.2,
                   max_points: int = MAX_POINTS, seed: int = 0) -> Path:
    """The figure of one benchmark run (``uncertain-facade-map benchmark``).

    Left: on the façades with the most scored points (at most :data:`BENCHMARK_FACADES`),
    each scored point at its place (u, v) on its façade, coloured by our map's signed
    distance (residual, metres, clipped to +-``residual_range``; grey crosses: not
    answered), the occlusion patches outlined. Right: per result (held-out points, and
    the exact truth on simulated scenes) the calibration curve of every map: the share of
    points inside the central interval against its nominal level, observed (solid) and
    occluded (dashed); a calibrated map lies on the diagonal.

    Args:
        results: the :class:`~uncertain_facade_map.evaluation.benchmark.BenchmarkResult`
            of one input (the first gives the residuals).
        path: PNG file to write.
        dpi: resolution.
        residual_range: the colour scale's half range, metres.
        max_points: at most this many points per façade panel (a seeded subset).
        seed: seed of the subsets.

    Returns:
        The path written.
    """
    from matplotlib.colors import Normalize
    from matplotlib.patches import Rectangle

    from uncertain_facade_map.evaluation.benchmark import LEVELS

    if not results:
        raise InputError('no benchmark results to plot')
    first = results[0]
    plot = first.plot
    facade, uv, residual, occluded = plot['facade'], plot['uv'], plot['residual'], plot['occluded']
    ids, counts = np.unique(facade[facade >= 0], return_counts=True)
    shown = ids[np.argsort(-counts, kind='stable')][:BENCHMARK_FACADES]
    rng = np.random.default_rng(seed)
    fig = _figure(16, 3.2 * max(len(shown), 2 * len(results), 2))
    left, right = fig.subfigures(1, 2, width_ratios=[2.2, 1])
    norm = Normalize(-residual_range, residual_range)
    axes = left.subplots(max(len(shown), 1), 1, squeeze=False)[:, 0]
    mappable = None
    for ax, j in zip(axes, shown):
        sel = np.flatnonzero(facade == j)
        sel = sel[_sample(len(sel), max_points, rng)]
        answered = np.isfinite(residual[sel])
        a, b = sel[answered], sel[~answered]
        mappable = ax.scatter(uv[a, 0], uv[a, 1], c=np.clip(residual[a], -residual_range, residual_range), s=3,
                              cmap='RdBu_r', norm=norm, linewidths=0)
        if len(b):
            ax.scatter(uv[b, 0], uv[b, 1], c='0.6', s=6, marker='x', linewidths=0.5, label='not answered')
            ax.legend(loc='upper right', fontsize=8)
        for f, u0, u1, v0, v1 in plot['patches']:
            if f == j:
                ax.add_patch(Rectangle((u0, v0), u1 - u0, v1 - v0, fill=False, edgecolor='k', linewidth=1.0))
        _facade_axes(ax)
        ax.set_title(f'façade {j}: residual of this package at {len(sel):,} scored points '
                     f'({int(occluded[sel].sum()):,} occluded, in the black patches)', fontsize=9)
    if not len(shown):
        axes[0].text(0.5, 0.5, 'no scored point on a façade', ha='center', va='center', transform=axes[0].transAxes)
        axes[0].set_axis_off()
    if mappable is not None:
        left.colorbar(mappable, ax=list(axes), location='bottom', shrink=0.5, aspect=40,
                      label='signed distance of the held-out point from our mean surface, outside + (m)')
    cal_axes = right.subplots(len(results), 1, squeeze=False)[:, 0]
    for ax, result in zip(cal_axes, results):
        ax.plot([0, 1], [0, 1], color='0.5', linewidth=0.8)
        for m in result.maps:
            colour = BENCHMARK_COLOURS.get(m.name)
            for split, style in (('observed', '-'), ('occluded', '--')):
                curve = np.asarray(m.calibration.get(split, []), dtype=float)
                if len(curve) and np.isfinite(curve).any():
                    ax.plot(LEVELS, curve, style, color=colour, marker='.', markersize=3, label=f'{m.name}, {split}')
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
        ax.set_aspect('equal')
        ax.set_xlabel('nominal level of the central interval')
        ax.set_ylabel('observed coverage')
        ax.set_title(f'calibration against {result.against}', fontsize=10)
        ax.legend(loc='lower right', fontsize=7)
    fig.suptitle(f'Benchmark of {first.name}', fontsize=12)
    return _save(fig, path, dpi)
