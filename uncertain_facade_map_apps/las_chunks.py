"""The tiled build's inputs, one piece at a time (issue 29): a cloud file or bag whole, LAS/LAZ
in chunks of points (laspy's chunk iterator), COPC files (``.copc.laz``) by area (laspy's
``CopcReader.query``), so that the reader holds one piece of the city at a time; and
:class:`BuildingChunks`, the building points of those pieces, what the build's survey tasks read."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

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


@dataclass(frozen=True)
class BuildingChunks:
    """An input's building points chunk by chunk, as the tiled build's survey reads them
    (:func:`uncertain_facade_map_apps.cluster.survey_input`, on a Dask worker or in the client):
    picklable, holding what the reading needs (the configuration, the selection, ``--topic``,
    ``--sensor``, ``--trajectory``, ``--bounds``).

    ``reader(path)`` yields, per non-empty piece of :func:`input_chunks`, (its input points,
    (xyz, building ids, sensor origins, map origin) of its building points:
    :data:`uncertain_facade_map.tiling.build.Chunk`).
    """

    config: Any
    selection: Any
    bounds: tuple[float, float, float, float] | None = None
    topic: str | None = None
    sensor: Any = None
    trajectory: Any = None

    def load(self, path: str) -> Cloud:
        """One whole input (not LAS/LAZ) as a cloud."""
        from msg_adapters.bag_io import load_inputs

        return load_inputs([path], topic=self.topic, max_distance=self.config.input.max_distance, warn=print,
                           config=self.config)

    def __call__(self, path: str) -> Iterator[tuple[int, tuple]]:
        from uncertain_facade_map.io.inputs import select_building_points

        for cloud in input_chunks(path, self.bounds, self.load):
            if not len(cloud):
                continue
            points = select_building_points(cloud, self.config.input, self.selection, sensor=self.sensor,
                                            trajectory=self.trajectory)
            yield len(cloud), (points.xyz, points.building_id, points.sensor_origins, points.map_origin)
