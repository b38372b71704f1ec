"""Helpers shared by the tests (imported as ``support``: ``test/`` is on sys.path through conftest.py).

- :data:`REPO`: the repository's root;
- :func:`assert_same_maps`: two map files hold the same map, bit for bit;
- :func:`edge_cases`, :func:`assignments`: every parameter's advertised range ends, and one
  value beyond each, as the node and the command line must take or refuse them;
- a seeded synthetic scene with known truth for the baseline tests: a flat wall scanned
  from a straight drive (:func:`wall_scan`), and voxels labelled by the truth, on the wall
  or in the free space in front of it (:func:`labelled_voxels`);
- :func:`evaluation_arrays`: a simulated campaign's building points and sensor origins, as
  the occupancy evaluation takes them.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from uncertain_facade_map.params import parameters

#: The repository's root folder.
REPO = Path(__file__).resolve().parents[1]

#: The wall is the plane y = WALL_Y, x in [0, 10], z in [0, 6]; the sensor drives along y = 0.
WALL_Y = 8.0


def wall_scan(n_origins: int = 40, rays: int = 400, noise: float = 0.02, seed: int = 0
              ) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) hits on the wall with Gaussian range noise and their (N, 3) sensor origins.

    The sensor moves from x = 1 to x = 9 at y = 0, z = 2; each origin fires ``rays`` rays at
    uniformly drawn points of the wall, x in [0, 10] and z in [0, 6].
    """
    rng = np.random.default_rng(seed)
    origins = np.stack([np.linspace(1.0, 9.0, n_origins), np.zeros(n_origins), np.full(n_origins, 2.0)], 1)
    origins = np.repeat(origins, rays, axis=0)
    target = np.stack([rng.uniform(0, 10, len(origins)), np.full(len(origins), WALL_Y),
                       rng.uniform(0, 6, len(origins))], 1)
    direction = target - origins
    length = np.linalg.norm(direction, axis=1, keepdims=True)
    hits = origins + direction / length * (length + rng.normal(0.0, noise, (len(origins), 1)))
    return hits, origins


def labelled_voxels(resolution: float) -> tuple[np.ndarray, np.ndarray]:
    """Voxel centres over the wall's middle and in front of it, and the truth.

    Returns:
        ``(centres, on_wall)``: (K, 3) voxel centres of the grid ``floor(x / r)`` over
        x in [2, 8], z in [1, 5], for the voxel layers from 2 m in front of the wall to the
        wall's own, and (K,) bool, True for the voxels the wall passes through.
    """
    r = resolution
    xs = (np.arange(int(2 / r), int(8 / r)) + 0.5) * r
    zs = (np.arange(int(1 / r), int(5 / r)) + 0.5) * r
    wall_row = int(np.floor(WALL_Y / r))
    ys = (np.arange(wall_row - int(2 / r), wall_row + 1) + 0.5) * r
    grid = np.stack(np.meshgrid(xs, ys, zs, indexing='ij'), -1).reshape(-1, 3)
    on_wall = np.floor(grid[:, 1] / r).astype(int) == wall_row
    return grid, on_wall


def assert_same_maps(path_a, path_b):
    """Two map files hold the same map: every array bit for bit, the meta record but timings."""
    a, b = np.load(path_a), np.load(path_b)
    assert a.files == b.files
    for key in a.files:
        if key != 'meta':
            assert a[key].dtype == b[key].dtype and a[key].tobytes() == b[key].tobytes(), key
    meta_a, meta_b = json.loads(str(a['meta'])), json.loads(str(b['meta']))
    for meta in (meta_a, meta_b):
        for f in meta['facades']:
            f['stats'].pop('seconds', None)
    differ = sorted(k for k in meta_a.keys() | meta_b.keys() if meta_a.get(k) != meta_b.get(k))
    assert meta_a == meta_b, f'meta differs in {differ}: ' + '; '.join(
        f'{k}: {str(meta_a.get(k))[:300]} != {str(meta_b.get(k))[:300]}' for k in differ if k != 'facades')


def _outside(value: float, kind: type, up: bool) -> float:
    """The next value of type ``kind`` beyond ``value`` (above if ``up``)."""
    if kind is int:
        return value + (1 if up else -1)
    return math.nextafter(value, math.inf if up else -math.inf)


def edge_cases() -> list[tuple[str, object, bool, tuple[str, ...]]]:
    """(parameter, value, accepted?, relation partners) for both ends of every advertised range."""
    cases = []
    for info in parameters():
        bounds = info.closed_range()
        if bounds is None:
            continue
        section = info.name.split('.')[0]
        partners = tuple(f'{section}.{n}' for rel in info.relations for n in rel.names)
        for end, up in ((bounds[0], False), (bounds[1], True)):
            value = info.type(end)
            cases.append((info.name, value, True, partners))
            beyond = _outside(value, info.type, up)
            if abs(beyond) < 1e308:
                cases.append((info.name, beyond, False, partners))
    return cases


def assignments(name: str, value: object, partners: tuple[str, ...]) -> list[dict]:
    """The value alone, then (if a relation with the others' defaults forbids it) with its
    relation partners at the same value."""
    out = [{name: value}]
    if partners:
        out.append(dict.fromkeys(partners, value))
    return out


def assert_edge_taken(read, name: str, value: object, accepted: bool, partners: tuple[str, ...]) -> None:
    """``read(params)`` (a configuration from ``{name: value}`` overrides) takes an advertised
    value (alone, or with its relation partners at the same value) and keeps it, or refuses
    a value beyond the range with an InputError naming the parameter."""
    import pytest

    from uncertain_facade_map.errors import InputError

    if not accepted:
        with pytest.raises(InputError, match=f'parameter {name}'):
            read({name: value})
        return
    errors = []
    for params in assignments(name, value, partners):
        try:
            config = read(params)
            break
        except InputError as exc:
            errors.append(str(exc))
    else:
        pytest.fail(f'{name}={value!r} advertised but refused: {errors}')
    section, key = name.split('.')
    assert getattr(getattr(config, section), key) == value


#: Labels of :func:`unclassified_street`.
GROUND, WALL, CAR, POLE, TREE = 0, 1, 2, 3, 4


def unclassified_street(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A seeded lidar-like sweep of a street without classes, for the building point selection.

    The sensor stands at (0, 0, 1.8) m; the ground is z = 0 within 40 m (denser near the
    sensor), walls 9 m tall along y = 10 (x in [-25, 25]) and y = -12 (x in [-20, 20]) and
    a side wall along x = 20 (y in [-12, -4]); a car (a 4.5 x 1.8 x 1.2 m box, 0.3 m above
    the ground) at (5, 4), a pole (0.1 m radius, 6 m) at (-6, 5), a tree (trunk, and a
    crown: a ball of 2.5 m radius at 5 m height) at (-12, -5). Range noise 2 cm.

    Returns:
        (N, 3) float64 points, (N,) int labels (``GROUND``, ``WALL``, ``CAR``, ``POLE``,
        ``TREE``), and the (3,) sensor position.
    """
    rng = np.random.default_rng(seed)
    parts: list[tuple[np.ndarray, int]] = []
    n = 20000
    r = 3.0 + 37.0 * rng.random(n) ** 2
    a = rng.uniform(0, 2 * np.pi, n)
    parts.append((np.stack([r * np.cos(a), r * np.sin(a), np.zeros(n)], 1), GROUND))
    for (x0, y0), (x1, y1), count in (((-25, 10), (25, 10), 8000), ((-20, -12), (20, -12), 7000),
                                      ((20, -12), (20, -4), 1500)):
        t = rng.random(count)
        parts.append((np.stack([x0 + t * (x1 - x0), y0 + t * (y1 - y0), rng.uniform(0, 9, count)], 1), WALL))
    box = rng.uniform([-2.25, -0.9, 0.3], [2.25, 0.9, 1.5], (1500, 3))
    side = rng.integers(0, 3, len(box))  # project onto the nearest face: a side, an end or the roof
    box[side == 0, 1] = np.sign(box[side == 0, 1]) * 0.9
    box[side == 1, 0] = np.sign(box[side == 1, 0]) * 2.25
    box[side == 2, 2] = 1.5
    parts.append((box + [5.0, 4.0, 0.0], CAR))
    a = rng.uniform(0, 2 * np.pi, 300)
    parts.append((np.stack([-6 + 0.1 * np.cos(a), 5 + 0.1 * np.sin(a), rng.uniform(0, 6, 300)], 1), POLE))
    a = rng.uniform(0, 2 * np.pi, 200)
    trunk = np.stack([-12 + 0.2 * np.cos(a), -5 + 0.2 * np.sin(a), rng.uniform(0, 2.5, 200)], 1)
    ball = rng.normal(size=(2500, 3))
    ball *= (2.5 * rng.random(2500) ** (1 / 3) / np.linalg.norm(ball, axis=1))[:, None]
    parts += [(trunk, TREE), (ball + [-12.0, -5.0, 5.0], TREE)]
    xyz = np.concatenate([p for p, _ in parts])
    labels = np.concatenate([np.full(len(p), k) for p, k in parts])
    sensor = np.array([0.0, 0.0, 1.8])
    ray = xyz - sensor
    xyz = xyz + ray / np.linalg.norm(ray, axis=1, keepdims=True) * rng.normal(0, 0.02, (len(xyz), 1))
    return xyz, labels, sensor


def evaluation_arrays(cloud, drop_outliers: bool) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) building points (class 1) of a simulated cloud and their (N, 3) sensor origins;
    ``drop_outliers``: without the points the simulator flags ``gt_outlier`` (a reference)."""
    keep = cloud.points['class'] == 1
    if drop_outliers:
        keep &= cloud.points['gt_outlier'] == 0
    p = cloud.points[keep]
    return np.stack([p['x'], p['y'], p['z']], 1), np.stack([p['origin_x'], p['origin_y'], p['origin_z']], 1)


def axis_angle(axis, angle: float) -> np.ndarray:
    """Quaternion (x, y, z, w) of a rotation by ``angle`` about ``axis``."""
    a = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    return np.r_[math.sin(angle / 2) * a, math.cos(angle / 2)]


def rodrigues(axis, angle: float) -> np.ndarray:
    """Rotation matrix by Rodrigues' formula, independent of the transform code under test."""
    a = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k
