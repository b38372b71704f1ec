"""City-scale maps (issue 29): a tiled map is a folder holding ``manifest.json`` and one
ordinary map file per tile (``tiles/<id>.npz``), each holding the buildings whose points'
bounding-box centre lies in the tile's square, whole.

- :mod:`.grid`: the square tiles of the map frame's x, y plane and their ids;
- :mod:`.manifest`: the manifest (format, version, parameters, tiles with bounds, extents,
  files and content hashes), written atomically; :func:`.manifest.save_tile` writes a tile;
- :mod:`.tiled_map`: :class:`~.tiled_map.TiledMap`, a reader loading tiles on demand
  through an LRU bounded in bytes, :func:`~.tiled_map.merge_maps` and :func:`~.tiled_map.open_map`;
- :mod:`.views`: squares of tiles holding what a query at a point reads;
- :mod:`.build`: the tiled build's plain pieces (routing points to tiles, one tile's task);
- :mod:`.cut`: a one-file map cut into a tiled map;
- :mod:`.serving`: :class:`~.serving.ServedMap`, the map a live mapper serves (its live map,
  the reading, a tiled map beside it; one query), and the thread that follows the pose.
"""
