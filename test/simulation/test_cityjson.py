"""Tests of uncertain_facade_map.simulation.cityjson: real footprints and heights from CityJSON."""

from __future__ import annotations

import copy
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.simulation.cityjson import Footprint, load_footprints
from uncertain_facade_map.simulation.scenes import DEFAULT_CITYJSON

#: The Zurich subset shipped with the package (the zurich scene's default).
ZURICH = DEFAULT_CITYJSON
#: Where it was copied from: the project's shared data folder beside the repository, if present.
SHARED_ZURICH = Path(__file__).resolve().parents[3] / 'shared' / 'data' / 'cityjson' / 'zurich_subset_lod2.json'
SCALE = np.array([0.001, 0.001, 0.001])
TRANSLATE = np.array([2683000.0, 1247000.0, 400.0])


# ----------------------------------------------------------------------------------------
# independent geometry checks


def signed_area(poly: np.ndarray) -> float:
    """Shoelace area of an (M, 2) ring, positive if counter-clockwise."""
    x, y = poly[:, 0] - poly[0, 0], poly[:, 1] - poly[0, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def segments_touch(p1: np.ndarray, p2: np.ndarray, q1: np.ndarray, q2: np.ndarray) -> bool:
    """True if closed segments p1-p2 and q1-q2 share a point (exact orientation test)."""
    def orient(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> float:
        return float(np.sign((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])))

    def on_segment(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> bool:
        return bool(np.all(np.minimum(a, b) <= c) and np.all(c <= np.maximum(a, b)))

    o1, o2, o3, o4 = orient(p1, p2, q1), orient(p1, p2, q2), orient(q1, q2, p1), orient(q1, q2, p2)
    if o1 * o2 < 0 and o3 * o4 < 0:
        return True
    return ((o1 == 0 and on_segment(p1, p2, q1)) or (o2 == 0 and on_segment(p1, p2, q2))
            or (o3 == 0 and on_segment(q1, q2, p1)) or (o4 == 0 and on_segment(q1, q2, p2)))


def is_simple(poly: np.ndarray) -> bool:
    """O(M^2) check that no two non-adjacent edges of the ring touch."""
    local = poly - poly[0]
    m = len(local)
    for i in range(m):
        for j in range(i + 2, m):
            if i == 0 and j == m - 1:
                continue
            if segments_touch(local[i], local[(i + 1) % m], local[j], local[(j + 1) % m]):
                return False
    return True


def same_ring(poly: np.ndarray, expected: np.ndarray, atol: float = 0.0) -> bool:
    """True if ``poly`` is ``expected`` up to the starting vertex (same orientation)."""
    if poly.shape != expected.shape:
        return False
    return any(np.allclose(np.roll(poly, -k, axis=0), expected, rtol=0, atol=atol)
               if atol else np.array_equal(np.roll(poly, -k, axis=0), expected)
               for k in range(len(poly)))


def real(xy_mm: list[tuple[int, int]]) -> np.ndarray:
    """(M, 2) coordinates, metres, of integer millimetre vertices, as the file defines them."""
    return np.array(xy_mm, dtype=np.float64) * SCALE[:2] + TRANSLATE[:2]


# ----------------------------------------------------------------------------------------
# hand-made CityJSON


class City:
    """A tiny CityJSON document: buildings made of prism parts over integer-mm polygons."""

    def __init__(self) -> None:
        self.vertices: list[list[int]] = []
        self.objects: dict[str, Any] = {}

    def vertex(self, x: int, y: int, z: int) -> int:
        self.vertices.append([x, y, z])
        return len(self.vertices) - 1

    def prism(self, ring_mm: list[tuple[int, int]], z0: int, z1: int, *, ground: bool = True,
              geometry_type: str = 'MultiSurface', semantics: bool = True) -> dict[str, Any]:
        """Geometry of a vertical prism over a CCW ring: ground, walls and a flat roof."""
        bottom = [self.vertex(x, y, z0) for x, y in ring_mm]
        top = [self.vertex(x, y, z1) for x, y in ring_mm]
        n = len(ring_mm)
        surfaces: list[list[list[int]]] = []
        kinds: list[int] = []
        if ground:
            surfaces.append([bottom[::-1]])
            kinds.append(0)
        for i in range(n):
            j = (i + 1) % n
            surfaces.append([[bottom[i], bottom[j], top[j], top[i]]])
            kinds.append(1)
        surfaces.append([top])
        kinds.append(2)
        geometry: dict[str, Any] = {'type': geometry_type, 'lod': '2'}
        nest = {'MultiSurface': 0, 'CompositeSurface': 0, 'Solid': 1, 'MultiSolid': 2}[geometry_type]
        boundaries: Any = surfaces
        values: Any = kinds
        for _ in range(nest):
            boundaries, values = [boundaries], [values]
        geometry['boundaries'] = boundaries
        if semantics:
            geometry['semantics'] = {
                'surfaces': [{'type': 'GroundSurface'}, {'type': 'WallSurface'}, {'type': 'RoofSurface'}],
                'values': values,
            }
        return geometry

    def building(self, bid: str, *parts: dict[str, Any], on_building: bool = False) -> None:
        """Add a Building whose geometry is in BuildingPart children (or on itself)."""
        if on_building:
            self.objects[bid] = {'type': 'Building', 'geometry': list(parts)}
            return
        children = [f'{bid}-part{k}' for k in range(len(parts))]
        self.objects[bid] = {'type': 'Building', 'children': children}
        for child, geometry in zip(children, parts):
            self.objects[child] = {'type': 'BuildingPart', 'parents': [bid], 'geometry': [geometry]}

    def doc(self) -> dict[str, Any]:
        return {'type': 'CityJSON', 'version': '1.1',
                'transform': {'scale': SCALE.tolist(), 'translate': TRANSLATE.tolist()},
                'CityObjects': self.objects, 'vertices': self.vertices}

    def write(self, path: Path) -> Path:
        path.write_text(json.dumps(self.doc()))
        return path


BOX = [(0, 0), (10000, 0), (10000, 6000), (0, 6000)]


# ----------------------------------------------------------------------------------------
# hand-made files


@pytest.mark.parametrize('variant', ['MultiSurface', 'CompositeSurface', 'Solid', 'MultiSolid',
                                     'on_building', 'no_ground', 'no_semantics'])
def test_box_building_is_exact(tmp_path: Path, variant: str) -> None:
    city = City()
    geometry_type = variant if variant[0].isupper() else 'MultiSurface'
    geometry = city.prism(BOX, 0, 9000, geometry_type=geometry_type,
                          ground=variant != 'no_ground', semantics=variant != 'no_semantics')
    city.building('box', geometry, on_building=variant == 'on_building')
    (fp,) = load_footprints(city.write(tmp_path / 'box.json'))
    assert isinstance(fp, Footprint) and fp.building_id == 'box'
    assert np.array_equal(fp.polygon, real(BOX))  # CCW, starting at the smallest (x, y)
    assert fp.polygon.dtype == np.float64 and not fp.polygon.flags.writeable
    assert fp.ground_z == 400.0
    assert fp.eave_height == pytest.approx(9.0, abs=1e-9)
    assert fp.ridge_height == pytest.approx(9.0, abs=1e-9)


def test_clockwise_input_gives_ccw_footprint(tmp_path: Path) -> None:
    city = City()
    geometry = city.prism(BOX[::-1], 0, 9000)  # walls and ground of a clockwise ring
    city.building('cw', geometry)
    (fp,) = load_footprints(city.write(tmp_path / 'cw.json'))
    assert np.array_equal(fp.polygon, real(BOX))


@pytest.mark.parametrize('second, exact', [
    ([(10000, 1000), (15000, 1000), (15000, 5000), (10000, 5000)], True),  # adjacent, T-junctions
    ([(8000, 1000), (15000, 1000), (15000, 5000), (8000, 5000)], False),  # overlapping
])
def test_parts_are_merged(tmp_path: Path, second: list[tuple[int, int]], exact: bool) -> None:
    city = City()
    city.building('two', city.prism(BOX, 0, 9000), city.prism(second, 0, 6000))
    (fp,) = load_footprints(city.write(tmp_path / 'two.json'))
    expected = real([(0, 0), (10000, 0), (10000, 1000), (15000, 1000), (15000, 5000),
                     (10000, 5000), (10000, 6000), (0, 6000)])
    assert same_ring(fp.polygon, expected, atol=0.0 if exact else 1e-6)
    assert fp.eave_height == pytest.approx(7.5)  # median of four 9 m and four 6 m walls
    assert fp.ridge_height == pytest.approx(9.0)


def test_roof_parts_do_not_change_the_footprint(tmp_path: Path) -> None:
    city = City()
    dormer = city.prism([(2000, 2000), (4000, 2000), (4000, 7000), (2000, 7000)], 9000, 11000, ground=False)
    city.building('house', city.prism(BOX, 0, 9000), dormer)
    (fp,) = load_footprints(city.write(tmp_path / 'house.json'))
    assert np.array_equal(fp.polygon, real(BOX))  # the overhanging dormer is no footprint
    assert fp.ridge_height == pytest.approx(11.0)
    assert fp.eave_height == pytest.approx(10.0)  # median over all walls: four at 9 m, four at 11 m


def test_disjoint_parts_keep_the_largest(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    city = City()
    shed = [(20000, 0), (25000, 0), (25000, 5000), (20000, 5000)]
    city.building('pair', city.prism(shed, 0, 3000), city.prism(BOX, 0, 9000))
    with caplog.at_level(logging.INFO):
        (fp,) = load_footprints(city.write(tmp_path / 'pair.json'))
    assert np.array_equal(fp.polygon, real(BOX))
    assert 'pair: 1 disjoint footprint ring(s) dropped' in caplog.text


def test_simplification(tmp_path: Path) -> None:
    noisy = [(0, 0), (5000, 50), (10000, 0), (10000, 5800), (9800, 6000),  # 0.28 m chamfer
             (6000, 6000), (6000, 6300), (5500, 6300), (5500, 6000),  # 0.5 m bump
             (0, 6000)]
    city = City()
    city.building('noisy', city.prism(noisy, 0, 9000))
    path = city.write(tmp_path / 'noisy.json')
    (fp,) = load_footprints(path)
    assert same_ring(fp.polygon, real(BOX), atol=1e-6)
    (raw,) = load_footprints(path, min_edge=0.0, simplify_tolerance=0.0)
    # Only the 1.1 degree bend goes; chamfer and bump stay.
    assert same_ring(raw.polygon, real([p for p in noisy if p != (5000, 50)]))


def test_small_buildings_are_dropped(tmp_path: Path) -> None:
    city = City()
    city.building('kiosk', city.prism([(0, 0), (4000, 0), (4000, 4000), (0, 4000)], 0, 3000))
    city.building('house', city.prism([(x + 20000, y) for x, y in BOX], 0, 9000))
    footprints = load_footprints(city.write(tmp_path / 'two.json'))
    assert [fp.building_id for fp in footprints] == ['house']
    only_kiosk = City()
    only_kiosk.building('kiosk', only_kiosk.prism([(0, 0), (4000, 0), (4000, 4000), (0, 4000)], 0, 3000))
    with pytest.raises(InputError, match='no usable building'):
        load_footprints(only_kiosk.write(tmp_path / 'kiosk.json'))


# ----------------------------------------------------------------------------------------
# errors


def error_of(path: Path, **kwargs: float) -> str:
    with pytest.raises(InputError) as err:
        load_footprints(path, **kwargs)
    message = str(err.value)
    assert '\n' not in message
    return message


def test_missing_file(tmp_path: Path) -> None:
    assert error_of(tmp_path / 'nope.json').startswith('no such file: ')


@pytest.mark.parametrize('text, message', [
    ('{"type": "CityJSON", "CityObjects": {', 'invalid JSON'),
    ('\xff\xfe garbage', 'invalid JSON'),
    ('[1, 2, 3]', 'not CityJSON'),
    ('{"type": "FeatureCollection", "features": []}', 'not CityJSON (no CityObjects, vertices, transform)'),
    ('{"type": "CityJSON", "CityObjects": {}, "vertices": []}', 'no transform'),
    ('{"type": "CityJSONFeature", "CityObjects": {}, "vertices": [], "transform": {}}', 'not a CityJSON file'),
    ('{"type": "CityJSON", "CityObjects": {}, "vertices": [],'
     ' "transform": {"scale": [1, 1, 1], "translate": [0, 0, 0]}}', 'no usable building'),
    ('{"type": "CityJSON", "CityObjects": {}, "vertices": [[1, 2]],'
     ' "transform": {"scale": [1, 1, 1], "translate": [0, 0, 0]}}', 'vertices must be'),
    ('{"type": "CityJSON", "CityObjects": {}, "vertices": [],'
     ' "transform": {"scale": [1, 1], "translate": [0, 0, 0]}}', 'scale and translate'),
])
def test_not_cityjson(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / 'bad.json'
    path.write_bytes(text.encode('latin-1'))
    assert message in error_of(path)


def test_malformed_geometry(tmp_path: Path) -> None:
    city = City()
    city.building('box', city.prism(BOX, 0, 9000))
    doc = city.doc()
    broken = copy.deepcopy(doc)
    broken['CityObjects']['box-part0']['geometry'][0]['boundaries'][0][0][0] = 99999
    (tmp_path / 'index.json').write_text(json.dumps(broken))
    assert 'box: vertex index out of range' in error_of(tmp_path / 'index.json')
    broken = copy.deepcopy(doc)
    broken['CityObjects']['box-part0']['geometry'][0]['boundaries'][1] = 7
    (tmp_path / 'nest.json').write_text(json.dumps(broken))
    assert 'malformed geometry boundaries' in error_of(tmp_path / 'nest.json')
    broken = copy.deepcopy(doc)
    broken['CityObjects']['box-part0']['geometry'][0]['boundaries'][1][0] = [0, 'a', 2]
    (tmp_path / 'ring.json').write_text(json.dumps(broken))
    assert 'malformed ring' in error_of(tmp_path / 'ring.json')


@pytest.mark.parametrize('kwargs', [{'min_edge': -1.0}, {'simplify_tolerance': float('nan')}])
def test_bad_parameters(tmp_path: Path, kwargs: dict[str, float]) -> None:
    city = City()
    city.building('box', city.prism(BOX, 0, 9000))
    assert 'must be a finite number' in error_of(city.write(tmp_path / 'box.json'), **kwargs)


# ----------------------------------------------------------------------------------------
# the real Zurich file (packaged with the simulator)


@pytest.fixture(scope='module')
def zurich() -> tuple[dict[str, Any], list[Footprint]]:
    doc = json.loads(ZURICH.read_text())
    return doc, load_footprints(ZURICH)


def test_zurich_footprints(zurich: tuple[dict[str, Any], list[Footprint]]) -> None:
    doc, footprints = zurich
    buildings = [k for k, v in doc['CityObjects'].items() if v['type'] == 'Building']
    assert 40 <= len(footprints) <= len(buildings) == 49
    ids = [fp.building_id for fp in footprints]
    assert len(set(ids)) == len(ids) and set(ids) <= set(buildings)
    for fp in footprints:
        poly = fp.polygon
        assert poly.ndim == 2 and poly.shape[1] == 2 and len(poly) >= 3 and poly.dtype == np.float64
        assert not np.array_equal(poly[0], poly[-1])
        assert signed_area(poly) >= 20.0, fp.building_id  # counter-clockwise, not degenerate
        assert is_simple(poly), fp.building_id
        edges = np.hypot(*(np.roll(poly, -1, axis=0) - poly).T)
        assert edges.min() >= 1.0, fp.building_id  # min_edge
        assert 3.0 < fp.eave_height <= fp.ridge_height < 80.0, fp.building_id
        ext = np.array(doc['CityObjects'][fp.building_id]['geographicalExtent'])
        assert np.all(poly >= ext[:2] - 0.5) and np.all(poly <= ext[3:5] + 0.5), fp.building_id
        assert ext[2] - 0.5 <= fp.ground_z <= ext[5], fp.building_id


def test_zurich_areas_match_ground_polygons(zurich: tuple[dict[str, Any], list[Footprint]]) -> None:
    doc, footprints = zurich
    vertices = np.array(doc['vertices'], dtype=np.float64) * doc['transform']['scale'] \
        + doc['transform']['translate']
    for fp in footprints:
        total = 0.0
        for child in doc['CityObjects'][fp.building_id]['children']:
            for geometry in doc['CityObjects'][child]['geometry']:
                sem = geometry['semantics']
                for surface, value in zip(geometry['boundaries'], sem['values']):
                    if value is not None and sem['surfaces'][value]['type'] == 'GroundSurface':
                        total += abs(signed_area(vertices[surface[0], :2]))
        assert signed_area(fp.polygon) == pytest.approx(total, rel=0.05), fp.building_id


def test_zurich_wall_bottoms_give_the_same_footprints(
        tmp_path: Path, zurich: tuple[dict[str, Any], list[Footprint]]) -> None:
    doc, footprints = zurich
    walls_only = copy.deepcopy(doc)
    for obj in walls_only['CityObjects'].values():
        for geometry in obj.get('geometry', []):
            for surface in geometry['semantics']['surfaces']:
                if surface['type'] == 'GroundSurface':
                    surface['type'] = 'ClosureSurface'
    (tmp_path / 'walls.json').write_text(json.dumps(walls_only))
    by_walls = {fp.building_id: fp for fp in load_footprints(tmp_path / 'walls.json')}
    same = [fp for fp in footprints if fp.building_id in by_walls
            and same_ring(by_walls[fp.building_id].polygon, fp.polygon, atol=1e-6)]
    assert len(same) >= len(footprints) - 3
