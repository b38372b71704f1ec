"""Reading and writing: point clouds, the inputs of a map, the map file.

- ``cloud``: :class:`Cloud`, a structured point array with its map origin, the record all
  readers and writers exchange;
- ``clouds``: PLY, NPZ, LAS/LAZ and PCD files, the format chosen by the suffix; one module
  per format: ``npz``, ``ply``, ``las`` (LAS and LAZ), ``pcd``, and ``_files``, their
  shared helpers;
- ``inputs``: any inputs joined into one cloud and reduced to the building points of a map
  (ROS bags are read by ``msg_adapters.bag_io``, outside the core);
- ``trajectory``: a sensor trajectory file, the sensor origins of clouds without them;
- ``map_file``: the versioned map file.
"""
