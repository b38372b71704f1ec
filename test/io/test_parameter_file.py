"""The ROS 2 parameter file: defaults, round trips, and one-line errors naming the parameter."""

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.io.parameter_file import (
    DEFAULT_CONFIG,
    PARAMETERS_PAGE,
    default_config_file,
    dump_config,
    load_config,
    markdown_parameters,
)
from uncertain_facade_map.io.parameter_file import main as print_default_file
from uncertain_facade_map.params import (
    LOCALIZER_NAME,
    LOCALIZER_SECTIONS,
    Config,
    InputConfig,
    config_from_parameters,
    node_sections,
    parameters,
)


def test_shipped_file_holds_the_defaults():
    assert load_config(DEFAULT_CONFIG) == Config()
    tree = yaml.safe_load(DEFAULT_CONFIG.read_text())
    assert 'ros__parameters' in tree['facade_mapper']


def test_shipped_file_is_the_generated_one(capsys):
    """config/facade_mapper.yaml is derived from the declarations, comments included."""
    print_default_file()
    assert capsys.readouterr().out == DEFAULT_CONFIG.read_text()


def test_each_node_has_its_own_sections_and_file(capsys):
    """config/facade_localizer.yaml holds the localiser's sections only, the mapper's file the
    others; both hold the defaults and are the generated ones."""
    localizer = default_config_file(LOCALIZER_NAME)
    print_default_file(['--node', LOCALIZER_NAME])
    assert capsys.readouterr().out == localizer.read_text(), (
        'config/facade_localizer.yaml is out of date: python -m uncertain_facade_map.io.parameter_file --node '
        'facade_localizer > config/facade_localizer.yaml')
    assert load_config(localizer, LOCALIZER_NAME) == Config() == load_config(node_name='facade_mapper')
    mapper = set(yaml.safe_load(DEFAULT_CONFIG.read_text())['facade_mapper']['ros__parameters'])
    assert set(yaml.safe_load(localizer.read_text())[LOCALIZER_NAME]['ros__parameters']) == set(LOCALIZER_SECTIONS)
    assert mapper == set(node_sections()) and not mapper & set(LOCALIZER_SECTIONS)
    assert {p.name.split('.')[0] for p in parameters()} == mapper | set(LOCALIZER_SECTIONS)


def test_parameter_page_is_the_generated_one(capsys):
    """docs/parameters.md is derived from the declarations (regenerate with --markdown)."""
    print_default_file(['--markdown'])
    assert capsys.readouterr().out == PARAMETERS_PAGE.read_text(), (
        'docs/parameters.md is out of date: python -m uncertain_facade_map.io.parameter_file --markdown '
        '> docs/parameters.md')


def test_parameter_page_has_a_row_per_parameter():
    """Every parameter is a table row of its section, with its default, unit and allowed values."""
    page = markdown_parameters()
    rows = {line.split(' | ')[0].strip('| `'): line for line in page.splitlines() if line.startswith('| `')}
    assert set(rows) == {p.name for p in parameters()}
    assert rows['gp.noise_sigma'] == ('| `gp.noise_sigma` | `0.02` | m | `[1e-06, 100]` | sigma_eta, the noise of the '
                                      'points, when not estimated or too few points are close enough to estimate it '
                                      '(paper: 0.02) |  |')
    assert '`plsc`, `fixed`' in rows['query.occupancy']
    assert '`band_front + band_back > 0`' in rows['extraction.band_back']
    assert page.index('## input') < page.index('## gp') < page.index('## persistence')
    custom = markdown_parameters(Config(input=InputConfig(class_field='a|b')))
    assert '| `input.class_field` | `a\\|b` |' in custom  # a pipe would split the cell


@settings(max_examples=60, deadline=None)
@given(
    classes=st.lists(st.integers(0, 255), min_size=1, max_size=4).map(tuple),
    field=st.text('abcdefghijklmnopqrstuvwxyz_', min_size=1, max_size=12),
    origin=st.tuples(*[st.floats(-1e7, 1e7, allow_nan=False)] * 3),
)
def test_dump_and_load_round_trip(tmp_path_factory, classes, field, origin):
    config = Config(input=InputConfig(class_field=field, building_classes=classes, map_origin=origin))
    path = tmp_path_factory.mktemp('cfg') / 'p.yaml'
    path.write_text(dump_config(config))
    assert load_config(path) == config


@pytest.mark.parametrize('params, words', [
    ({'input.nope': 1}, 'unknown parameter input.nope'),
    ({'input.building_classes': 'building'}, 'expected a list'),
    ({'input.building_classes': [1.5]}, 'expected an integer'),
    ({'input.map_origin': [0, 0]}, 'expected 3 values'),
    ({'input.map_origin': [0, 0, float('nan')]}, 'must be finite'),
    ({'input.class_field': 3}, 'expected a string'),
])
def test_bad_parameters_are_named(params, words):
    with pytest.raises(InputError, match=words):
        config_from_parameters(params)


@pytest.mark.parametrize('text, words', [
    ('facade_mapper: [1, 2', 'invalid YAML'),
    ('- 1\n- 2\n', 'not a ROS 2 parameter file'),
    ('other_node:\n  ros__parameters: {}\n', 'no "facade_mapper: ros__parameters:" section'),
])
def test_bad_files(tmp_path, text, words):
    path = tmp_path / 'p.yaml'
    path.write_text(text)
    with pytest.raises(InputError, match=words):
        load_config(path)


def test_missing_file():
    with pytest.raises(InputError, match='no such file'):
        load_config('/nonexistent/params.yaml')


def test_wildcard_section_applies():
    params = yaml.safe_load("/**:\n  ros__parameters:\n    input:\n      frame_id: world\n")
    assert params
