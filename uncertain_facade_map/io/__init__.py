"""Reading and writing: point clouds, the inputs of a map, the map file.

- ``cloud``: :class:`Cloud`, a structured point array with its map origin, the record all
  readers and writers exchange;
- ``clouds``: PLY, NPZ, LAS/LAZ and PCD files, the format chosen by the suffix; one module
  per format: ``npz``, ``ply``, ``las`` (LAS and LAZ), ``pcd``, and ``_files``, their
  shared helpers;
- ``inputs``: any inputs joined into one cloud and reduced to the building points of a map
  (ROS bags are read by ``msg_adapters.bag_io``, outside the core);
- ``scans``: one live scan (a PointCloud2's points) in its own frame to building points in
  the map frame, placed by the transforms: the one path of the node and offline replay;
- ``trajectory``: a sensor trajectory file, the sensor origins of clouds without them;
- ``av2``: an Argoverse 2 log folder (sweeps, ego poses, lidar extrinsics; pyarrow);
- ``map_file``: the versioned map file.
"""
