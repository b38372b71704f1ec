"""Tests of uncertain_facade_map.io.trajectory: the trajectory file and interpolation."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.io.trajectory import Trajectory, read_trajectory

SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def test_tum_file_with_header_and_comments(tmp_path) -> None:
    path = tmp_path / 'poses.txt'
    path.write_text('timestamp tx ty tz qx qy qz qw\n# a comment\n\n'
                    '10.0 1 2 3 0 0 0 1\n11.0 3 2 3 0 0 0 1\n')
    traj = read_trajectory(path)
    assert traj.time.tolist() == [10.0, 11.0]
    assert traj.position.tolist() == [[1, 2, 3], [3, 2, 3]]
    # Halfway in time is halfway in space; the ends hold within the tolerance.
    assert traj.positions_at(np.array([10.5, 9.95, 11.05])).tolist() == [[2, 2, 3], [1, 2, 3], [3, 2, 3]]


def test_a_single_pose_is_a_fixed_sensor() -> None:
    traj = Trajectory(np.array([5.0]), np.array([[1.0, 2.0, 3.0]]))
    assert traj.positions_at(np.array([5.0, 5.05])).tolist() == [[1, 2, 3], [1, 2, 3]]


@pytest.mark.parametrize('text, expected', [
    ('1 2 3\n', 'line 1: expected t x y z'),
    ('0 0 0 0\n1 a 0 0\n', 'line 2: expected t x y z'),
    ('# nothing\n', 'holds no pose'),
    ('0 0 0 0\n0 1 1 1\n', 'must increase strictly: pose 2'),
    ('0 0 0 0\n1 nan 0 0\n', 'NaN or infinite'),
])
def test_bad_files_one_line_error(tmp_path, text, expected) -> None:
    path = tmp_path / 't.txt'
    path.write_text(text)
    with pytest.raises(InputError) as err:
        read_trajectory(path)
    assert expected in str(err.value) and '\n' not in str(err.value)


def test_missing_and_binary_files(tmp_path) -> None:
    with pytest.raises(InputError, match='no such file'):
        read_trajectory(tmp_path / 'nope.txt')
    (tmp_path / 'b.bin').write_bytes(b'\xff\xfe\x00\x81' * 10)
    with pytest.raises(InputError, match='not a text trajectory file'):
        read_trajectory(tmp_path / 'b.bin')


def test_times_outside_the_span_are_refused() -> None:
    traj = Trajectory(np.array([0.0, 1.0]), np.zeros((2, 3)))
    with pytest.raises(InputError, match='1 of 2 point times lie outside'):
        traj.positions_at(np.array([0.5, 1.2]))
    with pytest.raises(InputError, match='NaN or infinite'):
        traj.positions_at(np.array([np.nan]))


finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)


@SETTINGS
@given(st.lists(st.tuples(st.floats(0.001, 100.0), finite, finite, finite), min_size=1, max_size=30),
       st.sampled_from([' ', '\t', ',', ', ']), st.booleans(), st.booleans())
def test_written_trajectories_read_back_exactly(tmp_path, rows, sep, header, quaternion) -> None:
    """Any increasing trajectory, in any separator, with or without a header and TUM's
    quaternion columns, reads back exactly; the positions at its own times are its poses."""
    times = np.cumsum([r[0] for r in rows])
    positions = np.array([r[1:] for r in rows])
    lines = ['t x y z qx qy qz qw'] if header else []
    for t, p in zip(times, positions):
        values = [repr(float(t))] + [repr(float(v)) for v in p] + (['0', '0', '0', '1'] if quaternion else [])
        lines.append(sep.join(values))
    path = tmp_path / 'traj.csv'
    path.write_text('\n'.join(lines) + '\n')
    traj = read_trajectory(path)
    assert np.array_equal(traj.time, times) and np.array_equal(traj.position, positions)
    assert np.allclose(traj.positions_at(times), positions, rtol=0, atol=1e-6 * (1 + np.abs(positions).max()))
