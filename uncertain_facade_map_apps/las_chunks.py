"""The tiled build's inputs, one piece at a time (issue 29): a cloud file or bag whole, LAS/LAZ
in chunks of points (laspy's chunk iterator), COPC files (``.copc.laz``) by area (laspy's
``CopcReader.query``), so that the client holds one piece of the city at a time."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Iterator

from uncertain_facade_map.io.cloud import Cloud

#: Points per LAS/LAZ chunk.
CHUNK_POINTS = 2_000_000


def input_chunks(path: str, bounds: tuple[float, float, float, float] | None,
                 load: Callable[[str], Cloud], chunk_points: int = CHUNK_POINTS) -> Iterator[Cloud]:
    """The clouds of one input in order: LAS/LAZ in chunks (COPC: only the nodes in ``bounds``,
    georeferenced x, y), any other input whole through ``load``."""
    name = Path(path).name.lower()
    if name.endswith(('.las', '.laz')):
        from uncertain_facade_map.io.las import iter_las

        yield from iter_las(path, chunk_points, bounds)
        return
    yield load(path)
