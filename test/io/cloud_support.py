"""Hypothesis strategies and helpers shared by the tests of the cloud file formats in this folder.

Imported as ``cloud_support`` (pytest puts this folder on sys.path); helpers for the whole
test tree live in ``test/support.py``.
"""

from __future__ import annotations

import hypothesis.extra.numpy as hnp
import numpy as np
import pytest
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.io.cloud import Cloud
from uncertain_facade_map.io.ply import PLY_TYPES

SETTINGS = settings(max_examples=40, deadline=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

TYPES = list(PLY_TYPES)  # i1 u1 i2 u2 i4 u4 f4 f8
EXTRA_NAMES = ['class', 'intensity', 'time', 'building_id', 'gt_facade', 'ring', 'r', 'g', 'b',
               'origin_x', 'return_number', 'a_1', 'Z2']


# --------------------------------------------------------------------------------------
# strategies


@st.composite
def dtypes(draw: st.DrawFn) -> np.dtype:
    """Packed structured dtypes: x, y, z plus 1..8 other fields, random types and order."""
    extra = draw(st.lists(st.sampled_from(EXTRA_NAMES), min_size=1, max_size=8, unique=True))
    names = draw(st.permutations(['x', 'y', 'z'] + extra))
    return np.dtype([(n, draw(st.sampled_from(TYPES))) for n in names])


@st.composite
def clouds(draw: st.DrawFn, dtype_strategy: st.SearchStrategy[np.dtype] | None = None) -> Cloud:
    """Clouds of 0..100 points whose values include NaN, +-inf, -0.0, subnormals, extremes."""
    dtype = draw(dtype_strategy if dtype_strategy is not None else dtypes())
    n = draw(st.integers(0, 100))
    points = np.zeros(n, dtype=dtype)  # zeroed so that padding bytes are defined
    for name in dtype.names:
        ftype = dtype.fields[name][0]
        points[name] = draw(hnp.arrays(ftype.base, (n,) + ftype.shape))
    origin = draw(st.lists(st.floats(allow_nan=False, allow_infinity=False, width=64),
                           min_size=3, max_size=3))
    return Cloud(points, np.array(origin))


@st.composite
def raw_clouds(draw: st.DrawFn) -> Cloud:
    """Clouds whose bytes are arbitrary (every NaN payload and sign bit)."""
    dtype = draw(dtypes())
    n = draw(st.integers(0, 30))
    raw = draw(st.binary(min_size=n * dtype.itemsize, max_size=n * dtype.itemsize))
    return Cloud(np.frombuffer(raw, dtype=dtype).copy(), np.array([1.5, -2.25, 1e7]))


# --------------------------------------------------------------------------------------
# helpers


def values_equal_nan_canonical(a: np.ndarray, b: np.ndarray) -> bool:
    """Bit equality except that any NaN equals any NaN (ASCII PLY drops NaN sign/payload)."""
    if a.dtype != b.dtype:
        return False
    for name in a.dtype.names:
        fa, fb = a[name], b[name]
        if fa.dtype.kind == 'f':
            nan_a, nan_b = np.isnan(fa), np.isnan(fb)
            if not np.array_equal(nan_a, nan_b):
                return False
            if fa[~nan_a].tobytes() != fb[~nan_b].tobytes():
                return False
        elif fa.tobytes() != fb.tobytes():
            return False
    return True


def xyz_points(n: int = 4, dtype: str = 'f4') -> np.ndarray:
    """A small plain (x, y, z) structured array."""
    pts = np.zeros(n, dtype=[('x', dtype), ('y', dtype), ('z', dtype)])
    pts['x'] = np.arange(n) + 0.5
    pts['y'] = -np.arange(n) * 0.25
    pts['z'] = 1e-3
    return pts


def one_line_error(func, *args, **kwargs) -> str:
    """Call ``func``, expect an InputError with a one-line message, return the message."""
    with pytest.raises(InputError) as err:
        func(*args, **kwargs)
    message = str(err.value)
    assert message and '\n' not in message and 'Traceback' not in message
    return message
