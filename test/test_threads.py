"""The numerical libraries' threads: the parallel compiled kernels run on every core."""

import os
import subprocess
import sys
import textwrap

import pytest

from uncertain_facade_map.pipeline import local_kernels, raster_kernels

TWINS = [(local_kernels.local_planes, local_kernels.local_planes_serial),
         (raster_kernels.assign_all, raster_kernels.assign_all_serial),
         (raster_kernels.raster_answer_all, raster_kernels.raster_answer_all_serial)]

#: A module with a parallel kernel and its one-core twin, both cached on disk.
KERNELS = textwrap.dedent('''
    import numpy as np
    from numba import get_thread_id, njit, prange

    from uncertain_facade_map.threads import serial_twin


    @njit(cache=True, parallel=True)
    def spread(n):
        """(n,) the thread that ran each of n slow iterations."""
        out = np.zeros(n, np.int64)
        for i in prange(n):
            x = 0.0
            for j in range(200_000):
                x += np.sin(x + j)
            out[i] = get_thread_id() + (x > 1e300)
        return out


    spread_serial = serial_twin(spread, 'spread_serial')
''')


@pytest.mark.parametrize('kernel, twin', TWINS, ids=lambda k: getattr(k, '__name__', ''))
def test_a_serial_twin_has_its_own_cache_entry(kernel, twin):
    # numba names a cache entry after the function's name and line, not its flags: a twin
    # under the same name would be loaded in place of the parallel kernel.
    assert kernel.targetoptions.get('parallel') and not twin.targetoptions.get('parallel')
    assert kernel._cache._cache_file._index_name != twin._cache._cache_file._index_name


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason='one core: nothing to run in parallel')
def test_the_parallel_kernel_runs_in_parallel_after_its_twin_was_cached(tmp_path):
    (tmp_path / 'kernels_mod.py').write_text(KERNELS)
    env = {**os.environ, 'PYTHONPATH': os.pathsep.join([str(tmp_path), *sys.path]), 'NUMBA_NUM_THREADS': '2'}
    run = 'import kernels_mod as k; {} print(len(set(k.spread(64).tolist())))'
    # First process: the twin compiled and cached first, then the kernel; the second loads both.
    for first in ('k.spread_serial(4);', ''):
        out = subprocess.run([sys.executable, '-c', run.format(first)], cwd=tmp_path, env=env, capture_output=True,
                             text=True, timeout=300, check=True)
        assert out.stdout.split()[-1] == '2', out.stdout + out.stderr
