"""Mobile-mapping scan simulator with exact ground truth.

Scenes (:mod:`.scenes`) are buildings with façade detail, occluders and a street; a
campaign (:mod:`.campaign`) drives a vehicle with profile scanners along the street and
ray-casts (:mod:`.raycast`) every laser shot against the scene. Everything is
deterministic by seed.

The hard simulator: :mod:`.walls` (walls as built: relief, plaster, glass), :mod:`.sensor`
(scan patterns and the error model), :mod:`.presets` (every sensor, walls and scene preset,
as data). Also :mod:`.scene` (geometry and truth), :mod:`.facades` (façade detail),
:mod:`.cityjson` (real footprints) and :mod:`.export` (scene.json, scans, a drive as a robot records it).
City scale (issue 29): :mod:`.city`, a grid of streets driven segment by segment, each segment
simulated and written on its own.
"""
