"""The evaluation's report: one Markdown file with the AUC tables and PNG figures
(precision-recall curves; AUC against the variance threshold and against the distance to
the mapped points, ours beside GPIS as in the paper, and every method against distance;
training and testing times: paper Figs. 4-7).
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from .occupancy import (
    MethodResult,
    ReferenceVoxels,
    auc_by_distance,
    auc_by_variance,
    decisive_bin,
    pr_curve,
    subset_auc,
    surface_breakdown,
)
from .truth_map import TruthMethod

#: Variance thresholds of the AUC-against-uncertainty figure, m^2.
VARIANCE_THRESHOLDS = tuple(float(x) for x in np.geomspace(1e-4, 1.0, 13))
#: Distance limits of the AUC-against-distance figure, metres.
DISTANCE_LIMITS = (0.05, 0.1, 0.2, 0.3, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 5.0)
OURS = 'Ours'
#: The ceiling's rows (:mod:`~uncertain_facade_map.evaluation.truth_map`): not a baseline.
TRUTH = TruthMethod.name
#: The methods of the uncertainty figures (paper Figs. 5, 6: our map beside GPIS).
UNCERTAINTY_PAIR = (OURS, 'GPIS')


def _fmt(x: float) -> str:
    return '-' if not np.isfinite(x) else f'{x:.3f}'


def accurate_label(threshold: float) -> str:
    return f'{OURS}, variance <= {threshold:g}'


def write_report(out: str | Path, refs: dict[float, ReferenceVoxels], results: Sequence[MethodResult],
                 distances: dict[float, np.ndarray], variance_threshold: float = 0.01, title: str = '',
                 notes: Sequence[str] = ()) -> Path:
    """Write ``report.md`` and its figures into ``out``.

    Args:
        out: output folder (created if its parent exists).
        refs: labelled voxels per resolution.
        results: one result per method and resolution.
        distances: per resolution, (K,) distance of each voxel to the nearest mapped point, metres.
        variance_threshold: the accurate-inference threshold, m^2 (paper: 0.01).
        title: the first line of the report (what was evaluated).
        notes: lines added under the title (data, settings).

    Returns:
        The path of ``report.md``.
    """
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    out = Path(out)
    out.mkdir(exist_ok=True)
    resolutions = list(refs)
    names = list(dict.fromkeys(r.name for r in results))
    by = {(r.name, r.resolution): r for r in results}
    accurate = {res: subset_auc(by[(OURS, res)], refs[res], by[(OURS, res)].variance <= variance_threshold)
                for res in resolutions if (OURS, res) in by and by[(OURS, res)].variance is not None}

    # Fig. 4: precision-recall curves.
    fig, axes = plt.subplots(1, len(resolutions), figsize=(6 * len(resolutions), 5), squeeze=False)
    for ax, res in zip(axes[0], resolutions):
        ref = refs[res]
        for name in names:
            r = by.get((name, res))
            if r is None:
                continue
            recall, precision = pr_curve(ref.positive, r.p, ref.weight)
            ax.plot(recall, precision, label=f'{name} ({r.pr_auc:.3f})', lw=1.5)
        if res in accurate:
            r = by[(OURS, res)]
            keep = r.variance <= variance_threshold
            recall, precision = pr_curve(ref.positive[keep], r.p[keep], ref.weight[keep])
            ax.plot(recall, precision, label=f'{accurate_label(variance_threshold)} ({accurate[res][0]:.3f})',
                    lw=1.5, ls='--', color='black')
        ax.set(xlabel='recall', ylabel='precision', title=f'{res:g} m voxels', xlim=(0, 1), ylim=(0, 1.02))
        ax.legend(fontsize=8, loc='lower left')
        ax.grid(alpha=0.3)
    fig.suptitle('Precision-recall curves (PR AUC in the legend)')
    fig.tight_layout()
    fig.savefig(out / 'pr_curves.png', dpi=100)
    plt.close(fig)

    # Figs. 5-6: AUC against the variance threshold and against the distance to the data,
    # our map beside GPIS (as in the paper; both variances are of a surface position, m^2
    # near the surface), with the share of voxels kept under each.
    paired = [n for n in UNCERTAINTY_PAIR if all(by.get((n, res)) is not None and by[(n, res)].variance is not None
                                                 for res in resolutions)]
    fig, axes = plt.subplots(2, 2, figsize=(12, 8), sharex='col')
    for name, colour in zip(paired, ('tab:blue', 'tab:red')):
        for res, ls in zip(resolutions, ('-', '--', ':', '-.')):
            auc, share = auc_by_variance(by[(name, res)], refs[res], VARIANCE_THRESHOLDS)
            axes[0, 0].semilogx(VARIANCE_THRESHOLDS, auc, ls, color=colour, marker='o', ms=3, label=f'{name}, {res:g} m')
            axes[1, 0].semilogx(VARIANCE_THRESHOLDS, share, ls, color=colour, marker='o', ms=3)
            auc, share = auc_by_distance(by[(name, res)], refs[res], distances[res], DISTANCE_LIMITS)
            axes[0, 1].plot(DISTANCE_LIMITS, auc, ls, color=colour, marker='o', ms=3, label=f'{name}, {res:g} m')
            axes[1, 1].plot(DISTANCE_LIMITS, share, ls, color=colour, marker='o', ms=3)
    for ax in axes[:, 0]:
        ax.axvline(variance_threshold, color='grey', lw=0.8)
    axes[0, 0].set(ylabel='PR AUC', title='Voxels whose variance is at most the threshold')
    axes[1, 0].set(xlabel='variance threshold (m^2)', ylabel='share of the voxels kept')
    axes[0, 1].set(ylabel='PR AUC', title='Voxels within a distance of the mapped points')
    axes[1, 1].set(xlabel='distance to the nearest mapped point, at most (m)', ylabel='share of the voxels kept')
    for ax in axes.flat:
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / 'auc_uncertainty.png', dpi=100)
    plt.close(fig)

    # AUC against the distance to the data, every method.
    fig, axes = plt.subplots(1, len(resolutions), figsize=(6 * len(resolutions), 4.5), squeeze=False, sharey=True)
    for ax, res in zip(axes[0], resolutions):
        for name in names:
            if (name, res) in by:
                auc, _ = auc_by_distance(by[(name, res)], refs[res], distances[res], DISTANCE_LIMITS)
                ax.plot(DISTANCE_LIMITS, auc, marker='o', ms=3, label=name,
                        ls='--' if name.endswith('(solid)') else '-')
        ax.set(xlabel='distance to the nearest mapped point, at most (m)', ylabel='PR AUC', title=f'{res:g} m voxels')
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / 'auc_distance.png', dpi=100)
    plt.close(fig)

    # Fig. 7: training and testing time.
    fig, axes = plt.subplots(1, len(resolutions), figsize=(6 * len(resolutions), 4), squeeze=False)
    for ax, res in zip(axes[0], resolutions):
        rs = [by[(n, res)] for n in names if (n, res) in by]
        x = np.arange(len(rs))
        ax.bar(x - 0.2, [r.fit_seconds for r in rs], 0.4, label='training')
        ax.bar(x + 0.2, [r.predict_seconds for r in rs], 0.4, label='testing')
        ax.set_xticks(x, [r.name for r in rs], rotation=20)
        ax.set(ylabel='seconds', title=f'{res:g} m: {len(refs[res].centres):,} test voxels')
        ax.legend()
        ax.grid(alpha=0.3, axis='y')
    fig.tight_layout()
    fig.savefig(out / 'timing.png', dpi=100)
    plt.close(fig)

    lines = [f'# {title or "Occupancy evaluation"}', '']
    lines += [f'- {n}' for n in notes]
    lines += [f'- {res:g} m: {refs[res].n_positives:,} occupied and {refs[res].n_negatives:,} free reference '
              f'voxels from {refs[res].n_rays:,} rays; {len(refs[res].centres):,} voxels asked'
              + ''.join(f' ({kind} ones subsampled, each weighing {w[0]:.2f})'
                        for kind, w in (('occupied', refs[res].weight[refs[res].positive]),
                                        ('free', refs[res].weight[~refs[res].positive])) if len(w) and w[0] > 1)
              for res in resolutions]
    lines += ['', '## Area under the precision-recall curve', '',
              '| method | ' + ' | '.join(f'{res:g} m' for res in resolutions) + ' |',
              '|---|' + '---:|' * len(resolutions)]
    for name in names:
        lines.append(f'| {name} | ' + ' | '.join(_fmt(by[(name, res)].pr_auc) if (name, res) in by else '-'
                                                 for res in resolutions) + ' |')
    if accurate:
        lines.append(f'| {accurate_label(variance_threshold)} | '
                     + ' | '.join(f'{_fmt(accurate[res][0])} ({accurate[res][1]:.0%} of voxels)'
                                  if res in accurate else '-' for res in resolutions) + ' |')
    learnt = [(name, res, by[(name, res)].plsc) for name in names for res in resolutions
              if (name, res) in by and by[(name, res)].plsc is not None]
    if learnt:
        lines += ['', 'PLSC parameters learnt from the mapped points alone (scale of the half voxel, spread added '
                      "to the map's sd; the fixed formula is scale 1, spread 0): "
                  + '; '.join(f'{name} at {res:g} m: {p.scale:.2f}, {p.spread * 100:.1f} cm' if p.learnt else
                              f'{name} at {res:g} m: too few labelled voxels, the fixed formula'
                              for name, res, p in learnt) + '.']
    lines += ['', '## Area under the ROC curve', '',
              '| method | ' + ' | '.join(f'{res:g} m' for res in resolutions) + ' |',
              '|---|' + '---:|' * len(resolutions)]
    for name in names:
        lines.append(f'| {name} | ' + ' | '.join(_fmt(by[(name, res)].roc_auc) if (name, res) in by else '-'
                                                 for res in resolutions) + ' |')
    lines += ['', '## Training and testing time (seconds, one run)', '',
              '| method | ' + ' | '.join(f'train {res:g} m | test {res:g} m' for res in resolutions) + ' |',
              '|---|' + '---:|---:|' * len(resolutions)]
    for name in names:
        lines.append(f'| {name} | ' + ' | '.join(
            f'{by[(name, res)].fit_seconds:.1f} | {by[(name, res)].predict_seconds:.1f}' if (name, res) in by
            else '- | -' for res in resolutions) + ' |')
    deferred = [n for n in names if any(by[(n, res)].trains_on_predict for res in resolutions if (n, res) in by)]
    if deferred:
        lines += ['', f'{", ".join(deferred)}: part of the training runs on demand in the first query (only '
                      'what the asked voxels need), so it is counted in the testing time.']
    readings = [n for n in names if n.startswith(OURS) and n != OURS]
    if readings and OURS in names:
        lines += ['', f'{", ".join(readings)}: other readings of the map {OURS} built, which they reuse: '
                      f"{OURS}'s training time holds the map's build and its PLSC calibration, theirs only "
                      'what they add.']
    truths = (TRUTH, f'{TRUTH} (PLSC)')  # the surface reading, fixed and learnt: the better is the ceiling
    ceiling = [(res, by[(OURS, res)].pr_auc, max((by[(t, res)].pr_auc, t) for t in truths if (t, res) in by))
               for res in resolutions if (OURS, res) in by and any((t, res) in by for t in truths)]
    if ceiling:
        lines += ['', '## Against the ceiling', '',
                  f"{TRUTH}: the simulated scene's exact geometry read as a map by our rules (variance 0, the "
                  "sensor's noise; the fixed formula and PLSC, the better of the two is the ceiling): what a "
                  "perfect surface map scores under this reference.", '']
        lines += [f'- {res:g} m: ours {ours:.3f}, {name} {truth:.3f}: {truth - ours:+.3f} to the ceiling'
                  for res, ours, (truth, name) in ceiling]
    lines += ['', '## Where a baseline wins', '']
    wins = []
    for res in resolutions:
        if (OURS, res) not in by:
            continue
        ours = by[(OURS, res)].pr_auc
        for name in names:
            r = by.get((name, res))
            if not name.startswith((OURS, TRUTH)) and r is not None and r.pr_auc > ours:
                line = (f'- {res:g} m: **{name}** {r.pr_auc:.3f} against our {ours:.3f} (PR AUC); it took '
                        f'{r.fit_seconds:.1f} s to train and {r.predict_seconds:.1f} s to test (ours '
                        f'{by[(OURS, res)].fit_seconds:.1f} s and {by[(OURS, res)].predict_seconds:.1f} s).')
                if 'signed_distance' in by[(OURS, res)].extra:
                    label, a_other, a_ours = decisive_bin(refs[res], by[(OURS, res)], r,
                                                          by[(OURS, res)].extra['signed_distance'])
                    line += (f' Most of its lead comes from the voxels {label} of our surface: without them '
                             f'{name} scores {a_other:.3f} and ours {a_ours:.3f} (see the table below).')
                wins.append(line)
    if len(names) < 2 or OURS not in names:
        lines.append('- No comparison: the run had no baseline, or not our map.')
    else:
        lines += wins or ['- Nowhere: our map has the highest PR AUC at every resolution.']
    for res in resolutions:
        ours = by.get((OURS, res))
        if ours is None or 'signed_distance' not in ours.extra:
            continue
        rs = [by[(n, res)] for n in names if (n, res) in by]
        if res == resolutions[0]:
            lines += ['', '## Where the voxels lie and what each method gives them', '',
                      "The labelled voxels binned by their centre's signed distance from our mean surface "
                      '(in voxel sides; behind = inside the building). A method ranks well when its mean p is '
                      'high where the share of positives is high. Reference rays rarely reach voxels behind the '
                      'surface, so the few labelled there are mostly positives (points put there by the noise '
                      'and the grid offset).']
        lines += ['', f'{res:g} m:', '',
                  '| voxels | positives | negatives (weighted) | share positive | '
                  + ' | '.join(f'mean p {r.name}' for r in rs) + ' |',
                  '|---|---:|---:|---:|' + '---:|' * len(rs)]
        for b in surface_breakdown(refs[res], rs, ours.extra['signed_distance']):
            lines.append(f'| {b.label} | {b.positives:,} | {b.negatives:,.0f} | {_fmt(b.share_positive)} | '
                         + ' | '.join(_fmt(b.mean_p[r.name]) for r in rs) + ' |')
    lines += ['', '## Figures', '', '![PR curves](pr_curves.png)', '',
              '![AUC against variance and distance, ours and GPIS](auc_uncertainty.png)', '',
              '![AUC against distance, every method](auc_distance.png)', '', '![Timing](timing.png)', '']
    path = out / 'report.md'
    path.write_text('\n'.join(lines))
    return path
