"""The parameter file of node and command line: a ROS 2 parameter file (YAML).

The file has the form ROS 2 nodes read with ``--params-file``::

    facade_mapper:
      ros__parameters:
        input:
          class_field: class
          ...

Nested keys are parameter names joined by dots (``input.class_field``), as rclpy flattens
them. :func:`load_config` reads such a file into a :class:`~uncertain_facade_map.params.Config`;
unknown names, wrong types and values outside their declared range raise
:class:`~uncertain_facade_map.errors.InputError` naming the parameter. :func:`dump_config`
writes one, each line commented with the parameter's description, unit and range from
its declaration in :mod:`uncertain_facade_map.params`. The shipped
``config/facade_mapper.yaml`` is ``python -m uncertain_facade_map.io.parameter_file``'s
output (a test keeps them equal).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import yaml

from ..errors import InputError
from ..params import NODE_NAME, Config, config_from_parameters, parameters

__all__ = ['DEFAULT_CONFIG', 'dump_config', 'load_config']

#: The default parameter file shipped in ``config/``.
DEFAULT_CONFIG = Path(__file__).resolve().parents[2] / 'config' / f'{NODE_NAME}.yaml'

_HEADER = """\
# Parameters of the facade_mapper node and of the uncertain-facade-map command line, at their
# defaults (the paper's where it gives them). ROS 2 parameter-file form:
#   ros2 run uncertain_facade_map facade_mapper --ros-args --params-file config/facade_mapper.yaml
#   uncertain-facade-map build INPUT... --out MAP --config config/facade_mapper.yaml
# Each comment: description (unit; allowed values). Every parameter is declared once, in
# uncertain_facade_map/params.py; regenerate with:
#   python -m uncertain_facade_map.io.parameter_file > config/facade_mapper.yaml
"""


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
    """Read a ROS 2 parameter file into a :class:`~uncertain_facade_map.params.Config`.

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
        raise InputError(f'{path}: invalid YAML ({str(exc).splitlines()[0]})') from exc
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
        raise InputError(f'{path}: {exc}') from exc


def _yaml_value(value: Any) -> str:
    text = yaml.safe_dump(list(value) if isinstance(value, tuple) else value, default_flow_style=True,
                          width=1000).strip()
    return text.removesuffix('...').strip()


def dump_config(config: Config | None = None, node_name: str = NODE_NAME, comments: bool = False) -> str:
    """The configuration as a ROS 2 parameter file (YAML text).

    Args:
        config: the values to write; the defaults if None.
        node_name: the node's section.
        comments: end each line with the parameter's description, unit and allowed values.
    """
    lines = [f'{node_name}:', '  ros__parameters:']
    section = None
    for p in parameters(config):
        sec, key = p.name.split('.', 1)
        if sec != section:
            lines.append(f'    {sec}:')
            section = sec
        line = f'      {key}: {_yaml_value(p.value)}'
        if comments:
            extra = p.spec.constraint_text()
            text = p.spec.description + (f' ({extra})' if extra else '')
            if p.relations:
                text += f' (need {"; ".join(r.text for r in p.relations)})'
            line = f'{line:46s} # {text}'
        lines.append(line)
    return '\n'.join(lines) + '\n'


def main() -> int:
    """Print the default parameter file with its comments (the shipped ``config/facade_mapper.yaml``)."""
    sys.stdout.write(_HEADER + dump_config(Config(), comments=True))
    return 0


if __name__ == '__main__':
    sys.exit(main())
