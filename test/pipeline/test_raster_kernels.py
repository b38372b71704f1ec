"""The compiled raster reading (issue 27) against the numpy reference, on random stepped rasters."""

from types import SimpleNamespace

import numpy as np
import pytest

from uncertain_facade_map.datatypes import SOURCE_GLOBAL, FacadeFrame, SurfaceRaster
from uncertain_facade_map.pipeline.raster_kernels import PackedRasters, packed
from uncertain_facade_map.pipeline.step7_queries import (
    STEP_REACH,
    _assign,
    _raster_answer,
    _raster_answer_compiled,
    assign_facades,
)


class Model(SimpleNamespace):
    """What the raster reading reads of a FacadeModel (a class: the packing keeps weak references)."""


def facade(rng: np.random.Generator, origin: np.ndarray, normal: np.ndarray) -> Model:
    """A façade with a random stepped raster (quantised depths: ties between faces; some
    global-prior cells; several facets: the nearest-cell rule of surface_at)."""
    h, w, cell = rng.integers(3, 30), rng.integers(3, 30), float(rng.choice([0.05, 0.1, 0.2]))
    mean = np.round(rng.normal(0, 0.3, (h, w)) * 4) / 4
    source = np.where(rng.random((h, w)) < 0.1, SOURCE_GLOBAL, 2).astype(np.int8)
    facet = np.where(source == SOURCE_GLOBAL, -1, rng.integers(0, 3, (h, w))).astype(np.int32)
    raster = SurfaceRaster(np.array([-1.0, 0.5]), cell, mean, rng.uniform(1e-4, 1e-2, (h, w)), facet, source)
    return Model(frame=FacadeFrame.from_normal(origin, normal), surface=raster,
                           noise_var=float(rng.uniform(1e-4, 1e-3)))


@pytest.mark.parametrize('seed', range(4))
def test_compiled_raster_reading_equals_numpy(seed):
    """Two façades at a corner, points on, off, around and between them: the same façades,
    and the same depths, variances and distances to the last bit."""
    rng = np.random.default_rng(seed)
    models = [facade(rng, np.array([0.0, 0.0, 0.0]), np.array([0.0, -1.0, 0.0])),
              facade(rng, np.array([0.5, 0.3, 0.0]), np.array([1.0, 0.2, 0.0]))]
    parts = []
    for m in models:  # around each raster: on it, beside it, in front and behind
        h, w = m.surface.mean.shape
        lo, hi = m.surface.origin - 0.3, m.surface.origin + m.surface.cell * np.array([w, h]) + 0.3
        uvd = np.c_[rng.uniform(lo, hi, (10000, 2)), rng.normal(0, 0.5, 10000)]
        parts.append(m.frame.to_world(uvd))
    xyz = np.concatenate(parts)
    band_back, band_front = 0.6, 1.2
    rasters = packed(models, STEP_REACH)
    assert isinstance(rasters, PackedRasters) and packed(models, STEP_REACH) is rasters
    want_which, want_uvd = assign_facades(models, xyz, band_back, band_front)
    which, uvd = _assign(rasters, rasters.boxes(band_back, band_front), xyz, band_back, band_front)
    assert (want_which >= 0).sum() > 2000 and len(np.unique(want_which)) == 3
    np.testing.assert_array_equal(which, want_which)
    np.testing.assert_allclose(uvd, want_uvd, rtol=0, atol=1e-12)
    want = _raster_answer(models, want_which, want_uvd)
    got, grad = _raster_answer_compiled(rasters, want_which, want_uvd)
    assert np.sum(np.abs(want[3] - (want_uvd[:, 2] - want[0])) > 1e-9) > 20  # step faces moved points
    for a, b in zip(got, want):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize('seed', range(3))
def test_normal_is_the_direction_of_the_signed_distance_gradient(seed):
    """``PointQuery.normal`` against central finite differences of ``signed_distance`` in the
    map frame, wherever the distance is differentiable (forward and backward differences
    agree: off facet borders, cell-centre lines of the nearest-cell rule and switches between
    step faces): on the raster's slopes, on the flat nearest cells and on the step faces."""
    from uncertain_facade_map.pipeline.step7_queries import query_points

    rng = np.random.default_rng(100 + seed)
    models = [facade(rng, np.array([0.0, 0.0, 0.0]), np.array([0.0, -1.0, 0.0])),
              facade(rng, np.array([0.5, 0.3, 0.0]), np.array([1.0, 0.2, 0.0]))]
    for i, m in enumerate(models):  # smooth facets too: bilinear slopes
        r = m.surface
        h, w = r.mean.shape
        mean = r.mean + 0.3 * np.sin(np.arange(w) / 3.0)[None, :] + 0.2 * np.arange(h)[:, None] / h
        facet = r.facet if i == 0 else np.zeros_like(r.facet)  # the second: one facet, all sloped
        m.surface = SurfaceRaster(r.origin, r.cell, mean, r.var, facet, r.source)
        m.facade_id = i
    parts = []
    for m in models:
        h, w = m.surface.mean.shape
        lo, hi = m.surface.origin, m.surface.origin + m.surface.cell * np.array([w, h])
        parts.append(m.frame.to_world(np.c_[rng.uniform(lo, hi, (3000, 2)), rng.normal(0, 0.4, 3000)]))
    xyz = np.concatenate(parts)

    def answer(points):
        return query_points(models, points, 0.1, 0.6, 1.2)

    base = answer(xyz)
    hit = base.facade >= 0
    assert hit.sum() > 3000
    assert np.isnan(base.normal[~hit]).all()
    np.testing.assert_allclose(np.linalg.norm(base.normal[hit], axis=1), 1.0, atol=1e-12)
    step = 1e-6
    grad, smooth = np.zeros_like(xyz), hit.copy()
    for k in range(3):
        e = np.zeros(3)
        e[k] = step
        fwd, bwd = answer(xyz + e), answer(xyz - e)
        smooth &= (fwd.facade == base.facade) & (bwd.facade == base.facade)
        df = (fwd.signed_distance - base.signed_distance) / step
        db = (base.signed_distance - bwd.signed_distance) / step
        smooth &= np.abs(df - db) < 1e-4
        grad[:, k] = 0.5 * (df + db)
    assert smooth.sum() > 0.8 * hit.sum()
    want = grad[smooth] / np.linalg.norm(grad[smooth], axis=1, keepdims=True)
    np.testing.assert_allclose(base.normal[smooth], want, atol=1e-5)
    # all three kinds were checked: sloped raster, flat (the plane's normal), step faces
    local_d = np.einsum('nj,nj->n', base.normal[smooth],
                        np.array([m.frame.normal for m in models])[base.facade[smooth]])
    assert (local_d > 1 - 1e-12).sum() > 50 and ((local_d < 1 - 1e-6) & (local_d > 0.1)).sum() > 50
    assert (np.abs(local_d) < 1e-9).sum() > 20
