"""The ``city`` scene: a grid of streets with blocks of buildings between them (issue 29).

Streets run along x and y on a square grid: the centreline of x-street ``j`` is y = j p and
that of y-street ``i`` is x = i p, with the pitch p = ``block`` + 2 ``FACADE_LINE`` (the
façade lines stand ``FACADE_LINE`` either side of every centreline, as in the other scenes).
``blocks = (NX, NY)`` blocks lie between them, each a ``block`` x ``block`` square inside the
façade lines, lined on its four sides by buildings facing the streets (a perimeter block with
a courtyard): rows along the x-streets of buildings 6 to 60 m wide, 8 to 22 m deep (some
small, a few large, 6 to 30 m high), shorter rows along the y-streets between them, gaps of
1 to 10 m. Trees and lamp posts stand on the pavements, cars are parked along the kerbs
(per drive).

The street network is cut into **segments**, one per street between two neighbouring
intersections (centre to centre, length p): the x-segments first (row by row, west to east),
then the y-segments (column by column, south to north). A drive (campaign ``k``) drives
every segment once, one after the other, as a straight run in the segment's direction
(campaign 0 on the right lane forwards, campaign 1 backwards on the other lane, as campaign 1
of the other scenes), its times continuing from one segment to the next. Each segment is
simulated on its own (:func:`segment_scene`: the buildings and trees within reach of it, with
their city-wide ids) and written to its own file, so that a city of tens of millions of
points is never held in one array and segments can be simulated in parallel.

Truth: ``City.scene`` holds every building (ids unique across the city, façade ids
city-wide) and the static occluders; its ``street`` is segment 0's. Every point carries the
city-wide ``building_id`` and ``gt_facade`` of what it hit and its sensor origin.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.cloud import Cloud
from .campaign import campaign, drive_duration, simulate_campaign
from .facades import FacadeStyle
from .presets import SCENE_SENSORS
from .scene import Building, Facade, Occluder, Pole, Scene, Street, Tree
from .scenes import FACADE_LINE, make_building, street_frame
from .sensor import SensorConfig

__all__ = ['CITY_FORMATS', 'CITY_PRESETS', 'City', 'CityConfig', 'Segment', 'build_city', 'city_files',
           'estimate_points', 'is_edge', 'segment_file', 'segment_scene', 'simulate_segment', 'SegmentTask', 'write_segment']

#: File formats a city's segments can be written in.
CITY_FORMATS = ('ply', 'npz')
#: Map origin of the city scenes (a georeference in the same UTM zone as ``street``).
CITY_ORIGIN = (550_000.0, 5_804_000.0, 55.0)
#: Buildings and trees further than this from a segment's run (beyond the sensor's range
#: limit) are left out of its simulation, metres.
REACH_MARGIN = 5.0


@dataclass(frozen=True)
class CityConfig:
    """Size of a city.

    Attributes:
        blocks: (NX, NY) blocks along x and y.
        block: side of a block between its façade lines, metres (at least 40).
    """

    blocks: tuple[int, int] = (4, 3)
    block: float = 90.0

    def __post_init__(self) -> None:
        if len(self.blocks) != 2 or min(self.blocks) < 1:
            raise InputError(f'city blocks must be two counts of at least 1 (NX,NY), got {self.blocks}')
        if not self.block >= 20.0:
            raise InputError(f'city block side must be at least 20 m, got {self.block}')

    @property
    def pitch(self) -> float:
        """Distance between neighbouring street centrelines, metres."""
        return self.block + 2 * FACADE_LINE

    @property
    def street_length(self) -> float:
        """Total centreline length of the street network, metres (intersection centre to centre)."""
        nx, ny = self.blocks
        return self.pitch * (nx * (ny + 1) + ny * (nx + 1))


#: Named city sizes: the default city (over 3 km of street, over 20 M points in 2 drives)
#: and a small one for tests (two blocks, 336 m of street, about 275 000 points a drive).
CITY_PRESETS: dict[str, CityConfig] = {'city': CityConfig(), 'city_small': CityConfig((2, 1), 30.0)}


@dataclass(frozen=True)
class Segment:
    """One street between two neighbouring intersections, driven as a straight run.

    Attributes:
        index: position in the drive (0 first).
        start: (2,) centreline start (an intersection centre), metres, map frame.
        end: (2,) centreline end, metres, map frame.
        axis: ``'x'`` or ``'y'``: the direction of the street.
    """

    index: int
    start: tuple[float, float]
    end: tuple[float, float]
    axis: str

    @property
    def length(self) -> float:
        """Centreline length, metres."""
        return float(np.hypot(self.end[0] - self.start[0], self.end[1] - self.start[1]))


@dataclass(eq=False)
class City:
    """A city scene: its truth and the segments its drives follow.

    Attributes:
        name: ``'city'``, ``'city_small'`` or ``'city'`` with another size.
        config: its size.
        scene: every building and static occluder (``street``: segment 0's).
        segments: the street segments in driving order.
    """

    name: str
    config: CityConfig
    scene: Scene
    segments: list[Segment]

    @property
    def seed(self) -> int:
        """The city's seed."""
        return self.scene.seed

    def describe(self) -> dict:
        """The city's layout for scene.json: size, segments, street length."""
        return {'blocks': list(self.config.blocks), 'block': self.config.block, 'pitch': self.config.pitch,
                'street_length': self.config.street_length,
                'segments': [{'index': s.index, 'start': list(s.start), 'end': list(s.end), 'axis': s.axis}
                             for s in self.segments]}


def _rect(x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float64)


def _style(rng: np.random.Generator) -> FacadeStyle:
    """A random choice of special features for a street façade."""
    on = rng.random(5) < np.array([0.35, 0.25, 0.2, 0.2, 0.3])
    return FacadeStyle(balconies=bool(on[0]), oriel=bool(on[1]), slope=bool(on[2]), round_bay=bool(on[3]),
                       columns=bool(on[4]))


def _lot(rng: np.random.Generator, room: float) -> tuple[float, float, float] | None:
    """(frontage, depth, height) of the next building of a row, None if less than 6 m are left.

    A quarter are small (6-9 m wide, 8-10 m deep, 6-10 m high), a tenth large (35-60 m,
    16-22 m, 18-30 m), the rest 10-25 m wide, 10-16 m deep, 10-20 m high.
    """
    if room < 6.0:
        return None
    kind = rng.random()
    if kind < 0.25:
        w, d, h = rng.uniform(6.0, 9.0), rng.uniform(8.0, 10.0), rng.uniform(6.0, 10.0)
    elif kind < 0.35:
        w, d, h = rng.uniform(35.0, 60.0), rng.uniform(16.0, 22.0), rng.uniform(18.0, 30.0)
    else:
        w, d, h = rng.uniform(10.0, 25.0), rng.uniform(10.0, 16.0), rng.uniform(10.0, 20.0)
    w = min(float(w), room)
    if room - w < 6.0:  # the row's last lot takes what is left
        w = room
    return w, float(d), float(h)


def _row_lots(rng: np.random.Generator, length: float, max_depth: float) -> list[tuple[float, float, float, float]]:
    """Lots along a row ``length`` metres long: (start, frontage, depth, height)."""
    lots, pos = [], 0.0
    while True:
        lot = _lot(rng, length - pos)
        if lot is None:
            return lots
        w, d, h = lot
        lots.append((pos, w, min(d, max_depth), h))
        pos += w + float(rng.uniform(1.0, 3.0) if rng.random() < 0.7 else rng.uniform(4.0, 10.0))


def _furniture(segment: Segment, rng: np.random.Generator, trees: bool) -> list[Occluder]:
    """Street trees (every 15-20 m) and lamp posts (every 25 m) on both pavements of a segment,
    clear of the intersections."""
    street = Street(np.array([segment.start, segment.end]))
    origin, u, s0, s1 = street_frame(street)
    n = np.array([-u[1], u[0]])
    lo, hi = s0 + FACADE_LINE + 2.0, s1 - FACADE_LINE - 2.0
    occ: list[Occluder] = []
    for side in (1.0, -1.0):
        if trees:
            for s in np.arange(lo + rng.uniform(1.0, 8.0), hi, float(rng.uniform(15.0, 20.0))):
                x, y = origin + float(s + rng.normal(0, 0.5)) * u + side * float(rng.uniform(6.6, 7.2)) * n
                occ.append(Tree(float(x), float(y), float(rng.uniform(0.15, 0.25)), float(rng.uniform(2.5, 3.5)),
                                float(rng.uniform(1.8, 3.0)), float(rng.uniform(0.4, 0.8))))
        for s in np.arange(lo + rng.uniform(2.0, 12.0), hi, 25.0):
            x, y = origin + float(s) * u + side * float(rng.uniform(6.0, 6.4)) * n
            occ.append(Pole(float(x), float(y), float(rng.uniform(0.06, 0.1)), float(rng.uniform(3.0, 7.0)),
                            sign=bool(rng.random() < 0.3)))
    return occ


def build_city(seed: int = 0, config: CityConfig | None = None, name: str | None = None) -> City:
    """Build a city (deterministic by seed).

    Args:
        seed: the city's seed (buildings, façade detail, trees, and the drives' draws).
        config: its size; :data:`CITY_PRESETS` ``'city'`` if None.
        name: its name; ``'city'`` if None.

    Returns:
        The city: buildings with ids 0..B-1 in block order (blocks row by row, in each the
        south, north, west and east rows), façade ids city-wide.
    """
    config = config or CITY_PRESETS['city']
    nx, ny = config.blocks
    p, size = config.pitch, config.block
    rng = np.random.default_rng([seed, 29])
    buildings: list[Building] = []
    facades = 0

    def add(poly: np.ndarray, height: float, street_wall: int) -> None:
        nonlocal facades
        b = make_building(len(buildings), facades, poly, height, {street_wall: _style(rng)}, rng)
        buildings.append(b)
        facades += len(b.facades)

    # Rows along the x-streets take at most this depth; the rows along the y-streets fit between.
    max_depth = min(22.0, 0.3 * size)
    for j in range(ny):
        for i in range(nx):
            bx0, by0 = i * p + FACADE_LINE, j * p + FACADE_LINE
            bx1, by1 = bx0 + size, by0 + size
            for x, w, d, h in _row_lots(rng, size, max_depth):  # south row: wall 0 faces the street
                add(_rect(bx0 + x, bx0 + x + w, by0, by0 + d), h, 0)
            for x, w, d, h in _row_lots(rng, size, max_depth):  # north row: wall 2
                add(_rect(bx1 - x - w, bx1 - x, by1 - d, by1), h, 2)
            inner = size - 2 * (max_depth + 2.0)
            side_depth = min(14.0, 0.5 * (size - 4.0) - max_depth)
            if inner >= 6.0 and side_depth >= 6.0:
                ys = by0 + max_depth + 2.0
                for y, w, d, h in _row_lots(rng, inner, side_depth):  # west row: wall 3
                    add(_rect(bx0, bx0 + d, ys + y, ys + y + w), h, 3)
                for y, w, d, h in _row_lots(rng, inner, side_depth):  # east row: wall 1
                    add(_rect(bx1 - d, bx1, ys + y, ys + y + w), h, 1)
    segments_x: list[tuple[tuple[float, float], tuple[float, float], str]] = []
    for j in range(ny + 1):
        for i in range(nx):
            segments_x.append(((i * p, j * p), ((i + 1) * p, j * p), 'x'))
    for i in range(nx + 1):
        for j in range(ny):
            segments_x.append(((i * p, j * p), (i * p, (j + 1) * p), 'y'))
    segments = [Segment(k, (float(a[0]), float(a[1])), (float(b[0]), float(b[1])), axis)
                for k, (a, b, axis) in enumerate(segments_x)]
    occluders: list[Occluder] = []
    for seg in segments:
        occluders += _furniture(seg, rng, trees=seg.axis == 'x' or seg.index % 2 == 0)
    scene = Scene(name or 'city', seed, buildings, occluders, _segment_street(segments[0]),
                  map_origin=np.array(CITY_ORIGIN))
    return City(name or 'city', config, scene, segments)


def _segment_street(segment: Segment) -> Street:
    """The street of a segment: its centreline, cars parked clear of the intersections."""
    return Street(np.array([segment.start, segment.end]), parking=(FACADE_LINE + 4.0, segment.length - FACADE_LINE - 4.0))


def segment_seed(city: City, segment: int) -> int:
    """Seed of a segment's drives (its campaigns' cars and noise follow from it)."""
    return int(np.random.SeedSequence([city.seed, 29, segment]).generate_state(1)[0])


def segment_scene(city: City, segment: int, sensor: SensorConfig) -> tuple[Scene, np.ndarray, np.ndarray]:
    """The part of the city one segment's drives see.

    Args:
        city: the city.
        segment: index of the segment.
        sensor: gives the range limit (buildings and trees beyond it are left out).

    Returns:
        ``(scene, building_ids, facade_ids)``: a scene with the buildings within reach of the
        segment renumbered 0..b-1 (façades 0..f-1), its street the segment's, its seed the
        segment's (:func:`segment_seed`); and (b,) int32 and (f,) int32 the city-wide id of
        each local building and façade.
    """
    seg = city.segments[segment]
    a, b = np.array(seg.start), np.array(seg.end)
    lo, hi = np.minimum(a, b) - sensor.range_max - REACH_MARGIN, np.maximum(a, b) + sensor.range_max + REACH_MARGIN
    near = [bd for bd in city.scene.buildings
            if np.all(bd.polygon.max(axis=0) >= lo) and np.all(bd.polygon.min(axis=0) <= hi)]
    local: list[Building] = []
    facade_ids: list[int] = []
    for k, bd in enumerate(near):
        first = len(facade_ids)
        local.append(Building(k, bd.polygon, bd.height,
                              tuple(Facade(first + m, k, f.wall, f.frame, f.features) for m, f in enumerate(bd.facades)),
                              bd.source))
        facade_ids += [f.facade_id for f in bd.facades]
    occluders = [o for o in city.scene.static_occluders if lo[0] <= o.x <= hi[0] and lo[1] <= o.y <= hi[1]]
    scene = Scene(city.name, segment_seed(city, segment), local, occluders, _segment_street(seg),
                  map_origin=city.scene.map_origin)
    return (scene, np.array([bd.building_id for bd in near], dtype=np.int32),
            np.array(facade_ids, dtype=np.int32))


def segment_offsets(city: City, index: int, sensor: SensorConfig) -> np.ndarray:
    """(S + 1,) seconds from the drive's start to the start of each segment (and its end)."""
    durations = []
    for seg in city.segments:
        street_scene_ = Scene(city.name, 0, [], [], _segment_street(seg))
        durations.append(drive_duration(street_scene_, campaign(street_scene_, index), sensor))
    return np.concatenate([[0.0], np.cumsum(durations)])


def simulate_segment(city: City, index: int, segment: int, sensor: SensorConfig | None = None, *,
                     xyz_dtype: str = 'f8') -> Cloud:
    """Simulate drive ``index`` along one segment of the city.

    Args:
        city: the city.
        index: campaign (drive) number: lane, direction, parked cars and noise follow from it.
        segment: index of the segment.
        sensor: the sensor; the city's default (``SCENE_SENSORS['city']``) if None.
        xyz_dtype: ``'f8'`` or ``'f4'`` coordinates.

    Returns:
        The returns (fields of ``SIMULATED_FIELDS``; ``building_id`` and ``gt_facade``
        city-wide), times continuing from the previous segments of the drive.
    """
    sensor = sensor or SCENE_SENSORS['city']
    if not 0 <= segment < len(city.segments):
        raise InputError(f'segment {segment} is not in the city (0..{len(city.segments) - 1})')
    scene, building_ids, facade_ids = segment_scene(city, segment, sensor)
    cloud = simulate_campaign(scene, index, sensor, xyz_dtype=xyz_dtype)
    pts = cloud.points
    pts['time'] += segment_offsets(city, index, sensor)[segment]
    for name, ids in (('building_id', building_ids), ('gt_facade', facade_ids)):
        hit = pts[name] >= 0
        pts[name][hit] = ids[pts[name][hit]]
    return cloud


def segment_file(out: str | Path, index: int, segment: int, fmt: str = 'ply') -> Path:
    """Where ``simulate --scene city`` writes drive ``index``'s segment: ``OUT/campaign<k>/seg_<sss>.<fmt>``."""
    if fmt not in CITY_FORMATS:
        raise InputError(f'unknown city segment format {fmt!r}; choose one of {", ".join(CITY_FORMATS)}')
    return Path(out) / f'campaign{index}' / f'seg_{segment:03d}.{fmt}'


def city_files(out: str | Path, campaigns: list[int] | None = None) -> list[Path]:
    """The segment files a ``simulate --scene city`` run wrote, in driving order, from its scene.json.

    Args:
        out: the run's output folder (holding scene.json).
        campaigns: which drives; all if None.

    Returns:
        Paths of the files, drive by drive, segment by segment.

    Raises:
        InputError: no scene.json of a city there, a drive it does not have, or a listed
            file missing.
    """
    from .export import read_scene_json

    out = Path(out)
    desc = read_scene_json(out / 'scene.json')
    if 'city' not in desc:
        raise InputError(f'{out / "scene.json"} describes the scene {desc.get("scene")!r}, not a city')
    drives = {c['index']: c for c in desc['campaigns']}
    wanted = sorted(drives) if campaigns is None else campaigns
    paths = []
    for k in wanted:
        if k not in drives:
            raise InputError(f'{out}: the city run has no campaign {k} (it has {sorted(drives)})')
        for name in drives[k]['files']:
            path = out / name
            if not path.exists():
                raise InputError(f'{path} is listed in scene.json but missing; simulate the city again')
            paths.append(path)
    return paths


def is_edge(city: City, segment: int) -> bool:
    """True for a segment on the city's outer boundary (buildings on one side only)."""
    seg = city.segments[segment]
    nx, ny = city.config.blocks
    p = city.config.pitch
    if seg.axis == 'x':
        return seg.start[1] in (0.0, ny * p)
    return seg.start[0] in (0.0, nx * p)


def estimate_points(city: City, sensor: SensorConfig | None = None, campaigns: int = 2, sample: int = 1) -> float:
    """Points a full simulation would give, from a few segments simulated for real.

    Campaign 0 is simulated on the first ``sample`` segments of the boundary (buildings on one
    side) and the first ``sample`` inside (buildings on both sides); each kind's mean is
    scaled to its number of segments, and the sum to ``campaigns`` drives.

    Args:
        city: the city.
        sensor: the sensor; the city's default if None.
        campaigns: drives of the full simulation.
        sample: segments simulated of each kind (at least 1).

    Returns:
        The estimated number of points.
    """
    total = 0.0
    for edge in (True, False):
        kind = [s.index for s in city.segments if is_edge(city, s.index) == edge]
        if kind:
            counts = [len(simulate_segment(city, 0, k, sensor)) for k in kind[:max(1, sample)]]
            total += float(np.mean(counts)) * len(kind)
    return total * campaigns


@dataclass(frozen=True)
class SegmentTask:
    """One segment of one drive to simulate and write (picklable: a pool's work item).

    Attributes:
        seed: the city's seed.
        config: the city's size.
        name: the city's name.
        sensor: the sensor.
        index: the drive.
        segment: the segment.
        path: the file to write (:func:`segment_file`); its suffix gives the format.
        xyz_dtype: ``'f8'`` or ``'f4'`` coordinates.
    """

    seed: int
    config: CityConfig
    name: str
    sensor: SensorConfig
    index: int
    segment: int
    path: Path
    xyz_dtype: str = 'f8'


def write_segment(task: SegmentTask) -> tuple[int, float]:
    """Simulate one segment of one drive and write it (atomically: a temporary file, then renamed).

    Returns:
        ``(points, seconds)``: the points written and the seconds taken.
    """
    from ..io.npz import write_npz
    from ..io.ply import write_ply

    started = time.perf_counter()
    city = cached_city(task.seed, task.config, task.name)
    cloud = simulate_segment(city, task.index, task.segment, task.sensor, xyz_dtype=task.xyz_dtype)
    path = Path(task.path)
    fmt = path.suffix.lstrip('.')
    if fmt not in CITY_FORMATS:
        raise InputError(f'unknown city segment format {fmt!r}; choose one of {", ".join(CITY_FORMATS)}')
    path.parent.mkdir(parents=True, exist_ok=True)
    part = path.with_name(path.stem + '.part' + path.suffix)
    (write_ply if fmt == 'ply' else write_npz)(part, cloud)
    os.replace(part, path)
    return len(cloud), time.perf_counter() - started


@lru_cache(maxsize=4)
def cached_city(seed: int, config: CityConfig, name: str) -> City:
    """:func:`build_city`, built once per process (the workers of a pool)."""
    return build_city(seed, config, name)
