"""Every preset of the simulator, as data: sensors, walls, and which scene uses which.

Sensors (:data:`SENSOR_PRESETS`, :class:`~.sensor.SensorConfig`):

- ``mms``: the clean simulator's mobile-mapping system (the default of ``street`` and
  ``zurich``): RIEGL VMX-250 geometry (two profile scanners in an X), 50 lines/s and 0.2
  degrees per scanner (a third of the real rate), Gaussian range noise of 2 cm, 1 %
  clutter outliers. ``mms-small``: the same, coarser (``small``).
- ``vmx250``: the RIEGL VMX-250 at its real rate, from the published RIEGL VQ-250 / VMX-250
  data sheets (as recalled, no copy at hand to quote): two VQ-250 scanners, 300 kHz each (2 x 300 000 measurements/s), 100 scan
  lines/s each (so 3000 shots per 360-degree line, 0.12 degrees), range precision 5 mm
  (1 sigma at 50 m) and accuracy 10 mm, beam divergence 0.35 mrad, minimum range 1.5 m.
  Here: sigma = 4 mm + 0.06 mm/m in quadrature (5 mm at 50 m), a constant offset per
  scanner of sigma 5 mm (accuracy), the footprint term of 0.35 mrad, mixed returns,
  registration offsets of 3 cm horizontally, 2 cm vertically and 0.01 degrees between
  campaigns (typical of GNSS/INS drives registered to each other), 1 % clutter.
  ``vmx250-thin``: the same error model at the clean ``mms`` rate (50 lines/s, 0.2
  degrees), so that the hard scenes are as large as the clean ones (the default sensor of
  ``street_hard`` and ``zurich_hard``); ``vmx250-small`` for ``small_hard``.
- ``av2``: the Argoverse 2 vehicle's two stacked Velodyne VLP-32C lidars, one upside down
  (Wilson et al., Argoverse 2, NeurIPS 2021): 10 Hz, 32 beams each at the VLP-32C's
  elevations (VLP-32C User Manual 63-9325 Rev. B, table of laser angles: -25 to +15
  degrees, 0.33 degrees apart around the horizon), 0.2 degrees between firings at 10 Hz
  (578 688 single-return measurements/s, manual section 8.2.4), mounted 1.94 m and 1.83 m
  above the ground (measured on the real AV2 sample: ring elevations and sensor origins);
  range accuracy +-3 cm (data sheet: read here as 1.5 cm sigma), a constant offset per
  laser of sigma 1 cm, beam divergence 3 mrad (the Puck family's figure, VLP-16 manual;
  the VLP-32C manual gives none), coordinates stored as float16 in the vehicle frame (as
  Argoverse does), registration offsets as ``vmx250``, 1 % clutter, 5 m/s.

Walls (:data:`WALL_PRESETS`, :class:`~.walls.WallRealism`): ``hard``: bow 1-4 cm, lean
0.5-3 mm per metre, two undulations of 1-4 mm, plaster texture of 2 mm on a 2 cm grid,
a quarter of the shots at window panes return from 0.5-5 m inside the room. The glass
share is the one figure fitted to the real samples: with it, the AV2 preset sees through
its walls (points 0.3-5 m behind a wall plane, through its occupied cells) about as often
as the real AV2 sweep does, about 30 % of the wall points (`evaluation/realism.py`); with
a half it was 47 %. The other figures are from the data sheets or the measured geometry.

Scenes: ``street``, ``zurich`` and ``small`` are the clean scenes; ``street_hard``,
``zurich_hard`` and ``small_hard`` are the same geometry with ``hard`` walls and the
``vmx250-thin`` (``vmx250-small``) sensor (:data:`HARD_SCENES`, :data:`SCENE_SENSORS`).
"""

from __future__ import annotations

from dataclasses import replace

from .sensor import SensorConfig
from .walls import WallRealism

#: Elevations of the 32 beams of a Velodyne VLP-32C, degrees (VLP-32C User Manual, Rev. B).
VLP32C_ELEVATIONS_DEG = (
    -25.0, -15.639, -11.31, -8.843, -7.254, -6.148, -5.333, -4.667, -4.0, -3.667, -3.333, -3.0, -2.667, -2.333,
    -2.0, -1.667, -1.333, -1.0, -0.667, -0.333, 0.0, 0.333, 0.667, 1.0, 1.333, 1.667, 2.333, 3.333, 4.667, 7.0,
    10.333, 15.0,
)

_MMS = SensorConfig()
_VMX250 = SensorConfig(
    scan_rate_hz=100.0, angular_step_deg=0.12, range_min=1.5, range_max=60.0, range_noise=0.004,
    range_noise_per_m=0.00006, beam_divergence_mrad=0.35, beam_bias=0.005, outlier_share=0.01,
    registration_sigma=(0.03, 0.02, 0.01))
_AV2 = SensorConfig(
    pattern='spinning', scanner_yaws_deg=(0.0, 0.0), mount=((0.0, 0.0, 1.94), (0.0, 0.0, 1.83)),
    beam_elevations_deg=(VLP32C_ELEVATIONS_DEG, tuple(-e for e in VLP32C_ELEVATIONS_DEG)),
    scan_rate_hz=10.0, angular_step_deg=0.2, elevation_min_deg=-90.0, range_min=1.0, range_max=100.0,
    range_noise=0.015, beam_divergence_mrad=3.0, beam_bias=0.01, quantise='float16', outlier_share=0.01,
    registration_sigma=(0.03, 0.02, 0.01))

#: Sensors by name (see the module docstring for where the numbers come from).
SENSOR_PRESETS: dict[str, SensorConfig] = {
    'mms': _MMS,
    'mms-small': replace(_MMS, scan_rate_hz=15.0, angular_step_deg=0.5),
    'vmx250': _VMX250,
    'vmx250-thin': replace(_VMX250, scan_rate_hz=50.0, angular_step_deg=0.2),
    'vmx250-small': replace(_VMX250, scan_rate_hz=15.0, angular_step_deg=0.5),
    'av2': _AV2,
}

#: Walls by name.
WALL_PRESETS: dict[str, WallRealism] = {'hard': WallRealism()}

#: The hard variant of each clean scene: (clean scene, walls preset).
HARD_SCENES: dict[str, tuple[str, str]] = {
    'street_hard': ('street', 'hard'), 'zurich_hard': ('zurich', 'hard'), 'small_hard': ('small', 'hard'),
}

#: Default sensor of every built-in scene; ``small`` scans coarser to stay under 50 000 points.
SCENE_SENSORS: dict[str, SensorConfig] = {
    'street': SENSOR_PRESETS['mms'],
    'zurich': SENSOR_PRESETS['mms'],
    'small': SENSOR_PRESETS['mms-small'],
    'street_hard': SENSOR_PRESETS['vmx250-thin'],
    'zurich_hard': SENSOR_PRESETS['vmx250-thin'],
    'small_hard': SENSOR_PRESETS['vmx250-small'],
}
