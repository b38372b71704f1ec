"""The parameter declarations: what they advertise is what they accept, everywhere.

Every parameter with an interval advertises a closed range (a ROS descriptor's). Each end
of it is fed to the declarations and to the command line and must be accepted; the next
value outside each end must be refused with a message naming the parameter. (The node's
own parameter path gets the same edges in ``test/node/test_parameters.py``.)
"""

from __future__ import annotations

import dataclasses
import math

import pytest
import yaml
from support import assert_edge_taken, assignments, edge_cases

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.params import (
    Config,
    GPParams,
    Interval,
    MapParams,
    OutlierParams,
    Section,
    config_from_parameters,
    map_params_from_record,
    map_params_record,
    parameters,
)
from uncertain_facade_map_apps import cli

CASES = edge_cases()


def test_every_parameter_is_declared_with_a_description():
    infos = list(parameters())
    assert len(infos) == sum(len(dataclasses.fields(type(getattr(Config(), f.name))))
                             for f in dataclasses.fields(Config))
    assert all(i.spec.description for i in infos)
    # Every numeric parameter but the grid's height band has an interval.
    numeric = [i for i in infos if i.type in (int, float) and not i.is_list]
    assert [i.name for i in numeric if i.closed_range() is None] == ['publish.grid_z_min', 'publish.grid_z_max']


def test_the_edge_cases_cover_every_interval():
    names = {c[0] for c in CASES}
    assert len(names) == sum(1 for i in parameters() if i.closed_range() is not None)
    assert len(CASES) >= 4 * len(names) - 10  # both ends, inside and outside (less the unbounded ends)


@pytest.mark.parametrize('name, value, accepted, partners', CASES,
                         ids=[f'{c[0]}={c[1]!r}' for c in CASES])
def test_advertised_edges_are_accepted_and_beyond_refused(name, value, accepted, partners):
    assert_edge_taken(config_from_parameters, name, value, accepted, partners)


def _write_params(path, params: dict) -> None:
    tree: dict = {}
    for name, value in params.items():
        section, key = name.split('.')
        tree.setdefault(section, {})[key] = value
    path.write_text(yaml.safe_dump({'facade_mapper': {'ros__parameters': tree}}))


@pytest.mark.parametrize('name, value, accepted, partners', CASES,
                         ids=[f'{c[0]}={c[1]!r}' for c in CASES])
def test_the_command_line_takes_what_is_advertised(tmp_path, capsys, name, value, accepted, partners):
    """``build --config`` reads the file first: a good file fails later, on the missing input."""
    outcomes = []
    for params in assignments(name, value, partners) if accepted else [{name: value}]:
        path = tmp_path / 'p.yaml'
        _write_params(path, params)
        status = cli.main(['build', str(tmp_path / 'missing.npz'), '--out', str(tmp_path / 'map.npz'),
                           '--config', str(path), '--quiet'])
        err = capsys.readouterr().err
        assert status == 2 and err.count('\n') == 1, err
        outcomes.append(err)
        if accepted and 'no such file' in err:
            break
    if accepted:
        assert 'no such file' in outcomes[-1], outcomes
    else:
        assert all(f'parameter {name}' in e for e in outcomes), outcomes


@pytest.mark.parametrize('kwargs, words', [
    ({'noise_sigma': 0.0}, r'parameter gp.noise_sigma: 0.0 is outside \[1e-06, 100\]'),
    ({'lengthscale2_min': 0.01}, 'need lengthscale2_min <= initial_lengthscale2 <= lengthscale2_max'),
    ({'optimise': 1}, 'parameter gp.optimise: expected true or false'),
    ({'opt_points': 10.0}, 'parameter gp.opt_points: expected an integer'),
    ({'c_min': float('nan')}, 'parameter gp.c_min: must be finite'),
])
def test_sections_check_their_fields_on_construction(kwargs, words):
    with pytest.raises(InputError, match=words):
        GPParams(**kwargs)


def test_integers_are_taken_for_floats_and_lists_for_tuples():
    assert GPParams(noise_sigma=1).noise_sigma == 1.0 and isinstance(GPParams(noise_sigma=1).noise_sigma, float)
    config = config_from_parameters({'input.building_classes': [1, 6], 'input.map_origin': [1, 2, 3]})
    assert config.input.building_classes == (1, 6) and config.input.map_origin == (1.0, 2.0, 3.0)


def test_open_ends_are_advertised_as_the_nearest_value_inside():
    assert Interval(0.0, 1.0, 'neither').closed_range(float) == (5e-324, math.nextafter(1.0, 0.0))
    assert Interval(0, 10, 'left').closed_range(int) == (0, 9)
    assert Interval(None, 3.0).closed_range(float)[0] == -1.7976931348623157e308
    assert str(Interval(0.0, 1.0, 'right')) == '(0, 1]' and str(Interval(None, 2, 'left')) == '(-inf, 2)'
    assert OutlierParams(alpha=5e-324).alpha == 5e-324
    with pytest.raises(InputError, match='parameter outliers.alpha: 1.0 is outside'):
        OutlierParams(alpha=1.0)


def test_every_section_is_a_checked_section():
    for f in dataclasses.fields(Config):
        assert issubclass(type(getattr(Config(), f.name)), Section)


def test_the_map_record_round_trips_and_refuses_what_it_does_not_know():
    params = MapParams(gp=GPParams(noise_sigma=0.005), seed=7)
    record = map_params_record(params)
    assert map_params_from_record(record) == params
    assert map_params_from_record({}) == MapParams()  # an older file: the defaults
    with pytest.raises(InputError, match='unknown parameter gp.noise in the map file'):
        map_params_from_record({**record, 'gp': {**record['gp'], 'noise': 0.02}})
    with pytest.raises(InputError, match='unknown parameter section mystery'):
        map_params_from_record({**record, 'mystery': {}})
    with pytest.raises(InputError, match='parameter outliers.alpha'):
        map_params_from_record({**record, 'outliers': {'alpha': 2.0}})
