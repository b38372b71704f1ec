"""Every preset of the simulator, as data: sensors, walls, and which scene uses which.

Sensors (:data:`SENSOR_PRESETS`, :class:`~.sensor.SensorConfig`):

- ``mms``: the clean simulator's mobile-mapping system (the default of ``street`` and
  ``zurich``): RIEGL VMX-250 geometry (two profile scanners in an X), 50 lines/s and 0.2
  degrees per scanner (a third of the real rate), Gaussian range noise of 2 cm, 1 %
  clutter outliers. ``mms-small``: the same, coarser (``small``, ``city_small``); ``mms-city``: the
  same at half the line rate and 0.25 degree steps (40 % of the points; the ``city``).
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
  ``street_hard`` and ``zurich_hard``); ``vmx250-small`` for ``small_hard`` and ``stacked_hard``.
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
- ``hdl64``: a Velodyne HDL-64E on a car roof, as on the KITTI car (Geiger, Lenz, Stiller
  and Urtasun, "Vision meets robotics: the KITTI dataset", IJRR 2013: one HDL-64E spinning
  at 10 Hz, 64 beams, mounted 1.73 m above the ground). Beam elevations: the 64
  ``vert_correction`` angles of a calibrated HDL-64E S3 (ros-drivers/velodyne,
  ``velodyne_pointcloud/params/64e_s3-xiesc.yaml``, radians, here in degrees rounded to
  0.01), +1.96 to -24.56 degrees: the upper block of 32 lasers about 1/3 degree apart down
  to -8.56, the lower block about 1/2 degree apart (the data sheet, whose specification list
  github:ZahraArj/SLAM-papers ``15_KITTI.md`` reproduces: vertical field of view +2.0 to
  -24.9 degrees, 64 channels, about 0.4 degree apart). Azimuth step 0.17 degrees:
  the data sheet gives 0.08 degrees at 5 Hz to 0.35 at 20 Hz, in proportion to the spin
  rate, and about 1.3 million points/s, i.e. 2,030 shots per beam and turn at 10 Hz (0.177
  degrees). Range 0.9 m (the manual: returns closer than about three feet are to be
  ignored, HDL-64E User's Manual, "Usage") to 120 m (data sheet), Gaussian range noise of
  2 cm (data sheet: accuracy up to +-2 cm), 1 % clutter, 5 m/s, coordinates in float64
  (KITTI stores float32: sub-millimetre at these ranges). The top beam at +1.96 degrees
  from 1.73 m sees a wall 10 m away up to 2.07 m, 20 m away up to 2.41 m: the walls of a
  residential street only low (``residential``). One sweep holds about 130,000 returns
  there, a drive of its 120 m at 5 m/s 240 sweeps: simulate a few with ``window``.

Walls (:data:`WALL_PRESETS`, :class:`~.walls.WallRealism`): ``hard``: bow 1-4 cm, lean
0.5-3 mm per metre, two undulations of 1-4 mm, plaster texture of 2 mm on a 2 cm grid,
a quarter of the shots at window panes return from 0.5-5 m inside the room. The glass
share is the one figure fitted to the real samples: with it, the AV2 preset sees through
its walls (points 0.3-5 m behind a wall plane, through its occupied cells) about as often
as the real AV2 sweep does, about 30 % of the wall points (`evaluation/realism.py`); with
a half it was 47 %. The other figures are from the data sheets or the measured geometry.

Scenes: ``street``, ``zurich`` and ``small`` are the clean scenes; ``street_hard``,
``zurich_hard`` and ``small_hard`` are the same geometry with ``hard`` walls and the
``vmx250-thin`` (``vmx250-small``) sensor (:data:`HARD_SCENES`, :data:`SCENE_SENSORS`);
``stacked`` (``mms-small``) and ``stacked_hard`` (``vmx250-small``) are a small street whose
façades are not one plane (a set-back ground floor, a mansard band; issue 26);
``residential`` (detached houses behind front yards) is scanned by ``hdl64``.
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

#: Elevations of the 64 beams of a Velodyne HDL-64E, degrees, highest first: the calibrated
#: vertical corrections of one HDL-64E S3 (ros-drivers/velodyne, params/64e_s3-xiesc.yaml).
HDL64E_ELEVATIONS_DEG = (
    1.96, 1.56, 1.29, 0.89, 0.59, 0.2, -0.09, -0.45, -0.76, -1.14, -1.46, -1.81, -2.09, -2.49, -2.79, -3.12,
    -3.47, -3.82, -4.16, -4.53, -4.81, -5.13, -5.48, -5.89, -6.19, -6.56, -6.85, -7.23, -7.55, -7.94, -8.22, -8.56,
    -8.77, -9.3, -9.74, -10.18, -10.75, -11.3, -11.91, -12.29, -12.83, -13.16, -13.81, -14.29, -14.93, -15.38,
    -15.91, -16.27, -16.8, -17.37, -17.96, -18.43, -18.92, -19.25, -19.89, -20.43, -21.06, -21.49, -21.98, -22.36,
    -22.97, -23.55, -24.15, -24.56,
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
_HDL64 = SensorConfig(
    pattern='spinning', scanner_yaws_deg=(0.0,), mount=((0.0, 0.0, 1.73),), beam_elevations_deg=(HDL64E_ELEVATIONS_DEG,),
    scan_rate_hz=10.0, angular_step_deg=0.17, elevation_min_deg=-90.0, range_min=0.9, range_max=120.0,
    range_noise=0.02, outlier_share=0.01)

#: Sensors by name (see the module docstring for where the numbers come from).
SENSOR_PRESETS: dict[str, SensorConfig] = {
    'mms': _MMS,
    'mms-small': replace(_MMS, scan_rate_hz=15.0, angular_step_deg=0.5),
    'vmx250': _VMX250,
    'vmx250-thin': replace(_VMX250, scan_rate_hz=50.0, angular_step_deg=0.2),
    'vmx250-small': replace(_VMX250, scan_rate_hz=15.0, angular_step_deg=0.5),
    'av2': _AV2,
    'hdl64': _HDL64,
    'mms-city': replace(_MMS, scan_rate_hz=25.0, angular_step_deg=0.25),
}

#: Walls by name.
WALL_PRESETS: dict[str, WallRealism] = {'hard': WallRealism()}

#: The hard variant of each clean scene: (clean scene, walls preset).
HARD_SCENES: dict[str, tuple[str, str]] = {
    'street_hard': ('street', 'hard'), 'zurich_hard': ('zurich', 'hard'), 'small_hard': ('small', 'hard'),
    'stacked_hard': ('stacked', 'hard'),
}

#: Default sensor of every built-in scene; ``small`` scans coarser to stay under 50 000 points.
SCENE_SENSORS: dict[str, SensorConfig] = {
    'street': SENSOR_PRESETS['mms'],
    'zurich': SENSOR_PRESETS['mms'],
    'small': SENSOR_PRESETS['mms-small'],
    'street_hard': SENSOR_PRESETS['vmx250-thin'],
    'zurich_hard': SENSOR_PRESETS['vmx250-thin'],
    'small_hard': SENSOR_PRESETS['vmx250-small'],
    'stacked': SENSOR_PRESETS['mms-small'],
    'stacked_hard': SENSOR_PRESETS['vmx250-small'],
    'residential': SENSOR_PRESETS['hdl64'],
    'city': SENSOR_PRESETS['mms-city'],
    'city_small': SENSOR_PRESETS['mms-small'],
}
