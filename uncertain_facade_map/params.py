"""Every parameter of the map, the node and the command line, declared once.

A parameter is a field of a frozen dataclass (a *section* of the parameter file) declared
with :func:`param`: its default, its unit, the values it may take (an :class:`Interval`
with open or closed ends, in the spirit of scikit-learn's ``_parameter_constraints``, or
:class:`Options`) and its description. Its type is the field's annotation. Everything
else derives from that one declaration:

- the checks: :class:`Section` validates every field on construction, then the section's
  :class:`Relation` s between fields, and raises :class:`~uncertain_facade_map.errors.InputError`
  naming the parameter (``parameter gp.noise_sigma: 0.0 is outside (0, 100]``);
- the parameter file and its comments (:mod:`uncertain_facade_map.io.parameter_file`);
- the node's ``ParameterDescriptor`` s, whose ranges are :meth:`Interval.closed_range`
  (ROS ranges are closed: an open end is advertised as the nearest value inside);
- the map file's parameter record (:func:`map_params_record`, :func:`map_params_from_record`).

Sections, in the order of the parameter file: the modelling stages (``extraction``,
``layers``, ``gp``, ``outliers``, ``update``) make :class:`MapParams`, the rest
(``input``, ``selection``, ``query``, ``model``, ``node``, ``publish``, ``service``, ``persistence``,
``localise``)
complete :class:`Config`, the whole file.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import sys
from dataclasses import dataclass, field
from typing import Any, Callable, ClassVar, Iterator, Literal, get_args, get_origin, get_type_hints

from .errors import InputError

__all__ = [
    'Config', 'ExtractionParams', 'GPParams', 'InputConfig', 'Interval', 'LayerParams', 'LocaliseParams', 'MapParams', 'ModelConfig',
    'NodeConfig', 'Options', 'OutlierParams', 'Param', 'PersistenceConfig', 'PublishConfig', 'QueryConfig',
    'Relation', 'Section', 'SelectionConfig', 'ServiceConfig', 'UpdateParams', 'config_from_parameters', 'map_params',
    'map_params_from_record', 'map_params_record', 'parameters', 'NODE_NAME', 'LOCALIZER_NAME', 'LOCALIZER_SECTIONS',
    'LocalizerConfig', 'TilesConfig', 'node_sections',
]

#: The node's name, and the section of the parameter file it reads.
NODE_NAME = 'facade_mapper'
#: The localiser node's name, and the section of its parameter file.
LOCALIZER_NAME = 'facade_localizer'
#: Largest int64 (ROS integer parameters are int64).
INT64_MAX = 2**63 - 1


# ----------------------------------------------------------------------------------------
# What a parameter may be
# ----------------------------------------------------------------------------------------
def _number(x: float) -> str:
    return str(x) if isinstance(x, int) else f'{x:g}'


@dataclass(frozen=True)
class Interval:
    """Numbers between two ends, each open, closed or absent (unbounded).

    Attributes:
        left: lower end, or None for none.
        right: upper end, or None for none.
        closed: which ends belong to the interval: ``'both'``, ``'left'``, ``'right'`` or
            ``'neither'``.
    """

    left: float | None
    right: float | None
    closed: Literal['both', 'left', 'right', 'neither'] = 'both'

    def __contains__(self, value: float) -> bool:
        left_ok = self.left is None or (value >= self.left if self.closed in ('both', 'left') else value > self.left)
        right_ok = self.right is None or (value <= self.right if self.closed in ('both', 'right')
                                          else value < self.right)
        return bool(left_ok and right_ok)

    def __str__(self) -> str:
        lo = '-inf' if self.left is None else _number(self.left)
        hi = 'inf' if self.right is None else _number(self.right)
        return (f'{"[" if self.closed in ("both", "left") and self.left is not None else "("}{lo}, '
                f'{hi}{"]" if self.closed in ("both", "right") and self.right is not None else ")"}')

    def closed_range(self, kind: type) -> tuple[float, float]:
        """The closed range ``[lo, hi]`` of the values of type ``kind`` (int or float) inside.

        An open float end becomes the next float inside (``math.nextafter``), an open
        integer end the next integer; an absent end the type's extreme (int64, or the
        largest finite float), as a ROS parameter range needs both ends.
        """
        if kind is int:
            lo = -INT64_MAX - 1 if self.left is None else math.ceil(self.left)
            hi = INT64_MAX if self.right is None else math.floor(self.right)
            if self.left is not None and self.closed in ('right', 'neither') and lo == self.left:
                lo += 1
            if self.right is not None and self.closed in ('left', 'neither') and hi == self.right:
                hi -= 1
            return int(lo), int(hi)
        big = sys.float_info.max
        lo = -big if self.left is None else float(self.left)
        hi = big if self.right is None else float(self.right)
        if self.left is not None and self.closed in ('right', 'neither'):
            lo = math.nextafter(lo, math.inf)
        if self.right is not None and self.closed in ('left', 'neither'):
            hi = math.nextafter(hi, -math.inf)
        return lo, hi


@dataclass(frozen=True)
class Options:
    """One of a fixed set of values."""

    values: tuple

    def __contains__(self, value: Any) -> bool:
        return value in self.values

    def __str__(self) -> str:
        return 'one of ' + ', '.join(str(v) for v in self.values)


@dataclass(frozen=True)
class Param:
    """The declaration of one parameter (see :func:`param`)."""

    description: str
    unit: str = ''
    allowed: Interval | Options | None = None

    def constraint_text(self) -> str:
        """The unit and the allowed values, for comments and descriptors (e.g. ``m; (0, 10]``)."""
        return '; '.join(x for x in (self.unit, '' if self.allowed is None else str(self.allowed)) if x)


def param(default: Any, description: str, *, unit: str = '', allowed: Interval | Options | None = None) -> Any:
    """A dataclass field declaring a parameter: default, description, unit, allowed values.

    For a tuple-typed parameter, ``allowed`` applies to every item.
    """
    value = tuple(default) if isinstance(default, (list, tuple)) else default
    return field(default=value, metadata={'param': Param(description, unit, allowed)})


@dataclass(frozen=True)
class Relation:
    """A condition between parameters of one section.

    Attributes:
        names: the parameters involved (in the section).
        holds: called with their values in that order; True if the condition holds.
        text: the condition as a user reads it (in messages and descriptors).
    """

    names: tuple[str, ...]
    holds: Callable[..., bool]
    text: str


# ----------------------------------------------------------------------------------------
# Sections: validation derived from the declarations
# ----------------------------------------------------------------------------------------
def _closed(lo: float, hi: float) -> Interval:
    return Interval(lo, hi, 'both')


def _positive(hi: float | None = None) -> Interval:
    return Interval(0, hi, 'neither' if hi is None else 'right')


@dataclass(frozen=True)
class Section:
    """Base of the parameter sections: checks and normalises every field from its declaration.

    A value of the wrong type, outside its interval or options, or breaking one of the
    section's :attr:`relations` raises :class:`InputError` naming ``section.parameter``.
    Integers are accepted for float parameters (and stored as floats); lists for tuples.
    """

    #: Name of the section in the parameter file.
    section: ClassVar[str] = ''
    #: Conditions between the section's parameters.
    relations: ClassVar[tuple[Relation, ...]] = ()

    def __post_init__(self) -> None:
        hints = _hints(type(self))
        for f in dataclasses.fields(self):
            name = f'{self.section}.{f.name}'
            value = _checked(name, getattr(self, f.name), hints[f.name], f.metadata['param'].allowed)
            object.__setattr__(self, f.name, value)
        for rel in self.relations:
            if not rel.holds(*(getattr(self, n) for n in rel.names)):
                values = ', '.join(f'{self.section}.{n} = {getattr(self, n)!r}' for n in rel.names)
                raise InputError(f'parameter {self.section}.{rel.names[0]}: need {rel.text} (got {values})')


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    return get_type_hints(cls)


def _type_name(typ: Any) -> str:
    return {int: 'an integer', float: 'a number', str: 'a string', bool: 'true or false'}.get(typ, str(typ))


def _checked(name: str, value: Any, typ: Any, allowed: Interval | Options | None) -> Any:
    """``value`` checked against its type and allowed values, normalised (int -> float, list -> tuple)."""
    if get_origin(typ) is tuple:
        if not isinstance(value, (list, tuple)):
            raise InputError(f'parameter {name}: expected a list, got {value!r}')
        args = get_args(typ)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_checked(name, v, args[0], allowed) for v in value)
        if len(value) != len(args):
            raise InputError(f'parameter {name}: expected {len(args)} values, got {len(value)}')
        return tuple(_checked(name, v, a, allowed) for v, a in zip(value, args))
    if typ is bool:
        ok = isinstance(value, bool)
    elif typ is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif typ is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        if ok:
            value = float(value)
            if not math.isfinite(value):
                raise InputError(f'parameter {name}: must be finite, got {value!r}')
    elif typ is str:
        ok = isinstance(value, str)
    else:
        ok = True
    if not ok:
        raise InputError(f'parameter {name}: expected {_type_name(typ)}, got {value!r}')
    if allowed is not None and value not in allowed:
        if isinstance(allowed, Options):
            raise InputError(f'parameter {name}: expected {allowed}, got {value!r}')
        raise InputError(f'parameter {name}: {value!r} is outside {allowed}')
    return value


# ----------------------------------------------------------------------------------------
# The modelling stages (paper, Section III)
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ExtractionParams(Section):
    """Buildings, RANSAC façade planes, PCA frames and point normals (:mod:`~.pipeline.step1_facades`)."""

    section: ClassVar[str] = 'extraction'
    relations: ClassVar[tuple[Relation, ...]] = (
        Relation(('band_front', 'band_back'), lambda front, back: front + back > 0, 'band_front + band_back > 0'),
    )

    ransac_threshold: float = param(0.08, 'inlier distance of plane hypotheses', unit='m',
                                    allowed=_closed(1e-4, 10.0))
    ransac_iterations: int = param(400, 'hypotheses per RANSAC round', allowed=_closed(1, 1_000_000))
    ransac_sample: int = param(30000, 'points drawn per building for hypothesis scoring',
                               allowed=_closed(3, 1_000_000_000))
    min_facade_points: int = param(300, 'a plane with fewer allocated points is no façade',
                                   allowed=_closed(3, 1_000_000_000))
    max_facades: int = param(20, 'most planes per building', allowed=_closed(1, 10_000))
    max_tilt_deg: float = param(45.0, 'planes tilted more than this from vertical (roofs, balcony undersides) are '
                                      'no façades', unit='degrees', allowed=Interval(0.0, 90.0, 'left'))
    merge_angle_deg: float = param(10.0, 'parallel planes within this angle ...', unit='degrees',
                                   allowed=Interval(0.0, 90.0, 'left'))
    merge_offset: float = param(2.0, '... and closer than this are one façade', unit='m', allowed=_closed(0.0, 1000.0))
    band_front: float = param(2.0, 'distance in front of the plane (outwards) still allocated to it (balconies, '
                                   'oriels, clutter)', unit='m', allowed=_closed(0.0, 1000.0))
    band_back: float = param(1.0, 'distance behind the plane still allocated to it (recesses)', unit='m',
                             allowed=_closed(0.0, 1000.0))
    extent_margin: float = param(1.0, "margin around a façade's (u, v) extent for allocation", unit='m',
                                 allowed=_closed(0.0, 1000.0))
    normal_neighbours: int = param(10, 'k of the per-point normal estimate (the point included)',
                                   allowed=_closed(3, 10_000))
    building_cell: float = param(0.5, 'grid cell of the clustering of points without building ids', unit='m',
                                 allowed=_closed(1e-3, 1000.0))


@dataclass(frozen=True)
class LayerParams(Section):
    """The GMM depth layers and their facets (:mod:`~.pipeline.step2_layers`)."""

    section: ClassVar[str] = 'layers'

    histogram_bin: float = param(0.01, 'bin width of the depth histogram', unit='m', allowed=_closed(1e-5, 10.0))
    min_peak_share: float = param(0.01, "a histogram peak needs this share of the façade's points nearby",
                                  allowed=Interval(0.0, 1.0, 'left'))
    max_layers: int = param(8, 'upper bound on K, the number of layers', allowed=_closed(1, 1000))
    gmm_sample: int = param(20000, 'EM is fitted on at most this many depths', allowed=_closed(10, 1_000_000_000))
    facet_cell: float = param(0.1, 'raster cell of the facets', unit='m', allowed=_closed(1e-3, 100.0))
    fill_distance: float = param(0.3, 'empty cells this close to a voted cell join its facet', unit='m',
                                 allowed=_closed(0.0, 100.0))
    relief_spacing: float = param(2.0, 'node spacing of the smooth wall surface the layers are offsets from (walls '
                                       'bow and lean); 0: flat walls, constant layers as in the paper', unit='m',
                                  allowed=_closed(0.0, 1000.0))
    relief_smoothing: float = param(10.0, 'weight of the wall surface\'s curvature penalty, per unit of data weight '
                                         'of a node', allowed=_closed(0.0, 1e9))
    relief_scale: float = param(4.0, 'points further from the wall surface than this many noise sigmas do not '
                                     'shape it (Tukey biweight scale)', allowed=_closed(0.5, 1000.0))
    min_facet_cells: int = param(2, 'a connected region with fewer voted cells than this is no facet (a lone '
                                    'outlier or a stray vote); its cells join the nearest real facet within '
                                    'fill_distance', allowed=_closed(1, 1_000_000))


@dataclass(frozen=True)
class GPParams(Section):
    """Training points and the local GPs in blocks (:mod:`~.pipeline.step3_training`,
    :mod:`~.pipeline.step4_gp_blocks`); the paper's values where it gives them."""

    section: ClassVar[str] = 'gp'
    relations: ClassVar[tuple[Relation, ...]] = (
        Relation(('lengthscale2_min', 'initial_lengthscale2', 'lengthscale2_max'), lambda lo, x, hi: lo <= x <= hi,
                 'lengthscale2_min <= initial_lengthscale2 <= lengthscale2_max'),
    )

    estimate_noise: bool = param(True, 'estimate sigma_eta per façade from the data (the nugget of its depths at '
                                       'lags up to noise_lag); else take noise_sigma')
    noise_sigma: float = param(0.02, 'sigma_eta, the noise of the points, when not estimated or too few points are '
                                     'close enough to estimate it (paper: 0.02)', unit='m',
                               allowed=_closed(1e-6, 100.0))
    noise_lag: float = param(0.05, 'pairs of points closer than this on the plane estimate the noise', unit='m',
                             allowed=_closed(1e-4, 10.0))
    min_noise_sigma: float = param(0.002, 'the estimated noise is at least this (a floor for perfectly smooth data)',
                                   unit='m', allowed=_closed(0.0, 100.0))
    initial_lengthscale2: float = param(0.0025, 'initial 1/b_1 = 1/b_2 (paper: 0.0025)', unit='m^2',
                                        allowed=_closed(1e-8, 1e4))
    lengthscale2_min: float = param(0.0025, 'lower bound of 1/b_m in the optimisation', unit='m^2',
                                    allowed=_closed(1e-8, 1e4))
    lengthscale2_max: float = param(0.04, 'upper bound of 1/b_m in the optimisation', unit='m^2',
                                    allowed=_closed(1e-8, 1e4))
    c_min: float = param(1e-4, 'covariance threshold that sets the block size (paper: 1e-4)',
                         allowed=Interval(0.0, 1.0, 'neither'))
    alpha_z_deg: float = param(25.0, 'a point whose normal deviates more than this from the façade normal is a '
                                     'training point (paper eq. 8: 25 degrees)', unit='degrees',
                               allowed=_closed(0.0, 90.0))
    inlier_sigmas: float = param(1.96, 'a point further than this many sigma_k from its layer is a training point '
                                       '(paper eq. 7: 1.96)', allowed=_positive(1000.0))
    max_planar_sigma: float = param(0.035, 'spread of a planar layer at most; a wider layer (a slope, a round bay, '
                                           'merged recesses) leaves only the points within inlier_sigmas of this to '
                                           'the plane, the rest are training points', unit='m',
                                    allowed=_closed(0.0, 1000.0))
    optimise: bool = param(True, 'fit b_1, b_2 by maximum marginal likelihood (else keep the initial value)')
    opt_points: int = param(150, 'size of the optimisation subset', allowed=_closed(10, 1_000_000))
    opt_patch: float = param(1.0, 'side of the square patches the subset is drawn from', unit='m',
                             allowed=_closed(1e-3, 1e4))
    max_block_points: int = param(64, 'at most this many training points per extended block (a random subset '
                                      'beyond); bounds the cost of a block', allowed=_closed(1, 100_000))
    planar_per_block: int = param(4, 'planar points (not selected by eqs. 7 and 8) added to the training points per '
                                     'block, so that the GP follows a wall that is not flat and the variance shrinks where it was '
                                     'observed; 0 reproduces the paper', allowed=_closed(0, 100_000))
    grid_resolution: float = param(0.1, 'cell of the raster the surface is predicted on', unit='m',
                                   allowed=_closed(1e-3, 100.0))


@dataclass(frozen=True)
class OutlierParams(Section):
    """The chi-squared outlier test (:mod:`~.pipeline.step5_outliers`)."""

    section: ClassVar[str] = 'outliers'

    alpha: float = param(0.01, 'significance level of the chi-squared test (1 degree of freedom)',
                         allowed=Interval(0.0, 1.0, 'neither'))
    iterations: int = param(1, 'train-test-remove rounds before the final training (paper: 1)',
                            allowed=_closed(0, 1000))


@dataclass(frozen=True)
class UpdateParams(Section):
    """How the map grows with new points (:mod:`~.mapping.facade_map`)."""

    section: ClassVar[str] = 'update'

    refit_growth: float = param(1.0, 'a façade is fitted whole again (GMM layers, length scales, every block) once '
                                     'its points have grown by this share since its last whole fit; below it only '
                                     'the blocks near new training points and the cells whose facet changed are '
                                     'recomputed', allowed=_positive(1e3))
    refit_max_points: int = param(20000, "... but only while the façade's last whole fit had fewer points than this: "
                                         'its layers and length scales are settled by then, and a whole fit costs '
                                         'all its points, so larger façades are updated block by block and fitted '
                                         'whole by flush() (the idle flush of live mapping, the end of a replay), '
                                         'which keeps the cost of an update following the new points',
                                  allowed=_closed(0, 1_000_000_000))
    extraction_growth: float = param(0.5, "RANSAC runs again on a building's unallocated points once they have "
                                          'grown by this share (and by at least min_facade_points) since the last '
                                          'run', allowed=_positive(1e3))
    normal_reach: float = param(1.0, "new points' normals use the building's points in the cells of this side "
                                     "that hold new points and in their neighbours (all within this distance of a "
                                     "new point)", unit='m', allowed=_positive(1e3))
    batch_points: int = param(100000, 'live mapping (add_points(..., defer=True)) holds new points back until at '
                                      'least this many have arrived, then maps them in one update: an update '
                                      'recomputes every block near a new training point, and the points of a few '
                                      'scans fall all over a façade, so small batches would solve the same blocks '
                                      'again and again (100 000: about 3 s of the street drive; 3x the throughput '
                                      'of 20 000 there)', allowed=_closed(1, 1_000_000_000))
    step_points: int = param(20000, "live mapping (node.batching latency) updates the façades in pieces between "
                                    "clouds: one building's stored points, this many a piece at most, so that a "
                                    'cloud waits for one piece at most before it is stored; a building waits until '
                                    'this many of its points or 100 clouds have come (an update costs nearly as '
                                    'much for a few points as for many)',
                             allowed=_closed(1, 1_000_000_000))
    store_voxel: float = param(0.1, "a building's points are stored at most store_per_voxel per cubic voxel of this "
                                    'side (map frame); a new point whose voxel is full is counted but not stored',
                               unit='m', allowed=_closed(1e-3, 100.0))
    store_per_voxel: int = param(4, '... this many points at most, the first to arrive (4 per 0.1 m voxel: a few '
                                    'per cell of the 0.1 m surface raster, about 2x the density of one drive of the '
                                    'street scene)', allowed=_closed(1, 1_000_000_000))
    store_spacing: float = param(0.0, '... and a new point is not stored (but counted) when a stored point lies '
                                      'within this distance of it; the noise estimate (gp.estimate_noise) then '
                                      'leaves out pairs closer than this on the plane (the rule kept them only '
                                      'where their depths differ). 0.03: a street driven again (its walls sampled '
                                      'near the same spots) adds next to nothing (five laps of the simulated street: '
                                      '+3 % stored a lap after lap 2, against +6-24 %), single drives map as before '
                                      'on the street, Zurich and the real sweeps, but the sparse small scene mapped '
                                      'in 1 s batches scores 8 % worse; 0: the voxel cap alone', unit='m',
                                 allowed=_closed(0.0, 1.0))
    registration_points: int = param(2000, 'each update compares up to this many of its points (a seeded draw) with '
                                           "the other scans' surface where both saw a wall, to learn how far scans "
                                           'lie off each other beyond their noise (pose and registration noise); '
                                           'the excess is added to the variance of every answer; 0: not learnt, '
                                           'no such term', allowed=_closed(0, 1_000_000))
    registration_max_std: float = param(0.3, '... the learnt scan-to-scan standard deviation is bounded by this',
                                        unit='m', allowed=_closed(0.0, 10.0))


@dataclass(frozen=True)
class MapParams:
    """All modelling parameters, by stage, and the seed of every random draw."""

    extraction: ExtractionParams = field(default_factory=ExtractionParams)
    layers: LayerParams = field(default_factory=LayerParams)
    gp: GPParams = field(default_factory=GPParams)
    outliers: OutlierParams = field(default_factory=OutlierParams)
    update: UpdateParams = field(default_factory=UpdateParams)
    seed: int = 0


# ----------------------------------------------------------------------------------------
# The rest of the parameter file: inputs, queries, the node
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class InputConfig(Section):
    """Which points of a classified cloud are mapped, and in which frame."""

    section: ClassVar[str] = 'input'

    class_field: str = param('class', 'point field holding the semantic class')
    building_classes: tuple[int, ...] = param(
        (1,), 'class values that mean "building"; a cloud without the class field is selected (see selection)')
    building_id_field: str = param('building_id', 'point field with a building id, used when present')
    frame_id: str = param('map', 'frame of the map: a cloud in another frame (its header.frame_id) is moved into it '
                                 'by the transform at its stamp (/tf, /tf_static, sensor_pose, node.odometry_topic; '
                                 'in bags the same topics)')
    time_field: str = param('time', 'per-point time field: a cloud not in the map frame has each point moved by the '
                                    "sensor's pose at its own time (motion compensation); float values are seconds, "
                                    'integer ones nanoseconds, absolute (UNIX) or from the header stamp as their size '
                                    'tells ("" or a cloud without the field: the header stamp for every point)')
    map_origin: tuple[float, float, float] = param(
        (0.0, 0.0, 0.0), 'georeference of the map frame (georeferenced = map + origin)', unit='m')
    max_distance: float = param(100_000.0, 'offline inputs (build, evaluate, benchmark): a point farther than this '
                                           'from the median point of its file in x, y or z is dropped and counted; a '
                                           'file with more than 1 % of such points (or NaN) is refused as corrupted '
                                           '(1e30 m, the wrong byte order)', unit='m', allowed=_closed(1.0, 1e9))


@dataclass(frozen=True)
class SelectionConfig(Section):
    """Building points of clouds without a class field (:mod:`~.selection.building_points`).

    Ground removal by Patchwork++, then the points on tall vertical planes: windows of
    ``(2 window_radius + 1)^2`` cells, each fitted with a vertical plane; a window is a wall
    if its band points are many, thin, long and tall enough; walls are windows linked into
    straight segments of at least ``min_segment_length``.
    """

    section: ClassVar[str] = 'selection'
    relations: ClassVar[tuple[Relation, ...]] = (
        Relation(('max_thickness', 'band'), lambda thick, band: thick <= band, 'max_thickness <= band'),
    )

    mode: str = param('auto', 'auto: select the building points of clouds without the class field '
                              '(input.class_field) and use the class of the others; on: select in every cloud, the '
                              'class field ignored; off: a cloud without the class field is all building',
                      allowed=Options(('auto', 'on', 'off')))
    min_ground_share: float = param(0.05, 'a cloud in which Patchwork++ finds less ground than this share is no raw '
                                          'scan but building points cut already: all of it is kept (0: select '
                                          'always)', allowed=_closed(0.0, 1.0))
    sensor_height: float = param(1.73, "Patchwork++'s sensor height: each scan is centred on its sensor (or the "
                                       "cloud's median) this high above the ground found around it", unit='m',
                                 allowed=_positive(100.0))
    max_range: float = param(80.0, 'Patchwork++ looks for ground this far from the scan centre; clouds without '
                                   'sensor origins wider than twice this are cut into tiles of this side', unit='m',
                             allowed=_closed(5.0, 10_000.0))
    scan_cell: float = param(20.0, 'points whose sensor origins lie in one square cell of this side are one scan for '
                                   'ground removal', unit='m', allowed=_positive(1e6))
    ground_cell: float = param(2.0, 'cell of the ground height map built from the ground points', unit='m',
                               allowed=_closed(0.1, 100.0))
    cell: float = param(0.5, 'cell of the plane windows', unit='m', allowed=_closed(0.05, 10.0))
    window_radius: int = param(1, 'a window is its centre cell and this many cells around it each way',
                               allowed=_closed(0, 10))
    band: float = param(0.4, "half-width of a window's vertical plane band: its points in the band are building "
                             'points if the window is a wall', unit='m', allowed=_positive(10.0))
    max_thickness: float = param(0.15, "RMS distance of a wall window's band points from its plane at most (tree "
                                       'crowns are thicker)', unit='m', allowed=_positive(10.0))
    min_share: float = param(0.5, "share of a wall window's points in its band at least",
                             allowed=_closed(0.0, 1.0))
    min_window_points: int = param(10, 'band points of a wall window at least', allowed=_closed(3, 1_000_000))
    min_window_length: float = param(1.0, "extent of a wall window's band points along its plane at least "
                                          '(sqrt(12) standard deviations; poles are narrower)', unit='m',
                                     allowed=_closed(0.0, 100.0))
    min_structure_height: float = param(3.0, "top of a wall window's band points above the ground at least (cars "
                                             'and hedges are lower), unless the window is cut off by the top of the '
                                             "sensor's vertical field of view (selection.fov_margin, "
                                             'selection.min_cut_distance)', unit='m', allowed=_closed(0.0, 1000.0))
    fov_margin: float = param(0.5, 'with sensor origins: a window with a band point within this angle below the top '
                                   "of the sensor's vertical field of view (the line, height over range, that the "
                                   'highest points seen all around follow) is cut off by it: seen as high as the '
                                   'sensor could see there, a wall however low (0: no such rule)', unit='degrees',
                              allowed=_closed(0.0, 10.0))
    min_cut_distance: float = param(7.0, 'a window cut off by the field of view is a wall only if its plane passes at '
                                         'least this far from the sensor: the side of a van parked along the road '
                                         'passes nearer, the front of a house behind its front yard farther', unit='m',
                                    allowed=_closed(0.0, 1000.0))
    min_extent: float = param(1.0, "vertical extent of a wall window's band points at least (cables, eaves); half of "
                                   'it for a window cut off by the field of view (hedges and cars hide its foot)',
                              unit='m', allowed=_closed(0.0, 1000.0))
    segment_angle: float = param(25.0, 'wall windows whose planes differ by less than this angle ...',
                                 unit='degrees', allowed=_closed(0.0, 90.0))
    link_distance: float = param(2.5, '... whose centre cells are at most this far apart and whose centroids lie in '
                                      "each other's band are one wall segment", unit='m', allowed=_closed(0.0, 100.0))
    min_segment_length: float = param(2.5, 'a wall segment shorter than this along its plane is no wall (tree '
                                           'crowns, signs, poles)', unit='m', allowed=_closed(0.0, 1000.0))
    warn_kept_share: float = param(0.05, 'warn when a cloud keeps less than this share of its non-ground points, '
                                         'naming the parameter that dropped most of them (0: never)',
                                   allowed=_closed(0.0, 1.0))


@dataclass(frozen=True)
class QueryConfig(Section):
    """Answers to point queries."""

    section: ClassVar[str] = 'query'

    resolution: float = param(0.1, 'default voxel side of the occupancy probability', unit='m',
                              allowed=_closed(1e-3, 10.0))
    occupancy: str = param('plsc', 'p_occupied by: plsc, the cumulative Gaussian whose two parameters the map '
                                   'learnt from its own scans (the paper; the fixed formula until it has learnt '
                                   'them); fixed, the formula Phi((r/2 - s) / sd)', allowed=Options(('plsc', 'fixed')))
    occupancy_event: str = param('surface', 'p_occupied is the probability that: surface, the surface crosses the '
                                            'voxel (the same in front of the surface and behind it); solid, the '
                                            'voxel lies at least partly behind the surface',
                                 allowed=Options(('surface', 'solid')))
    surface: str = param('local', 'the surface a query reads: local, a plane through the stored points near the '
                                  'point where they are dense, blended with the raster where they are not (beyond '
                                  'the paper); raster, the façade raster alone (the paper)',
                         allowed=Options(('local', 'raster')))
    local_neighbours: int = param(12, 'stored points a local plane is fitted to', allowed=Interval(3, 1000, 'both'))
    local_radius: float = param(0.5, 'the raster alone answers where the nearest stored point lies farther than '
                                     'this', unit='m', allowed=Interval(0.0, 100.0, 'right'))
    local_inner: float = param(0.2, 'the local plane alone answers where the nearest stored point lies within '
                                    'this; between it and local_radius the two blend (equal: a switch, not a blend)', unit='m',
                               allowed=_closed(0.0, 100.0))
    local_reach: float = param(1.5, 'where no façade raster answers a point (off every raster and band), the local '
                                    'plane of its nearest stored points still answers it if the nearest lies within '
                                    "this, its variance widened by the façade's prior variance (0 or at most "
                                    'local_radius: no answer beyond local_radius)', unit='m',
                               allowed=_closed(0.0, 100.0))

    relations: ClassVar[tuple[Relation, ...]] = (
        Relation(('local_inner', 'local_radius'), lambda inner, radius: inner <= radius, 'local_inner <= local_radius'),
    )


@dataclass(frozen=True)
class ModelConfig(Section):
    """The map as a whole."""

    section: ClassVar[str] = 'model'

    seed: int = param(0, 'seed of every random draw of the modelling (EM subsample, RANSAC, subsets)',
                      allowed=_closed(0, 2**31 - 1))


@dataclass(frozen=True)
class NodeConfig(Section):
    """The facade_mapper node's input handling (the command line ignores this section)."""

    section: ClassVar[str] = 'node'

    qos: str = param('sensor_data', 'QoS of the points subscription: sensor_data (best effort, as drivers publish) '
                                    'or reliable', allowed=Options(('sensor_data', 'reliable')))
    queue_size: int = param(1000, 'clouds waiting for the mapping worker at most; when full (or queue_points is '
                                  'reached) the oldest waiting cloud is dropped (and counted), so the map follows '
                                  'the newest data', allowed=_closed(1, 100000))
    queue_points: int = param(2_000_000, '... and building points waiting at most (memory: about 50 bytes each): '
                                         'the queue is bounded by what it holds, so small clouds at a high rate '
                                         '(the street drive at 8x: 80 clouds of 5,600 points a second) wait through '
                                         'an update instead of being dropped', allowed=_closed(1, 1_000_000_000))
    max_cloud_points: int = param(5_000_000, 'a cloud with more points is refused with a warning',
                                  allowed=_closed(1, 1_000_000_000))
    mapping_process: bool = param(True, 'update the map in a process of its own, so that queries and incoming '
                                        'clouds never wait for the update\'s Python code (the interpreter lock); '
                                        'false: in a thread of the node\'s process (one process, less memory)')
    mapping_nice: int = param(10, 'niceness added to the mapping process and the process that computes the '
                                  'published maps (node.mapping_process): queries and incoming clouds get the CPU '
                                  'first when both want it; 0: the same priority', allowed=_closed(0, 19))
    batching: str = param('latency', 'when the mapper maps the clouds it was given: latency (two tiers: each cloud '
                                     'is stored as soon as the mapper is free, with the clouds that came while it '
                                     'was busy, and is queryable from its stored points at once; its façades are '
                                     'updated after, in pieces of update.step_points points, whenever no cloud '
                                     'waits) or fixed (points are held back until '
                                     'update.batch_points have come: the map then depends only on the clouds, not '
                                     "on their timing, and equals the offline replay's bit for bit)",
                          allowed=Options(('latency', 'fixed')))
    idle_flush: float = param(2.0, 'when no cloud has come for this long, the points held back '
                                   '(update.batch_points) are mapped; after as long again the façades updated '
                                   'block by block are fitted whole (0: never)', unit='s',
                              allowed=_closed(0.0, 3600.0))
    local_refresh: float = param(5.0, 'while the map is being updated, queries read the stored points per point '
                                      '(query.surface local) from an earlier reading, rebuilt in the background '
                                      'once it is this old and the map has stored local_growth more points (its '
                                      'set-up costs about 1 s per million stored points, and takes the CPU from '
                                      'the queries); the façade rasters are always the newest; once the map '
                                      "settles, its own reading is built at once (in the background: /diagnostics "
                                      "says settled when queries read it) (0: always the newest, built by the "
                                      'query that needs it)',
                                 unit='s', allowed=_closed(0.0, 3600.0))
    local_growth: float = param(0.05, '... the share of stored points the map must have gained since the reading '
                                      'was built: the rebuilds then cost, over a whole drive, a bounded multiple of '
                                      'building the final reading once, not a share of the CPU for as long as the '
                                      'drive lasts (a smaller gain still rebuilds it after 6 x local_refresh)',
                                allowed=_closed(0.0, 10.0))
    use_tf: bool = param(True, 'read the transforms on /tf and /tf_static (tf2_msgs/TFMessage; static ones with '
                               'transient-local QoS, as robots publish them)')
    odometry_topic: str = param('', 'a nav_msgs/Odometry topic whose poses (header.frame_id -> child_frame_id) join '
                                    'the transforms ("" for none)')
    transform_timeout: float = param(0.5, "a cloud whose transform into the map frame at its stamp (and its points' "
                                          'times) is not known yet waits this long for it, its pose may come after '
                                          'it; then it is mapped with the nearest pose within pose_tolerance or '
                                          'rejected with the frames it needed', unit='s', allowed=_closed(0.0, 60.0))
    transform_queue: int = param(20, 'clouds waiting for their transform at most, in arrival order; when full the '
                                     'oldest is rejected', allowed=_closed(1, 10000))
    transform_cache: float = param(10.0, "seconds of transforms kept per frame (tf2's default: 10)", unit='s',
                                   allowed=_closed(0.1, 86400.0))
    pose_tolerance: float = param(0.05, 'a cloud whose stamp lies outside the span of its transforms by at most this '
                                        '(after waiting transform_timeout) is mapped with the nearest pose; 0: never '
                                        '(as tf2)', unit='s', allowed=_closed(0.0, 3600.0))
    pose_buffer: int = param(1000, 'transforms kept per frame at most (within transform_cache; with 1 only the newest, '
                                   'which answers its own stamp, or others within pose_tolerance)',
                             allowed=_closed(1, 1_000_000))
    log_period: float = param(5.0, 'an info line this often while clouds come: clouds in, mapped, waiting for a '
                                   'transform, dropped, rejected (why), share of the points the selection kept '
                                   '(0: never; every cloud is logged at debug level)', unit='s',
                              allowed=_closed(0.0, 3600.0))
    max_coordinate: float = param(100_000.0, 'a cloud with a point (after its pose), or a pose, farther than this '
                                             'from the map origin in x, y or z is refused: no street is that big, '
                                             'a corrupted cloud (wrong endianness, 1e30 m) is', unit='m',
                                  allowed=_closed(1.0, 1e9))


@dataclass(frozen=True)
class PublishConfig(Section):
    """What the node publishes, and how often."""

    section: ClassVar[str] = 'publish'
    relations: ClassVar[tuple[Relation, ...]] = (
        Relation(('grid_z_max', 'grid_z_min'), lambda hi, lo: hi > lo, 'grid_z_max > grid_z_min'),
    )

    period: float = param(5.0, 'the maps are published at most this often after an update (0: after every update)',
                          unit='s', allowed=_closed(0.0, 3600.0))
    surface_step: float = param(0.1, 'grid step of the mean-surface cloud (a multiple of gp.grid_resolution keeps '
                                     'the raster values)', unit='m', allowed=_closed(1e-3, 10.0))
    mesh_step: float = param(0.2, 'grid step of the surface mesh (RViz and the message size set the limit)',
                             unit='m', allowed=_closed(1e-3, 10.0))
    voxel_resolution: float = param(0.2, 'voxel side of the 3D occupancy map', unit='m', allowed=_closed(1e-3, 10.0))
    voxel_shell: float = param(0.3, 'the 3D occupancy map holds the voxels within this distance of a mean surface',
                               unit='m', allowed=_closed(0.0, 10.0))
    grid_resolution: float = param(0.1, 'cell of the 2D occupancy grid', unit='m', allowed=_closed(1e-3, 10.0))
    grid_z_min: float = param(0.5, "lower end of the 2D grid's height band, map frame", unit='m')
    grid_z_max: float = param(2.0, "upper end of the 2D grid's height band, map frame", unit='m')
    diagnostics_period: float = param(1.0, 'diagnostics are published this often', unit='s',
                                      allowed=_closed(0.01, 3600.0))
    diagnostics_window: float = param(60.0, 'the diagnostic level and last_error tell of the drops, rejections and '
                                            'failures of this recent window, not of the whole run', unit='s',
                                      allowed=_closed(1.0, 86400.0))
    grid_max_cells: int = param(4_000_000, 'the 2D occupancy grid (topic and get_map) has at most this many cells: '
                                           'a wider map is served at 2, 4, 8... times grid_resolution, with a '
                                           'warning', allowed=_closed(1, 1_000_000_000))


@dataclass(frozen=True)
class ServiceConfig(Section):
    """Limits of the node's services."""

    section: ClassVar[str] = 'service'

    max_query_points: int = param(1_000_000, 'a query with more points is refused (ask in batches)',
                                  allowed=_closed(1, 100_000_000))


@dataclass(frozen=True)
class PersistenceConfig(Section):
    """Where the node keeps its map."""

    section: ClassVar[str] = 'persistence'

    map_path: str = param('', 'map file loaded at start when it exists, and the default of the save and load '
                              'services ("" for none)')
    autosave_period: float = param(0.0, 'save the map to map_path this often when it changed (0: never)', unit='s',
                                   allowed=_closed(0.0, 1e6))
    map_dir: str = param('', 'the map folder: the save_map and load_map services resolve their path in it and '
                             'refuse any that leads out of it (absolute, "..", a symbolic link out); "": the folder '
                             'of map_path, or "maps" under the working directory when map_path is empty')
    allow_any_path: bool = param(False, 'let save_map and load_map use any path the node\'s user may write or '
                                        'read: any participant of the DDS domain can then overwrite that user\'s '
                                        'files with a map (ROS 2 without SROS2 authenticates nobody)')
    max_load_mb: float = param(4096.0, 'load_map refuses a map file, or a tiled map\'s manifest, larger than this '
                                       '(on disk or unpacked) before reading it', unit='MB',
                               allowed=_closed(0.001, 1e7))


@dataclass(frozen=True)
class TilesConfig(Section):
    """City-scale maps (issue 29): the tiled map file (a manifest and one map file per tile,
    :mod:`~.tiling`), how it is built and how much of it a reader keeps loaded."""

    section: ClassVar[str] = 'tiles'

    side: float = param(50.0, "side of a map tile (a square of the map frame's x, y grid from the map frame's "
                              "origin); a building belongs to the tile of the centre of its points' bounding box "
                              "at its first build, whole, so a tile's content may reach past its square",
                        unit='m', allowed=_closed(1.0, 100_000.0))
    cache_mb: float = param(2048.0, 'a tiled map keeps at most this much of its tiles (with their local reading) and '
                                    'of its views loaded (views first out, then the least recently used tiles; one tile '
                                    'and one view are always kept, whatever their size)', unit='MB',
                            allowed=_closed(1.0, 10_000_000.0))
    view_tiles: int = param(3, 'queries are answered from views of this many tiles a side (the façades and stored '
                               'points near a square of tiles, built once from the loaded tiles and kept in the cache): '
                               'a batch whose points fit in one view is one call of the compiled kernels; larger views '
                               'take longer to build and more memory', allowed=_closed(1, 64))
    radius: float = param(150.0, 'the node keeps the tiles within this distance of its latest pose loaded, and '
                                 'list_tiles answers within it by default', unit='m', allowed=_closed(0.0, 100_000.0))
    follow_period: float = param(1.0, 'the node looks at its pose and loads the tiles near it this often (0: it '
                                      'does not follow its pose; tiles load when a query needs them)', unit='s',
                                 allowed=_closed(0.0, 3600.0))
    follow_frame: str = param('', 'the frame whose map-frame position the node follows, looked up in its transform '
                                  'buffer (/tf, sensor_pose, odometry), e.g. base_link; empty: the child frame of the '
                                  'latest sensor_pose or odometry message, else the frame of the latest cloud')


@dataclass(frozen=True)
class LocaliseParams(Section):
    """The localiser against the map (:mod:`~.localisation`, ``uncertain-facade-map localise``): a MAP estimate of
    the sensor's 6-DoF pose from a scan, a prior pose and the map's answers (issue 28)."""

    section: ClassVar[str] = 'localise'

    sensor_noise: float = param(0.03, "standard deviation of the scan's own points along the surface normal "
                                      '(range noise, motion, timing); added to the variance of every answer',
                                unit='m', allowed=_closed(1e-4, 10.0))
    kernel: str = param('geman', 'robust kernel of the point-to-surface residuals, in units of their sigma: geman '
                                 '(Geman-McClure, weight 1/(1 + (u/k)^2)^2: points far off the surface, parked cars, '
                                 'trees, weigh nothing, their pull falls as 1/u^3), cauchy (weight 1/(1 + (u/k)^2); '
                                 'their pull falls only as 1/u, enough for many of them to bias the pose by a '
                                 'centimetre), huber, or none (least squares)',
                         allowed=Options(('geman', 'cauchy', 'huber', 'none')))
    kernel_scale: float = param(3.0, "the kernel's scale k in sigmas (huber is quadratic up to it)",
                                allowed=_closed(0.1, 1000.0))
    anneal_start: float = param(0.5, "the first round's kernel scale is at least this (k sigma_i grown to "
                                     'k sqrt(sigma_i^2 + tau^2), tau this), shrinking 8x a round and ending below '
                                     '1 cm: the first rounds, still up to half a search step off, weigh every '
                                     'answer; the last ones leave outliers out; converged only then (0: off)',
                                unit='m', allowed=_closed(0.0, 100.0))
    voxel: float = param(0.2, 'the scan is thinned to one point per cubic voxel of this side (a seeded draw), so '
                              'that dense near ranges do not outweigh the far walls; 0: no thinning', unit='m',
                         allowed=_closed(0.0, 100.0))
    max_points: int = param(1500, '... then to at most this many points, a seeded draw', allowed=_closed(10, 100_000_000))
    batch_points: int = param(20000, 'points per call of the map query at most (ask in batches)',
                              allowed=_closed(1, 100_000_000))
    max_queries: int = param(6, 'rounds at most: each queries the map at the current pose, then solves on the '
                                'linearised surfaces', allowed=_closed(1, 1000))
    max_iterations: int = param(30, 'Levenberg-Marquardt iterations per round at most', allowed=_closed(1, 100_000))
    translation_tolerance: float = param(0.002, 'converged when a round moves the pose less than this ...', unit='m',
                                         allowed=_closed(0.0, 100.0))
    rotation_tolerance: float = param(0.01, '... and turns it less than this', unit='degrees',
                                      allowed=_closed(0.0, 180.0))
    mahalanobis_tolerance: float = param(0.2, '... or moves it less than this many of its own standard deviations (the '
                                              "Mahalanobis length of the move under the round's Hessian): directions "
                                              'the map hardly sees (height, along a straight street) may wander more '
                                              'than the tolerances above while staying well inside their uncertainty',
                                         allowed=_closed(0.0, 100.0))
    search_radius: float = param(3.0, 'before the first round, horizontal offsets of the prior up to this far (and '
                                      'its yaw turned by search_yaw) are scored with a few points each and the best '
                                      'starts the solve: the map answers only within its façade bands (about 1 m '
                                      'behind and 2 m in front of a wall), so a prior 3 m off may see no wall at '
                                      'all; 0: start from the prior', unit='m', allowed=_closed(0.0, 1000.0))
    search_step: float = param(1.0, 'grid step of the horizontal offsets', unit='m', allowed=_closed(0.01, 1000.0))
    search_yaw: float = param(5.0, '... and yaws of the prior turned by up to this much either way (0: the prior yaw '
                                   'only; a turn moves a wall 30 m away by 0.5 m per degree)', unit='degrees',
                              allowed=_closed(0.0, 180.0))
    search_yaw_step: float = param(2.5, 'step of those yaws', unit='degrees', allowed=_closed(0.01, 180.0))
    search_points: int = param(100, 'scan points scored per offset', allowed=_closed(10, 1_000_000))
    correlation_length: float = param(2.0, "the map's surface errors are alike within this distance (one error of the "
                                           'mean surface seen by many points): the surface variance of each point '
                                           '(not the noise about the surface) is multiplied by the number of used '
                                           'points of its façade within a cube of this side, so a patch counts once, '
                                           'not once per point; 2 m: the wall surface\'s node spacing '
                                           '(layers.relief_spacing), over which its errors are alike; 0: points '
                                           'independent (the plain Gauss-Newton covariance, overconfident)',
                                      unit='m', allowed=_closed(0.0, 1000.0))
    prior_position_std: tuple[float, float, float] = param(
        (2.0, 2.0, 2.0), 'the command line\'s default standard deviation of the prior position (x, y, z), a GNSS '
                         'fix in a street canyon', unit='m', allowed=Interval(0.0, 1e6, 'neither'))
    prior_rotation_std: tuple[float, float, float] = param(
        (3.0, 3.0, 3.0), "the command line's default standard deviation of the prior rotation about the map's X, Y, "
                         'Z axes (roll, pitch, yaw)', unit='degrees', allowed=Interval(0.0, 180.0, 'neither'))
    facade_offsets: bool = param(True, "each façade's mean surface may be off as a whole by its answered surface "
                                       "variance (the median over its used points): that shared offset is "
                                       'marginalised out of the covariance (issue 40), so that many points on one '
                                       'wall pin the pose along its normal no better than the wall is known')
    alternatives: int = param(1, 'after the solve, this many of the best-scored starts of the search at least a '
                                 'search_step from every solution so far are solved too (issue 40): a scan that '
                                 'another solution explains nearly as well is ambiguous (a slip along a street); '
                                 '0: none', allowed=_closed(0, 1000))
    ambiguity_cost: float = param(10.0, 'a solution whose robust cost over every thinned point (an unanswered point '
                                        "costing an outlier's) exceeds the best one's by less than this is kept as "
                                        'an alternative: the answer is "ambiguous", not converged, and its '
                                        'covariance spans the alternative (a negative log-likelihood ratio: 10 is '
                                        'odds of about 20,000 to 1 for independent points)',
                                  allowed=_closed(0.0, 1e9))
    max_residual_ratio: float = param(2.0, "the used points' weighted mean of (residual / sigma)^2 above this marks "
                                           'the answer "inconsistent" (not converged); above 1 the covariance is '
                                           'scaled by it (a scan distorted by motion, a map off by more than its '
                                           'variance)', allowed=_closed(1.0, 1e9))
    seed: int = param(0, 'seed of the thinning and the draws of the search', allowed=_closed(0, 2**31 - 1))


@dataclass(frozen=True)
class LocalizerConfig(Section):
    """The facade_localizer node: where its scans, priors and map come from."""

    section: ClassVar[str] = 'localizer'

    map_frame: str = param('map', "the map's frame: priors must be in it, estimates are published in it")
    query_service: str = param('query_points', "the mapper's query service the node asks the map through")
    query_timeout: float = param(5.0, 'a query the service has not answered in this time fails the scan', unit='s',
                                 allowed=_positive(3600.0))
    prior_max_age: float = param(0.5, 'a prior pose further than this from a scan\'s stamp is not used for it (the '
                                      'last estimate moved on by the last motion is)', unit='s',
                                 allowed=_closed(0.0, 3600.0))
    motion_std_position: float = param(0.5, "growth of the moved-on estimate's position standard deviation in "
                                             'each direction, per square root of a second (its variance grows '
                                             'by this squared per second)', unit='m', allowed=_closed(0.0, 100.0))
    motion_std_rotation: float = param(2.0, '... and of its rotation', unit='degrees', allowed=_closed(0.0, 180.0))
    publish_tf: bool = param(True, 'publish each estimate on /tf as the transform map_frame -> tf_child')
    tf_child: str = param('', 'the child frame of that transform ("": the scan\'s own frame)')


@dataclass(frozen=True)
class Config:
    """All parameters of the parameter file, by section (the modelling stages, then the rest)."""

    input: InputConfig = field(default_factory=InputConfig)
    selection: SelectionConfig = field(default_factory=SelectionConfig)
    extraction: ExtractionParams = field(default_factory=ExtractionParams)
    layers: LayerParams = field(default_factory=LayerParams)
    gp: GPParams = field(default_factory=GPParams)
    outliers: OutlierParams = field(default_factory=OutlierParams)
    update: UpdateParams = field(default_factory=UpdateParams)
    query: QueryConfig = field(default_factory=QueryConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    node: NodeConfig = field(default_factory=NodeConfig)
    publish: PublishConfig = field(default_factory=PublishConfig)
    service: ServiceConfig = field(default_factory=ServiceConfig)
    persistence: PersistenceConfig = field(default_factory=PersistenceConfig)
    tiles: TilesConfig = field(default_factory=TilesConfig)
    localise: LocaliseParams = field(default_factory=LocaliseParams)
    localizer: LocalizerConfig = field(default_factory=LocalizerConfig)


#: The sections the localiser node reads (its parameter file's); the mapper reads the others.
LOCALIZER_SECTIONS = ('localise', 'localizer')


def node_sections(node_name: str = NODE_NAME) -> tuple[str, ...]:
    """The sections of :class:`Config` a node declares and its parameter file holds."""
    names = tuple(name for name, _ in _sections())
    if node_name == LOCALIZER_NAME:
        return LOCALIZER_SECTIONS
    return tuple(n for n in names if n not in LOCALIZER_SECTIONS)


def map_params(config: Config) -> MapParams:
    """The modelling parameters of a configuration."""
    return MapParams(seed=config.model.seed, **{name: getattr(config, name) for name in _map_sections()})


# ----------------------------------------------------------------------------------------
# Derived views: the flat list of parameters, and configurations from flat names
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ParameterInfo:
    """One parameter as the node and the parameter file see it.

    Attributes:
        name: dotted name, ``section.parameter``.
        value: its value (tuples for lists).
        type: its Python type (for a tuple, the items' type).
        spec: its declaration.
        relations: the conditions of its section it takes part in.
    """

    name: str
    value: Any
    type: Any
    spec: Param
    relations: tuple[Relation, ...] = ()

    @property
    def is_list(self) -> bool:
        """True for a list parameter."""
        return isinstance(self.value, tuple)

    def closed_range(self) -> tuple[float, float] | None:
        """The closed range a ROS descriptor advertises, or None (no interval, or a list)."""
        if not isinstance(self.spec.allowed, Interval) or self.is_list or self.type not in (int, float):
            return None
        return self.spec.allowed.closed_range(self.type)


def _sections(cls: type = Config) -> Iterator[tuple[str, type]]:
    hints = _hints(cls)
    for f in dataclasses.fields(cls):
        yield f.name, hints[f.name]


def _item_type(typ: Any) -> Any:
    return get_args(typ)[0] if get_origin(typ) is tuple else typ


def parameters(config: Config | None = None, sections: tuple[str, ...] | None = None) -> Iterator[ParameterInfo]:
    """Every parameter of the parameter file, in file order, with its value in ``config``.

    Args:
        config: the values to list; the defaults if None.
        sections: only these sections (:func:`node_sections`); None for all.
    """
    config = config or Config()
    for section, cls in _sections():
        if sections is not None and section not in sections:
            continue
        sub = getattr(config, section)
        hints = _hints(cls)
        for f in dataclasses.fields(cls):
            related = tuple(r for r in cls.relations if f.name in r.names)
            yield ParameterInfo(f'{section}.{f.name}', getattr(sub, f.name), _item_type(hints[f.name]),
                                f.metadata['param'], related)


def _section_from(cls: type, values: dict[str, Any], where: str) -> Any:
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise InputError(f'unknown parameter {cls.section}.{unknown[0]}{where} '
                         f'(known in {cls.section}: {", ".join(sorted(names))})')
    return cls(**values)


def config_from_parameters(params: dict[str, Any]) -> Config:
    """A :class:`Config` from flat dotted parameter names (as rclpy and the parameter file give them).

    Args:
        params: ``{'section.name': value}``; missing names keep their defaults.

    Raises:
        InputError: an unknown name, or a value of the wrong type, outside its allowed values
            or breaking a relation; the message names the parameter.
    """
    sections = dict(_sections())
    values: dict[str, dict[str, Any]] = {}
    for name, value in params.items():
        section, _, key = name.partition('.')
        if section not in sections or not key:
            raise InputError(f'unknown parameter {name} (sections: {", ".join(sections)})')
        values.setdefault(section, {})[key] = value
    return Config(**{s: _section_from(cls, values.get(s, {}), '') for s, cls in sections.items()})


# ----------------------------------------------------------------------------------------
# The map file's parameter record
# ----------------------------------------------------------------------------------------
def _map_sections() -> dict[str, type]:
    """The sections of :class:`MapParams` (all its fields but the seed), by name."""
    return {name: cls for name, cls in _sections(MapParams) if name != 'seed'}


def map_params_record(params: MapParams) -> dict[str, Any]:
    """The modelling parameters as a JSON-ready record: ``{section: {name: value}, 'seed': seed}``."""
    record: dict[str, Any] = {}
    for section, cls in _map_sections().items():
        sub = getattr(params, section)
        record[section] = {f.name: (list(v) if isinstance(v := getattr(sub, f.name), tuple) else v)
                           for f in dataclasses.fields(cls)}
    record['seed'] = params.seed
    return record


def map_params_from_record(record: dict[str, Any]) -> MapParams:
    """The modelling parameters of a map file's record (see :func:`map_params_record`).

    Parameters a record lacks (an older file) take their defaults.

    Raises:
        InputError: an unknown section or parameter, or a value that is not allowed; the
            message names it.
    """
    if not isinstance(record, dict):
        raise InputError(f'parameters: expected a record, got {type(record).__name__}')
    sections_of = _map_sections()
    unknown = sorted(set(record) - set(sections_of) - {'seed'})
    if unknown:
        raise InputError(f'unknown parameter section {unknown[0]}')
    sections = {}
    for section, cls in sections_of.items():
        values = record.get(section, {})
        if not isinstance(values, dict):
            raise InputError(f'parameters: section {section} is not a record')
        sections[section] = _section_from(cls, values, ' in the map file')
    return MapParams(seed=ModelConfig(seed=record.get('seed', 0)).seed, **sections)
