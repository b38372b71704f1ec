"""Localisation against the uncertain map, compared honestly: one command, one report (issue 28).

```sh
.venv/bin/python -m uncertain_facade_map_apps.localise_report --out output/localisation
```

Drives of campaigns 1-4 of ``street`` and ``zurich`` (clean and hard simulator, and an
occlusion-heavy variant whose mapping drive passes tall vans and dense trees) localised scan
by scan against the map of campaign 0, and the real Argoverse 2 sweep 1 against the map of
sweep 0 (``../shared/data/real/``, skipped when absent), from priors perturbed like GNSS in a
street canyon (:mod:`uncertain_facade_map.evaluation.localisation` says how). Rows:

- (a) ``localise`` of :mod:`uncertain_facade_map.localisation` asking our map, with its variance;
- (b) the same with one constant variance for the whole map (the median of the map's
  ``variance + noise_variance`` at its own points, unless ``--constant-variance`` is given);
- (c) GICP of small_gicp (PyPI ``small-gicp``) from the same prior against the points the map
  was built from, coarse to fine (``--gicp-stages``: maximum correspondence distances, metres;
  the library's defaults otherwise: 0.25 m downsampling, 10 neighbours, 20 iterations);
- (d) the prior alone.

Writes ``report.md``, ``report.json`` (summaries and every scan's outcome) and
``localisation.png`` into ``--out``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import shlex
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from uncertain_facade_map.errors import InputError
from uncertain_facade_map.evaluation import localisation as L
from uncertain_facade_map.localisation import localise

REPO = Path(__file__).resolve().parents[1]
SHARED_REAL = REPO.parent / 'shared' / 'data' / 'real'
DEFAULT_SCENES = ('street', 'zurich', 'street_hard', 'zurich_hard', 'street_occluded', 'zurich_hard_occluded')
ROW_NAMES = {'a': '(a) map + variance', 'b': '(b) map, constant variance', 'c': '(c) GICP raw points',
             'd': '(d) prior alone', 'e': '(e) GICP whole cloud'}


# ---------------------------------------------------------------------------------------
# Rows


def gicp_row(stages: tuple[float, ...] = (3.0, 1.5, 0.5), downsampling: float = 0.25, neighbours: int = 10,
             iterations: int = 20, threads: int = 1, whole_cloud: bool = False) -> L.Method:
    """Row (c): small_gicp's GICP from the prior against the scenario's mapped points, one
    alignment per maximum correspondence distance in ``stages`` (each starting from the
    last). ``whole_cloud``: the target is every return of the mapping drive (thinned to one
    per 0.1 m voxel: ground, cars and trees too) instead of the building points. The target
    is preprocessed once per scenario (not timed); the scan's
    preprocessing (downsampling, covariances, k-d tree) is timed with the alignment."""
    import small_gicp

    targets: dict[int, Any] = {}

    def row(scan: np.ndarray, prior: np.ndarray, covariance: np.ndarray, scenario: L.Scenario) -> L.Estimate:
        key = id(scenario)
        if key not in targets:
            points = scenario.cloud_points if whole_cloud else scenario.map_points
            if points is None:
                raise InputError(f'scenario {scenario.name} keeps no whole cloud for GICP')
            targets[key] = small_gicp.preprocess_points(np.ascontiguousarray(points, dtype=np.float64),
                                                        downsampling, neighbours, threads)
        target, tree = targets[key]
        started = time.perf_counter()
        source, _ = small_gicp.preprocess_points(np.ascontiguousarray(scan, dtype=np.float64), downsampling,
                                                 neighbours, threads)
        pose = prior.copy()
        converged = True
        for distance in stages:
            result = small_gicp.align(target, source, tree, pose, registration_type='GICP',
                                      max_correspondence_distance=distance, num_threads=threads,
                                      max_iterations=iterations)
            pose = np.asarray(result.T_target_source, dtype=np.float64)
            converged = bool(result.converged)
        return L.Estimate(pose, None, time.perf_counter() - started, converged)

    return row


def truth_check(scenario: L.Scenario, stages: tuple[float, ...], threads: int = 1) -> str:
    """How far GICP moves the real scan when started at the stated truth: a check of the truth."""
    case = scenario.cases[0]
    est = gicp_row(stages, threads=threads)(case.points, case.truth, case.prior_covariance, scenario)
    err = L.pose_error(est.pose, case.truth)
    return (f'truth check: GICP started at the truth moves it by {np.linalg.norm(err[:3]) * 100:.1f} cm '
            f'and {np.rad2deg(np.linalg.norm(err[3:])):.3f} deg')


# ---------------------------------------------------------------------------------------
# Report


def _fmt(v: float, digits: int = 2) -> str:
    return 'n/a' if v is None or not np.isfinite(v) else f'{v:.{digits}f}'


def _band(n: int) -> str:
    """' [lo, hi]': the 95 % band of the mean NEES over ``n`` scans ('' for none)."""
    if not n:
        return ''
    lo, hi = L.mean_nees_band(n)
    return f' [{lo:.2f}, {hi:.2f}]'


def markdown_table(summaries: dict[str, dict[str, float]], band: tuple[float, float]) -> list[str]:
    """One scenario's rows as a markdown table."""
    lines = ['| row | scans | pos. median (m) | pos. p95 (m) | horiz. median (m) | horiz. p95 (m) | vert. p95 (m) | '
             'heading median (deg) | heading p95 (deg) | <= 0.2 m & 1 deg | horiz. <= 0.2 m & 1 deg | NEES mean | '
             'NEES in band | NEES mean, converged (band) | converged | horiz. p95, converged (m) | failures (flagged) | '
             'within 3 sigma x / y / yaw (all) | confident misses | ms/scan median | ms p95 |',
             '|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|---|---:|---:|---:|']
    for row, s in summaries.items():
        lines.append(f"| {row} | {s['n']} | {_fmt(s['position_median'], 3)} | {_fmt(s['position_p95'], 3)} | "
                     f"{_fmt(s['horizontal_median'], 3)} | {_fmt(s['horizontal_p95'], 3)} | "
                     f"{_fmt(s['vertical_p95'], 3)} | "
                     f"{_fmt(s['heading_median'])} | {_fmt(s['heading_p95'])} | {_fmt(s['good_share'])} | "
                     f"{_fmt(s['good_share_horizontal'])} | "
                     f"{_fmt(s['nees_mean'], 1)} | {_fmt(s['nees_in_band'])} | {_fmt(s['nees_mean_converged'], 1)}"
                     f"{_band(s.get('nees_n_converged', 0))} | "
                     f"{_fmt(s['converged_share'])} | {_fmt(s['horizontal_p95_kept'], 3)} | "
                     f"{s['failures']} ({s['failures_flagged']}) | "
                     f"{_fmt(s['within_3sigma_x'])} / {_fmt(s['within_3sigma_y'])} / {_fmt(s['within_3sigma_yaw'])} "
                     f"({_fmt(s['within_3sigma'])}) | {s['confident_misses']} | "
                     f"{_fmt(s['ms_median'], 0)} | {_fmt(s['ms_p95'], 0)} |")
    return lines


def plot(outcomes: list[L.Outcome], path: Path) -> Path:
    """Per scenario and row: the 95th-percentile (bar) and median (dot) position error (3-D,
    then horizontal) and heading error, log scale; a PNG on the Agg canvas."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    tab = L.table(outcomes)
    scenarios = list(tab)
    rows = list(dict.fromkeys(o.row for o in outcomes))
    fig = Figure(figsize=(max(8.0, 1.6 * len(scenarios) + 3), 10.0))
    FigureCanvasAgg(fig)
    axes = fig.subplots(3, 1, sharex=True)
    width = 0.8 / max(len(rows), 1)
    colours = ['tab:blue', 'tab:orange', 'tab:green', 'tab:grey', 'tab:red', 'tab:purple']
    for ax, key, unit, good in ((axes[0], 'position', 'm', L.GOOD_POSITION),
                                (axes[1], 'horizontal', 'm', L.GOOD_POSITION),
                                (axes[2], 'heading', 'deg', L.GOOD_HEADING_DEG)):
        for j, row in enumerate(rows):
            x = np.arange(len(scenarios)) + (j - (len(rows) - 1) / 2) * width
            p95 = [tab[s].get(row, {}).get(f'{key}_p95', np.nan) for s in scenarios]
            med = [tab[s].get(row, {}).get(f'{key}_median', np.nan) for s in scenarios]
            ax.bar(x, np.maximum(p95, 1e-4), width * 0.9, color=colours[j % len(colours)], alpha=0.6,
                   label=f'{row}: p95 (bar), median (dot)')
            ax.plot(x, np.maximum(med, 1e-4), 'o', color=colours[j % len(colours)], markeredgecolor='k')
        ax.axhline(good, color='k', lw=0.8, ls='--')
        ax.set_yscale('log')
        ax.set_ylabel(f"{'3-D position' if key == 'position' else key} error ({unit})")
        ax.grid(True, axis='y', which='both', alpha=0.3)
    axes[0].legend(fontsize=7, loc='upper left', ncol=2)
    axes[2].set_xticks(np.arange(len(scenarios)))
    axes[2].set_xticklabels(scenarios, rotation=20, fontsize=8)
    axes[0].set_title('Localisation error per scenario and row (dashed: 0.2 m / 1 deg)')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path


def targets(tab: dict, kinds: dict[str, tuple[str, int]]) -> list[str]:
    """The issue's figures per scenario: (a)'s 95th-percentile position error over (b)'s
    (target <= 0.7 on the occlusion-heavy rows, <= 1 everywhere) and over (c)'s (<= 1), and
    (a)'s mean NEES against the band of the mean."""
    a, b, c = ROW_NAMES['a'], ROW_NAMES['b'], ROW_NAMES['c']
    lines = ['## The issue\'s figures', '',
             '| scenario | kind | p95 (a) / p95 (b) | horiz. p95 (a) / (b) | target | p95 (a) / p95 (c) | '
             'horiz. p95 (a) / (c) | horiz. p95 (a) / (b), converged | mean NEES (a) | band of the mean |',
             '|---|---|---:|---:|---:|---:|---:|---:|---:|---|']
    for name, rows in tab.items():
        kind, n = kinds.get(name, ('?', 0))
        if a not in rows:
            continue

        def ratio(other: str, key: str = 'position_p95') -> str:
            if other not in rows or not rows[other][key] > 0:
                return 'n/a'
            return f"{rows[a][key] / rows[other][key]:.2f}"

        lo, hi = L.mean_nees_band(max(rows[a]['nees_n'], 1))
        lines.append(f"| {name} | {kind} | {ratio(b)} | {ratio(b, 'horizontal_p95')} | "
                     f"{'<= 0.7' if kind == 'occluded' else '<= 1'} | {ratio(c)} | {ratio(c, 'horizontal_p95')} | "
                     f"{ratio(b, 'horizontal_p95_kept')} | "
                     f"{_fmt(rows[a]['nees_mean'], 1)} | [{lo:.2f}, {hi:.2f}] |")
    return lines + ['']


def paired_table(outcomes: list[L.Outcome], scenarios: list[L.Scenario]) -> list[str]:
    """Row (a) against (b), (c) and (e) scan by scan, per kind of scenario: the scans only one
    of the two got within 0.2 m horizontally and 1 degree."""
    a = ROW_NAMES['a']
    others = [ROW_NAMES[k] for k in ('b', 'c', 'e') if any(o.row == ROW_NAMES[k] for o in outcomes)]
    if not any(o.row == a for o in outcomes) or not others:
        return []
    lines = ['## Scan by scan', '', 'Scans that only one of two rows got within 0.2 m (horizontally) and 1 deg.', '',
             '| kind | other row | scans | only (a) | only the other | both failed |', '|---|---|---:|---:|---:|---:|']
    for kind in dict.fromkeys(s.kind for s in scenarios):
        names = {s.name for s in scenarios if s.kind == kind}
        sel = [o for o in outcomes if o.scenario in names]
        for other in others:
            p = L.paired(sel, a, other)
            lines.append(f"| {kind} | {other} | {p['scans']} | {p['first_only']} | {p['second_only']} | "
                         f"{p['both_failed']} |")
    return lines + ['']


def _commit() -> str:
    try:
        out = subprocess.run(['git', 'rev-parse', '--short', 'HEAD'], cwd=REPO, capture_output=True, text=True,
                             timeout=5, check=False)
        dirty = subprocess.run(['git', 'status', '--porcelain', '--untracked-files=no'], cwd=REPO,
                               capture_output=True, text=True, timeout=5, check=False)
    except (OSError, subprocess.SubprocessError):
        return 'unknown'
    return out.stdout.strip() + (' (with uncommitted changes)' if dirty.stdout.strip() else '')


def write_report(out: Path, scenarios: list[L.Scenario], outcomes: list[L.Outcome], meta: dict) -> dict:
    """Write report.md, report.json and localisation.png; return the JSON dict."""
    out.mkdir(parents=True, exist_ok=True)
    tab = L.table(outcomes)
    png = plot(outcomes, out / 'localisation.png') if outcomes else None
    lines = ['# Localisation against the uncertain map (issue 28)', '',
             f"Command: `{meta['command']}`  ", f"Date: {meta['date']} (UTC), commit {meta['commit']}, "
             f"wall time {meta['wall_seconds']:.0f} s.", '']
    lines += ['Errors: position 3-D (m), and its horizontal (x-y) and vertical parts; heading = yaw of the sensor x axis, absolute, wrapped (deg); '
              '"<= 0.2 m & 1 deg" the share of scans within both; failures: scans more than 0.2 m off horizontally or '
              '1 deg in heading, "flagged" those the row reported as not converged; NEES of the (6-D) error under the output '
              f'covariance, "in band" the share inside chi-square(6)\'s central 95 % band '
              f'[{L.NEES_BAND[0]:.2f}, {L.NEES_BAND[1]:.2f}] (n/a: the row gives no covariance); '
              'ms/scan: wall time of one localisation (GICP: the scan\'s preprocessing included, the '
              "map's not; (a)/(b): the map's queries included).", '',
              f"Priors: horizontal offset {meta['perturbation']['position']} m (uniform, any direction), turn "
              f"{meta['perturbation']['heading_deg']} deg (uniform, either sign), z sigma "
              f"{meta['perturbation']['z_sigma']} m, roll/pitch sigma {meta['perturbation']['tilt_sigma_deg']} deg; "
              f"prior covariance diagonal, sigma {meta['prior_sigma']}. Seed {meta['seed']}.", '',
              f"Rows: {'; '.join(f'{k} {v}' for k, v in meta['row_descriptions'].items())}. "
              f"Normals of rows (a)/(b): {meta['normals']}.", '']
    for sc in scenarios:
        lines.append(f'## {sc.name} ({sc.kind})')
        lines.append('')
        lines += [f'- {n}' for n in sc.notes]
        if sc.name in meta['constant_variance']:
            lines.append(f"- row (b)'s constant variance: {meta['constant_variance'][sc.name]:.3g} m^2 "
                         f"(sd {np.sqrt(meta['constant_variance'][sc.name]) * 100:.1f} cm)")
        n = len(sc.cases)
        lo, hi = L.mean_nees_band(n)
        lines.append(f'- simulated and mapped in {sc.seconds:.1f} s; 95 % band of the mean NEES over {n} scans: '
                     f'[{lo:.2f}, {hi:.2f}]')
        lines.append('')
        lines += markdown_table(tab.get(sc.name, {}), L.NEES_BAND)
        lines.append('')
    pooled: dict[str, dict[str, float]] = {}
    for row in dict.fromkeys(o.row for o in outcomes):
        for kind in ('clean', 'hard', 'occluded', 'real'):
            names = {s.name for s in scenarios if s.kind == kind}
            sel = [o for o in outcomes if o.row == row and o.scenario in names]
            if sel:
                pooled.setdefault(kind, {})[row] = L.summarise(sel)
    lines += targets(tab, {s.name: (s.kind, len(s.cases)) for s in scenarios})
    lines += paired_table(outcomes, scenarios)
    lines.append('## Pooled by kind of scenario')
    lines.append('')
    for kind, summaries in pooled.items():
        lines.append(f'### {kind}')
        lines.append('')
        lines += markdown_table(summaries, L.NEES_BAND)
        lines.append('')
    if png is not None:
        lines += [f'![errors]({png.name})', '']
    (out / 'report.md').write_text('\n'.join(lines))
    data = {
        'meta': meta, 'nees_band': L.NEES_BAND, 'summary': tab, 'pooled': pooled,
        'scenarios': [{'name': s.name, 'kind': s.kind, 'notes': s.notes, 'seconds': s.seconds, 'scans': len(s.cases)}
                      for s in scenarios],
        'scans': [{'scenario': o.scenario, 'row': o.row, 'label': o.label, 'error': o.error.tolist(),
                   'position': o.position, 'heading_deg': o.heading_deg,
                   'nees': o.nees if np.isfinite(o.nees) else None,
                   'ms': o.seconds * 1e3 if np.isfinite(o.seconds) else None, 'converged': o.converged,
                   'prior_error': o.prior_error.tolist(),
                   'sigmas': [float(v) if np.isfinite(v) else None for v in o.sigmas]}
                  for o in outcomes],
    }
    (out / 'report.json').write_text(json.dumps(_clean(data), indent=1, default=_json_default, allow_nan=False))
    return data


def _json_default(v: Any) -> Any:
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    return str(v)


def _clean(obj: Any) -> Any:
    """NaN -> None throughout (JSON)."""
    if isinstance(obj, dict):
        return {k: _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


# ---------------------------------------------------------------------------------------
# Command line


def _ints(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(t) for t in text.split(',') if t.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected comma-separated integers, got {text!r}') from None


def _floats(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(t) for t in text.split(',') if t.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected comma-separated numbers, got {text!r}') from None


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='python -m uncertain_facade_map_apps.localise_report',
                                description=__doc__.split('\n\n')[0])
    p.add_argument('--out', default='output/localisation', help='output folder (default: %(default)s)')
    p.add_argument('--scenes', default=','.join(DEFAULT_SCENES),
                   help='simulated scenes, comma-separated; NAME_occluded maps a drive past tall vans and dense '
                        'trees (default: %(default)s)')
    p.add_argument('--campaigns', type=_ints, default=(1, 2, 3, 4), help='drives localised (default: 1,2,3,4)')
    p.add_argument('--scans-per-drive', type=int, default=8, help='scans per drive (default: %(default)s)')
    p.add_argument('--scan-seconds', type=float, default=1.0, help='seconds of returns per scan (default: %(default)s)')
    p.add_argument('--max-points', type=int, default=20_000, help='most points per scan (default: %(default)s)')
    p.add_argument('--seed', type=int, default=0, help='seed of the priors and subsets (default: %(default)s)')
    p.add_argument('--real', choices=('auto', 'off'), default='auto',
                   help='the Argoverse 2 row from ../shared/data/real (auto: when present)')
    p.add_argument('--real-draws', type=int, default=10, help='priors drawn for the real sweep (default: %(default)s)')
    p.add_argument('--rows', default='a,b,c,d,e', help='rows to run (default: %(default)s)')
    p.add_argument('--constant-variance', type=float, default=None,
                   help="row (b)'s variance, m^2 (default: per scenario, the median of the map's variance + noise "
                        'variance at its own points)')
    p.add_argument('--gicp-stages', type=_floats, default=(3.0, 1.5, 0.5),
                   help='GICP maximum correspondence distances, coarse to fine, m (default: 3,1.5,0.5)')
    p.add_argument('--gicp-threads', type=int, default=1, help='GICP threads (default: %(default)s)')
    p.add_argument('--normals', choices=('surface', 'plane'), default='surface',
                   help="normals of rows (a)/(b): the map's answers' (the mean surface's) or the façade "
                        "plane's (default: %(default)s)")
    p.add_argument('--quick', action='store_true',
                   help='a smoke run: scene small, campaign 1, one scan, 3,000 points, no real row')
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    started = time.perf_counter()
    argv = sys.argv[1:] if argv is None else argv
    if args.quick:
        args.scenes, args.campaigns, args.scans_per_drive, args.max_points, args.real = 'small', (1,), 1, 3000, 'off'
        args.real_draws = 0
    rows_wanted = [r.strip() for r in args.rows.split(',') if r.strip()]
    unknown = [r for r in rows_wanted if r not in ROW_NAMES]
    if unknown:
        print(f'error: unknown rows {unknown}; choose from {", ".join(ROW_NAMES)}', file=sys.stderr)
        return 2
    spec = L.Perturbation()
    constant_used: dict[str, float] = {}

    def constant(scenario: L.Scenario) -> float:
        value = args.constant_variance if args.constant_variance is not None else L.constant_variance(scenario)
        constant_used[scenario.name] = value
        return value

    rows: dict[str, L.Method] = {}
    descriptions = {}
    for r in rows_wanted:
        if r == 'a':
            rows[ROW_NAMES[r]] = L.localiser_row(localise, plane_normals=args.normals == 'plane')
            descriptions[r] = 'localise() with the map\'s variance'
        elif r == 'b':
            rows[ROW_NAMES[r]] = L.localiser_row(localise, constant, plane_normals=args.normals == 'plane')
            descriptions[r] = 'localise() with one constant variance'
        elif r == 'c':
            rows[ROW_NAMES[r]] = gicp_row(args.gicp_stages, threads=args.gicp_threads)
            descriptions[r] = (f'small_gicp GICP, max. correspondence {"/".join(f"{s:g}" for s in args.gicp_stages)} m, '
                               'downsampling 0.25 m, 10 neighbours, 20 iterations per stage, '
                               f'{args.gicp_threads} thread(s), against the mapped building points')
        elif r == 'e':
            rows[ROW_NAMES[r]] = gicp_row(args.gicp_stages, threads=args.gicp_threads, whole_cloud=True)
            descriptions[r] = ('the same GICP against every return of the mapping drive (ground, cars, trees; one '
                               'per 0.1 m voxel): more than our map holds, but what a point-cloud map keeps')
        else:
            rows[ROW_NAMES[r]] = L.prior_row
            descriptions[r] = 'the prior, its covariance'
    scenarios: list[L.Scenario] = []
    try:
        for name in [s.strip() for s in args.scenes.split(',') if s.strip()]:
            scenarios.append(L.simulated_scenario(name, args.campaigns, args.scans_per_drive, args.scan_seconds,
                                                  args.max_points, args.seed, spec, progress=print))
        if args.real == 'auto' and args.real_draws > 0:
            ply0, ply1 = SHARED_REAL / 'av2_7fab_sweep0.ply', SHARED_REAL / 'av2_7fab_sweep1.ply'
            if ply0.exists() and ply1.exists():
                scenarios.append(L.real_scenario(str(ply0), str(ply1), args.real_draws, args.max_points, args.seed,
                                                 spec))
                if 'c' in rows_wanted:
                    scenarios[-1].notes.append(truth_check(scenarios[-1], args.gicp_stages, args.gicp_threads))
                print(f'real: {scenarios[-1].notes[0]}')
            else:
                print(f'real row skipped: {SHARED_REAL} not found')
    except InputError as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 2
    outcomes = L.run(scenarios, rows, progress=print)
    normals_used = ('the façade planes\' (--normals plane)' if args.normals == 'plane' else
                    "the map answers' (the mean surface's gradient)")
    cov = L.prior_covariance(spec)
    sd = np.sqrt(np.diag(cov))
    meta = {
        'command': 'python -m uncertain_facade_map_apps.localise_report ' + ' '.join(shlex.quote(a) for a in argv),
        'date': datetime.datetime.now(datetime.UTC).strftime('%Y-%m-%d %H:%M'),
        'commit': _commit(), 'wall_seconds': time.perf_counter() - started,
        'seed': args.seed,
        'perturbation': {'position': list(spec.position), 'heading_deg': list(spec.heading_deg),
                         'z_sigma': spec.z_sigma, 'tilt_sigma_deg': spec.tilt_sigma_deg},
        'prior_sigma': (f'x, y {sd[0]:.2f} m, z {sd[2]:.2f} m, roll/pitch {np.rad2deg(sd[3]):.2f} deg, '
                        f'yaw {np.rad2deg(sd[5]):.2f} deg'),
        'row_descriptions': descriptions, 'constant_variance': constant_used, 'normals': normals_used,
        'options': dict(vars(args)),
    }
    write_report(Path(args.out), scenarios, outcomes, _clean(meta))
    print((Path(args.out) / 'report.md').read_text())
    print(f'wrote {args.out}/report.md, report.json, localisation.png in {time.perf_counter() - started:.0f} s')
    return 0


if __name__ == '__main__':
    sys.exit(main())
