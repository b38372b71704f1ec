"""Mobile-mapping scan simulator with exact ground truth.

Scenes (:mod:`.scenes`) are buildings with façade detail, occluders and a street; a
campaign (:mod:`.campaign`) drives a vehicle with profile scanners along the street and
ray-casts (:mod:`.raycast`) every laser shot against the scene. Everything is
deterministic by seed.
"""
