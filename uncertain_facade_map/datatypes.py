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

from dataclasses import dataclass, field

import numpy as np

from .errors import InputError

_UP = np.array([0.0, 0.0, 1.0])


def _read_only(obj: object, *names: str) -> None:
    """Replace the array attributes ``names`` of a frozen dataclass by read-only views.

    A model is shared with other threads (the node's query callbacks read the map worker's
    snapshots): a write into one of its arrays raises instead of changing it under a reader.
    """
    for name in names:
        value = getattr(obj, name)
        if value is None:
            continue
        view = np.asarray(value).view()
        view.setflags(write=False)
        object.__setattr__(obj, name, view)


def array_bytes(*objects: object) -> int:
    """Bytes of the numpy arrays reachable from ``objects``, each buffer counted once.

    Followed: arrays (to the array that owns the buffer, so that a read-only view counts its
    base once), dicts, lists, tuples, and the attributes of this package's objects (façade
    models, maps and their caches). For the map's memory in the diagnostics (issue 13:
    what of a process's memory is the map's own).
    """
    seen: set[int] = set()
    total = 0
    stack = list(objects)
    while stack:
        obj = stack.pop()
        if isinstance(obj, np.ndarray):
            while isinstance(obj.base, np.ndarray):
                obj = obj.base
            if id(obj) not in seen:
                seen.add(id(obj))
                total += obj.nbytes
        elif isinstance(obj, dict):
            stack.extend(obj.values())
        elif isinstance(obj, (list, tuple)):
            stack.extend(obj)
        elif type(obj).__module__.startswith('uncertain_facade_map.') and hasattr(obj, '__dict__'):
            if id(obj) not in seen:
                seen.add(id(obj))
                stack.extend(vars(obj).values())
    return total


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
        _read_only(self, 'origin', 'axes')

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


@dataclass(frozen=True, eq=False)
class DepthLayers:
    """A fitted 1D Gaussian mixture of depths.

    Attributes:
        weights_: (K,) mixture weights pi_k.
        means_: (K,) layer depths mu_k, metres along the façade normal.
        sigmas_: (K,) layer standard deviations sigma_k, metres.
        main_: index of the main layer (largest weight).
    """

    weights_: np.ndarray
    means_: np.ndarray
    sigmas_: np.ndarray
    main_: int

    def __post_init__(self) -> None:
        _read_only(self, 'weights_', 'means_', 'sigmas_')

    @property
    def n_layers(self) -> int:
        """K, the number of layers."""
        return len(self.means_)

    def log_responsibilities(self, depth: np.ndarray) -> np.ndarray:
        """(N, K) log pi_k N(d | mu_k, sigma_k^2) for (N,) depths (unnormalised)."""
        z = (np.asarray(depth, dtype=np.float64)[:, None] - self.means_) / self.sigmas_
        return np.log(self.weights_) - np.log(self.sigmas_) - 0.5 * z * z

    def predict(self, depth: np.ndarray) -> np.ndarray:
        """(N,) index of the most responsible layer for (N,) depths."""
        return np.argmax(self.log_responsibilities(depth), axis=1)


@dataclass(frozen=True, eq=False)
class Relief:
    """The smooth reference surface of a wall: how far it bows and leans from its plane.

    The depth layers are offsets from this surface, not from the plane (a departure from
    the paper, which takes every layer as a constant depth; see
    :func:`~uncertain_facade_map.pipeline.step2_layers.fit_relief`). A relief of one node
    with value 0 is the paper's flat wall.

    Attributes:
        origin: (2,) (u, v) of node [0, 0], metres, façade frame.
        spacing: distance between nodes, metres.
        values: (H, W) depth of the surface at the nodes (row = v, column = u), metres.
    """

    origin: np.ndarray
    spacing: float
    values: np.ndarray

    def __post_init__(self) -> None:
        _read_only(self, 'origin', 'values')

    @classmethod
    def flat(cls) -> Relief:
        """The paper's flat wall: depth 0 everywhere."""
        return cls(np.zeros(2), 1.0, np.zeros((1, 1)))

    def at(self, uv: np.ndarray) -> np.ndarray:
        """(N,) depth of the surface at (N, 2) locations (u, v), metres: bilinear between
        the nodes, the nearest edge value beyond them."""
        nodes, weights = bilinear_weights(np.asarray(uv, dtype=np.float64), self.origin, self.spacing,
                                          self.values.shape)
        return (self.values.ravel()[nodes] * weights).sum(axis=1)


def bilinear_weights(uv: np.ndarray, origin: np.ndarray, spacing: float, shape: tuple[int, int]
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear interpolation on a node grid, clamped to its edges.

    Args:
        uv: (N, 2) locations, metres.
        origin: (2,) location of node [0, 0], metres.
        spacing: node spacing, metres.
        shape: (H, W) nodes (row = v, column = u).

    Returns:
        ``(nodes, weights)``: (N, 4) flat node indices and their (N, 4) weights (sum 1).
    """
    h, w = shape
    g = (uv - origin) / spacing
    gx, gy = np.clip(g[:, 0], 0.0, w - 1.0), np.clip(g[:, 1], 0.0, h - 1.0)
    c0 = np.minimum(gx.astype(np.int64), max(w - 2, 0))
    r0 = np.minimum(gy.astype(np.int64), max(h - 2, 0))
    c1, r1 = np.minimum(c0 + 1, w - 1), np.minimum(r0 + 1, h - 1)
    tx, ty = gx - c0, gy - r0
    nodes = np.stack([r0 * w + c0, r0 * w + c1, r1 * w + c0, r1 * w + c1], axis=1)
    weights = np.stack([(1 - ty) * (1 - tx), (1 - ty) * tx, ty * (1 - tx), ty * tx], axis=1)
    return nodes, weights


#: A point this close below a cell boundary (in cells) counts in the cell above it.
GRID_GUARD = 1e-9


def grid_index(x: np.ndarray, origin: float, cell: float) -> np.ndarray:
    """Index of the cell of side ``cell`` from ``origin`` that each coordinate lies in (int64).

    A raster's origin is set from its points' extreme (minus a margin of whole cells), so
    the extreme points lie on a cell boundary, where round-off (1e-13 m) of how the points
    were moved into the map frame would pick the cell: a point within :data:`GRID_GUARD`
    cells below a boundary is counted above it, so the cell does not depend on it.

    Args:
        x: (N,) coordinates, metres.
        origin: the raster's origin along that axis, metres.
        cell: cell side, metres (> 0).
    """
    return np.floor((np.asarray(x, dtype=np.float64) - origin) / cell + GRID_GUARD).astype(np.int64)


@dataclass(frozen=True, eq=False)
class Facets:
    """Facets of a façade on a raster.

    Attributes:
        origin: (2,) (u, v) of the raster's lower-left corner, metres, façade frame.
        cell: cell size, metres.
        facet: (H, W) int32 facet index per cell (row = v, column = u), -1 for none.
        layer_of_facet: (F,) int32 layer of each facet.
    """

    origin: np.ndarray
    cell: float
    facet: np.ndarray
    layer_of_facet: np.ndarray

    def __post_init__(self) -> None:
        _read_only(self, 'origin', 'facet', 'layer_of_facet')

    @property
    def n_facets(self) -> int:
        """F, the number of facets."""
        return len(self.layer_of_facet)

    def cells_of(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Raster (row, column) of (N, 2) points and a mask of those inside the raster."""
        col = grid_index(uv[:, 0], self.origin[0], self.cell)
        row = grid_index(uv[:, 1], self.origin[1], self.cell)
        inside = (row >= 0) & (row < self.facet.shape[0]) & (col >= 0) & (col < self.facet.shape[1])
        return row, col, inside

    def facet_at(self, uv: np.ndarray) -> np.ndarray:
        """(N,) facet index at (N, 2) façade locations, -1 outside every facet."""
        row, col, inside = self.cells_of(uv)
        out = np.full(len(uv), -1, dtype=np.int32)
        out[inside] = self.facet[row[inside], col[inside]]
        return out

    def boundaries(self) -> list[np.ndarray]:
        """Per facet, (B, 2) (u, v) centres of its cells that touch another facet or none."""
        padded = np.pad(self.facet, 1, constant_values=-2)
        core = padded[1:-1, 1:-1]
        edge = np.zeros_like(core, dtype=bool)
        for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            edge |= padded[1 + dr:padded.shape[0] - 1 + dr, 1 + dc:padded.shape[1] - 1 + dc] != core
        rows, cols = np.nonzero(edge & (core >= 0))
        ids = core[rows, cols]
        centres = np.stack([self.origin[0] + (cols + 0.5) * self.cell, self.origin[1] + (rows + 0.5) * self.cell], 1)
        order = np.argsort(ids, kind='stable')
        splits = np.searchsorted(ids[order], np.arange(1, self.n_facets))
        return np.split(centres[order], splits)


@dataclass(frozen=True, eq=False)
class ExtractedFacade:
    """One façade of a building, with the points allocated to it.

    Attributes:
        frame: façade frame from PCA of the main plane's points, normal outwards, map frame.
        index: (M,) int64 indices of the allocated points into the building's points.
        uvd: (M, 3) float64 façade coordinates (u, v, d) of those points, metres.
        normal_cos: (M,) float64 ``|cos|`` of the angle between each point's normal and the
            façade normal, in [0, 1] (paper eq. 8's ``n_z``).
        extent: (u_min, u_max, v_min, v_max) of the allocated points, metres, façade frame.
        plane_extent: (u_min, u_max, v_min, v_max) of the building's points within
            ``ransac_threshold`` of the plane near the façade (the wall itself, without
            balconies or clutter; robust to a few strays), metres, façade frame: the
            extent the allocation rule of :func:`assign_to_facades` grows by
            ``extent_margin``. None (e.g. a façade built from stored fields): ``extent``.
    """

    frame: FacadeFrame
    index: np.ndarray
    uvd: np.ndarray
    normal_cos: np.ndarray
    extent: tuple[float, float, float, float]
    plane_extent: tuple[float, float, float, float] | None = None

    def __post_init__(self) -> None:
        if self.plane_extent is None:
            object.__setattr__(self, 'plane_extent', self.extent)

    def __len__(self) -> int:
        return int(self.index.shape[0])


#: Source of a raster cell's value.
SOURCE_GLOBAL, SOURCE_FACET_PRIOR, SOURCE_GP = 0, 1, 2


def cell_centres(origin: np.ndarray, cell: float, shape: tuple[int, int]) -> np.ndarray:
    """(H*W, 2) centres (u, v) of the cells of a raster, metres, row-major.

    Args:
        origin: (2,) (u, v) of the raster's lower-left corner, metres.
        cell: cell side, metres.
        shape: (H, W), rows along v and columns along u.
    """
    h, w = shape
    cu = origin[0] + (np.arange(w) + 0.5) * cell
    cv = origin[1] + (np.arange(h) + 0.5) * cell
    uu, vv = np.meshgrid(cu, cv)
    return np.stack([uu.ravel(), vv.ravel()], axis=1)


@dataclass(frozen=True, eq=False)
class SurfaceRaster:
    """A façade's surface predicted on a regular raster of its plane (its arrays read-only).

    Attributes:
        origin: (2,) (u, v) of the lower-left corner, metres, façade frame.
        cell: cell side, metres.
        mean: (H, W) mean depth d(x), metres (row = v, column = u).
        var: (H, W) variance of the surface, m^2 (without noise).
        facet: (H, W) int32 facet of the cell, -1 where the global prior holds.
        source: (H, W) int8: 0 global prior, 1 facet prior (no data near), 2 GP posterior.
    """

    origin: np.ndarray
    cell: float
    mean: np.ndarray
    var: np.ndarray
    facet: np.ndarray
    source: np.ndarray

    def __post_init__(self) -> None:
        _read_only(self, 'origin', 'mean', 'var', 'facet', 'source')

    def centres(self) -> np.ndarray:
        """(H*W, 2) cell centres (u, v), metres, row-major."""
        return cell_centres(self.origin, self.cell, self.mean.shape)


@dataclass(frozen=True, eq=False)
class FacadeModel:
    """The uncertain surface model of one façade: immutable, its arrays read-only views.

    Attributes:
        facade_id: index in the map.
        building: building label.
        frame: façade frame (PCA, normal outwards).
        extent: (u_min, u_max, v_min, v_max) of the façade's points, metres.
        layers: GMM depth layers.
        facets: facets of the layers on the plane.
        lengthscale2_: (K, 2) fitted 1/b_1, 1/b_2 per layer, m^2.
        global_mean_: main layer's mean depth, metres (global prior mean).
        global_var_: mean squared deviation of all the façade's depths from the main layer,
            m^2 (global prior variance).
        noise_var: sigma_eta^2, m^2.
        surface: the predicted raster.
        point_index: (M,) int64 indices of the façade's points in its building's points.
        outlier_index: (R,) int64 indices (in the building's points) of the training points
            the chi-squared test removed.
        stats: counts (points, training points, outliers removed) and timings.
        plane_extent: (u_min, u_max, v_min, v_max) of the wall itself, metres: the extent
            that, grown by ``extent_margin``, takes new points (None: ``extent``).
        anchor: (2,) (u, v) corner of the block grid, metres, façade frame; fixed at the
            first fit so that blocks and cells keep their identity as the map grows
            (None: the surface raster's origin).
        fitted_points: number of points at the last whole fit (0: ``len(point_index)``).
        relief: the wall's smooth surface the layers are offsets from (None: flat, the paper).
    """

    facade_id: int
    building: int
    frame: FacadeFrame
    extent: tuple[float, float, float, float]
    layers: DepthLayers
    facets: Facets
    lengthscale2_: np.ndarray
    global_mean_: float
    global_var_: float
    noise_var: float
    surface: SurfaceRaster
    point_index: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    outlier_index: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    stats: dict = field(default_factory=dict)
    plane_extent: tuple[float, float, float, float] | None = None
    anchor: np.ndarray | None = None
    fitted_points: int = 0
    relief: Relief | None = None

    def __post_init__(self) -> None:
        if self.relief is None:
            object.__setattr__(self, 'relief', Relief.flat())
        if self.plane_extent is None:
            object.__setattr__(self, 'plane_extent', tuple(self.extent))
        if self.anchor is None:
            object.__setattr__(self, 'anchor', np.asarray(self.surface.origin, dtype=np.float64).copy())
        if not self.fitted_points:
            object.__setattr__(self, 'fitted_points', int(len(self.point_index)))
        _read_only(self, 'lengthscale2_', 'point_index', 'outlier_index', 'anchor')
