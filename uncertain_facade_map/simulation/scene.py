"""The simulated world: buildings with façade detail, occluders and the ground.

Geometry is exact: a building is a vertical prism over its footprint, minus window
recesses, plus protrusions (balconies, oriels, sloped parts, round bays, columns). Each
wall of the footprint is a façade with its own frame (``u`` along the wall, ``v`` up,
``n`` out of the building towards the street); detail is placed in that frame. Rays are
cast against a two-level hierarchy of axis-aligned boxes, so a campaign of a few million
shots takes seconds.

All coordinates are metres in the map frame (z up, ground at z = 0).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Iterable, Sequence

import numpy as np

from ..io.cloud import CLASS_BUILDING, CLASS_NAMES
from .raycast import (
    INF,
    inverse_directions,
    points_in_polygon,
    ray_aabb,
    ray_convex,
    ray_prism,
    ray_sphere,
    ray_vertical_cylinder,
)
from .walls import FacadeRelief, WallRealism, on_pane, panes

CLASS_OTHER = 0
CLASS_GROUND = 2
CLASS_VEGETATION = 3
CLASS_VEHICLE = 4
CLASS_POLE = 5
assert CLASS_NAMES[CLASS_GROUND] == 'ground' and CLASS_NAMES[CLASS_POLE] == 'pole'

#: How far a recess box reaches out of the wall, metres, so hits on the wall plane fall in it.
_RECESS_LIP = 1e-3


# ----------------------------------------------------------------------------------------
# Façade frames and detail features (all lengths in metres, in the façade frame)
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FacadeFrame:
    """Frame of one wall: point = origin + U u + V v + N n, with v = +z.

    Attributes:
        origin: (3,) start of the wall at ground level, map frame.
        u: (3,) unit vector along the wall (horizontal).
        n: (3,) unit outward normal (horizontal).
        length: wall length along u.
        height: wall height along v.
    """

    origin: np.ndarray
    u: np.ndarray
    n: np.ndarray
    length: float
    height: float

    @property
    def v(self) -> np.ndarray:
        """(3,) up vector of the frame."""
        return np.array([0.0, 0.0, 1.0])

    def to_world(self, uvn: np.ndarray) -> np.ndarray:
        """Map (K, 3) façade coordinates (u, v, n) to (K, 3) map-frame points."""
        uvn = np.asarray(uvn, dtype=np.float64)
        return self.origin + uvn[:, 0:1] * self.u + uvn[:, 1:2] * self.v + uvn[:, 2:3] * self.n

    def to_facade(self, xyz: np.ndarray) -> np.ndarray:
        """Map (K, 3) map-frame points to (K, 3) façade coordinates (u, v, n)."""
        rel = np.asarray(xyz, dtype=np.float64) - self.origin
        return np.stack([rel @ self.u, rel @ self.v, rel @ self.n], axis=1)

    def half_space(self, a_u: float, a_v: float, a_n: float, c: float) -> tuple[np.ndarray, float]:
        """Return (normal (3,), offset) of the half-space a_u U + a_v V + a_n N <= c."""
        w = a_u * self.u + a_v * self.v + a_n * self.n
        norm = float(np.linalg.norm(w))
        return w / norm, (c + float(w @ self.origin)) / norm


@dataclass(frozen=True)
class Recess:
    """A window or door recess: the box u0..u1, v0..v1, depth metres into the wall."""

    u0: float
    u1: float
    v0: float
    v1: float
    depth: float


@dataclass(frozen=True)
class Block:
    """A box protrusion (balcony parapet, oriel): u0..u1, v0..v1, ``out`` metres out of the wall."""

    u0: float
    u1: float
    v0: float
    v1: float
    out: float
    kind: str = 'balcony'


@dataclass(frozen=True)
class Slope:
    """A sloped (non-vertical) part: a wedge whose front goes from ``out0`` at v0 to ``out1`` at v1."""

    u0: float
    u1: float
    v0: float
    v1: float
    out0: float
    out1: float


@dataclass(frozen=True)
class Round:
    """A vertical cylinder (round bay or column) of ``radius`` with its axis at (uc, nc)."""

    uc: float
    nc: float
    radius: float
    v0: float
    v1: float
    kind: str = 'bay'


Feature = Recess | Block | Slope | Round


@dataclass(frozen=True)
class Facade:
    """One wall of a building with its detail.

    Attributes:
        facade_id: scene-wide index of the façade.
        building_id: index of the building.
        wall: index of the footprint edge the façade lies on.
        frame: the façade frame.
        features: detail in the façade frame.
    """

    facade_id: int
    building_id: int
    wall: int
    frame: FacadeFrame
    features: tuple[Feature, ...] = ()


@dataclass(frozen=True)
class Building:
    """A vertical prism over a counter-clockwise footprint, with façades on its walls.

    Attributes:
        building_id: index of the building.
        polygon: (M, 2) footprint, counter-clockwise, metres, map frame.
        height: roof height above the ground, metres.
        facades: one per wall of the footprint, in edge order.
        source: where the footprint came from ('synthetic' or a CityJSON id).
    """

    building_id: int
    polygon: np.ndarray
    height: float
    facades: tuple[Facade, ...]
    source: str = 'synthetic'


# ----------------------------------------------------------------------------------------
# Occluders
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Car:
    """A parked car, a box ``length`` x ``width`` x ``height`` centred at (x, y), heading ``yaw`` rad."""

    x: float
    y: float
    yaw: float
    length: float = 4.5
    width: float = 1.8
    height: float = 1.5


@dataclass(frozen=True)
class Tree:
    """A tree: trunk cylinder and a porous spherical crown (Beer-Lambert density per metre)."""

    x: float
    y: float
    trunk_radius: float
    trunk_height: float
    crown_radius: float
    density: float = 0.5


@dataclass(frozen=True)
class Pole:
    """A pole (street lamp, sign post) with an optional rectangular sign on top."""

    x: float
    y: float
    radius: float
    height: float
    sign: bool = False


@dataclass(frozen=True)
class Hedge:
    """A hedge or a fence: a box ``length`` x ``width`` x ``height`` standing on the ground,
    centred at (x, y), its length along heading ``yaw`` rad; a hedge is vegetation, a fence
    (``kind='fence'``) is of class other."""

    x: float
    y: float
    yaw: float
    length: float
    width: float
    height: float
    kind: str = 'hedge'


Occluder = Car | Tree | Pole | Hedge


# ----------------------------------------------------------------------------------------
# Ray casting
# ----------------------------------------------------------------------------------------
@dataclass
class Hits:
    """Closest hits of N rays.

    Attributes:
        t: (N,) range to the hit, metres; ``inf`` for none.
        label: (N,) uint8 semantic class of the surface hit.
        building_id: (N,) int32, -1 where no building was hit.
        facade_id: (N,) int32 scene-wide façade index, -1 for none (also roofs).
    """

    t: np.ndarray
    label: np.ndarray
    building_id: np.ndarray
    facade_id: np.ndarray

    @classmethod
    def empty(cls, n: int) -> Hits:
        """N rays that have hit nothing yet."""
        return cls(
            np.full(n, INF), np.zeros(n, np.uint8), np.full(n, -1, np.int32), np.full(n, -1, np.int32)
        )

    def update(self, idx: np.ndarray, t: np.ndarray, label: int, building: int, facade: np.ndarray | int) -> None:
        """Keep ``t`` for rays ``idx`` where it is closer than the current hit."""
        closer = t < self.t[idx]
        if not closer.any():
            return
        sel = idx[closer]
        self.t[sel] = t[closer]
        self.label[sel] = label
        self.building_id[sel] = building
        self.facade_id[sel] = facade[closer] if isinstance(facade, np.ndarray) else facade


@dataclass
class _Context:
    """What a cast needs besides the rays: the random source for porous solids, filters."""

    rng: np.random.Generator | None


class _Node:
    """A leaf solid: an AABB and a method to cast rays at it."""

    lo: np.ndarray
    hi: np.ndarray
    building: int = -1

    def cast(self, o: np.ndarray, d: np.ndarray, idx: np.ndarray, hits: Hits, ctx: _Context) -> None:
        """Update ``hits`` for rays ``idx`` (indices into ``o``, ``d``) with this solid."""
        raise NotImplementedError


class _Bvh:
    """Bounding-volume hierarchy over leaf solids, traversed with shrinking ray subsets.

    A ray goes down a branch only if it enters the branch's box before its current
    closest hit, so rays into the sky or stopped by a near object cost a few box tests.
    """

    def __init__(self, leaves: Sequence[_Node], leaf_size: int = 2) -> None:
        self.leaves = list(leaves)
        # Padded by a micrometre so that rays grazing a leaf's box are still tested.
        self.lo = np.min([n.lo for n in leaves], axis=0) - 1e-6 if leaves else np.zeros(3)
        self.hi = np.max([n.hi for n in leaves], axis=0) + 1e-6 if leaves else np.zeros(3)
        self.children: list[_Bvh] = []
        if len(leaves) > leaf_size:
            centres = np.array([(n.lo + n.hi) / 2 for n in leaves])
            axis = int(np.argmax(np.ptp(centres, axis=0)))
            order = np.argsort(centres[:, axis], kind='stable')
            half = len(order) // 2
            self.children = [_Bvh([leaves[i] for i in order[:half]], leaf_size),
                             _Bvh([leaves[i] for i in order[half:]], leaf_size)]

    def visit(self, o: np.ndarray, d: np.ndarray, inv: np.ndarray, idx: np.ndarray, hits: Hits,
              ctx: _Context) -> None:
        """Cast rays ``idx`` through this branch."""
        if not len(idx) or not self.leaves:
            return
        t_box = ray_aabb(o[idx], inv[idx], self.lo, self.hi)
        idx = idx[t_box < hits.t[idx]]
        if not len(idx):
            return
        if self.children:
            for child in self.children:
                child.visit(o, d, inv, idx, hits, ctx)
        else:
            for leaf in self.leaves:
                leaf.cast(o, d, idx, hits, ctx)


class _Convex(_Node):
    """A convex solid from half-spaces, e.g. a box or a wedge."""

    def __init__(self, planes: list[tuple[np.ndarray, float]], corners: np.ndarray, label: int,
                 building: int = -1, facade: int = -1) -> None:
        self.normals = np.array([p[0] for p in planes])
        self.offsets = np.array([p[1] for p in planes])
        self.lo, self.hi = corners.min(axis=0) - 1e-6, corners.max(axis=0) + 1e-6
        self.label, self.building, self.facade = label, building, facade

    def cast(self, o, d, idx, hits, ctx) -> None:
        t, _ = ray_convex(o[idx], d[idx], self.normals, self.offsets)
        hits.update(idx, t, self.label, self.building, self.facade)

    def contains(self, p: np.ndarray) -> np.ndarray:
        return np.all(p @ self.normals.T <= self.offsets + 1e-9, axis=1)


class _Cylinder(_Node):
    def __init__(self, centre: np.ndarray, radius: float, z0: float, z1: float, label: int,
                 building: int = -1, facade: int = -1) -> None:
        self.centre, self.radius, self.z0, self.z1 = np.asarray(centre, float), radius, z0, z1
        self.lo = np.array([centre[0] - radius, centre[1] - radius, z0])
        self.hi = np.array([centre[0] + radius, centre[1] + radius, z1])
        self.label, self.building, self.facade = label, building, facade

    def cast(self, o, d, idx, hits, ctx) -> None:
        t = ray_vertical_cylinder(o[idx], d[idx], self.centre, self.radius, self.z0, self.z1)
        hits.update(idx, t, self.label, self.building, self.facade)

    def contains(self, p: np.ndarray) -> np.ndarray:
        r2 = ((p[:, :2] - self.centre) ** 2).sum(axis=1)
        return (r2 <= self.radius**2 + 1e-9) & (p[:, 2] >= self.z0) & (p[:, 2] <= self.z1)


class _Crown(_Node):
    """A porous sphere: a ray through it is stopped at an exponentially distributed depth."""

    def __init__(self, centre: np.ndarray, radius: float, density: float) -> None:
        self.centre, self.radius, self.density = np.asarray(centre, float), radius, density
        self.lo, self.hi = self.centre - radius, self.centre + radius

    def cast(self, o, d, idx, hits, ctx) -> None:
        if ctx.rng is None:  # truth queries see through vegetation
            return
        t0, t1 = ray_sphere(o[idx], d[idx], self.centre, self.radius)
        crossing = np.isfinite(t0)
        chord = np.where(crossing, t1 - np.where(crossing, t0, 0.0), 0.0)
        # Beer-Lambert: depth of the first leaf ~ Exp(density), truncated to the chord.
        u = ctx.rng.random(len(idx))
        p_stop = 1.0 - np.exp(-self.density * chord)
        stopped = crossing & (u < p_stop)
        with np.errstate(divide='ignore', invalid='ignore'):
            depth = -np.log1p(-np.where(stopped, u, 0.0)) / self.density
        t = np.where(stopped, t0 + depth, INF)
        hits.update(idx, t, CLASS_VEGETATION, -1, -1)


def _cast_ground(o: np.ndarray, d: np.ndarray, hits: Hits, z: float = 0.0) -> None:
    """The ground plane z = ``z``, seen from above."""
    dz = d[:, 2]
    with np.errstate(divide='ignore', invalid='ignore'):
        t = (z - o[:, 2]) / dz
    t = np.where((dz < 0.0) & (t > 0.0), t, INF)
    hits.update(np.arange(len(o)), t, CLASS_GROUND, -1, -1)


class _BuildingBody(_Node):
    """The prism of a building minus its recesses."""

    def __init__(self, building: Building) -> None:
        self.polygon = building.polygon
        self.height = building.height
        self.building = building.building_id
        self.lo = np.array([*building.polygon.min(axis=0), 0.0])
        self.hi = np.array([*building.polygon.max(axis=0), building.height])
        m = len(building.polygon)
        self.face_facade = np.full(m + 2, -1, np.int32)
        self.recesses: dict[int, tuple[Facade, np.ndarray, list[_Convex]]] = {}
        for facade in building.facades:
            self.face_facade[facade.wall] = facade.facade_id
            rec = [f for f in facade.features if isinstance(f, Recess)]
            if rec:
                rects = np.array([[r.u0, r.u1, r.v0, r.v1] for r in rec])
                solids = [_box_solid(facade, r.u0, r.u1, r.v0, r.v1, -r.depth, _RECESS_LIP,
                                     CLASS_BUILDING) for r in rec]
                self.recesses[facade.wall] = (facade, rects, solids)

    def cast(self, o, d, idx, hits, ctx) -> None:
        t, face = ray_prism(o[idx], d[idx], self.polygon, 0.0, self.height)
        for wall, (facade, rects, solids) in self.recesses.items():
            rows = np.flatnonzero(face == wall)
            if not len(rows):
                continue
            p = o[idx[rows]] + t[rows, None] * d[idx[rows]]
            uvn = facade.frame.to_facade(p)
            inside = ((uvn[:, 0:1] >= rects[:, 0]) & (uvn[:, 0:1] <= rects[:, 1])
                      & (uvn[:, 1:2] >= rects[:, 2]) & (uvn[:, 1:2] <= rects[:, 3]))
            which = np.where(inside.any(axis=1), inside.argmax(axis=1), -1)
            for k in np.unique(which[which >= 0]):
                sel = rows[which == k]
                _, t_exit = ray_convex(o[idx[sel]], d[idx[sel]], solids[k].normals, solids[k].offsets)
                t[sel] = t_exit
        facade_ids = self.face_facade[np.where(face >= 0, face, len(self.face_facade) - 1)]
        hits.update(idx, t, CLASS_BUILDING, self.building, facade_ids)


def _box_solid(facade: Facade, u0: float, u1: float, v0: float, v1: float, n0: float, n1: float,
               label: int) -> _Convex:
    fr = facade.frame
    planes = [fr.half_space(1, 0, 0, u1), fr.half_space(-1, 0, 0, -u0), fr.half_space(0, 1, 0, v1),
              fr.half_space(0, -1, 0, -v0), fr.half_space(0, 0, 1, n1), fr.half_space(0, 0, -1, -n0)]
    corners = fr.to_world(np.array([[u, v, n] for u in (u0, u1) for v in (v0, v1) for n in (n0, n1)]))
    return _Convex(planes, corners, label, facade.building_id, facade.facade_id)


def _slope_solid(facade: Facade, s: Slope) -> _Convex:
    fr = facade.frame
    # Front plane through (v0, out0) and (v1, out1): n - k (v - v0) <= out0 with k = slope.
    k = (s.out1 - s.out0) / (s.v1 - s.v0)
    planes = [fr.half_space(1, 0, 0, s.u1), fr.half_space(-1, 0, 0, -s.u0), fr.half_space(0, 1, 0, s.v1),
              fr.half_space(0, -1, 0, -s.v0), fr.half_space(0, -k, 1, s.out0 - k * s.v0),
              fr.half_space(0, 0, -1, 0.0)]
    corners = fr.to_world(np.array([[u, v, n] for u in (s.u0, s.u1) for v in (s.v0, s.v1)
                                    for n in (0.0, max(s.out0, s.out1))]))
    return _Convex(planes, corners, CLASS_BUILDING, facade.building_id, facade.facade_id)


def _feature_solid(facade: Facade, f: Feature) -> _Node | None:
    if isinstance(f, Block):
        return _box_solid(facade, f.u0, f.u1, f.v0, f.v1, 0.0, f.out, CLASS_BUILDING)
    if isinstance(f, Slope):
        return _slope_solid(facade, f)
    if isinstance(f, Round):
        c = facade.frame.to_world(np.array([[f.uc, 0.0, f.nc]]))[0]
        return _Cylinder(c[:2], f.radius, f.v0, f.v1, CLASS_BUILDING, facade.building_id, facade.facade_id)
    return None  # recesses are part of the body


def _ground_box(occ: Car | Hedge, label: int) -> _Convex:
    """The box of a car or a hedge: on the ground, turned by its yaw."""
    c, s = np.cos(occ.yaw), np.sin(occ.yaw)
    ax, ay = np.array([c, s, 0.0]), np.array([-s, c, 0.0])
    centre = np.array([occ.x, occ.y, occ.height / 2])
    half = np.array([occ.length, occ.width, occ.height]) / 2
    planes, corners = [], []
    for axis, h in ((ax, half[0]), (ay, half[1]), (np.array([0.0, 0.0, 1.0]), half[2])):
        planes += [(axis, float(axis @ centre + h)), (-axis, float(-axis @ centre + h))]
    for sx in (-1, 1):
        for sy in (-1, 1):
            for sz in (-1, 1):
                corners.append(centre + sx * half[0] * ax + sy * half[1] * ay + sz * half[2] * np.array([0, 0, 1.0]))
    return _Convex(planes, np.array(corners), label)


def _occluder_nodes(occ: Occluder) -> list[_Node]:
    if isinstance(occ, Car):
        return [_ground_box(occ, CLASS_VEHICLE)]
    if isinstance(occ, Hedge):
        return [_ground_box(occ, CLASS_VEGETATION if occ.kind == 'hedge' else CLASS_OTHER)]
    if isinstance(occ, Tree):
        top = occ.trunk_height + occ.crown_radius
        return [_Cylinder(np.array([occ.x, occ.y]), occ.trunk_radius, 0.0, occ.trunk_height + 0.5 * occ.crown_radius,
                          CLASS_VEGETATION),
                _Crown(np.array([occ.x, occ.y, top]), occ.crown_radius, occ.density)]
    nodes: list[_Node] = [_Cylinder(np.array([occ.x, occ.y]), occ.radius, 0.0, occ.height, CLASS_POLE)]
    if occ.sign:
        lo = np.array([occ.x - 0.35, occ.y - 0.03, occ.height - 0.9])
        hi = np.array([occ.x + 0.35, occ.y + 0.03, occ.height - 0.2])
        planes = [(np.array(v, float), float(o)) for v, o in (
            ([1, 0, 0], hi[0]), ([-1, 0, 0], -lo[0]), ([0, 1, 0], hi[1]), ([0, -1, 0], -lo[1]),
            ([0, 0, 1], hi[2]), ([0, 0, -1], -lo[2]))]
        nodes.append(_Convex(planes, np.stack([lo, hi]), CLASS_POLE))
    return nodes


# ----------------------------------------------------------------------------------------
# The scene
# ----------------------------------------------------------------------------------------
class Caster:
    """Casts rays against a fixed set of solids (and optionally the ground).

    ``relief``, if given, is called with ``(origins, directions, hits)`` after the cast and
    moves the hits on bent façades (see :mod:`.walls`).
    """

    def __init__(self, bvh: _Bvh, ground: bool,
                 relief: Callable[[np.ndarray, np.ndarray, Hits], None] | None = None) -> None:
        self.bvh = bvh
        self.ground = ground
        self.relief = relief

    def cast(self, origins: np.ndarray, directions: np.ndarray, rng: np.random.Generator | None = None) -> Hits:
        """Closest hit of every ray.

        Args:
            origins: (N, 3) ray origins, metres, map frame, outside every solid.
            directions: (N, 3) unit directions.
            rng: random source for porous vegetation; None sees through vegetation.

        Returns:
            The closest :class:`Hits`.
        """
        origins = np.ascontiguousarray(origins, dtype=np.float64)
        directions = np.ascontiguousarray(directions, dtype=np.float64)
        hits = Hits.empty(len(origins))
        if self.ground:
            _cast_ground(origins, directions, hits)
        self.bvh.visit(origins, directions, inverse_directions(directions), np.arange(len(origins)), hits,
                       _Context(rng=rng))
        if self.relief is not None:
            self.relief(origins, directions, hits)
        return hits


@dataclass(frozen=True)
class Street:
    """The drivable street: a centreline polyline and the lane offsets of campaigns.

    Attributes:
        centreline: (K, 2) metres, map frame, in driving order.
        lanes: lateral offsets (metres, left positive) of the lanes campaigns drive in.
        kerb: distance from the centreline of the line the parked cars keep 0.8 to 1.1 m
            beyond (their centres), metres.
        van_share: share of the parked vehicles that are vans (5-5.5 m long, 2.0-2.5 m tall).
        parking: (start, end) of the stretch where cars park, metres of arc length from the
            centreline's start; None for 6 m after the start to 6 m before the end.
    """

    centreline: np.ndarray
    lanes: tuple[float, ...] = (-1.75, 1.75)
    kerb: float = 5.6
    van_share: float = 0.0
    parking: tuple[float, float] | None = None


@dataclass(eq=False)
class Scene:
    """Buildings, occluders, ground and street, with exact ray casting.

    Attributes:
        name: scene name (``street``, ``small``, ``zurich``, or one of them with ``_hard``).
        seed: seed the scene was built from.
        buildings: the buildings, indexed by ``building_id``.
        static_occluders: trees and poles, the same in every campaign.
        street: the street the campaigns drive.
        map_origin: (3,) georeference of the map frame, metres.
        walls: how the walls differ from their plans (relief, plaster, glass; see
            :mod:`.walls`); None for walls exactly as planned.
    """

    name: str
    seed: int
    buildings: list[Building]
    static_occluders: list[Occluder]
    street: Street
    map_origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    walls: WallRealism | None = None

    def __post_init__(self) -> None:
        self._building_leaves = {b.building_id: self._building_leaves_of(b) for b in self.buildings}
        self._static_leaves = [n for occ in self.static_occluders for n in _occluder_nodes(occ)]
        self._truth_casters: dict[int, Caster] = {}
        self._plan_casters: dict[int, Caster] = {}
        #: Relief of every façade (empty without ``walls``), drawn from the seed.
        self.reliefs: dict[int, FacadeRelief] = {}
        self._panes: dict[int, np.ndarray] = {}
        if self.walls is not None:
            for f in self.facades:
                rng = np.random.default_rng([self.seed, 17, f.facade_id])
                self.reliefs[f.facade_id] = FacadeRelief.draw(self.walls, f.frame.length, f.frame.height, rng)
                self._panes[f.facade_id] = panes(f.features, self.walls.frame)

    @property
    def facades(self) -> list[Facade]:
        """Every façade of the scene, indexed by ``facade_id``."""
        return [f for b in self.buildings for f in b.facades]

    @staticmethod
    def _building_leaves_of(b: Building) -> list[_Node]:
        leaves: list[_Node] = [_BuildingBody(b)]
        for facade in b.facades:
            leaves += [s for f in facade.features if (s := _feature_solid(facade, f)) is not None]
        return leaves

    @property
    def _relief_hook(self) -> Callable[[np.ndarray, np.ndarray, Hits], None] | None:
        return self._bend_hits if self.reliefs else None

    def caster(self, parked: Iterable[Occluder] = ()) -> Caster:
        """A ray caster for the whole scene with the given parked cars (one per campaign)."""
        leaves = [leaf for ls in self._building_leaves.values() for leaf in ls] + self._static_leaves
        leaves += [n for occ in parked for n in _occluder_nodes(occ)]
        return Caster(_Bvh(leaves), ground=True, relief=self._relief_hook)

    def building_caster(self) -> Caster:
        """A ray caster for the buildings alone (no ground, no occluders)."""
        return Caster(_Bvh([leaf for ls in self._building_leaves.values() for leaf in ls]), ground=False,
                      relief=self._relief_hook)

    def cast(self, origins: np.ndarray, directions: np.ndarray, *, parked: Iterable[Occluder] = (),
             rng: np.random.Generator | None = None) -> Hits:
        """Closest hit of every ray in the whole scene (see :meth:`Caster.cast`)."""
        return self.caster(parked).cast(origins, directions, rng)

    def _truth_caster(self, building_id: int) -> Caster:
        if building_id not in self._truth_casters:
            self._truth_casters[building_id] = Caster(_Bvh(self._building_leaves[building_id]), ground=False,
                                                      relief=self._relief_hook)
        return self._truth_casters[building_id]

    def _plan_caster(self, building_id: int) -> Caster:
        """The building as planned (no relief)."""
        if building_id not in self._plan_casters:
            self._plan_casters[building_id] = Caster(_Bvh(self._building_leaves[building_id]), ground=False)
        return self._plan_casters[building_id]

    def _bend_hits(self, origins: np.ndarray, directions: np.ndarray, hits: Hits, passes: int = 2) -> None:
        """Move the hits on façades to their bent surface (relief, see :mod:`.walls`).

        Each ray that hit a façade is cast again against its building's plan after the
        inverse bend, linearised at its current hit, ``passes`` times. A ray whose bent
        cast misses the façade (within millimetres of its edges) keeps its planned hit.
        """
        fid_all = hits.facade_id
        rows_all = np.flatnonzero((fid_all >= 0) & np.isfinite(hits.t))
        if not len(rows_all):
            return
        facades = self.facades
        for fid in np.unique(fid_all[rows_all]):
            rows = rows_all[fid_all[rows_all] == fid]
            facade = facades[fid]
            fr = facade.frame
            axes = np.stack([fr.u, fr.v, fr.n])  # (3, 3): rows are the façade axes
            o_f = (origins[rows] - fr.origin) @ axes.T
            d_f = directions[rows] @ axes.T
            t = hits.t[rows].copy()
            relief = self.reliefs[int(fid)]
            caster = self._plan_caster(facade.building_id)
            for _ in range(passes):
                hit_uv = o_f[:, :2] + t[:, None] * d_f[:, :2]
                o_b, d_b = relief.bend(o_f, d_f, hit_uv)
                scale = np.linalg.norm(d_b, axis=1)
                o_w = fr.origin + o_b @ axes
                d_w = (d_b / scale[:, None]) @ axes
                again = caster.cast(o_w, d_w)
                t_new = again.t / scale
                ok = np.isfinite(t_new) & (again.facade_id == fid)
                t = np.where(ok, t_new, t)
            hits.t[rows] = t

    def relief_at(self, facade_id: int, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(K,) relief of a façade at (u, v), metres along its normal (zeros without walls)."""
        relief = self.reliefs.get(facade_id)
        u = np.asarray(u, dtype=np.float64)
        return relief.depth(u, np.asarray(v, dtype=np.float64))[0] if relief is not None else np.zeros(len(u))

    def glass(self, facade_id: int, points: np.ndarray) -> np.ndarray:
        """(K,) bool: map-frame points (on the façade's surface) that lie on a window pane."""
        pane = self._panes.get(facade_id)
        if pane is None or not len(pane):
            return np.zeros(len(points), dtype=bool)
        uvn = self.facades[facade_id].frame.to_facade(points)
        uvn[:, 2] -= self.relief_at(facade_id, uvn[:, 0], uvn[:, 1])
        return on_pane(uvn, pane)

    def true_depth(self, facade_id: int, u: np.ndarray, v: np.ndarray, *, reach: float = 5.0) -> np.ndarray:
        """The true surface of a façade as a depth map over its plane.

        The depth is the position along the outward normal of the first surface of the
        façade's building met by a ray coming from the street, ``reach`` metres out. With
        ``walls`` set, it includes the façade's relief (the wall as built), not its plaster.

        Args:
            facade_id: scene-wide façade index.
            u: (K,) positions along the wall, metres, façade frame.
            v: (K,) heights, metres, façade frame.
            reach: how far in front of the wall the truth rays start, metres.

        Returns:
            (K,) depth along the façade normal, metres (0 on the wall plane, positive out,
            negative in recesses); NaN where the ray meets nothing of the building.
        """
        facade = self.facades[facade_id]
        fr = facade.frame
        u = np.asarray(u, dtype=np.float64)
        v = np.asarray(v, dtype=np.float64)
        start = fr.to_world(np.stack([u, v, np.full_like(u, reach)], axis=1))
        dirs = np.tile(-fr.n, (len(u), 1))
        hits = self._truth_caster(facade.building_id).cast(start, dirs)
        return np.where(np.isfinite(hits.t), reach - hits.t, np.nan)

    def true_surface_along(self, points: np.ndarray, normals: np.ndarray, building_id: int,
                           *, reach: float = 5.0) -> np.ndarray:
        """Signed position of the true surface along given lines.

        For a model's façade frame (not the simulator's), this gives the truth in the
        model's own depth direction.

        Args:
            points: (K, 3) points on the lines, metres, map frame.
            normals: (K, 3) unit directions of the lines, pointing out of the building.
            building_id: the building whose surface is wanted.
            reach: the lines are searched from ``reach`` metres in front of ``points``.

        Returns:
            (K,) offset ``s`` such that ``points + s * normals`` lies on the true surface,
            metres; NaN where the line misses the building.
        """
        return self.true_surface_hits(points, normals, building_id, reach=reach)[0]

    def true_surface_hits(self, points: np.ndarray, normals: np.ndarray, building_id: int, *,
                          reach: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`true_surface_along`, and the scene façade each line meets.

        Returns:
            ``(offset, facade_id)``: (K,) as in :meth:`true_surface_along`, and (K,) int32
            the scene-wide façade the surface belongs to (-1 for a roof or none).
        """
        points = np.asarray(points, dtype=np.float64)
        normals = np.asarray(normals, dtype=np.float64)
        hits = self._truth_caster(building_id).cast(points + reach * normals, -normals)
        return np.where(np.isfinite(hits.t), reach - hits.t, np.nan), hits.facade_id

    def inside_building(self, points: np.ndarray) -> np.ndarray:
        """(K,) bool: True for points inside any building's solid as planned (no relief; for tests)."""
        points = np.asarray(points, dtype=np.float64)
        inside = np.zeros(len(points), dtype=bool)
        for leaves in self._building_leaves.values():
            body = leaves[0]
            assert isinstance(body, _BuildingBody)
            in_body = (points_in_polygon(points[:, :2], body.polygon) & (points[:, 2] >= 0)
                       & (points[:, 2] <= body.height))
            for _, _, solids in body.recesses.values():
                for s in solids:
                    in_body &= ~s.contains(points)
            inside |= in_body
            for leaf in leaves[1:]:
                inside |= leaf.contains(points)  # type: ignore[attr-defined]
        return inside
