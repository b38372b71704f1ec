"""Figures: `plot` writes a readable PNG per façade and an overview; its helpers agree with
the model; bad input is one line, exit 2."""

import contextlib
import io

import numpy as np
import pytest

from uncertain_facade_map.io.map_file import load_map, save_map
from uncertain_facade_map.mapping.facade_map import FacadeMap, build_map
from uncertain_facade_map_apps.cli import main
from uncertain_facade_map_apps.plots import block_layout, facade_arrays, training_points


@pytest.fixture(scope='module')
def map_path(tmp_path_factory, scenes):
    cloud = scenes.campaign('small', 0)
    pts = cloud.points[cloud.points['class'] == 1]
    fmap = build_map(np.stack([pts['x'], pts['y'], pts['z']], 1), pts['building_id'],
                     np.stack([pts['origin_x'], pts['origin_y'], pts['origin_z']], 1), map_origin=cloud.map_origin)
    assert len(fmap.facades) >= 2
    return save_map(fmap, tmp_path_factory.mktemp('map') / 'map.npz')


@pytest.fixture(scope='module')
def plotted(map_path, tmp_path_factory):
    out = tmp_path_factory.mktemp('plots') / 'figures'  # does not exist yet: its parent does
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = main(['plot', str(map_path), '--out', str(out), '--quiet', '--dpi', '60'])
    assert code == 0
    return out, printed.getvalue().split()


def read_png(path):
    from matplotlib.image import imread

    with open(path, 'rb') as fh:
        assert fh.read(8) == b'\x89PNG\r\n\x1a\n'
    return imread(path)


def distinct_colours(img):
    rgb = (img[..., :3] * 255).astype(np.uint32).reshape(-1, 3)
    return len(np.unique((rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]))


def test_plot_writes_a_png_per_facade_and_an_overview(map_path, plotted):
    out, printed = plotted
    fmap = load_map(map_path)
    expected = [f'facade_{f.facade_id}.png' for f in fmap.facades] + ['overview.png']
    assert sorted(p.name for p in out.iterdir()) == sorted(expected)
    assert [p.split('/')[-1] for p in printed] == expected  # the paths, in order, on stdout
    for name in expected:
        img = read_png(out / name)
        assert img.ndim == 3 and img.shape[2] in (3, 4)
        assert min(img.shape[:2]) > 300, (name, img.shape)
        # Not blank: colour maps, layer colours and anti-aliasing give many colours.
        assert distinct_colours(img) > 200, name
        assert (img[..., :3] < 0.5).mean() > 0.002, name  # some dark ink (text, points)


def test_dpi_sets_the_resolution(map_path, plotted, tmp_path):
    out, _ = plotted
    assert main(['plot', str(map_path), '--out', str(tmp_path), '--facades', '0', '--dpi', '120', '--quiet']) == 0
    small, large = read_png(out / 'facade_0.png'), read_png(tmp_path / 'facade_0.png')
    assert large.shape[1] == pytest.approx(2 * small.shape[1], abs=2)


def test_facades_selects_and_progress_goes_to_stderr(map_path, tmp_path, capsys):
    assert main(['plot', str(map_path), '--out', str(tmp_path), '--facades', '1,1', '--dpi', '50']) == 0
    captured = capsys.readouterr()
    assert sorted(p.name for p in tmp_path.iterdir()) == ['facade_1.png', 'overview.png']
    assert captured.out.split() == [str(tmp_path / 'facade_1.png'), str(tmp_path / 'overview.png')]
    assert 'façade' in captured.err  # the tqdm bar and the summary


def test_empty_map_gives_the_overview_only(tmp_path, capsys):
    empty = save_map(FacadeMap(), tmp_path / 'empty.npz')
    assert main(['plot', str(empty), '--out', str(tmp_path / 'figs'), '--quiet']) == 0
    captured = capsys.readouterr()
    assert captured.out.split() == [str(tmp_path / 'figs' / 'overview.png')]
    assert 'no façades' in captured.err
    assert distinct_colours(read_png(tmp_path / 'figs' / 'overview.png')) > 10


@pytest.mark.parametrize('case, words', [
    ('missing map', 'no such file'),
    ('damaged map', 'not a map file'),
    ('unknown facade', 'no façade 99'),
    ('bad ids', '--facades'),
    ('no parent', 'does not exist'),
    ('out is a file', 'is a file'),
    ('bad dpi', '--dpi'),
])
def test_bad_input_one_line_exit_2(map_path, tmp_path, capsys, case, words):
    args = ['plot', str(map_path), '--out', str(tmp_path / 'figs'), '--quiet']
    if case == 'missing map':
        args[1] = str(tmp_path / 'nope.npz')
    elif case == 'damaged map':
        (tmp_path / 'bad.npz').write_bytes(map_path.read_bytes()[:5000])
        args[1] = str(tmp_path / 'bad.npz')
    elif case == 'unknown facade':
        args += ['--facades', '0,99']
    elif case == 'bad ids':
        args += ['--facades', '0,x']
    elif case == 'no parent':
        args[3] = str(tmp_path / 'a' / 'b')
    elif case == 'out is a file':
        (tmp_path / 'file').write_text('x')
        args[3] = str(tmp_path / 'file')
    else:
        args += ['--dpi', '0']
    code = main(args)
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count('\n') == 1 and err.startswith('uncertain-facade-map: error:') and words in err, err
    assert not (tmp_path / 'figs').exists() or not any((tmp_path / 'figs').iterdir())


def test_training_points_are_those_of_the_fit(map_path):
    fmap = load_map(map_path)
    for f in fmap.facades:
        uvd, cos = facade_arrays(fmap, f)
        training = training_points(f, uvd, cos, fmap.params.gp)
        assert int(training.sum()) == f.stats['training'], f.facade_id
        # The chi-squared test removes only GP data: training points, and the planar points
        # each block takes besides (gp.planar_per_block), all on facets.
        outlier = np.isin(f.point_index, f.outlier_index)
        on_facet = f.facets.facet_at(uvd[:, :2]) >= 0
        assert outlier.sum() == len(f.outlier_index) and not (outlier & ~on_facet).any()


def test_block_layout_covers_the_facets_and_tells_neighbours_apart(map_path):
    fmap = load_map(map_path)
    for f in fmap.facades:
        code, parity, sizes = block_layout(f, fmap.params.gp.c_min)
        inside = f.surface.facet >= 0
        np.testing.assert_array_equal(code >= 0, inside)
        np.testing.assert_array_equal(parity >= 0, inside)
        assert sizes.shape == (f.facets.n_facets, 2) and np.all(sizes > 0)
        assert len(np.unique(code[inside])) >= f.facets.n_facets
        # Adjacent cells of one facet in different blocks have different tones.
        for a, b, fa, fb, pa, pb in ((code[:, 1:], code[:, :-1], f.surface.facet[:, 1:], f.surface.facet[:, :-1],
                                      parity[:, 1:], parity[:, :-1]),
                                     (code[1:], code[:-1], f.surface.facet[1:], f.surface.facet[:-1],
                                      parity[1:], parity[:-1])):
            step = (a != b) & (fa == fb) & (fa >= 0)
            assert np.all(pa[step] != pb[step])
