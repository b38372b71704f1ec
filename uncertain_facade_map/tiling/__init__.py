"""City-scale maps (issue 29): a tiled map is a folder holding ``manifest.json`` and one
ordinary map file per tile (``tiles/<id>.npz``), each holding the buildings whose points'
bounding-box centre lies in the tile's square, whole.

- :mod:`.grid`: the square tiles of the map frame's x, y plane and their ids;
- :mod:`.manifest`: the manifest (format, version, parameters, tiles with bounds, extents,
  files and content hashes), written atomically; :func:`.manifest.save_tile` writes a tile;
- :mod:`.tiled_map`: :class:`~.tiled_map.TiledMap`, a reader loading tiles on demand
  through an LRU bounded in bytes, :func:`~.tiled_map.merge_maps` and :func:`~.tiled_map.open_map`.
"""
