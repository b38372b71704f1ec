"""The surface evaluation's command on a hard scene: its truth is the bent wall."""

from uncertain_facade_map.evaluation import surface


def test_surface_evaluation_runs_on_a_hard_scene(capsys):
    assert surface.main(['--scene', 'small_hard']) == 0
    out = capsys.readouterr().out
    assert out.startswith('scene small_hard seed 0:')
    rmse = float(out.split('observed, off steps: RMSE ')[1].split(' m')[0])
    assert 0.0 < rmse < 0.1  # against the bent walls (the clean small scene: 0.024 m)
