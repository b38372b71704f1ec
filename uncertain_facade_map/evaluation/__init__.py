"""How good a map is: against a simulated scene's truth, and as occupancy against the baselines.

- ``surface``: accuracy and calibration of the mean surface and its variance against the
  exact truth of a simulated scene;
- ``occupancy``: the paper's occupancy protocol (Section IV.C): reference voxels from a
  second drive, PR and ROC AUC, accurate-inference curves;
- ``baselines``: occupancy methods behind one interface: our map and the paper's five
  baselines (OctoMap, BGKOctoMap, GPOM, LARD Hilbert maps, GPIS maps);
- ``report``: ``report.md`` with its tables and figures;
- ``benchmark``: the surface benchmark for any cloud: hold points out, map the rest, score
  the held-out points (and, on simulated scenes, the exact truth) beside reference maps;
- ``references``: the benchmark's reference maps (local plane of the 12 nearest points,
  one plane per façade);
- ``wall_points``: the wall points of an unclassified sweep (the benchmark's default pick);
- ``realism``: how hard a cloud is (wall density, residual spread of planar patches), for
  checking the simulator's sensor presets against real samples.
"""
