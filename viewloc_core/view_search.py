"""Which training view, at which angle and scale, explains an image location best.

The 2D alignment (:mod:`viewloc_core.align`) finds *where* an object is, but
its model view is a cluster of training views, and neighbouring clusters fit
an outline about equally well in 2D (a barbell's plate seen end-on or seen
from the side). Here every training view of the model is laid over the
location, at a few in-plane angles and scales around the match, and scored
by how much of its outline the image edges confirm, against how often edges
of that orientation occur by chance in this image (the background model of
Pope & Lowe's g(E, T), applied to dense edge samples rather than to sparse
features). The best few are fitted by weighted least squares and scored
again; the 6D pose starts from the winner.

Scoring is the log-likelihood ratio object vs. clutter of
:mod:`viewloc_core.edge_evidence`, summed over the edge samples of a view.
Each sample is weighted by the edge length it stands for in the image, so a
view that explains the whole outline beats one that explains a part of it
(one plate of a barbell) equally well.

A part's two sides show mirrored outlines, which the edges can tell apart
worse than the fitted surface's shading and colour can: on request the
search also returns the best view of the other side of the part, for the
pose stage to fit and compare (``search_views(other_side=...)``).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from viewloc_core import similarity as sim2
from viewloc_core.align import coverage_many, extend_many, sample_spacing_px, spread_subset
from viewloc_core.edge_evidence import (
    ChanceRates,
    lay_over_grid_of_templates,
    lay_over_templates,
    outline_samples,
)
from viewloc_core.features import (
    ImageFeatures,
    orientation_bin,
)
from viewloc_core.model import ObjectModel, cached_per_model
from viewloc_core.sample_classes import sample_codes, training_view_sample_classes

F64 = NDArray[np.float64]

#: In-plane angle offsets (degrees) and scale factors of the coarse grid. The
#: spread orientation map accepts ±1 bin (±11°), so 5° steps leave no gap.
COARSE_ANGLES_DEG = (-10.0, -5.0, 0.0, 5.0, 10.0)
COARSE_SCALES = (0.93, 1.0, 1.07)

#: Angle offsets (degrees) at which every view is screened, at the seed's
#: scale, before the best ``SCREENED_VIEWS`` get the full grid.
SCREEN_ANGLES_DEG = (-5.0, 0.0, 5.0)
SCREENED_VIEWS = 16

#: Edge samples per view in the coarse grid.
COARSE_POINTS = 48

#: A screen of more (view, similarity) pairs than this is done in two
#: passes: every pair on the first PRESCREEN_POINTS of its view's coarse
#: samples (farthest-point order, so they spread over the whole view), and
#: the best PRESCREEN_KEPT share of them on all COARSE_POINTS. The colour
#: locations of a real photo screen about 105,000 pairs each (72 angles and
#: scales times 9 offsets times 162 views): on all samples that took 76 ms
#: of LM-O's 230 ms per image, in two passes 38 ms.
PRESCREEN_MIN_PAIRS = 20_000
PRESCREEN_POINTS = 12
PRESCREEN_KEPT = 0.04

#: Coarse candidates that get the least-squares fit on all their samples.
FITTED_CANDIDATES = 12

#: Search radii (px) of the least-squares fit's nearest-edge matching.
FIT_RADII_PX = (4.0, 2.5, 1.5)

#: Views whose directions lie at least this far apart see a part from its
#: two sides: a half turn about any axis in the image plane takes the line
#: of sight to its opposite, and the outline to its mirror image, which on
#: a nearly mirror-symmetric part is the outline turned.
OTHER_SIDE_MIN_DEG = 110.0

#: With ``other_side`` (:func:`search_views`), the other side's best views
#: in the screen that get the full grid of their own. LM-O objects 1, 5,
#: 6, 8, learning seed 0, 4 and 2: AR_MSSD / AR_MSPD 0.151 / 0.208 and
#: 0.151 / 0.207.
OTHER_SIDE_SCREENED = 2


@dataclass(frozen=True, slots=True, eq=False)
class ViewTemplates:
    """Edge samples of every training view of a model, padded to one length.

    Attributes
    ----------
    pts : (T, P, 2) float64
        Edge samples in each training view's own frame, pixels.
    theta : (T, P) float64
        Their orientations modulo π.
    bins : (T, P) int64
        Their orientation bins.
    valid : (T, P) bool
        False for padding.
    coarse : (T, C) int64
        Indices of a well-spread subset of each view's samples (repeated
        indices pad views with fewer samples).
    length_px : (T,) float64
        Edge length one sample stands for at scale 1, pixels.
    px, py : (T, P) float32
        ``pts`` split by coordinate in the precision the scoring uses.
    bins8 : (T, P) uint8
        ``bins`` with each sample's class, as the scoring reads them
        (:func:`viewloc_core.sample_classes.sample_codes`).
    coarse_px, coarse_py : (T, C) float32
    coarse_bins8 : (T, C) uint8
    coarse_valid : (T, C) bool
        The same for the coarse subsets (what every screening reads).
    directions : (T, 3) float64
        Unit direction from the part to each view's camera, part frame.
    """

    pts: F64
    theta: F64
    bins: NDArray[np.int64]
    valid: NDArray[np.bool_]
    coarse: NDArray[np.int64]
    length_px: F64
    px: NDArray[np.float32]
    py: NDArray[np.float32]
    bins8: NDArray[np.uint8]
    coarse_px: NDArray[np.float32]
    coarse_py: NDArray[np.float32]
    coarse_bins8: NDArray[np.uint8]
    coarse_valid: NDArray[np.bool_]
    directions: F64

    def __len__(self) -> int:
        return int(self.pts.shape[0])


def build_templates(model: ObjectModel) -> ViewTemplates:
    """Stack the training views' edge samples (once per model)."""
    tr = model.training
    n_views = len(tr)
    n_max = max(1, max(len(e) for e in tr.edge_xy))
    pts = np.zeros((n_views, n_max, 2))
    theta = np.zeros((n_views, n_max))
    valid = np.zeros((n_views, n_max), bool)
    coarse = np.zeros((n_views, COARSE_POINTS), np.int64)
    length = np.ones(n_views)
    rng = np.random.default_rng(0)
    for t in range(n_views):
        xy = np.asarray(tr.edge_xy[t], np.float64)
        n = len(xy)
        if n == 0:
            continue
        pts[t, :n] = xy
        theta[t, :n] = tr.edge_theta[t]
        valid[t, :n] = True
        pick = spread_subset(xy, COARSE_POINTS, rng)
        coarse[t] = np.resize(pick, COARSE_POINTS)
        length[t] = sample_spacing_px(xy)
    bins = orientation_bin(theta)
    px = np.ascontiguousarray(pts[..., 0], dtype=np.float32)
    py = np.ascontiguousarray(pts[..., 1], dtype=np.float32)
    # The kernels read each sample's class (outline, crease, interior) with
    # its bin: each class is found at the true pose at its own rate.
    bins8 = sample_codes(bins, training_view_sample_classes(model, pts, valid.sum(axis=1)))
    rows = np.arange(n_views)[:, None]
    return ViewTemplates(
        pts, theta, bins, valid, coarse, length, px, py, bins8,
        px[rows, coarse], py[rows, coarse], bins8[rows, coarse], valid[rows, coarse],
        # The camera looks along its +z: from the part it lies along -z,
        # the third row of each view's rotation negated.
        -np.asarray(tr.R_m2c, np.float64).reshape(n_views, 3, 3)[:, 2, :],
    )


_TEMPLATES: weakref.WeakKeyDictionary[ObjectModel, ViewTemplates] = weakref.WeakKeyDictionary()


def view_templates(model: ObjectModel) -> ViewTemplates:
    """The model's view templates, built once and cached while the model lives."""
    return cached_per_model(_TEMPLATES, model, build_templates)


@dataclass(frozen=True, slots=True)
class ViewCandidate:
    """One training view laid over the image.

    Attributes
    ----------
    view : int
        Training view index.
    sim : (4,) float64
        Training-view frame -> image similarity ``(x, y, angle_rad, scale)``.
    log_likelihood_ratio : float
        Object vs. clutter evidence of its edge samples (see module docstring).
    hit_fraction : float
        Share of its edge samples confirmed by an image edge.
    """

    view: int
    sim: F64
    log_likelihood_ratio: float
    hit_fraction: float


def score_views(
    feats: ImageFeatures, templates: ViewTemplates, views: NDArray[np.int64], sims: F64,
    chance: ChanceRates, subset: NDArray[np.int64] | None = None,
) -> tuple[F64, F64, F64]:
    """Log-likelihood ratio and hit fraction of H (view, similarity) pairs.

    Parameters
    ----------
    feats : ImageFeatures
        The image, with its spread orientation map.
    templates : ViewTemplates
    views : (H,) int
        Training views.
    sims : (H, 4) float64
        Training-view frame -> image similarities.
    chance : ChanceRates
        From :func:`chance_rates`.
    subset : (H, C) int, optional
        Sample indices per pair (all valid samples when None).

    Returns
    -------
    llr : (H,) float64
        Summed over samples, each weighted by the image edge length it stands
        for, that length growing less than in proportion to the scale
        (:func:`viewloc_core.edge_evidence.outline_samples`).
    hit_fraction : (H,) float64
    evidence_fraction : (H,) float64
        ``llr`` as a share of what it would be if every sample in the image
        found its edge: 1 for a perfect fit, about 0 or below for a fit no
        better than chance; independent of the object's size in the image.
    """
    if subset is None:
        px, py, bins, valid, rows = (templates.px, templates.py, templates.bins8,
                                     templates.valid, views)
    else:
        gather = views[:, None]
        px, py = templates.px[gather, subset], templates.py[gather, subset]
        bins, valid = templates.bins8[gather, subset], templates.valid[gather, subset]
        rows = np.arange(len(views))
    llr, hits, n_valid, llr_all_found = lay_over_templates(feats, px, py, bins, valid, rows,
                                                           sims, chance)
    return (llr * outline_samples(templates.length_px[views], sims[:, 3]),
            hits / np.maximum(n_valid, 1),
            llr / np.maximum(llr_all_found, 1e-9))


def _coarse_samples(templates: ViewTemplates, points: int) -> tuple[
        NDArray[np.float32], NDArray[np.float32], NDArray[np.uint8], NDArray[np.bool_]]:
    """px, py, bins and valid of each view's first ``points`` coarse samples."""
    if points >= COARSE_POINTS:
        return (templates.coarse_px, templates.coarse_py, templates.coarse_bins8,
                templates.coarse_valid)
    return (np.ascontiguousarray(templates.coarse_px[:, :points]),
            np.ascontiguousarray(templates.coarse_py[:, :points]),
            np.ascontiguousarray(templates.coarse_bins8[:, :points]),
            np.ascontiguousarray(templates.coarse_valid[:, :points]))


def _score_coarse(feats: ImageFeatures, templates: ViewTemplates, views: NDArray[np.int64],
                  sims: F64, chance: ChanceRates, points: int = COARSE_POINTS) -> F64:
    """The log-likelihood ratio of :func:`score_views` on each view's coarse
    subset (its first ``points`` samples)."""
    llr = lay_over_templates(feats, *_coarse_samples(templates, points), views, sims,
                             chance)[0]
    return llr * outline_samples(templates.length_px[views], sims[:, 3])


def _score_coarse_grid(feats: ImageFeatures, templates: ViewTemplates, sims: F64,
                       chance: ChanceRates, points: int = COARSE_POINTS) -> F64:
    """:func:`_score_coarse` of every view at every one of the (S, 4)
    similarities, (S * V,) similarity-major: the pairs are not built."""
    views = np.arange(len(templates))
    llr = lay_over_grid_of_templates(feats, *_coarse_samples(templates, points), views, sims,
                                     chance)
    return llr * outline_samples(templates.length_px[None, :], sims[:, 3, None]).ravel()


def _screen(feats: ImageFeatures, templates: ViewTemplates, sims: F64, chance: ChanceRates) -> F64:
    """:func:`_score_coarse_grid` of every view at every similarity, or of
    the pairs a pre-screen on fewer samples ranks best (``-inf`` for the
    rest) when there are more than PRESCREEN_MIN_PAIRS."""
    n_views = len(templates)
    n_pairs = len(sims) * n_views
    if n_pairs <= PRESCREEN_MIN_PAIRS:
        return _score_coarse_grid(feats, templates, sims, chance)
    pre = _score_coarse_grid(feats, templates, sims, chance, PRESCREEN_POINTS)
    kept = _largest(pre, int(PRESCREEN_KEPT * n_pairs))
    llr = np.full(n_pairs, -np.inf)
    llr[kept] = _score_coarse(feats, templates, kept % n_views, sims[kept // n_views], chance)
    return llr


#: :func:`_largest` reads every this many values first, and looks for the
#: largest among those at least as large as a threshold the sample gives.
LARGEST_SAMPLE_STRIDE = 16


def _largest(values: F64, n: int) -> NDArray[np.int64]:
    """Indices of the ``n`` largest of ``values`` (0 < ``n`` < their number),
    in no particular order; of equal values at the ``n``-th place, which
    are taken is not defined.

    Selecting them among all 105,000 of a real photo's colour locations
    took 1.3-1.8 ms, 15 times an image (LM-O). The largest values lie
    above a threshold a strided sample gives (chosen with half as many
    again as its share of them, so that nearly always at least ``n`` values
    pass): the selection runs on those, about a tenth of the cost, and on
    all values when too few pass.
    """
    sample = values[::LARGEST_SAMPLE_STRIDE]
    in_sample = min(len(sample), int(1.5 * n / LARGEST_SAMPLE_STRIDE) + 1)
    threshold = np.partition(sample, len(sample) - in_sample)[len(sample) - in_sample]
    passed = np.flatnonzero(values >= threshold)
    if len(passed) < n:
        return np.argpartition(-values, n)[:n]
    return passed[np.argpartition(-values[passed], n - 1)[:n]]


def best_member(
    model: ObjectModel, model_view: int, sim: F64, feats: ImageFeatures
) -> tuple[int, F64]:
    """Member training view of a model view that fits the image best, by coverage.

    The same choice as composing the match with every member's similarity and
    calling :func:`viewloc_core.align.coverage` on each (the first of equals
    wins), in one batch.

    Parameters
    ----------
    model : ObjectModel
    model_view : int
        The matched model view.
    sim : (4,) float64
        Model-view frame -> image similarity of the match.
    feats : ImageFeatures
        The image, with its spread orientation map.

    Returns
    -------
    view : int
        Training view index.
    sim : (4,) float64
        Its training-view frame -> image similarity.
    """
    tr = model.training
    templates = view_templates(model)
    members = np.flatnonzero(tr.model_view == model_view)
    sims = sim2.compose_many(sim, tr.sim_to_model[members])
    cov = coverage_many(feats, sims, templates.pts[members], templates.bins[members],
                        templates.valid[members])
    best = int(np.argmax(cov))
    return int(members[best]), sims[best]


def _distinct_seeds(seeds: F64) -> F64:
    """Drop seeds the coarse grid of an earlier seed already covers."""
    dx = seeds[:, None, :2] - seeds[None, :, :2]
    covers = ((np.hypot(dx[..., 0], dx[..., 1]) < 3.0)
              & (np.abs(sim2.wrap_angle(seeds[:, None, 2] - seeds[None, :, 2]))
                 < np.radians(7.5))
              & (np.abs(np.log(seeds[:, None, 3] / seeds[None, :, 3])) < 0.07))
    kept: list[int] = []
    for i in range(len(seeds)):
        if not covers[i, kept].any():
            kept.append(i)
    return seeds[kept]


def _grid_sims(seeds: F64, angles_rad: NDArray[np.float64] | tuple[float, ...],
               scales: tuple[float, ...]) -> F64:
    """Every seed turned by every angle offset and scaled by every factor:
    (K * A * S, 4), seed-major, then angle, then scale."""
    seeds = np.asarray(seeds, np.float64).reshape(-1, 4)
    angles = np.asarray(angles_rad, np.float64)
    factors = np.asarray(scales, np.float64)
    out = np.empty((len(seeds), len(angles), len(factors), 4))
    out[..., 0] = seeds[:, 0, None, None]
    out[..., 1] = seeds[:, 1, None, None]
    out[..., 2] = seeds[:, 2, None, None] + angles[None, :, None]
    out[..., 3] = seeds[:, 3, None, None] * factors[None, None, :]
    return out.reshape(-1, 4)


def _column_best(table: F64) -> tuple[NDArray[np.int64], F64]:
    """Each column's best score in a (R, C) table of scores (finite or
    ``-inf``) and the first row that holds it, (C,) each.

    The searches score every view at every similarity, similarity-major:
    the scores of view ``c`` are a column of that table. Reading a view's
    best from its column replaces a scatter-maximum over all entries
    (``np.maximum.at``) and a sort of them by view, several milliseconds
    for a colour proposal's hundred thousand entries.
    """
    row = np.argmax(table, axis=0)
    return row, table[row, np.arange(table.shape[1])]


def _best_columns(view_ids: NDArray[np.int64], best: F64, count: int) -> NDArray[np.int64]:
    """Positions in ``view_ids`` (C,) of the ``count`` views whose ``best``
    scores (C,) are highest, best first; views of equal score in the order
    of their ids."""
    by_id = np.argsort(view_ids, kind="stable")
    return np.asarray(by_id[np.argsort(-best[by_id], kind="stable")[:count]], np.int64)


def _other_side_best(templates: ViewTemplates, view_best: F64, of_view: int,
                     count: int) -> NDArray[np.int64]:
    """The ``count`` views that score best (``view_best``, (V,): each view's
    best score) among those that see the part from the other side than
    ``of_view`` (at least :data:`OTHER_SIDE_MIN_DEG` away); best first."""
    cos = templates.directions @ templates.directions[of_view]
    other = np.flatnonzero(cos <= np.cos(np.radians(OTHER_SIDE_MIN_DEG)))
    return np.asarray(other[_best_columns(other, view_best[other], count)], np.int64)


def _shifted(seeds: F64, offsets_px: F64) -> F64:
    """Every seed moved by every image offset: (K * O, 4)."""
    moved = seeds[:, None, :].repeat(len(offsets_px), axis=1)
    moved[:, :, :2] += offsets_px[None]
    return moved.reshape(-1, 4)


def search_views(
    feats: ImageFeatures, templates: ViewTemplates, seeds: F64, chance: ChanceRates,
    max_candidates: int = 3, offsets_px: F64 | None = None, kept_seeds: int | None = None,
    screen_angles_deg: tuple[float, ...] = SCREEN_ANGLES_DEG, other_side: int = 0,
    screened_views: int = SCREENED_VIEWS,
) -> list[ViewCandidate]:
    """The training views that explain an image location best.

    Parameters
    ----------
    feats : ImageFeatures
        The image.
    templates : ViewTemplates
    seeds : (K, 4) float64
        Training-view frame -> image similarities to start from (the 2D
        match and its alternatives at one location).
    chance : ChanceRates
        From :func:`chance_rates`.
    max_candidates : int
        Most candidates returned, each of a different training view.
    offsets_px : (O, 2) float64, optional
        Image offsets at which every seed is also screened, for seeds whose
        position is uncertain by more than the spread map's tolerance.
    kept_seeds : int, optional
        Only the seeds (after offsets) whose best screened view scores
        highest go on to the full grid; all of them when None.
    screen_angles_deg : tuple of float
        Angle offsets (degrees) at which every view is screened at each seed.
    other_side : int
        After the ``max_candidates`` best, up to this many more: the best
        candidates among the views that see the part from the other side
        than the first's (:data:`OTHER_SIDE_MIN_DEG`), however they rank.
        Their views go through the full grid and the fit on their own, so
        they leave the other candidates as they were.
    screened_views : int
        The views that score best in the screen go on to the full grid, this
        many distinct ones; at least ``max_candidates`` of them get the
        least-squares fit (:data:`FITTED_CANDIDATES` when more).

    Returns
    -------
    list of ViewCandidate
        Best first by log-likelihood ratio.
    """
    n_views = len(templates)
    seeds = _distinct_seeds(np.atleast_2d(np.asarray(seeds, np.float64)))
    if offsets_px is not None:
        seeds = _shifted(seeds, np.asarray(offsets_px, np.float64))
    # Stage 1: every view at the seeds' scale and a few angles (and
    # positions), pre-screened when they are many (_screen); stage 2: the
    # views that scored best there on the full angle and scale grid, at the
    # seeds that did.
    stage1 = _grid_sims(seeds, np.radians(screen_angles_deg), (1.0,))
    llr1 = _screen(feats, templates, stage1, chance)
    # (similarity, view) scores; each view's best over the similarities.
    view_best = _column_best(llr1.reshape(len(stage1), n_views))[1]
    best_views = _best_columns(np.arange(n_views), view_best, screened_views)
    if kept_seeds is not None and len(seeds) > kept_seeds:
        per_seed = llr1.reshape(len(seeds), -1).max(axis=1)
        seeds = seeds[np.sort(np.argsort(-per_seed)[:kept_seeds])]
    stage2 = _grid_sims(seeds, np.radians(COARSE_ANGLES_DEG), COARSE_SCALES)
    candidates = _grid_and_fit(feats, templates, best_views, stage2, chance,
                               max(FITTED_CANDIDATES, max_candidates))[:max_candidates]
    if other_side and candidates:
        other = _other_side_best(templates, view_best, candidates[0].view, OTHER_SIDE_SCREENED)
        other = other[~np.isin(other, [c.view for c in candidates])]
        candidates += _grid_and_fit(feats, templates, other, stage2, chance,
                                    other_side)[:other_side]
    return candidates


def _grid_and_fit(
    feats: ImageFeatures, templates: ViewTemplates, view_ids: NDArray[np.int64], grid: F64,
    chance: ChanceRates, fitted_count: int,
) -> list[ViewCandidate]:
    """Stage 2 of :func:`search_views`: ``view_ids`` (distinct) on every
    similarity of ``grid``, the best ``fitted_count`` of them fitted by
    least squares; best first."""
    if not len(view_ids):
        return []
    views = np.tile(view_ids, len(grid))
    sims = np.repeat(grid, len(view_ids), axis=0)
    llr = _score_coarse(feats, templates, views, sims, chance)
    # The best few distinct views go on to the least-squares fit.
    row, view_best = _column_best(llr.reshape(len(grid), len(view_ids)))
    columns = _best_columns(view_ids, view_best, fitted_count)
    pick = row[columns] * len(view_ids) + columns
    fit_views = views[pick]
    fitted = extend_many(feats, sims[pick], templates.pts[fit_views],
                          templates.theta[fit_views], templates.valid[fit_views],
                          FIT_RADII_PX, 22.5)
    after = score_views(feats, templates, fit_views, fitted, chance)
    # The fit can wander onto clutter; keep whichever of before/after scores higher.
    before = score_views(feats, templates, fit_views, sims[pick], chance)
    better = after[0] >= before[0]
    final_sims = np.where(better[:, None], fitted, sims[pick])
    llr = np.where(better, after[0], before[0])
    frac = np.where(better, after[1], before[1])
    best = np.argsort(-llr)
    return [ViewCandidate(int(fit_views[i]), final_sims[i], float(llr[i]), float(frac[i]))
            for i in best]
