"""The one configuration of node and command line: a ROS 2 parameter file.

The file has the form ROS 2 nodes read with ``--params-file``::

    facade_mapper:
      ros__parameters:
        input:
          class_field: class
          ...

Nested keys are parameter names joined by dots (``input.class_field``), as rclpy
flattens them. :func:`load_config` reads such a file into :class:`Config`, a tree of
frozen dataclasses; unknown names, wrong types and out-of-range values raise
:class:`~uncertain_facade_map.errors.InputError` naming the parameter. The node declares
every parameter from the same dataclasses (:func:`parameter_items`), so both read one
source of truth.
"""

from __future__ import annotations

import dataclasses
import inspect
import re
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Iterator, get_args, get_origin, get_type_hints

import numpy as np
import yaml

from .errors import InputError
from .pipeline.step1_facades import ExtractionParams
from .pipeline.step2_layers import LayerParams
from .pipeline.step4_gp_blocks import GPParams
from .pipeline.step5_outliers import OutlierParams


@dataclass(frozen=True)
class UpdateParams:
    """How the map grows with new points (incremental mapping).

    Attributes:
        refit_growth: a façade is fitted whole again (GMM layers, length scales, every
            block) once its points have grown by this share since its last whole fit;
            below it only the blocks near new training points and the cells whose facet
            changed are recomputed.
        extraction_growth: RANSAC runs again on a building's unallocated points once
            they have grown by this share (and by at least ``min_facade_points``) since
            the last run.
        normal_reach: new points' normals use the building's points within this distance
            of the new points' bounding box, metres.
        batch_points: live mapping (``add_points(..., defer=True)``) holds new points back
            until at least this many have arrived, then maps them in one update: an update
            recomputes every block near a new training point, and the points of a few
            scans fall all over a façade, so small batches would solve the same blocks
            again and again (100 000: about 3 s of the street drive; 3x the throughput of
            20 000 there).

    Raises:
        InputError: a parameter is out of range.
    """

    refit_growth: float = 1.0
    extraction_growth: float = 0.5
    normal_reach: float = 1.0
    batch_points: int = 100000

    def __post_init__(self) -> None:
        for name in ('refit_growth', 'extraction_growth', 'normal_reach'):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise InputError(f'update.{name} must be a positive number, got {value!r}')
        if isinstance(self.batch_points, bool) or not isinstance(self.batch_points, int) or self.batch_points < 1:
            raise InputError(f'update.batch_points must be an integer >= 1, got {self.batch_points!r}')


@dataclass(frozen=True)
class MapParams:
    """All modelling parameters, by stage."""

    extraction: ExtractionParams = field(default_factory=ExtractionParams)
    layers: LayerParams = field(default_factory=LayerParams)
    gp: GPParams = field(default_factory=GPParams)
    outliers: OutlierParams = field(default_factory=OutlierParams)
    update: UpdateParams = field(default_factory=UpdateParams)
    seed: int = 0


NODE_NAME = 'facade_mapper'
#: The default parameter file shipped in ``config/``.
DEFAULT_CONFIG = Path(__file__).resolve().parent.parent / 'config' / f'{NODE_NAME}.yaml'


def _meta(description: str, lo: float | None = None, hi: float | None = None) -> dict:
    return {'description': description, 'range': (lo, hi)}


@dataclass(frozen=True)
class InputConfig:
    """Which points of a classified cloud are mapped, and in which frame."""

    class_field: str = field(default='class', metadata=_meta('point field holding the semantic class'))
    building_classes: tuple[int, ...] = field(
        default=(1,), metadata=_meta('class values that mean "building"; a cloud without the class field is all building'))
    building_id_field: str = field(default='building_id', metadata=_meta('point field with a building id, used when present'))
    frame_id: str = field(default='map', metadata=_meta('frame of the map; clouds must be in it'))
    map_origin: tuple[float, float, float] = field(
        default=(0.0, 0.0, 0.0), metadata=_meta('georeference of the map frame, metres (georeferenced = map + origin)'))


@dataclass(frozen=True)
class QueryConfig:
    """Answers to point queries.

    Attributes:
        resolution: default voxel side of the occupancy probability, metres.
    """

    resolution: float = field(default=0.1, metadata=_meta('default voxel side of the occupancy probability, metres',
                                                           1e-3, 10.0))


@dataclass(frozen=True)
class ModelConfig:
    """The map as a whole.

    Attributes:
        seed: seed of every random draw of the modelling (EM subsample, RANSAC, subsets).
    """

    seed: int = 0


@dataclass(frozen=True)
class NodeConfig:
    """The facade_mapper node's input handling (the command line ignores this section)."""

    qos: str = field(default='sensor_data', metadata=_meta(
        'QoS of the points subscription: sensor_data (best effort, as drivers publish) or reliable'))
    queue_size: int = field(default=20, metadata=_meta(
        'clouds waiting for the mapping worker at most; when full the oldest waiting cloud is dropped '
        '(and counted), so the map follows the newest data', 1, 10000))
    max_cloud_points: int = field(default=5_000_000, metadata=_meta(
        'a cloud with more points is refused with a warning', 1, 1_000_000_000))
    idle_flush: float = field(default=2.0, metadata=_meta(
        'when no cloud has come for this long, the points held back (update.batch_points) are mapped and the '
        'façades updated block by block are fitted whole, seconds (0: never)', 0.0, 3600.0))
    pose_tolerance: float = field(default=0.05, metadata=_meta(
        'a cloud in another frame is mapped with the sensor pose nearest its stamp if closer than this, seconds',
        0.0, 3600.0))
    pose_buffer: int = field(default=1000, metadata=_meta('sensor poses kept for clouds in another frame', 1, 1_000_000))


@dataclass(frozen=True)
class PublishConfig:
    """What the node publishes, and how often."""

    period: float = field(default=5.0, metadata=_meta(
        'the maps are published at most this often after an update, seconds (0: after every update)', 0.0, 3600.0))
    surface_step: float = field(default=0.1, metadata=_meta(
        'grid step of the mean-surface cloud, metres (a multiple of gp.grid_resolution keeps the raster values)',
        1e-3, 10.0))
    mesh_step: float = field(default=0.2, metadata=_meta(
        'grid step of the surface mesh, metres (RViz and the message size set the limit)', 1e-3, 10.0))
    voxel_resolution: float = field(default=0.2, metadata=_meta('voxel side of the 3D occupancy map, metres',
                                                                1e-3, 10.0))
    voxel_shell: float = field(default=0.3, metadata=_meta(
        'the 3D occupancy map holds the voxels within this distance of a mean surface, metres', 0.0, 10.0))
    grid_resolution: float = field(default=0.1, metadata=_meta('cell of the 2D occupancy grid, metres', 1e-3, 10.0))
    grid_z_min: float = field(default=0.5, metadata=_meta('lower end of the 2D grid\'s height band, metres, map frame'))
    grid_z_max: float = field(default=2.0, metadata=_meta('upper end of the 2D grid\'s height band, metres, map frame'))
    diagnostics_period: float = field(default=1.0, metadata=_meta('diagnostics are published this often, seconds',
                                                                  0.01, 3600.0))


@dataclass(frozen=True)
class ServiceConfig:
    """Limits of the node's services."""

    max_query_points: int = field(default=1_000_000, metadata=_meta(
        'a query with more points is refused (ask in batches)', 1, 100_000_000))


@dataclass(frozen=True)
class PersistenceConfig:
    """Where the node keeps its map."""

    map_path: str = field(default='', metadata=_meta(
        'map file loaded at start when it exists, and the default of the save and load services ("" for none)'))
    autosave_period: float = field(default=0.0, metadata=_meta(
        'save the map to map_path this often when it changed, seconds (0: never)', 0.0, 1e6))


@dataclass(frozen=True)
class Config:
    """All parameters, by section (one section per pipeline stage, then the node's)."""

    input: InputConfig = field(default_factory=InputConfig)
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

    def __post_init__(self) -> None:
        if self.node.qos not in ('sensor_data', 'reliable'):
            raise InputError(f'parameter node.qos: expected sensor_data or reliable, got {self.node.qos!r}')
        if self.publish.grid_z_max <= self.publish.grid_z_min:
            raise InputError(f'parameter publish.grid_z_max ({self.publish.grid_z_max}) must exceed '
                             f'publish.grid_z_min ({self.publish.grid_z_min})')


def map_params(config: Config) -> MapParams:
    """The modelling parameters of a config."""
    return MapParams(extraction=config.extraction, layers=config.layers, gp=config.gp, outliers=config.outliers,
                     update=config.update, seed=config.model.seed)


#: Ranges of the modelling parameters (their dataclasses check finer conditions); the node
#: declares them in its parameter descriptors.
RANGES: dict[str, tuple[float, float]] = {
    'extraction.ransac_threshold': (1e-4, 10.0), 'extraction.ransac_iterations': (1, 1_000_000),
    'extraction.ransac_sample': (3, 1_000_000_000), 'extraction.min_facade_points': (3, 1_000_000_000),
    'extraction.max_facades': (1, 10_000), 'extraction.max_tilt_deg': (0.0, 90.0),
    'extraction.merge_angle_deg': (0.0, 90.0), 'extraction.merge_offset': (0.0, 1000.0),
    'extraction.band_front': (0.0, 1000.0), 'extraction.band_back': (0.0, 1000.0),
    'extraction.extent_margin': (0.0, 1000.0), 'extraction.normal_neighbours': (3, 10_000),
    'extraction.building_cell': (1e-3, 1000.0),
    'layers.histogram_bin': (1e-5, 10.0), 'layers.min_peak_share': (0.0, 1.0), 'layers.max_layers': (1, 1000),
    'layers.gmm_sample': (2, 1_000_000_000), 'layers.facet_cell': (1e-3, 100.0), 'layers.fill_distance': (0.0, 100.0),
    'layers.min_facet_cells': (1, 1_000_000),
    'gp.noise_sigma': (1e-6, 100.0), 'gp.initial_lengthscale2': (1e-8, 1e4), 'gp.lengthscale2_min': (1e-8, 1e4),
    'gp.lengthscale2_max': (1e-8, 1e4), 'gp.c_min': (1e-300, 1.0), 'gp.alpha_z_deg': (0.0, 90.0),
    'gp.inlier_sigmas': (0.0, 1000.0), 'gp.max_planar_sigma': (0.0, 1000.0), 'gp.opt_points': (1, 1_000_000),
    'gp.opt_patch': (1e-3, 1e4), 'gp.max_block_points': (1, 100_000), 'gp.planar_per_block': (0, 100_000),
    'gp.grid_resolution': (1e-3, 100.0),
    'outliers.alpha': (0.0, 1.0), 'outliers.iterations': (0, 1000),
    'update.refit_growth': (1e-3, 1e3), 'update.extraction_growth': (1e-3, 1e3), 'update.normal_reach': (0.0, 1e3),
    'update.batch_points': (1, 1_000_000_000),
    'model.seed': (0, 2**31 - 1),
}


@lru_cache(maxsize=None)
def _attribute_docs(cls: type) -> dict[str, str]:
    """Descriptions of a dataclass's fields from the ``Attributes:`` section of its docstring."""
    doc = inspect.getdoc(cls) or ''
    match = re.search(r'^Attributes:\n(.*?)(?:\n\S|\Z)', doc, flags=re.S | re.M)
    out: dict[str, str] = {}
    if match:
        name = None
        for line in match.group(1).splitlines():
            head = re.match(r'^    (\w+)(?: \(.*?\))?: (.*)$', line)
            if head:
                name = head.group(1)
                out[name] = head.group(2).strip()
            elif name and line.strip():
                out[name] += ' ' + line.strip()
    return out


def _sections(cls: type = Config) -> Iterator[tuple[str, type]]:
    hints = get_type_hints(cls)
    for f in dataclasses.fields(cls):
        yield f.name, hints[f.name]


def parameter_items(config: Config | None = None) -> Iterator[tuple[str, Any, str, tuple]]:
    """Every parameter as (dotted name, value, description, (min, max)).

    Args:
        config: values to list; the defaults if None.
    """
    config = config or Config()
    for section, cls in _sections():
        sub = getattr(config, section)
        docs = _attribute_docs(cls)
        for f in dataclasses.fields(cls):
            name = f'{section}.{f.name}'
            yield name, getattr(sub, f.name), f.metadata.get('description', docs.get(f.name, '')), \
                f.metadata.get('range', RANGES.get(name, (None, None)))


def _coerce(name: str, value: Any, typ: Any, bounds: tuple) -> Any:
    origin = get_origin(typ)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise InputError(f'parameter {name}: expected a list, got {value!r}')
        args = get_args(typ)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(name, v, args[0], bounds) for v in value)
        if len(value) != len(args):
            raise InputError(f'parameter {name}: expected {len(args)} values, got {len(value)}')
        return tuple(_coerce(name, v, a, bounds) for v, a in zip(value, args))
    if typ is bool:
        if not isinstance(value, bool):
            raise InputError(f'parameter {name}: expected true or false, got {value!r}')
        return value
    if typ is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise InputError(f'parameter {name}: expected an integer, got {value!r}')
    elif typ is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InputError(f'parameter {name}: expected a number, got {value!r}')
        value = float(value)
        if value != value or value in (float('inf'), float('-inf')):
            raise InputError(f'parameter {name}: must be finite, got {value!r}')
    elif typ is str:
        if not isinstance(value, str):
            raise InputError(f'parameter {name}: expected a string, got {value!r}')
        return value
    lo, hi = bounds
    if lo is not None and value < lo or hi is not None and value > hi:
        raise InputError(f'parameter {name}: {value!r} is outside [{lo}, {hi}]')
    return value


def config_from_parameters(params: dict[str, Any]) -> Config:
    """Build a :class:`Config` from flat dotted parameter names (as rclpy gives them).

    Args:
        params: ``{'section.name': value}``; missing names keep their defaults.

    Raises:
        InputError: an unknown name or a value of the wrong type or range.
    """
    known = {name: (section, f) for section, cls in _sections() for f in dataclasses.fields(cls)
             for name in [f'{section}.{f.name}']}
    unknown = sorted(set(params) - set(known))
    if unknown:
        raise InputError(f'unknown parameter {unknown[0]} (known: {", ".join(sorted(known))})')
    values: dict[str, dict[str, Any]] = {}
    for name, value in params.items():
        section, f = known[name]
        cls = dict(_sections())[section]
        typ = get_type_hints(cls)[f.name]
        values.setdefault(section, {})[f.name] = _coerce(name, value, typ,
                                                         f.metadata.get('range', RANGES.get(name, (None, None))))
    return Config(**{section: cls(**values.get(section, {})) for section, cls in _sections()})  # validates ranges


def _flatten(tree: dict, prefix: str = '') -> dict[str, Any]:
    flat: dict[str, Any] = {}
    for key, value in tree.items():
        name = f'{prefix}{key}'
        if isinstance(value, dict):
            flat.update(_flatten(value, f'{name}.'))
        else:
            flat[name] = value
    return flat


def load_config(path: str | Path | None = None, node_name: str = NODE_NAME) -> Config:
    """Read a ROS 2 parameter file into a :class:`Config`.

    Args:
        path: YAML file; the shipped ``config/facade_mapper.yaml`` if None.
        node_name: the node's section; ``/**`` (all nodes) is read too.

    Returns:
        The configuration (defaults for parameters the file does not set).

    Raises:
        InputError: missing file, invalid YAML, no section for the node, unknown or invalid parameters.
    """
    path = Path(path) if path is not None else DEFAULT_CONFIG
    try:
        tree = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise InputError(f'no such file: {path}') from None
    except yaml.YAMLError as exc:
        raise InputError(f'{path}: invalid YAML ({str(exc).splitlines()[0]})') from None
    if not isinstance(tree, dict):
        raise InputError(f'{path}: not a ROS 2 parameter file (expected "{node_name}: ros__parameters:")')
    params: dict[str, Any] = {}
    found = False
    for key in ('/**', node_name, f'/{node_name}'):
        node = tree.get(key)
        if isinstance(node, dict) and isinstance(node.get('ros__parameters'), dict):
            params.update(_flatten(node['ros__parameters']))
            found = True
    if not found:
        raise InputError(f'{path}: no "{node_name}: ros__parameters:" section')
    try:
        return config_from_parameters(params)
    except InputError as exc:
        raise InputError(f'{path}: {exc}') from None


def dump_config(config: Config, node_name: str = NODE_NAME, comments: bool = False) -> str:
    """The configuration as a ROS 2 parameter file (YAML text), optionally with descriptions."""
    lines = [f'{node_name}:', '  ros__parameters:']
    section = None
    for name, value, description, _ in parameter_items(config):
        sec, key = name.split('.', 1)
        if sec != section:
            lines.append(f'    {sec}:')
            section = sec
        text = yaml.safe_dump(list(value) if isinstance(value, tuple) else value, default_flow_style=True,
                              width=1000).strip()
        if text.endswith('\n...'):
            text = text[:-4].strip()
        text = text.removesuffix('...').strip()
        line = f'      {key}: {text}'
        if comments and description:
            line = f'{line:46s} # {description}'
        lines.append(line)
    return '\n'.join(lines) + '\n'


if __name__ == '__main__':
    import sys

    sys.stdout.write('# Parameters of the facade_mapper node and of the uncertain-facade-map command line, at their\n'
                     "# defaults (the paper's where it gives them). ROS 2 parameter-file form:\n"
                     '#   ros2 run uncertain_facade_map facade_mapper --ros-args --params-file config/facade_mapper.yaml\n'
                     '#   uncertain-facade-map build INPUT... --out MAP --config config/facade_mapper.yaml\n'
                     '# Regenerate with: python -m uncertain_facade_map.config > config/facade_mapper.yaml\n')
    sys.stdout.write(dump_config(Config(), comments=True))
