"""Scene description as JSON, and splitting a campaign into sensor messages."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from ..errors import InputError
from ..io.cloud import Cloud
from .campaign import Campaign, SensorConfig
from .scene import Scene

#: Format tag of scene.json.
SCENE_FORMAT = 'uncertain_facade_map.scene/1'


def _jsonable(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        out = {'type': type(obj).__name__}
        out.update({f.name: _jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)})
        return out
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (list, tuple)):
        return [_jsonable(x) for x in obj]
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    return obj


def scene_description(scene: Scene, sensor: SensorConfig, campaigns: list[tuple[Campaign, int, dict[str, str]]]) -> dict:
    """Everything needed to understand and rebuild a simulated data set.

    The scene is rebuilt exactly by ``build_scene(name, seed)``; the geometry is listed so
    that other tools can read the truth without this package (for a hard scene with its
    walls and the relief of every façade: depth r(u, v) of :mod:`.walls`).

    Args:
        scene: the scene.
        sensor: the sensor used.
        campaigns: per campaign, (campaign, number of points, {format: file name}).

    Returns:
        A JSON-serialisable dict.
    """
    description = {
        'format': SCENE_FORMAT,
        'scene': scene.name,
        'seed': scene.seed,
        'map_origin': scene.map_origin.tolist(),
        'frame': 'map: metres, z up, ground at z = 0; georeferenced = map + map_origin',
        'sensor': _jsonable(sensor),
        'campaigns': [dict(_jsonable(c), points=n, files=files, role='mapped' if c.index == 0 else 'reference')
                      for c, n, files in campaigns],
        'street': _jsonable(scene.street),
        'buildings': [_jsonable(b) for b in scene.buildings],
        'static_occluders': [_jsonable(o) for o in scene.static_occluders],
    }
    if scene.walls is not None:
        # Walls as built: the relief of each façade is part of the truth (see simulation/walls.py).
        description['walls'] = _jsonable(scene.walls)
        description['reliefs'] = {str(k): _jsonable(r) for k, r in scene.reliefs.items()}
    return description


def write_scene_json(path: str | Path, description: dict) -> Path:
    """Write a scene description (see :func:`scene_description`)."""
    path = Path(path)
    path.write_text(json.dumps(description, indent=1))
    return path


def read_scene_json(path: str | Path) -> dict:
    """Read a scene description.

    Raises:
        InputError: missing file, invalid JSON or another format.
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f'no such file: {path}') from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f'{path}: not a JSON file ({exc})') from None
    if not isinstance(data, dict) or data.get('format') != SCENE_FORMAT:
        raise InputError(f'{path}: not a scene description ({SCENE_FORMAT})')
    return data


def split_scans(cloud: Cloud, period: float) -> Iterator[tuple[int, np.ndarray]]:
    """Split a time-ordered cloud into messages as a sensor sends them.

    Args:
        cloud: points with a ``time`` field (seconds since the UNIX epoch), time-ordered.
        period: seconds of data per message.

    Yields:
        ``(stamp_ns, points)``: the start of each period in nanoseconds and its points.

    Raises:
        InputError: no ``time`` field, or a period that is not positive.
    """
    if period <= 0:
        raise InputError(f'scan period must be positive, got {period}')
    if 'time' not in cloud.fields:
        raise InputError('the cloud has no time field to split it into scans')
    if not len(cloud):
        return
    t = cloud.points['time']
    # Integer nanoseconds avoid float rounding at period boundaries.
    t_ns = np.round(t * 1e9).astype(np.int64)
    period_ns = int(round(period * 1e9))
    slot = (t_ns - t_ns[0]) // period_ns
    bounds = np.flatnonzero(np.diff(slot)) + 1
    starts = np.concatenate([[0], bounds])
    ends = np.concatenate([bounds, [len(t)]])
    for a, b in zip(starts, ends):
        yield int(t_ns[0] + slot[a] * period_ns), cloud.points[a:b]
