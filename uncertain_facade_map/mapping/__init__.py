"""Mapping with the pipeline: the map of all buildings, live and incremental, and what it publishes.

- ``facade_map``: :class:`FacadeMap`, the orchestrator: building points in, per building
  façades extracted and fitted (:mod:`uncertain_facade_map.pipeline`), updated block by
  block as points arrive;
- ``gate``: :class:`CloudGate`, a live cloud waits for its transform, is placed, selected and
  handed to the worker, in a thread of its own (tf2's MessageFilter shape);
- ``worker``: :class:`MapWorker`, the map in a thread of its own with a bounded queue and its
  drop policy, read-only snapshots for queries; ``map_scans`` feeds recorded scans as the
  node does;
- ``products``: the maps the node publishes, as arrays: surface grid and mesh, voxel and
  2D occupancy.
- ``engine``: where the map is updated, in the worker's thread or a child process;
- ``served``: :class:`ServedReading`, the per-point reading a live map's queries read, and
  when it is built again;
- ``accounts``: :class:`Accounts`, what became of every cloud and pose a live mapper
  received, counted so that it adds up; its diagnostics and summary line;
- ``calibration``: what the map learns from its stored points (occupancy, registration);
- ``allocator``: freed memory given back to the system by the long-running processes.
"""
