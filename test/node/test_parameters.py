"""The node's parameter path takes what its descriptors advertise, and refuses the rest by name.

Each end of every advertised range, and one value beyond it, is given to a node as a
parameter override (as ``--ros-args -p`` or a parameter file would) and read through the
node's own :func:`~uncertain_facade_map_node.node.declare_config`.
"""

from __future__ import annotations

import pytest

pytest.importorskip('rclpy')
pytest.importorskip('uncertain_facade_map.srv')

import rclpy  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from support import assert_edge_taken, edge_cases  # noqa: E402

from uncertain_facade_map.errors import InputError  # noqa: E402
from uncertain_facade_map.params import (  # noqa: E402
    LOCALIZER_NAME,
    LOCALIZER_SECTIONS,
    NODE_NAME,
    Config,
    node_sections,
    parameters,
)
from uncertain_facade_map_node.runtime import declare_config  # noqa: E402

CASES = edge_cases()


@pytest.fixture(scope='module')
def context():
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.shutdown(context=ctx)


def _node_of(params: dict) -> str:
    """The node that declares these parameters (the localiser's sections, or the mapper's)."""
    return LOCALIZER_NAME if any(n.split('.')[0] in LOCALIZER_SECTIONS for n in params) else NODE_NAME


def node_config(context, params: dict) -> Config:
    """The configuration a node reads with these overrides (the node that declares them)."""
    name = _node_of(params)
    node = rclpy.create_node(name, context=context,
                             parameter_overrides=[Parameter(n, value=v) for n, v in params.items()])
    try:
        return declare_config(node, node_sections(name))
    finally:
        node.destroy_node()


@pytest.mark.parametrize('name', [NODE_NAME, LOCALIZER_NAME])
def test_defaults_and_descriptors(context, name):
    node = rclpy.create_node(name, context=context)
    try:
        assert declare_config(node, node_sections(name)) == Config()
        declared = {n.split('.')[0] for n in node.get_parameters_by_prefix('')}
        assert declared >= set(node_sections(name))
        others = set(node_sections(LOCALIZER_NAME if name == NODE_NAME else NODE_NAME))
        assert not declared & others  # each node declares its own sections only
        for info in parameters(sections=node_sections(name)):
            d = node.describe_parameter(info.name)
            assert d.read_only and d.description.startswith(info.spec.description)
            bounds = info.closed_range()
            ranges = list(d.integer_range) + list(d.floating_point_range)
            if bounds is None:
                assert not ranges, info.name
            else:
                assert (ranges[0].from_value, ranges[0].to_value) == bounds, info.name
            if info.relations:
                assert info.relations[0].text in d.additional_constraints
    finally:
        node.destroy_node()


@pytest.mark.parametrize('name, value, accepted, partners', CASES, ids=[f'{c[0]}={c[1]!r}' for c in CASES])
def test_advertised_edges_start_a_node_and_beyond_is_refused(context, name, value, accepted, partners):
    assert_edge_taken(lambda params: node_config(context, params), name, value, accepted, partners)


def test_a_value_of_the_wrong_type_is_refused_by_name(context):
    with pytest.raises(InputError, match='parameter gp.noise_sigma'):
        node_config(context, {'gp.noise_sigma': 'two centimetres'})
    with pytest.raises(InputError, match='parameter node.qos: expected one of sensor_data, reliable'):
        node_config(context, {'node.qos': 'fast'})
