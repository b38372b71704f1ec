"""Real building footprints and heights from CityJSON, for placing real houses in a scene.

:func:`load_footprints` turns every ``Building`` of a CityJSON file (1.0, 1.1 or 2.0, with a
``transform``) into a :class:`Footprint`: a simple, counter-clockwise polygon in the
file's reference system (metres; EPSG:2056 for the packaged Zurich subset), the ground
height and the eave and ridge heights above it.

How the footprint is made
-------------------------
1. Geometry: per city object the 3-D geometry (MultiSurface, CompositeSurface, Solid,
   MultiSolid, CompositeSolid) of the highest LoD; surfaces are typed by their semantics
   (WallSurface, RoofSurface, GroundSurface; other types are ignored). A geometry none of
   whose surfaces has a semantic type is typed by its normals instead (near-vertical:
   wall; near-horizontal and at the object's lowest z: ground; anything else: roof). A
   building's geometry is its own plus that of all its ``BuildingPart`` descendants.
2. Rings: if any part of the building has GroundSurface polygons, the rings are their
   exterior rings (interior rings, i.e. courtyards, are ignored). Otherwise, per part,
   the bottom edges of the WallSurface polygons -- edges whose two vertices lie within
   :data:`BOTTOM_TOLERANCE` of the part's lowest z -- are chained into closed rings
   (open chains are dropped).
3. Union: the rings are merged into the outer boundary of their union by a small planar
   overlay (shapely is not a dependency): all edges are split at all crossings and at
   vertices lying on them (within 1 mm), pieces shared by two rings running opposite ways
   (adjacent polygons) are dropped, as are pieces inside another ring, and the rest is
   chained. Holes of the union (courtyards) are dropped. If the union has several
   disjoint outer rings, the one of largest area is kept and the others are dropped; this
   is logged (``logging`` at INFO) with the building id. For the Zurich subset no outer
   ring is dropped: every building there has exactly one part with ground polygons (two
   have 2 and 6 adjacent ground polygons, which merge into one ring), and its other parts
   are dormers and roof structures standing on it.
4. Simplification, one change at a time until nothing changes, in this order of
   preference: drop a vertex where the boundary turns by less than :data:`MIN_TURN_DEG`;
   turn an edge shorter than ``min_edge`` into a corner where the lines of its
   neighbouring edges cross, if that point lies within ``simplify_tolerance`` of it (a
   chamfered corner becomes a sharp one); drop the vertex nearest to the line through its
   neighbours if it is within ``simplify_tolerance``; drop the end vertex of the shortest
   edge under ``min_edge`` whose removal changes the area least.
   If simplification would make the polygon self-intersecting, only the near-collinear
   vertices are dropped. The result is counter-clockwise, starts at its lexicographically
   smallest (x, then y) vertex and is not closed; footprints under :data:`MIN_AREA` are
   dropped (logged).
5. Heights: ``ground_z`` is the lowest z of the vertices that made the rings;
   ``eave_height`` is the median over all wall surfaces of the building of (highest z of
   the wall) - ``ground_z``; ``ridge_height`` is the highest z of its roof surfaces (of
   its walls if it has no roof) - ``ground_z``. The eave height is capped at the ridge
   height; a building without walls takes the lowest roof z as its eave. Buildings whose
   heights are not positive are dropped.

For the packaged Zurich subset (``data/zurich_subset_lod2.json``, 49 buildings) the
defaults give 45 footprints (4 buildings are sheds or kiosks under 20 m^2) with 4 to 20
vertices, areas within 2.4 % of the area of their ground polygons, eave heights of 5.1 to
28.7 m and ridge heights of 5.6 to 31.4 m.
Ignoring the GroundSurfaces and chaining wall bottoms instead gives the same polygons for
44 of them; the 45th stands on stepped terrain and has no closed ring of wall bottoms.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from typing import Any, Iterator, Union

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..errors import InputError

PathLike = Union[str, 'os.PathLike[str]']

_log = logging.getLogger(__name__)

#: Footprints with a smaller area, square metres, are dropped.
MIN_AREA = 20.0
#: A wall edge is a bottom edge if both its vertices are this close to the part's lowest z, metres.
BOTTOM_TOLERANCE = 0.3
#: Vertices where the boundary turns by less than this many degrees are dropped.
MIN_TURN_DEG = 5.0

#: A vertex this close to an edge splits it in the union overlay, metres (coordinates of
#: CityJSON files are typically quantised to 1 mm, so edges meant to coincide differ by less).
_SNAP = 1e-3
#: Points closer than this are one vertex in the union overlay, metres.
_MERGE = 4e-4
#: Outer rings of the union smaller than this are slivers from rounding, square metres.
_SLIVER = 0.01
#: Nesting depth of the surfaces in the ``boundaries`` of each geometry type.
_SURFACE_DEPTH = {'MultiSurface': 1, 'CompositeSurface': 1, 'Solid': 2, 'MultiSolid': 3, 'CompositeSolid': 3}
_WALL, _ROOF, _GROUND = 'WallSurface', 'RoofSurface', 'GroundSurface'


@dataclass(frozen=True, eq=False)
class Footprint:
    """Footprint and heights of one real building.

    Attributes:
        building_id: key of the ``Building`` in ``CityObjects``.
        polygon: (M, 2) float64, metres, in the file's reference system (EPSG:2056 for the
            Zurich subset); simple, counter-clockwise, not closed (first != last), M >= 3.
            Read-only.
        ground_z: height of the ground under the building, metres, in the file's vertical
            reference system.
        eave_height: typical height of the top of the walls above ``ground_z``, metres.
        ridge_height: height of the highest roof point above ``ground_z``, metres;
            ``ridge_height >= eave_height``.
    """

    building_id: str
    polygon: np.ndarray
    ground_z: float
    eave_height: float
    ridge_height: float


@dataclass(frozen=True)
class _Surface:
    """One polygon of a city object: its type, part number and rings ((K, 3) metres, exterior first)."""

    kind: str
    part: int
    rings: tuple[np.ndarray, ...]


def load_footprints(path: PathLike, *, min_edge: float = 1.0,
                    simplify_tolerance: float = 0.2) -> list[Footprint]:
    """Read the footprints and heights of all buildings of a CityJSON file.

    See the module documentation for how footprints, simplification and heights are made.

    Args:
        path: CityJSON file (1.x or 2.0; integer vertices with ``transform``).
        min_edge: footprint edges shorter than this are removed, metres (0 keeps all).
        simplify_tolerance: vertices this close to the line through their neighbours are
            removed, metres (0 removes only those where the boundary turns by less than
            :data:`MIN_TURN_DEG`).

    Returns:
        One footprint per usable ``Building``, in file order.

    Raises:
        InputError: negative or non-finite parameters, a missing or unreadable file,
            invalid JSON, a file that is not CityJSON (no ``CityObjects``, ``vertices`` or
            ``transform``), malformed geometry, or no usable building in the file.
    """
    for pname, value in (('min_edge', min_edge), ('simplify_tolerance', simplify_tolerance)):
        if not np.isfinite(value) or value < 0:
            raise InputError(f'{pname} must be a finite number >= 0, not {value!r}')
    name = os.fspath(path)
    doc = _read_json(name)
    vertices = _vertices(doc, name)
    objects = doc['CityObjects']
    footprints: list[Footprint] = []
    skipped: list[str] = []
    for oid, obj in objects.items():
        if not isinstance(obj, dict) or obj.get('type') != 'Building':
            continue
        surfaces = [s for k, part in enumerate(_building_parts(oid, objects))
                    for s in _surfaces(part, k, vertices, f'{name}: {oid}')]
        fp = _footprint(oid, surfaces, min_edge, simplify_tolerance)
        if fp is None:
            skipped.append(oid)
        else:
            footprints.append(fp)
    if skipped:
        _log.info('%s: %d building(s) without a usable footprint skipped: %s',
                  name, len(skipped), ', '.join(skipped))
    if not footprints:
        raise InputError(f'{name}: no usable building (need Building objects with walls and a '
                         f'footprint of at least {MIN_AREA:g} m^2)')
    return footprints


# ----------------------------------------------------------------------------------------
# Reading


def _read_json(name: str) -> dict[str, Any]:
    """Load the JSON document and check that it looks like CityJSON."""
    if not os.path.exists(name):
        raise InputError(f'no such file: {name}')
    try:
        with open(name, 'rb') as stream:
            doc = json.load(stream)
    except OSError as exc:
        raise InputError(f'cannot read {name}: {" ".join(str(exc).split())}') from exc
    except ValueError as exc:  # JSONDecodeError, UnicodeDecodeError
        raise InputError(f'{name}: invalid JSON: {" ".join(str(exc).split())}') from exc
    if not isinstance(doc, dict):
        raise InputError(f'{name}: not CityJSON (the top level is a {type(doc).__name__}, not an object)')
    missing = [k for k in ('CityObjects', 'vertices', 'transform') if k not in doc]
    if missing:
        raise InputError(f'{name}: not CityJSON (no {", ".join(missing)})')
    if doc.get('type', 'CityJSON') != 'CityJSON':
        raise InputError(f'{name}: not a CityJSON file (type {doc.get("type")!r})')
    if not isinstance(doc['CityObjects'], dict):
        raise InputError(f'{name}: malformed CityJSON (CityObjects is not an object)')
    return doc


def _vertices(doc: dict[str, Any], name: str) -> np.ndarray:
    """(V, 3) float64 vertex coordinates, metres: vertex * scale + translate."""
    transform = doc['transform']
    try:
        scale = np.asarray(transform['scale'], dtype=np.float64)
        translate = np.asarray(transform['translate'], dtype=np.float64)
        raw = np.asarray(doc['vertices'], dtype=np.float64)
    except (TypeError, ValueError, KeyError) as exc:
        raise InputError(f'{name}: malformed transform or vertices ({" ".join(str(exc).split())})') from exc
    if scale.shape != (3,) or translate.shape != (3,):
        raise InputError(f'{name}: transform scale and translate must have 3 numbers each')
    if raw.size == 0:
        return np.empty((0, 3))
    if raw.ndim != 2 or raw.shape[1] != 3 or not np.all(np.isfinite(raw)):
        raise InputError(f'{name}: vertices must be a list of [x, y, z] numbers')
    return raw * scale + translate


def _building_parts(oid: str, objects: dict[str, Any]) -> list[dict[str, Any]]:
    """The building itself and all its BuildingPart descendants (each once)."""
    parts, seen, todo = [], {oid}, [oid]
    while todo:
        obj = objects[todo.pop(0)]
        parts.append(obj)
        for child in obj.get('children') or []:
            if isinstance(child, str) and child not in seen and isinstance(objects.get(child), dict) \
                    and objects[child].get('type') == 'BuildingPart':
                seen.add(child)
                todo.append(child)
    return parts


def _lod(geometry: dict[str, Any]) -> float:
    """The LoD of a geometry as a number (``'2.2'`` -> 2.2), -1 if missing or odd."""
    try:
        return float(str(geometry.get('lod', -1)))
    except ValueError:
        return -1.0


def _surfaces(obj: dict[str, Any], part: int, vertices: np.ndarray, where: str) -> list[_Surface]:
    """Typed surfaces of the highest-LoD 3-D geometry of one city object."""
    geometries = [g for g in obj.get('geometry') or []
                  if isinstance(g, dict) and isinstance(g.get('type'), str) and g['type'] in _SURFACE_DEPTH]
    if not geometries:
        return []
    geometry = max(geometries, key=_lod)
    semantics = geometry.get('semantics')
    if semantics is not None and not isinstance(semantics, dict):
        raise InputError(f'{where}: malformed semantics')
    types = [s.get('type') if isinstance(s, dict) else None for s in (semantics or {}).get('surfaces') or []]
    values = (semantics or {}).get('values')
    surfaces: list[tuple[str | None, tuple[np.ndarray, ...]]] = []
    for rings, value in _flatten(geometry.get('boundaries'), values, _SURFACE_DEPTH[geometry['type']], where):
        if value is not None and not (isinstance(value, int) and 0 <= value < len(types)):
            raise InputError(f'{where}: semantic value {value!r} out of range')
        coords = tuple(vertices[_ring_indices(ring, len(vertices), where)] for ring in rings)
        if coords and len(coords[0]):
            surfaces.append((types[value] if value is not None else None, coords))
    if all(kind is None for kind, _ in surfaces):
        return _typed_by_normals(surfaces, part)
    return [_Surface(kind, part, coords) for kind, coords in surfaces if kind in (_WALL, _ROOF, _GROUND)]


def _flatten(node: Any, values: Any, depth: int, where: str) -> Iterator[tuple[list, Any]]:
    """Yield (surface, semantic value) from ``boundaries`` nested ``depth`` levels deep."""
    if not isinstance(node, list):
        raise InputError(f'{where}: malformed geometry boundaries')
    for k, child in enumerate(node):
        value = values[k] if isinstance(values, list) and k < len(values) else None
        if depth == 1:
            if not isinstance(child, list):
                raise InputError(f'{where}: malformed geometry boundaries')
            yield child, value
        else:
            yield from _flatten(child, value, depth - 1, where)


def _ring_indices(ring: Any, count: int, where: str) -> np.ndarray:
    """A ring as an int array of vertex indices, checked against ``count`` vertices."""
    try:
        idx = np.asarray(ring)
    except (ValueError, OverflowError):  # ragged nesting, huge numbers
        idx = np.empty((0, 0))
    if not isinstance(ring, list) or idx.ndim != 1 or (idx.size and idx.dtype.kind not in 'iu'):
        raise InputError(f'{where}: malformed ring (not a list of vertex indices)')
    idx = idx.astype(np.int64)
    if idx.size and (idx.min() < 0 or idx.max() >= count):
        raise InputError(f'{where}: vertex index out of range (file has {count} vertices)')
    return idx


def _typed_by_normals(surfaces: list[tuple[str | None, tuple[np.ndarray, ...]]], part: int) -> list[_Surface]:
    """Type unlabelled surfaces by their Newell normal (wall, ground at the lowest z, roof)."""
    if not surfaces:
        return []
    z_low = min(float(coords[0][:, 2].min()) for _, coords in surfaces)
    typed = []
    for _, coords in surfaces:
        ring = coords[0] - coords[0].mean(axis=0)
        nxt = np.roll(ring, -1, axis=0)
        normal = np.array([np.sum((ring[:, 1] - nxt[:, 1]) * (ring[:, 2] + nxt[:, 2])),
                           np.sum((ring[:, 2] - nxt[:, 2]) * (ring[:, 0] + nxt[:, 0])),
                           np.sum((ring[:, 0] - nxt[:, 0]) * (ring[:, 1] + nxt[:, 1]))])
        length = float(np.linalg.norm(normal))
        if length == 0.0:
            continue
        nz = abs(normal[2]) / length
        if nz < 0.2:
            kind = _WALL
        elif nz > 0.9 and coords[0][:, 2].max() <= z_low + BOTTOM_TOLERANCE:
            kind = _GROUND
        else:
            kind = _ROOF
        typed.append(_Surface(kind, part, coords))
    return typed


# ----------------------------------------------------------------------------------------
# Footprint of one building


def _footprint(oid: str, surfaces: list[_Surface], min_edge: float, tolerance: float) -> Footprint | None:
    """The footprint of one building from its typed surfaces, or None if it is not usable."""
    grounds = [s.rings[0] for s in surfaces if s.kind == _GROUND]
    if grounds:
        rings = [g[:, :2] for g in grounds]
        base_z = np.concatenate([g[:, 2] for g in grounds])
    else:
        rings, base = [], []
        for part in sorted({s.part for s in surfaces}):
            walls = [s.rings[0] for s in surfaces if s.part == part and s.kind == _WALL]
            z_low = min((float(s.rings[0][:, 2].min()) for s in surfaces if s.part == part), default=np.inf)
            part_rings, part_z = _wall_bottom_rings(walls, z_low)
            rings += part_rings
            base += part_z
        base_z = np.array(base)
    if not rings or not base_z.size:
        return None
    outer, dropped = _union_outer(rings)
    if outer is None:
        return None
    if dropped:
        _log.info('building %s: %d disjoint footprint ring(s) dropped, kept the largest', oid, dropped)
    polygon = _simplify_checked(outer, min_edge, tolerance)
    if polygon is None or _area(polygon) < MIN_AREA:
        _log.info('building %s: footprint under %g m^2 dropped', oid, MIN_AREA)
        return None
    ground_z = float(base_z.min())
    wall_tops = np.array([s.rings[0][:, 2].max() for s in surfaces if s.kind == _WALL])
    roof_z = np.concatenate([s.rings[0][:, 2] for s in surfaces if s.kind == _ROOF] or [np.empty(0)])
    if not wall_tops.size and not roof_z.size:
        return None
    ridge = float(roof_z.max() if roof_z.size else wall_tops.max()) - ground_z
    eave = float(np.median(wall_tops) if wall_tops.size else roof_z.min()) - ground_z
    eave = min(eave, ridge)
    if not (np.isfinite(eave) and eave > 0.0):
        return None
    polygon.setflags(write=False)
    return Footprint(oid, polygon, ground_z, eave, ridge)


def _wall_bottom_rings(walls: list[np.ndarray], z_low: float) -> tuple[list[np.ndarray], list[float]]:
    """Closed (K, 2) rings chained from the bottom edges of walls, and the z of their vertices.

    Args:
        walls: exterior rings of the wall surfaces of one part, each (K, 3) metres.
        z_low: lowest z of the part, metres.

    Returns:
        The rings (unoriented) and the z values of the bottom-edge vertices used.
    """
    starts, ends = [], []
    for wall in walls:
        nxt = np.roll(wall, -1, axis=0)
        low = np.abs(wall[:, 2] - z_low) <= BOTTOM_TOLERANCE
        keep = low & np.roll(low, -1)
        starts.append(wall[keep])
        ends.append(nxt[keep])
    if not starts:
        return [], []
    a, b = np.concatenate(starts), np.concatenate(ends)
    if not len(a):
        return [], []
    points = np.concatenate([a, b])
    ids, rep = _cluster(points[:, :2], 1e-3)
    n = len(a)
    edges = np.stack([ids[:n], ids[n:]], axis=1)
    edges = edges[edges[:, 0] != edges[:, 1]]
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    neighbours: dict[int, list[int]] = {}
    for k, (u, v) in enumerate(edges):
        neighbours.setdefault(int(u), []).append(k)
        neighbours.setdefault(int(v), []).append(k)
    used = np.zeros(len(edges), dtype=bool)
    rings: list[np.ndarray] = []
    for first in range(len(edges)):
        if used[first]:
            continue
        used[first] = True
        start, here = int(edges[first, 0]), int(edges[first, 1])
        chain = [start]
        while here != start:
            chain.append(here)
            options = [k for k in neighbours[here] if not used[k]]
            if not options:
                break
            used[options[0]] = True
            u, v = edges[options[0]]
            here = int(v if u == here else u)
        if here == start and len(chain) >= 3:
            rings.append(points[rep[chain], :2])
    zs = points[:, 2].tolist() if rings else []
    return rings, zs


def _cluster(points: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Merge points closer than ``tol``.

    Args:
        points: (P, D) coordinates.
        tol: merge distance, same unit.

    Returns:
        ``ids`` (P,) cluster number of each point and ``rep`` (C,) index of the first point
        of each cluster.
    """
    pairs = cKDTree(points).query_pairs(tol, output_type='ndarray')
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(points),) * 2)
    _, labels = connected_components(graph, directed=False)
    # Number clusters by their first point so that representatives are original points.
    first = np.full(labels.max() + 1, len(points))
    np.minimum.at(first, labels, np.arange(len(points)))
    order = np.argsort(first)
    renumber = np.empty_like(order)
    renumber[order] = np.arange(len(order))
    return renumber[labels], first[order]


# ----------------------------------------------------------------------------------------
# Polygon union (outer boundary)


def _union_outer(rings: list[np.ndarray]) -> tuple[np.ndarray | None, int]:
    """Outer boundary of the union of polygons, by a planar overlay.

    All rings are turned counter-clockwise and their edges split at every crossing and at
    every vertex lying on them (within :data:`_SNAP`), so that coinciding pieces of
    different rings get identical end points. A piece is on the union's boundary if it is
    not shared with a ring running the other way (adjacent polygons) and its midpoint is
    inside no other ring; the kept pieces are chained into rings with the union on their
    left.

    Args:
        rings: polygons, each (K, 2) metres, either orientation, not closed.

    Returns:
        The counter-clockwise outer ring of largest area ((M, 2), vertices taken from the
        input where they are input vertices) or None if the union is empty, and the number
        of further disjoint outer rings (ignoring slivers under :data:`_SLIVER`) dropped.
    """
    rings = [r for r in (_dedupe(r) for r in rings) if len(r) >= 3 and _area(r) != 0.0]
    if not rings:
        return None, 0
    rings = [r if _area(r) > 0 else r[::-1] for r in rings]
    origin = rings[0][0]
    local = [r - origin for r in rings]
    a = np.concatenate(local)
    b = np.concatenate([np.roll(r, -1, axis=0) for r in local])
    seg_global = np.concatenate([np.concatenate(rings), np.concatenate([np.roll(r, -1, axis=0) for r in rings])])
    seg_ring = np.repeat(np.arange(len(rings)), [len(r) for r in rings])
    d = b - a
    length = np.hypot(d[:, 0], d[:, 1])
    e = len(a)

    # Split points: (segment, t, local point, global point); original vertices first.
    seg = [np.arange(e), np.arange(e)]
    ts = [np.zeros(e), np.ones(e)]
    loc = [a, b]
    glo = [seg_global[:e], seg_global[e:]]
    # Vertices lying on the inside of a segment (T-junctions, collinear overlaps).
    rel = a[None, :, :] - a[:, None, :]  # [i, j] = a_j - a_i
    t = (rel[..., 0] * d[:, None, 0] + rel[..., 1] * d[:, None, 1]) / length[:, None] ** 2
    dist = np.abs(d[:, None, 0] * rel[..., 1] - d[:, None, 1] * rel[..., 0]) / length[:, None]
    margin = _MERGE / length[:, None]
    i, j = np.nonzero((dist < _SNAP) & (t > margin) & (t < 1 - margin))
    seg.append(i)
    ts.append(t[i, j])
    loc.append(a[j])
    glo.append(seg_global[j])
    # Proper crossings.
    denom = d[:, None, 0] * d[None, :, 1] - d[:, None, 1] * d[None, :, 0]
    with np.errstate(divide='ignore', invalid='ignore'):
        t = (rel[..., 0] * d[None, :, 1] - rel[..., 1] * d[None, :, 0]) / denom
        u = (rel[..., 0] * d[:, None, 1] - rel[..., 1] * d[:, None, 0]) / denom
    ok = np.abs(denom) > 1e-12 * length[:, None] * length[None, :]
    m_i, m_j = _MERGE / length[:, None], _MERGE / length[None, :]
    i, j = np.nonzero(ok & (t > m_i) & (t < 1 - m_i) & (u > m_j) & (u < 1 - m_j))
    cross = a[i] + t[i, j][:, None] * d[i]
    seg.append(i)
    ts.append(t[i, j])
    loc.append(cross)
    glo.append(cross + origin)

    seg_all, t_all = np.concatenate(seg), np.concatenate(ts)
    loc_all, glo_all = np.concatenate(loc), np.concatenate(glo)
    ids, rep = _cluster(loc_all, _MERGE)
    order = np.lexsort((t_all, seg_all))
    same = seg_all[order][:-1] == seg_all[order][1:]
    pieces = np.stack([ids[order][:-1][same], ids[order][1:][same]], axis=1)  # directed, CCW
    piece_ring = seg_ring[seg_all[order][:-1][same]]
    keep = pieces[:, 0] != pieces[:, 1]
    pieces, piece_ring = pieces[keep], piece_ring[keep]
    if not len(pieces):
        return None, 0

    # Group coinciding pieces; drop groups running both ways, and those inside another ring.
    keys, group = np.unique(np.sort(pieces, axis=1), axis=0, return_inverse=True)
    group = group.reshape(-1)
    forward = pieces[:, 0] < pieces[:, 1]
    n_groups = len(keys)
    has_fwd = np.zeros(n_groups, dtype=bool)
    has_bwd = np.zeros(n_groups, dtype=bool)
    has_fwd[group[forward]] = True
    has_bwd[group[~forward]] = True
    member = np.zeros((n_groups, len(rings)), dtype=bool)
    member[group, piece_ring] = True
    pts = loc_all[rep]
    mid = 0.5 * (pts[keys[:, 0]] + pts[keys[:, 1]])
    inside = np.stack([_inside_any(mid, [ring]) for ring in local], axis=1)
    boundary = (has_fwd != has_bwd) & ~np.any(inside & ~member, axis=1)
    edges = np.where(has_fwd[:, None], keys, keys[:, ::-1])[boundary]

    outers = [ring for ring in _chain_directed(edges, pts) if _area(pts[ring]) > 0]
    if not outers:  # numerically hopeless overlay: fall back to the largest input ring
        best = int(np.argmax([_area(r) for r in rings]))
        return rings[best], len(rings) - 1
    areas = [_area(pts[ring]) for ring in outers]
    best = int(np.argmax(areas))
    dropped = sum(1 for k, area in enumerate(areas) if k != best and area >= _SLIVER)
    return glo_all[rep[outers[best]]], dropped


def _inside_any(points: np.ndarray, rings: list[np.ndarray]) -> np.ndarray:
    """(P,) bool: inside at least one ring (even-odd rule); points (P, 2), rings (K, 2)."""
    inside = np.zeros(len(points), dtype=bool)
    px, py = points[:, 0:1], points[:, 1:2]
    for ring in rings:
        x0, y0 = ring[:, 0], ring[:, 1]
        x1, y1 = np.roll(x0, -1), np.roll(y0, -1)
        spans = (y0 > py) != (y1 > py)
        with np.errstate(divide='ignore', invalid='ignore'):
            x_at = x0 + (py - y0) * (x1 - x0) / (y1 - y0)
        inside |= (spans & (px < x_at)).sum(axis=1) % 2 == 1
    return inside


def _chain_directed(edges: np.ndarray, pts: np.ndarray) -> list[list[int]]:
    """Chain directed edges into closed rings, turning left where several edges go on.

    A walk that comes back to one of its own vertices closes the loop there (so a stray
    edge leading into a ring does not spoil it); a walk that gets stuck is dropped.

    Args:
        edges: (E, 2) vertex ids, from -> to.
        pts: (V, 2) vertex coordinates, metres.

    Returns:
        The rings as lists of vertex ids (not closed).
    """
    outgoing: dict[int, list[int]] = {}
    for k, (u, _) in enumerate(edges):
        outgoing.setdefault(int(u), []).append(k)
    used = np.zeros(len(edges), dtype=bool)
    rings: list[list[int]] = []
    for first in range(len(edges)):
        if used[first]:
            continue
        used[first] = True
        chain = [int(edges[first, 0])]
        prev, here = chain[0], int(edges[first, 1])
        while True:
            if here in chain:
                pos = chain.index(here)
                if len(chain) - pos >= 3:
                    rings.append(chain[pos:])
                del chain[pos + 1:]
                if pos == 0:
                    break
                prev = chain[pos - 1]
            else:
                chain.append(here)
            options = [k for k in outgoing.get(here, []) if not used[k]]
            if not options:
                break
            come = pts[here] - pts[prev]
            heading = np.arctan2(come[1], come[0])
            goes = pts[edges[options, 1]] - pts[here]
            turn = (np.arctan2(goes[:, 1], goes[:, 0]) - heading + np.pi) % (2 * np.pi)
            k = options[int(np.argmax(turn))]
            used[k] = True
            prev, here = here, int(edges[k, 1])
    return rings


# ----------------------------------------------------------------------------------------
# Polygon helpers


def _area(ring: np.ndarray) -> float:
    """Signed area of a (K, 2) ring (positive if counter-clockwise)."""
    x, y = ring[:, 0] - ring[0, 0], ring[:, 1] - ring[0, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _dedupe(ring: np.ndarray) -> np.ndarray:
    """Drop consecutive duplicate vertices (and a closing vertex) of a (K, 2) ring."""
    if len(ring) < 2:
        return ring
    keep = np.any(ring != np.roll(ring, -1, axis=0), axis=1)
    return ring[keep]


def _simplify_checked(ring: np.ndarray, min_edge: float, tolerance: float) -> np.ndarray | None:
    """Simplified, simple, CCW ring starting at its smallest vertex; None if degenerate."""
    if _area(ring) < 0:
        ring = ring[::-1]
    result = _simplify(ring, min_edge, tolerance)
    if result is None or not _is_simple(result):
        result = _simplify(ring, 0.0, 0.0)
    if result is None or _area(result) <= 0:
        return None
    start = int(np.lexsort((result[:, 1], result[:, 0]))[0])
    return np.ascontiguousarray(np.roll(result, -start, axis=0), dtype=np.float64)


def _simplify(ring: np.ndarray, min_edge: float, tolerance: float) -> np.ndarray | None:
    """Drop near-collinear vertices and resolve short edges (see the module documentation).

    One change at a time, in this order of preference: drop a vertex where the boundary
    turns by less than :data:`MIN_TURN_DEG` (or a spike); make a short edge a corner
    where its neighbours' lines cross within ``tolerance`` of it; drop the vertex nearest
    to the line through its neighbours if within ``tolerance``; drop an end vertex of the
    shortest edge if that is shorter than ``min_edge``.

    Args:
        ring: (K, 2) counter-clockwise ring, metres.
        min_edge: shortest edge to keep, metres.
        tolerance: distance to the line through the neighbours under which a vertex goes, metres.

    Returns:
        The simplified (M, 2) ring, or None if fewer than 3 vertices remain.
    """
    pts = ring.copy()
    min_sin = np.sin(np.radians(MIN_TURN_DEG))
    while len(pts) >= 3:
        n = len(pts)
        prev, nxt = np.roll(pts, 1, axis=0), np.roll(pts, -1, axis=0)
        d_in, d_out, chord = pts - prev, nxt - pts, nxt - prev
        l_in, l_out = np.hypot(*d_in.T), np.hypot(*d_out.T)
        l_chord = np.hypot(*chord.T)
        cross = d_in[:, 0] * d_out[:, 1] - d_in[:, 1] * d_out[:, 0]
        dot = np.sum(d_in * d_out, axis=1)
        with np.errstate(divide='ignore', invalid='ignore'):
            offset = np.where(l_chord > 0, np.abs(cross) / l_chord, 0.0)  # distance to the chord
        straight = ((np.abs(cross) <= min_sin * l_in * l_out) & (dot > 0)) | (l_in == 0) | (offset == 0)
        if straight.any():
            pts = np.delete(pts, int(np.argmin(np.where(straight, offset, np.inf))), axis=0)
            continue
        short = np.flatnonzero(l_out < min_edge)
        short = short[np.argsort(l_out[short])]
        corner_made = False
        for k in short if n > 3 else ():
            k1 = (k + 1) % n
            corner = _line_crossing(pts[k - 1], pts[k], pts[k1], pts[(k + 2) % n])
            if corner is not None and _distance_to_segment(corner, pts[k], pts[k1]) <= tolerance:
                pts[k] = corner
                pts = np.delete(pts, k1, axis=0)
                corner_made = True
                break
        if corner_made:
            continue
        if offset.min() <= tolerance:
            pts = np.delete(pts, int(np.argmin(offset)), axis=0)
            continue
        if not len(short):
            break
        k = int(short[0])  # edge k runs from vertex k to k + 1
        k1 = (k + 1) % n
        # Triangle area each end spans with its neighbours: the smaller one goes.
        pts = np.delete(pts, k if abs(cross[k]) <= abs(cross[k1]) else k1, axis=0)
    return pts if len(pts) >= 3 else None


def _line_crossing(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray) -> np.ndarray | None:
    """Crossing of the lines p0-p1 and q0-q1 (2-D), None if they are (nearly) parallel."""
    dp, dq = p1 - p0, q1 - q0
    denom = dp[0] * dq[1] - dp[1] * dq[0]
    if abs(denom) < np.sin(np.radians(MIN_TURN_DEG)) * np.hypot(*dp) * np.hypot(*dq):
        return None
    s = ((q0[0] - p0[0]) * dq[1] - (q0[1] - p0[1]) * dq[0]) / denom
    return p0 + s * dp


def _distance_to_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Distance of point p to segment a-b (2-D)."""
    ab = b - a
    denom = float(np.dot(ab, ab))
    t = 0.0 if denom == 0 else float(np.clip(np.dot(p - a, ab) / denom, 0.0, 1.0))
    return float(np.hypot(*(p - a - t * ab)))


def _is_simple(ring: np.ndarray) -> bool:
    """True if no two non-adjacent edges of the (K, 2) ring touch or cross."""
    n = len(ring)
    if n < 3:
        return False
    a, b = ring - ring[0], np.roll(ring, -1, axis=0) - ring[0]
    ai, bi = a[:, None, :], b[:, None, :]
    aj, bj = a[None, :, :], b[None, :, :]

    def orient(p: np.ndarray, q: np.ndarray, r: np.ndarray) -> np.ndarray:
        return np.sign((q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1])
                       - (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0]))

    def within(p: np.ndarray, q: np.ndarray, r: np.ndarray) -> np.ndarray:
        """r inside the bounding box of segment p-q (for r collinear with it)."""
        return np.all((np.minimum(p, q) <= r) & (r <= np.maximum(p, q)), axis=-1)

    o1, o2 = orient(ai, bi, aj), orient(ai, bi, bj)
    o3, o4 = orient(aj, bj, ai), orient(aj, bj, bi)
    hit = (o1 * o2 < 0) & (o3 * o4 < 0)
    hit |= (o1 == 0) & within(ai, bi, aj)
    hit |= (o2 == 0) & within(ai, bi, bj)
    hit |= (o3 == 0) & within(aj, bj, ai)
    hit |= (o4 == 0) & within(aj, bj, bi)
    idx = np.arange(n)
    gap = np.abs(idx[:, None] - idx[None, :])
    adjacent = (gap <= 1) | (gap == n - 1)
    return not np.any(hit & ~adjacent)
