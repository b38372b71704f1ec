"""Occupancy evaluation against a reference scan (paper, Section IV.C).

Every method maps the same points (:mod:`~uncertain_facade_map.evaluation.baselines`), all are asked for the occupancy
probability of the same voxels, and the voxels are labelled by a *reference* scan of the
same scene (another drive): **positives** are the voxels holding reference points,
**negatives** the voxels the reference rays passed through on their way (sensor origin to
point) and that hold no reference point. The figures are the precision-recall curve and
its area (average precision: the area under the step-wise curve, which is the positives'
share for a constant map and 1 for a perfect one), the ROC AUC beside it, and, for the
maps that give a variance, the same areas over the voxels whose variance is below a
threshold ("accurate inference", paper Fig. 5) or that lie within a distance of the
mapped points (Fig. 6).

Choices where the paper is silent:

- Voxels form a grid aligned with the map frame's origin (voxel ``floor(x / r)``).
- Positives are the voxels holding *any* reference point (all of them, as the paper's
  11.7 M ground-truth points); a voxel some ray crossed but another ray's point lies in is
  positive.
- Rays are a seeded subset of the reference (``max_rays``); a ray marks the voxels of
  samples every ``r / 3`` from the origin to ``r / 2`` before its point.
- Free voxels far outnumber the occupied ones (that skew is why the paper uses PR, not
  ROC). When there are more than ``max_negatives``, a seeded subset is kept and each kept
  negative weighs ``n_negatives / max_negatives`` in every curve and area, so the figures
  estimate those of all the negatives without asking every method for millions of voxels;
  the same for more than ``max_positives`` positives.

Protocols (:data:`PROTOCOLS`; the report names the one used): the paper's maps one campaign
and takes the four others as the reference; the one-campaign protocol takes one other.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from ..errors import InputError
from ..pipeline.step8_occupancy import PLSC
from ..voxels import ReferenceVoxels, reference_voxels

#: Reference campaigns by protocol name (campaign 0 is the mapped one).
PROTOCOLS = {'paper': 4, 'one-campaign': 1}


def protocol_label(n_reference: int) -> str:
    """How the report names the protocol of ``n_reference`` reference campaigns."""
    if n_reference == PROTOCOLS['paper']:
        return "the paper's protocol (one campaign mapped, four others as the reference)"
    if n_reference == 1:
        return 'the one-campaign protocol (one campaign mapped, one other as the reference)'
    return f'one campaign mapped, {n_reference} others as the reference'


def pr_auc(positive: np.ndarray, score: np.ndarray, weight: np.ndarray | None = None) -> float:
    """Area under the precision-recall curve (average precision, step-wise).

    Args:
        positive: (K,) bool labels.
        score: (K,) occupancy probabilities (any monotone score).
        weight: (K,) sample weights, or None.

    Returns:
        The area in [0, 1]; NaN when there are no positives or no negatives.
    """
    from sklearn.metrics import average_precision_score

    positive = np.asarray(positive, dtype=bool)
    if not positive.any() or positive.all():
        return float('nan')
    return float(average_precision_score(positive, score, sample_weight=weight))


def roc_auc(positive: np.ndarray, score: np.ndarray, weight: np.ndarray | None = None) -> float:
    """Area under the ROC curve; NaN when there are no positives or no negatives."""
    from sklearn.metrics import roc_auc_score

    positive = np.asarray(positive, dtype=bool)
    if not positive.any() or positive.all():
        return float('nan')
    return float(roc_auc_score(positive, score, sample_weight=weight))


def pr_curve(positive: np.ndarray, score: np.ndarray, weight: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray]:
    """``(recall, precision)`` of the precision-recall curve, recall decreasing, ending at
    recall 0 and precision 1 (as scikit-learn's ``precision_recall_curve``)."""
    ranked = _Ranked.of(np.asarray(positive, dtype=bool), np.asarray(score, dtype=np.float64),
                        None if weight is None else np.asarray(weight, dtype=np.float64))
    recall, precision = ranked.steps(np.ones(len(ranked.order), dtype=bool))  # every voxel
    return np.r_[recall[::-1], 0.0], np.r_[precision[::-1], 1.0]


@dataclass(frozen=True, eq=False)
class _Ranked:
    """Voxels ranked once by decreasing score, so that many subsets of them are scored
    without sorting again (a subset of a ranking is ranked).

    Attributes:
        order: (K,) the voxels' indices, highest score first.
        positive, score, weight: (K,) labels, scores and weights in that order.
    """

    order: np.ndarray
    positive: np.ndarray
    score: np.ndarray
    weight: np.ndarray

    @classmethod
    def of(cls, positive: np.ndarray, score: np.ndarray, weight: np.ndarray | None) -> _Ranked:
        order = np.argsort(-score, kind='stable')
        w = np.ones(len(score)) if weight is None else weight[order]
        return cls(order, positive[order], score[order], w)

    def steps(self, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(recall, precision)`` at each distinct score of the kept voxels ((K,) bool in
        ranked order), highest score first: the steps of the PR curve."""
        pos, score, w = self.positive[k], self.score[k], self.weight[k]
        tp = np.cumsum(np.where(pos, w, 0.0))
        fp = np.cumsum(np.where(pos, 0.0, w))
        last = np.r_[np.flatnonzero(np.diff(score)), len(score) - 1]  # one step per distinct score
        tp, fp = tp[last], fp[last]
        return tp / tp[-1], tp / (tp + fp)

    def subset(self, keep: np.ndarray) -> tuple[float, float]:
        """``(pr_auc, share)`` over the kept voxels (as :func:`subset_auc`): the step-wise
        area, sum over the steps of the recall gained times the precision there."""
        k = keep[self.order]
        share = float(self.weight[k].sum() / self.weight.sum())
        if not self.positive[k].any() or self.positive[k].all():
            return float('nan'), share
        recall, precision = self.steps(k)
        return float(np.sum(np.diff(np.r_[0.0, recall]) * precision)), share


@dataclass(eq=False)
class MethodResult:
    """One method at one resolution.

    Attributes:
        name: the method's label.
        resolution: voxel side, metres.
        p: (K,) occupancy probability of each reference voxel.
        variance: (K,) the method's variance at each voxel, or None.
        fit_seconds: training (map building) time, seconds.
        predict_seconds: testing (query) time, seconds.
        pr_auc: area under the precision-recall curve.
        roc_auc: area under the ROC curve.
        extra: the method's per-voxel diagnostics (:meth:`OccupancyMethod.diagnostics`).
        trains_on_predict: part of the training ran in ``predict`` (so in the testing time).
        plsc: the PLSC parameters the method learnt (its ``plsc_``), or None.
    """

    name: str
    resolution: float
    p: np.ndarray
    variance: np.ndarray | None
    fit_seconds: float
    predict_seconds: float
    pr_auc: float
    roc_auc: float
    extra: dict = field(default_factory=dict)
    trains_on_predict: bool = False
    plsc: PLSC | None = None


def run_method(method, points: np.ndarray, origins: np.ndarray, ref: ReferenceVoxels) -> MethodResult:
    """Fit ``method`` (an :class:`~uncertain_facade_map.evaluation.baselines.base.OccupancyMethod`) on the mapped points,
    predict the reference voxels, time both and score them.

    Raises:
        InputError: the method's predictions are not (K,) probabilities in [0, 1].
    """
    t0 = time.perf_counter()
    method.fit(points, origins)
    t1 = time.perf_counter()
    p = np.asarray(method.predict(ref.centres), dtype=np.float64)
    variance = method.predict_variance(ref.centres)
    t2 = time.perf_counter()
    if p.shape != (len(ref.centres),) or not np.all((p >= 0) & (p <= 1)):
        raise InputError(f'{method.name} returned no (K,) probabilities in [0, 1]')
    return MethodResult(method.name, ref.resolution, p, None if variance is None else np.asarray(variance, float),
                        t1 - t0, t2 - t1, pr_auc(ref.positive, p, ref.weight), roc_auc(ref.positive, p, ref.weight),
                        dict(method.diagnostics(ref.centres)), bool(getattr(method, 'trains_on_predict', False)),
                        getattr(method, 'plsc_', None))


def subset_auc(result: MethodResult, ref: ReferenceVoxels, keep: np.ndarray) -> tuple[float, float]:
    """``(pr_auc, share)`` over the voxels where ``keep`` holds; share: their weighted share
    of all voxels."""
    keep = np.asarray(keep, dtype=bool)
    share = float(ref.weight[keep].sum() / ref.weight.sum())
    return pr_auc(ref.positive[keep], result.p[keep], ref.weight[keep]), share


def auc_by_variance(result: MethodResult, ref: ReferenceVoxels, thresholds: Sequence[float]
                    ) -> tuple[np.ndarray, np.ndarray]:
    """PR AUC over the voxels whose variance is at most each threshold (paper Figs. 5, 6a).

    Returns:
        ``(auc, share)``, each (T,); NaN where the subset lacks positives or negatives.

    Raises:
        InputError: the method gives no variance.
    """
    if result.variance is None:
        raise InputError(f'{result.name} gives no variance')
    ranked = _Ranked.of(ref.positive, result.p, ref.weight)
    out = [ranked.subset(result.variance <= t) for t in thresholds]
    return np.array([a for a, _ in out]), np.array([s for _, s in out])


def distance_to_points(centres: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(K,) distance of each voxel centre to the nearest of (N, 3) points, metres."""
    from scipy.spatial import cKDTree

    return cKDTree(points).query(centres, workers=-1)[0]


def auc_by_distance(result: MethodResult, ref: ReferenceVoxels, distance: np.ndarray,
                    limits: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """PR AUC over the voxels within each distance limit of the mapped points (paper Fig. 6b).

    Args:
        distance: (K,) distance of each voxel centre to the nearest mapped point, metres.
        limits: distance limits, metres.

    Returns:
        ``(auc, share)``, each (L,).
    """
    ranked = _Ranked.of(ref.positive, result.p, ref.weight)
    out = [ranked.subset(distance <= d) for d in limits]
    return np.array([a for a, _ in out]), np.array([s for _, s in out])


#: Bins of the voxel centre's signed distance from our mean surface, in voxel sides
#: (negative: behind the surface, inside the building).
SURFACE_BINS = (-np.inf, -1.5, -0.5, 0.5, 1.5, np.inf)
SURFACE_BIN_LABELS = ('behind, > 1.5 voxels', 'behind, 0.5-1.5 voxels', 'at the surface, +-0.5 voxel',
                      'in front, 0.5-1.5 voxels', 'in front, > 1.5 voxels', 'no façade')


@dataclass(frozen=True)
class SurfaceBin:
    """The labelled voxels of one bin of :data:`SURFACE_BINS`.

    Attributes:
        label: the bin's label.
        positives: voxels holding reference points.
        negatives: weighted count of free voxels.
        mean_p: method name -> weighted mean occupancy probability over the bin's voxels.
    """

    label: str
    positives: int
    negatives: float
    mean_p: dict

    @property
    def share_positive(self) -> float:
        """The bin's share of positives (its precision if all of it were called occupied)."""
        total = self.positives + self.negatives
        return self.positives / total if total else float('nan')


def surface_breakdown(ref: ReferenceVoxels, results: Sequence[MethodResult], signed_distance: np.ndarray
                      ) -> list[SurfaceBin]:
    """Where the labelled voxels lie relative to our mean surface, and what each method
    gives them: explains where methods differ (the report's "why").

    Args:
        ref: the labelled voxels of one resolution.
        results: the methods' results at that resolution.
        signed_distance: (K,) each voxel centre's signed distance from our mean surface,
            metres, positive in front; NaN where no façade covers it.

    Returns:
        One :class:`SurfaceBin` per bin of :data:`SURFACE_BINS`, then one for "no façade"
        (bins without voxels included, with NaN means).
    """
    which = surface_bins(ref, signed_distance)
    out = []
    for b, label in enumerate(SURFACE_BIN_LABELS):
        sel = which == b
        w = ref.weight[sel]
        mean_p = {r.name: float(np.average(r.p[sel], weights=w)) if sel.any() else float('nan') for r in results}
        out.append(SurfaceBin(label, int(ref.positive[sel].sum()), float(w[~ref.positive[sel]].sum()), mean_p))
    return out


def surface_bins(ref: ReferenceVoxels, signed_distance: np.ndarray) -> np.ndarray:
    """(K,) index into :data:`SURFACE_BIN_LABELS` of each labelled voxel.

    Args:
        ref: the labelled voxels of one resolution.
        signed_distance: (K,) each voxel centre's signed distance from our mean surface,
            metres, positive in front; NaN where no façade covers it (the last bin).
    """
    s = np.asarray(signed_distance, dtype=np.float64) / ref.resolution
    known = np.isfinite(s)
    return np.where(known, np.digitize(np.where(known, s, 0.0), SURFACE_BINS[1:-1]), len(SURFACE_BINS) - 1)


def decisive_bin(ref: ReferenceVoxels, ours: MethodResult, other: MethodResult, signed_distance: np.ndarray
                 ) -> tuple[str, float, float]:
    """The surface bin whose voxels give ``other`` most of its PR AUC lead over ``ours``:
    the one that, left out, shrinks ``other.pr_auc - ours.pr_auc`` the most.

    Returns:
        ``(label, other_auc, ours_auc)``: the bin and both PR AUCs without its voxels.
    """
    which = surface_bins(ref, signed_distance)
    best = None
    for b, label in enumerate(SURFACE_BIN_LABELS):
        keep = which != b
        if keep.all():
            continue
        a_other = pr_auc(ref.positive[keep], other.p[keep], ref.weight[keep])
        a_ours = pr_auc(ref.positive[keep], ours.p[keep], ref.weight[keep])
        if best is None or a_other - a_ours < best[1] - best[2]:
            best = (label, a_other, a_ours)
    return best if best is not None else ('', other.pr_auc, ours.pr_auc)


def evaluate(methods: Sequence[Callable[[float], object]], points: np.ndarray, origins: np.ndarray,
             ref_points: np.ndarray, ref_origins: np.ndarray, resolutions: Sequence[float] = (0.1, 0.05),
             max_rays: int = 50_000, max_negatives: int = 400_000, seed: int = 0,
             progress: Callable[[str], None] | None = None, max_positives: int = 400_000
             ) -> tuple[dict[float, ReferenceVoxels], list[MethodResult]]:
    """Run every method at every resolution on the same points and reference voxels.

    Args:
        methods: factories ``resolution -> OccupancyMethod``.
        points: (N, 3) mapped points, map frame, metres.
        origins: (N, 3) their sensor origins.
        ref_points: (M, 3) reference points.
        ref_origins: (M, 3) their sensor origins.
        resolutions: voxel sides, metres.
        max_rays, max_negatives, seed, max_positives: see :func:`reference_voxels`.
        progress: called with a line of text after each step.

    Returns:
        ``(references, results)``: the labelled voxels per resolution, and one result per
        method and resolution (resolution-major, in the order of ``methods``).
    """
    refs, results = {}, []
    for r in resolutions:
        t0 = time.perf_counter()
        ref = reference_voxels(ref_points, ref_origins, r, max_rays, max_negatives, seed,
                               max_positives=max_positives)
        refs[r] = ref
        if progress is not None:
            progress(f'{r:g} m: {ref.n_positives:,} occupied and {ref.n_negatives:,} free reference voxels '
                     f'from {ref.n_rays:,} rays ({len(ref.centres):,} asked, {time.perf_counter() - t0:.1f} s)')
        for factory in methods:
            res = run_method(factory(r), points, origins, ref)
            results.append(res)
            if progress is not None:
                learnt = '' if res.plsc is None else f'  PLSC scale {res.plsc.scale:.3g} spread {res.plsc.spread:.3g} m'
                progress(f'{r:g} m: {res.name:<12} PR AUC {res.pr_auc:.3f}  ROC AUC {res.roc_auc:.3f}  '
                         f'train {res.fit_seconds:.1f} s  test {res.predict_seconds:.1f} s{learnt}')
    return refs, results
