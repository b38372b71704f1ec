"""Built-in scenes: ``street`` (default), ``small`` (for tests), ``zurich`` (real footprints) and
``residential`` (detached houses behind front yards, for a car's lidar), ``stacked`` (a
ground floor set back under the upper storeys, a mansard roof band), and the hard variants
``street_hard``, ``small_hard``, ``zurich_hard`` and ``stacked_hard`` (the same geometry with
walls as built: relief, plaster, glass; see :mod:`.walls` and :mod:`.presets`).

Every scene is a straight street along +x with its centreline on y = 0, façade lines at
y = +-``FACADE_LINE`` (``residential``: set back 3 to 8 m behind ``PROPERTY_LINE``) and
buildings behind them; trees and poles stand on the pavements, cars are parked along the
kerbs (drawn per campaign, see :mod:`.campaign`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import InputError
from .facades import FacadeStyle, decorate
from .presets import HARD_SCENES, WALL_PRESETS
from .scene import Block, Building, Car, Facade, FacadeFrame, Hedge, Occluder, Pole, Recess, Scene, Slope, Street, Tree

#: Distance from the street centreline to the façade lines, metres.
FACADE_LINE = 9.0
#: Distance from the centreline to the kerb where cars park, metres (``Street.kerb``'s default).
KERB = 5.6
#: ``residential``: distance from the centreline to the property line (the kerb is 5.5 m
#: out, the pavement 2 m wide), metres.
PROPERTY_LINE = 7.5

#: ``stacked``: height of the set-back ground floor (the underside of the upper storeys), its
#: setback under them, metres; the mansard band's height, metres, and tilt from vertical, degrees.
STACKED_GROUND_FLOOR = 4.0
STACKED_SETBACK = 1.0
STACKED_HEIGHT = 9.0
MANSARD_HEIGHT = 3.0
MANSARD_TILT_DEG = 36.0

#: Default CityJSON file of the ``zurich`` scene: the Zurich LoD2 subset shipped with the
#: package (cjio project's test data, MIT; see ``data/README.md`` and ``data/LICENSE-cjio-MIT.txt``).
DEFAULT_CITYJSON = Path(__file__).resolve().parent / 'data' / 'zurich_subset_lod2.json'


def _rng(seed: int, *keys: int) -> np.random.Generator:
    return np.random.default_rng([seed, *keys])


def make_building(building_id: int, first_facade_id: int, polygon: np.ndarray, height: float,
                  styles: dict[int, FacadeStyle], rng: np.random.Generator, source: str = 'synthetic',
                  min_wall: float = 4.0) -> Building:
    """Build a prism with a façade on every wall of at least ``min_wall`` metres.

    Args:
        building_id: index of the building in the scene.
        first_facade_id: scene-wide index of its first façade.
        polygon: (M, 2) counter-clockwise footprint, metres, map frame.
        height: metres.
        styles: special features per wall index; other walls get windows only.
        rng: random source for the detail.
        source: provenance of the footprint.
        min_wall: walls shorter than this get no façade detail (still a façade).

    Returns:
        The building.
    """
    polygon = np.asarray(polygon, dtype=np.float64)
    facades = []
    for wall in range(len(polygon)):
        a, b = polygon[wall], polygon[(wall + 1) % len(polygon)]
        e = b - a
        length = float(np.hypot(*e))
        u = np.array([e[0], e[1], 0.0]) / length
        n = np.array([u[1], -u[0], 0.0])
        frame = FacadeFrame(np.array([a[0], a[1], 0.0]), u, n, length, height)
        style = styles.get(wall, FacadeStyle())
        features = decorate(length, height, style, rng) if length >= min_wall else ()
        facades.append(Facade(first_facade_id + len(facades), building_id, wall, frame, features))
    return Building(building_id, polygon, height, tuple(facades), source)


def _rect(x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float64)


def _street_furniture(x0: float, x1: float, rng: np.random.Generator, tree_every: float,
                      pole_every: float) -> list[Occluder]:
    occ: list[Occluder] = []
    for side in (1.0, -1.0):
        for x in np.arange(x0 + rng.uniform(2, tree_every), x1, tree_every):
            occ.append(Tree(float(x + rng.normal(0, 1.0)), side * float(rng.uniform(6.6, 7.2)),
                            float(rng.uniform(0.15, 0.25)), float(rng.uniform(2.5, 3.5)),
                            float(rng.uniform(1.8, 3.0)), float(rng.uniform(0.4, 0.8))))
        for x in np.arange(x0 + rng.uniform(3, pole_every), x1, pole_every):
            occ.append(Pole(float(x), side * float(rng.uniform(6.0, 6.4)), float(rng.uniform(0.06, 0.1)),
                            float(rng.uniform(3.0, 7.0)), sign=bool(rng.random() < 0.5)))
    return occ


def street_frame(street: Street) -> tuple[np.ndarray, np.ndarray, float, float]:
    """The frame of a straight street: arc length ``s`` along it and lateral offset ``l`` (left positive).

    A point is ``origin + s u + l n`` with ``u`` the unit direction from the centreline's first
    to its last vertex and ``n`` its left normal; ``origin`` is the foot of the perpendicular
    from the map origin, so for a street along +x on y = 0 the frame is the map frame itself
    (``s`` = x, ``l`` = y, exactly). Axis-aligned directions get exact unit vectors.

    Args:
        street: the street (its centreline's first and last vertex give the direction).

    Returns:
        ``(origin, u, s0, s1)``: (2,) metres, (2,) unit vector, and the ``s`` of the
        centreline's first and last vertex, metres.
    """
    a, b = street.centreline[0], street.centreline[-1]
    e = b - a
    if e[1] == 0.0 or e[0] == 0.0:  # along an axis: exact unit vectors keep the map frame's values
        u = np.sign(e).astype(np.float64)
    else:
        u = e / float(np.hypot(*e))
    s0 = float(a @ u)
    return a - s0 * u, u, s0, float(b @ u)


def parked_cars(scene: Scene, rng: np.random.Generator, share: float = 0.45) -> list[Car]:
    """Draw the cars parked along both kerbs for one campaign.

    Cars park in slots every 6 m from 6 m after the centreline's start to 6 m before its end
    (``Street.parking`` sets another stretch), in the street's frame (:func:`street_frame`);
    a street along +x gets the cars it always had.

    Args:
        scene: the scene (its straight street gives the direction and the length).
        rng: the campaign's random source.
        share: probability that a parking slot is taken.

    Returns:
        Cars with their long side along the street.
    """
    origin, u, x0, x1 = street_frame(scene.street)
    first, last = (x0 + 6.0, x1 - 6.0) if scene.street.parking is None else (x0 + scene.street.parking[0],
                                                                             x0 + scene.street.parking[1])
    kerb, vans = scene.street.kerb, scene.street.van_share
    cars = []
    for side in (1.0, -1.0):
        for x in np.arange(first, last, 6.0):
            if rng.random() < share:
                # Vans draw from the stream only in streets that have them: the others keep their cars.
                if vans > 0 and rng.random() < vans:
                    length, width, height = rng.uniform(5.0, 5.5), rng.uniform(1.9, 2.1), rng.uniform(2.0, 2.5)
                    cars.append(Car(float(x + rng.normal(0, 0.3)), side * float(kerb + 0.1 + width / 2),
                                    float(rng.normal(0, 0.03)), float(length), float(width), float(height)))
                    continue
                cars.append(Car(float(x + rng.normal(0, 0.5)), side * float(kerb + rng.uniform(0.8, 1.1)),
                                float(rng.normal(0, 0.03)), float(rng.uniform(4.0, 5.0)),
                                float(rng.uniform(1.7, 1.9)), float(rng.uniform(1.4, 1.9))))
    if u[0] == 1.0 and origin[0] == 0.0 and origin[1] == 0.0:
        return cars  # a street along +x through the map origin's y: the frame is the map frame
    heading = float(np.arctan2(u[1], u[0]))
    n = np.array([-u[1], u[0]])
    return [Car(*(origin + c.x * u + c.y * n).tolist(), c.yaw + heading, c.length, c.width, c.height) for c in cars]


def street_scene(seed: int = 0) -> Scene:
    """The default scene: a 150 m street with six buildings and about 20 façades in view.

    North side (y > 0): three buildings, one L-shaped, one set back; south side: three.
    Gaps between buildings expose their side walls to the oblique scanners.
    """
    rng = _rng(seed, 1)
    north = [  # x0, x1, setback, depth, height, style of the street façade
        (0.0, 26.0, 0.0, 14.0, 16.0, FacadeStyle(balconies=True, columns=True)),
        (32.0, 58.0, 1.5, 13.0, 19.0, FacadeStyle(oriel=True, slope=True)),
        (64.0, 96.0, 0.0, 15.0, 13.0, FacadeStyle(round_bay=True, balconies=True)),
        (103.0, 135.0, 0.0, 12.0, 17.0, FacadeStyle(columns=True, oriel=True, windows=True)),
    ]
    south = [
        (4.0, 34.0, 0.0, 14.0, 15.0, FacadeStyle(slope=True, round_bay=True)),
        (40.0, 70.0, 0.0, 13.0, 18.0, FacadeStyle(oriel=True, columns=True)),
        (77.0, 110.0, 1.0, 14.0, 14.0, FacadeStyle(balconies=True, round_bay=True, slope=True)),
    ]
    buildings: list[Building] = []
    for k, (x0, x1, setback, depth, height, style) in enumerate(north):
        y0 = FACADE_LINE + setback
        if k == 2:  # L-shaped: a wing reaching back on the east side
            poly = np.array([[x0, y0], [x1, y0], [x1, y0 + depth + 8.0], [x1 - 12.0, y0 + depth + 8.0],
                             [x1 - 12.0, y0 + depth], [x0, y0 + depth]])
        else:
            poly = _rect(x0, x1, y0, y0 + depth)
        # wall 0 runs along +x at y0 with outward normal -y: the street façade.
        buildings.append(make_building(len(buildings), sum(len(b.facades) for b in buildings), poly, height,
                                       {0: style}, rng))
    for x0, x1, setback, depth, height, style in south:
        y1 = -FACADE_LINE - setback
        poly = _rect(x0, x1, y1 - depth, y1)
        # wall 2 runs along -x at y1 with outward normal +y: the street façade.
        buildings.append(make_building(len(buildings), sum(len(b.facades) for b in buildings), poly, height,
                                       {2: style}, rng))
    street = Street(np.array([[-10.0, 0.0], [145.0, 0.0]]))
    occluders = _street_furniture(-5.0, 140.0, rng, tree_every=17.0, pole_every=23.0)
    return Scene('street', seed, buildings, occluders, street, map_origin=np.array([550_000.0, 5_804_000.0, 55.0]))


def small_scene(seed: int = 0) -> Scene:
    """A 40 m street with two buildings on one side, every kind of façade detail, one of
    each occluder; at most 50 000 points a campaign (for tests)."""
    rng = _rng(seed, 2)
    buildings = [
        make_building(0, 0, _rect(0.0, 17.0, FACADE_LINE, FACADE_LINE + 10.0), 12.0,
                      {0: FacadeStyle(balconies=True, oriel=True, columns=True)}, rng),
    ]
    buildings.append(make_building(1, len(buildings[0].facades), _rect(23.0, 40.0, FACADE_LINE, FACADE_LINE + 10.0),
                                   11.0, {0: FacadeStyle(slope=True, columns=True, round_bay=True)}, rng))
    occluders: list[Occluder] = [Tree(9.0, 7.0, 0.2, 3.0, 2.2, 0.6), Pole(31.0, 6.2, 0.08, 5.0, sign=True)]
    street = Street(np.array([[-5.0, 0.0], [45.0, 0.0]]))
    return Scene('small', seed, buildings, occluders, street, map_origin=np.array([550_000.0, 5_804_000.0, 55.0]))


def stacked_scene(seed: int = 0) -> Scene:
    """A 40 m street with two buildings on one side whose street façades are not one plane
    (issue 26); at most about 50 000 points a campaign, like ``small``.

    Building 0 (x 0 to 17 m, ``STACKED_HEIGHT`` high): the ground floor, a shop floor
    ``STACKED_GROUND_FLOOR`` high with shop windows and doors, is set back ``STACKED_SETBACK``
    under two upper storeys (a box over the whole width, ``Block`` of kind ``'storeys'``, its
    underside a soffit). A tree with a dense crown stands in front of it and hides a patch of
    the upper storeys from campaign 0 (about u 1.5 to 4.5 m, v 6.5 m to the eaves). Building 1
    (x 23 to 40 m): a plain wall 9 m high crowned by a mansard roof band ``MANSARD_HEIGHT``
    high leaning back ``MANSARD_TILT_DEG`` from vertical up to the roof at
    12 m (the footprint is the band's top edge; the wall is a box in front of it).
    """
    rng = _rng(seed, 5)
    b0 = make_building(0, 0, _rect(0.0, 17.0, FACADE_LINE + STACKED_SETBACK, FACADE_LINE + STACKED_SETBACK + 11.0),
                       STACKED_HEIGHT, {0: FacadeStyle()}, rng)
    street_wall = b0.facades[0]
    # Only the ground floor's recesses stay (the others would lie behind the storeys' box,
    # and their panes would put glass on its front).
    shops = tuple(f for f in street_wall.features if isinstance(f, Recess) and f.v1 <= STACKED_GROUND_FLOOR - 0.2)
    storeys = Block(0.0, street_wall.frame.length, STACKED_GROUND_FLOOR, b0.height, STACKED_SETBACK, kind='storeys')
    b0 = Building(0, b0.polygon, b0.height, (Facade(street_wall.facade_id, 0, 0, street_wall.frame,
                                                    shops + (storeys,)),) + b0.facades[1:], b0.source)
    out = MANSARD_HEIGHT * float(np.tan(np.deg2rad(MANSARD_TILT_DEG)))
    height, eave = 12.0, 12.0 - MANSARD_HEIGHT
    b1 = make_building(1, len(b0.facades), _rect(23.0, 40.0, FACADE_LINE + out, FACADE_LINE + out + 10.0), height,
                       {}, rng)
    wall = b1.facades[0]
    band = (Block(0.0, wall.frame.length, 0.0, eave, out, kind='wall'), Slope(0.0, wall.frame.length, eave, height, out, 0.0))
    b1 = Building(1, b1.polygon, b1.height, (Facade(wall.facade_id, 1, 0, wall.frame, band),) + b1.facades[1:],
                  b1.source)
    occluders: list[Occluder] = [Tree(8.5, 5.5, 0.2, 4.5, 3.0, 5.0), Pole(31.0, 6.2, 0.08, 5.0, sign=True)]
    street = Street(np.array([[-5.0, 0.0], [45.0, 0.0]]))
    return Scene('stacked', seed, [b0, b1], occluders, street, map_origin=np.array([550_000.0, 5_804_000.0, 55.0]))


def residential_scene(seed: int = 0) -> Scene:
    """A residential street of detached houses behind front yards, for a car's lidar.

    110 m of street along +x (x from -10 to 110; the campaigns drive two lanes 1.6 m either
    side of the centreline at 5 m/s). On each side, lots 15 to 19 m wide along the street
    from x = 0 to about 100 m, each with a detached two-storey house: a flat-roofed box (the
    scene model has no pitched roofs; a car's lidar never sees a roof from the street) 9 to
    12.5 m wide and 8 to 11 m deep, eaves 5 to 7 m, set back 3 to 8 m behind the property
    line at ``PROPERTY_LINE`` = 7.5 m (the kerb at 5.5 m, the pavement 2 m wide), with 2.5 m
    or more between neighbours; windows on every wall. Along the property line of most lots a
    hedge (1.0-1.5 m tall, 0.5-0.8 m thick) or a fence (1.0-1.4 m, 5 cm), broken by a 3 m
    gate or driveway; street trees on the pavement every 12 to 18 m, a tree in some front
    yards, a street lamp every 25 m. Cars and vans (a quarter; 2.0-2.5 m tall) park along
    both kerbs, drawn per campaign (:func:`parked_cars`).

    With the ``hdl64`` sensor (1.73 m up, top beam +1.96 degrees) the street façades, 8 to
    17 m from the lanes, are seen up to 2.0-2.3 m across the street and a little higher
    down it: hedges, fences and cars hide their feet, the field of view their upper floors.
    """
    rng = _rng(seed, 4)
    buildings: list[Building] = []
    occluders: list[Occluder] = []
    for side in (1.0, -1.0):
        x = float(rng.uniform(0.0, 3.0))
        while x < 95.0:
            lot = float(rng.uniform(15.0, 19.0))
            width = float(rng.uniform(9.0, 12.5))
            depth = float(rng.uniform(8.0, 11.0))
            eave = float(rng.uniform(5.0, 7.0))
            setback = float(rng.uniform(3.0, 8.0))
            x0 = x + float(rng.uniform(1.25, lot - width - 1.25))
            front = PROPERTY_LINE + setback
            if side > 0:  # wall 0 runs along +x at the front, outward normal -y: the street façade
                poly = _rect(x0, x0 + width, front, front + depth)
            else:  # wall 2 runs along -x at the front, outward normal +y
                poly = _rect(x0, x0 + width, -front - depth, -front)
            buildings.append(make_building(len(buildings), sum(len(b.facades) for b in buildings), poly, eave, {}, rng))
            # Hedge, fence or nothing along the property line, with a 3 m gate or driveway.
            kind = rng.choice(['hedge', 'fence', 'open'], p=[0.45, 0.35, 0.2])
            if kind != 'open':
                gate = float(rng.uniform(x + 1.0, x + lot - 4.0))
                thick = float(rng.uniform(0.5, 0.8)) if kind == 'hedge' else 0.05
                height = float(rng.uniform(1.0, 1.5)) if kind == 'hedge' else float(rng.uniform(1.0, 1.4))
                y = side * (PROPERTY_LINE + 0.05 + thick / 2)
                for a, b in ((x, gate), (gate + 3.0, x + lot)):
                    if b - a > 0.5:
                        occluders.append(Hedge((a + b) / 2, y, 0.0, b - a, thick, height, str(kind)))
            if rng.random() < 0.4:  # a tree in the front yard
                occluders.append(Tree(float(rng.uniform(x + 2.0, x + lot - 2.0)),
                                      side * (PROPERTY_LINE + float(rng.uniform(1.5, max(1.6, setback - 1.5)))),
                                      float(rng.uniform(0.12, 0.2)), float(rng.uniform(2.0, 3.0)),
                                      float(rng.uniform(1.5, 2.5)), float(rng.uniform(0.4, 0.8))))
            x += lot
        for tx in np.arange(float(rng.uniform(2.0, 12.0)), 105.0, float(rng.uniform(12.0, 18.0))):
            occluders.append(Tree(float(tx + rng.normal(0, 0.5)), side * float(rng.uniform(6.3, 6.8)),
                                  float(rng.uniform(0.15, 0.25)), float(rng.uniform(2.5, 3.5)),
                                  float(rng.uniform(1.8, 2.8)), float(rng.uniform(0.4, 0.8))))
        for px in np.arange(float(rng.uniform(5.0, 20.0)), 105.0, 25.0):
            occluders.append(Pole(float(px), side * float(rng.uniform(5.7, 5.9)), float(rng.uniform(0.06, 0.1)),
                                  float(rng.uniform(4.5, 6.0)), sign=False))
    street = Street(np.array([[-10.0, 0.0], [110.0, 0.0]]), lanes=(-1.6, 1.6), kerb=3.6, van_share=0.25)
    return Scene('residential', seed, buildings, occluders, street, map_origin=np.array([550_000.0, 5_804_000.0, 55.0]))


def zurich_scene(seed: int = 0, path: str | Path | None = None, count: int = 8) -> Scene:
    """A street lined with real buildings: Zurich LoD2 footprints and eave heights.

    The footprints keep their shape and size; each is turned so that its longest wall faces
    the street and placed along it with gaps of 3 to 8 m. Every wall of 4 m or more gets
    façade detail; the wall facing the street gets special features.

    Args:
        seed: chooses the buildings, their order and their detail.
        path: CityJSON file; defaults to the packaged Zurich subset (``DEFAULT_CITYJSON``).
        count: number of buildings to place.

    Raises:
        InputError: the file cannot be read or has too few usable buildings.
    """
    from .cityjson import load_footprints

    rng = _rng(seed, 3)
    footprints = load_footprints(path or DEFAULT_CITYJSON)
    usable = []
    for fp in footprints:
        ext = fp.polygon.max(axis=0) - fp.polygon.min(axis=0)
        area = 0.5 * float(np.sum(fp.polygon[:, 0] * np.roll(fp.polygon[:, 1], -1)
                                  - np.roll(fp.polygon[:, 0], -1) * fp.polygon[:, 1]))
        if 8.0 <= ext.max() <= 45.0 and 80.0 <= area <= 1200.0 and 5.0 <= fp.eave_height <= 30.0:
            usable.append(fp)
    if len(usable) < count:
        raise InputError(f'{path or DEFAULT_CITYJSON}: only {len(usable)} buildings fit a street scene, need {count}')
    chosen = [usable[i] for i in rng.choice(len(usable), size=count, replace=False)]
    styles = [FacadeStyle(balconies=True, columns=True), FacadeStyle(oriel=True, slope=True),
              FacadeStyle(round_bay=True, balconies=True), FacadeStyle(slope=True, columns=True)]
    buildings: list[Building] = []
    cursor = {1.0: 0.0, -1.0: 0.0}
    for k, fp in enumerate(chosen):
        side = 1.0 if k % 2 == 0 else -1.0
        poly = fp.polygon - fp.polygon.mean(axis=0)
        edges = np.roll(poly, -1, axis=0) - poly
        longest = int(np.argmax(np.hypot(edges[:, 0], edges[:, 1])))
        # Turn the longest wall's outward normal to face the street (-y for north, +y for south).
        e = edges[longest]
        normal_angle = np.arctan2(-e[0], e[1])
        target = -np.pi / 2 if side > 0 else np.pi / 2
        rot = target - normal_angle
        c, s = np.cos(rot), np.sin(rot)
        poly = poly @ np.array([[c, s], [-s, c]])
        x_shift = cursor[side] - poly[:, 0].min()
        y_shift = (FACADE_LINE - poly[:, 1].min()) if side > 0 else (-FACADE_LINE - poly[:, 1].max())
        poly = poly + np.array([x_shift, y_shift])
        cursor[side] = float(poly[:, 0].max() + rng.uniform(3.0, 8.0))
        styles_by_wall = {longest: styles[k % len(styles)]}
        buildings.append(make_building(len(buildings), sum(len(b.facades) for b in buildings), poly,
                                       float(fp.eave_height), styles_by_wall, rng, source=fp.building_id))
    x_end = max(cursor.values())
    street = Street(np.array([[-10.0, 0.0], [x_end + 5.0, 0.0]]))
    occluders = _street_furniture(-5.0, x_end, rng, tree_every=19.0, pole_every=25.0)
    return Scene('zurich', seed, buildings, occluders, street, map_origin=np.array([2_683_000.0, 1_247_000.0, 400.0]))


def with_walls(scene: Scene, walls: str = 'hard', name: str | None = None) -> Scene:
    """The same scene with walls as built (a preset of :data:`~.presets.WALL_PRESETS`).

    Args:
        scene: a scene (its geometry, occluders and seed are kept).
        walls: name of the walls preset.
        name: name of the new scene; ``<scene>_<walls>`` if None.

    Raises:
        InputError: unknown walls preset.
    """
    try:
        realism = WALL_PRESETS[walls]
    except KeyError:
        raise InputError(f'unknown walls preset {walls!r}; choose one of {", ".join(WALL_PRESETS)}') from None
    return Scene(name or f'{scene.name}_{walls}', scene.seed, scene.buildings, scene.static_occluders, scene.street,
                 map_origin=scene.map_origin, walls=realism)


SCENES: dict[str, Callable[[int], Scene]] = {'street': street_scene, 'small': small_scene, 'zurich': zurich_scene,
                                             'residential': residential_scene, 'stacked': stacked_scene}
SCENES.update({hard: (lambda seed, clean=clean, walls=walls, hard=hard: with_walls(SCENES[clean](seed), walls, hard))
               for hard, (clean, walls) in HARD_SCENES.items()})


def build_scene(name: str, seed: int = 0, cityjson: str | Path | None = None) -> Scene:
    """Build a named scene.

    Args:
        name: one of :data:`SCENES`.
        seed: the scene's seed.
        cityjson: for ``zurich`` and ``zurich_hard``: another CityJSON file than the packaged one.

    Raises:
        InputError: unknown scene name, or a CityJSON file for another scene.
    """
    try:
        factory = SCENES[name]
    except KeyError:
        raise InputError(f'unknown scene {name!r}; choose one of {", ".join(SCENES)}') from None
    if cityjson is None:
        return factory(seed)
    clean, walls = HARD_SCENES.get(name, (name, None))
    if clean != 'zurich':
        raise InputError(f'a CityJSON file is for the zurich scenes, not {name!r}')
    scene = zurich_scene(seed, cityjson)
    return scene if walls is None else with_walls(scene, walls, name)
