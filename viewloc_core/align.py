"""Probabilistic alignment of model views to an image (Pope & Lowe 2000; DESIGN.md §2 step 6).

1. *Pairings.* Every image feature is paired with the model features of the
   same kind whose attributes are likely under the model's attribute density;
   each pairing is ranked by ``log p_j + log f_j(a_k) − log f_bg(a_k)``.
2. *Seeds.* A junction or parallel-pair pairing fixes a whole similarity
   ``(x, y, α, s)``. Seeds vote in a coarse (view, x, y, α, s) table so the
   consistent ones are tried first, not merely the individually likeliest.
3. *Verification.* Each hypothesis is checked against the image's spread
   orientation map with the model view's dense edge samples (LINE-2D's trick,
   cheap enough to test dozens of seeds).
4. *Extension.* The best hypotheses are extended greedily: model edge samples
   pair with image edges under the current similarity and the similarity is
   re-fitted by weighted least squares (point-to-line), shrinking the gate.
5. *Quality.* ``g(E, T) ≈ log P(H | E, T)`` over the feature pairings E
   (matched terms, unmatched ``log(1 − p_j)``, Gaussian position term times
   the image area for the uniform background), and the fraction of dense edge
   samples confirmed by the image (the ``coverage``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from viewloc_core import similarity as sim2
from viewloc_core.clutter_density import log_image_density
from viewloc_core.features import (
    KIND_ARC,
    KIND_JUNCTION,
    KIND_PARALLEL,
    ORIENTATION_BINS,
    ImageFeatures,
    orientation_bin,
    orientation_turn,
    wanted_bits,
)
from viewloc_core.model import ModelView, ObjectModel
from viewloc_core.seed_votes import bin_supports, peak_bins
from viewloc_core.seeding import seed_similarities
from viewloc_core.similarity_fit import fit_similarities

F64 = NDArray[np.float64]

#: Attribute standard deviations per feature kind (junction: opening angle rad,
#: log arm ratio; parallel pair: log overlap/separation, unused; arc: angular
#: span rad, unused; spans vary with occlusion and where the chain splits).
ATTR_SIGMA = {KIND_JUNCTION: np.array([0.12, 0.7]), KIND_PARALLEL: np.array([0.5, 1e3]),
              KIND_ARC: np.array([0.6, 1e3])}


@dataclass(frozen=True, slots=True)
class AlignConfig:
    """Tuning of the alignment search.

    Attributes
    ----------
    min_scale, max_scale : float
        Range of image scale relative to the training views.
    attr_gate : float
        Pairings further than this many attribute sigmas are not formed.
    vote_xy_px, vote_angle_deg, vote_log2_scale : float
        Bin sizes of the seed voting table.
    max_peaks : int
        Peaks of the location vote map searched for hypotheses.
    hypotheses_per_peak : int
        (view, angle, scale) vote bins per peak turned into hypotheses.
    max_bins : int
        Best (view, x, y, angle, scale) vote bins turned into hypotheses besides.
    max_scored : int
        Hypotheses (by quick coverage) whose g is computed.
    max_hypotheses : int
        Hypotheses extended on all edge samples after ranking by g.
    max_alternatives : int
        Other model views kept per image location for the 6D verification.
    max_pairings : int
        Most (image feature, model feature) pairings kept, strongest first
        (a paper-set image makes about 12,000; a 160-view textured model in
        a 400x300 real photo 1.8 million).
    min_coverage : float
        Hypotheses whose quick coverage is below this are dropped early.
    icp_radii_px : tuple of float
        Pairing gates of the successive extension steps (fine edge samples).
    coarse_radii_px : tuple of float
        The same for the quick extension of every voted hypothesis.
    coverage_weight : float
        Hypotheses are ranked by ``g + coverage_weight * coverage``: g decides,
        coverage breaks near-ties in favour of complete outlines.
    orientation_tol_deg : float
        Largest orientation difference of paired edge samples.
    """

    min_scale: float = 0.3
    max_scale: float = 3.0
    attr_gate: float = 2.5
    vote_xy_px: float = 12.0
    vote_angle_deg: float = 20.0
    vote_log2_scale: float = 0.35
    max_peaks: int = 12
    hypotheses_per_peak: int = 4
    max_bins: int = 40
    max_scored: int = 10
    max_hypotheses: int = 5
    max_alternatives: int = 2
    max_pairings: int = 40000
    min_coverage: float = 0.25
    icp_radii_px: tuple[float, ...] = (4.0, 2.5, 1.5, 1.5)
    coarse_radii_px: tuple[float, ...] = (8.0, 4.0)
    coverage_weight: float = 20.0
    orientation_tol_deg: float = 20.0


@dataclass(frozen=True, slots=True)
class Match2D:
    """An aligned model view.

    Attributes
    ----------
    model_view : int
    sim : (4,) float64
        Model-view frame -> image, ``(x, y, angle_rad, scale)``.
    log_probability : float
        g(E, T).
    coverage : float
        Fraction of the view's edge samples confirmed by image edges.
    n_pairs : int
        Number of feature pairings in E.
    alternatives : tuple of Match2D
        Other model views that fit about the same image location, best
        first (their ``alternatives`` are empty). A 2D similarity cannot
        tell some views apart (a barbell's plate seen end-on or a plate of
        a side view), the 6D verification can.
    """

    model_view: int
    sim: F64
    log_probability: float
    coverage: float
    n_pairs: int
    alternatives: tuple[Match2D, ...] = ()


@dataclass(frozen=True, slots=True)
class ModelIndex:
    """Model features stacked over all views with attribute search trees.

    The edge samples of every view are padded to one length twice: a
    well-spread subset (``coarse_*``, screening) and all of them (``fine_*``,
    the final extension), so hypotheses of different views batch together.
    """

    view_of: NDArray[np.int64]
    kind: NDArray[np.int8]
    xy: F64
    theta: F64
    scale: F64
    attrs: F64
    log_presence: F64
    trees: dict[int, tuple[cKDTree, NDArray[np.int64]]]
    coarse_pts: F64
    coarse_bins: NDArray[np.int64]
    coarse_valid: NDArray[np.bool_]
    fine_pts: F64
    fine_theta: F64
    fine_bins: NDArray[np.int64]
    fine_valid: NDArray[np.bool_]
    view_radius_px: float

    def fine_samples(self, views: NDArray[np.int64]) -> tuple[F64, F64, NDArray[np.int64],
                                                            NDArray[np.bool_]]:
        """All edge samples of some views, padded to the longest of them.

        Returns
        -------
        pts : (H, P, 2) float64
            Model-view pixels.
        theta : (H, P) float64
            Orientations modulo π.
        bins : (H, P) int64
            Their orientation bins.
        valid : (H, P) bool
            False for padding.
        """
        n = int(self.fine_valid[views].sum(axis=1).max(initial=0))
        return (self.fine_pts[views, :n], self.fine_theta[views, :n],
                self.fine_bins[views, :n], self.fine_valid[views, :n])


def build_index(model: ObjectModel, coarse_points: int = 48) -> ModelIndex:
    """Precompute the pairing trees and edge subsets of a model (once per model)."""
    views = model.model_views
    view_of = np.concatenate([np.full(len(v.kind), i, np.int64) for i, v in enumerate(views)])
    kind = np.concatenate([v.kind for v in views])
    xy = np.concatenate([v.xy for v in views]).astype(np.float64)
    theta = np.concatenate([v.theta for v in views]).astype(np.float64)
    scale = np.concatenate([v.scale for v in views]).astype(np.float64)
    attrs = np.concatenate([v.attrs for v in views]).astype(np.float64)
    log_presence = np.log(np.concatenate([v.presence for v in views]).astype(np.float64))
    trees = {}
    for k, sigma in ATTR_SIGMA.items():
        idx = np.flatnonzero(kind == k)
        if len(idx):
            trees[k] = (cKDTree(attrs[idx] / sigma), idx)
    rng = np.random.default_rng(0)
    # Coarse edge subsets padded to one length so hypotheses batch together.
    coarse_pts = np.zeros((len(views), coarse_points, 2))
    coarse_bins = np.zeros((len(views), coarse_points), np.int64)
    coarse_valid = np.zeros((len(views), coarse_points), bool)
    n_fine = max((len(v.edge_theta) for v in views), default=0)
    fine_pts = np.zeros((len(views), n_fine, 2))
    fine_theta = np.zeros((len(views), n_fine))
    fine_valid = np.zeros((len(views), n_fine), bool)
    for i, v in enumerate(views):
        exy = v.edge_xy.astype(np.float64)
        eth = v.edge_theta.astype(np.float64)
        fine_pts[i, : len(eth)], fine_theta[i, : len(eth)], fine_valid[i, : len(eth)] = (
            exy, eth, True)
        pick = spread_subset(exy, coarse_points, rng)
        coarse_pts[i, : len(pick)] = exy[pick]
        coarse_bins[i, : len(pick)] = orientation_bin(eth[pick])
        coarse_valid[i, : len(pick)] = True
    radius = model.f_train_px * model.diameter_mm / model.d0_mm / 2.0
    return ModelIndex(
        view_of, kind, xy, theta, scale, attrs, log_presence, trees,
        coarse_pts, coarse_bins, coarse_valid, fine_pts, fine_theta, orientation_bin(fine_theta),
        fine_valid, radius,
    )


def spread_subset(pts: F64, n: int, rng: np.random.Generator) -> NDArray[np.int64]:
    """Indices of up to ``n`` points spread over the set (farthest-point sampling)."""
    if len(pts) <= n:
        return np.arange(len(pts))
    chosen = [int(rng.integers(len(pts)))]
    dist = np.linalg.norm(pts - pts[chosen[0]], axis=1)
    for _ in range(n - 1):
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(pts - pts[nxt], axis=1))
    return np.array(chosen, np.int64)


def _log_background_density(kind: int, attrs: F64) -> F64:
    """log f_bg(a): attribute density of clutter features.

    Junction opening angles are about uniform over the accepted range and arm
    ratios about log-normal; parallel-pair overlap ratios about log-normal.
    Clutter arcs are mostly short (on the paper set their spans fall off
    about exponentially from the 80° minimum, scale ~75°) and rarely closed
    (~1%): a closed circle counts as a 2% chance spread over 0.5 rad.
    """
    if kind == KIND_JUNCTION:
        span = np.pi - 2 * np.radians(25.0)
        return -np.log(span) - 0.5 * (attrs[:, 1] / 1.2) ** 2 - np.log(1.2 * np.sqrt(2 * np.pi))
    if kind == KIND_ARC:
        lo, hi, tau = np.radians(80.0), np.radians(330.0), 1.3
        norm = tau * (1.0 - np.exp(-(hi - lo) / tau))
        open_arc = np.log(0.98 / norm) - (attrs[:, 0] - lo) / tau
        return np.where(attrs[:, 0] >= 2 * np.pi - 1e-3, np.log(0.02 / 0.5), open_arc)
    return -0.5 * ((attrs[:, 0] - 1.0) / 1.0) ** 2 - np.log(np.sqrt(2 * np.pi))


def _log_rarity(feats: ImageFeatures) -> F64:
    """Per image feature: how much rarer its attributes are in this image than
    in clutter at large, log f_bg(a) - log f_image(a) (see
    :mod:`viewloc_core.clutter_density`); (F,) float64, 0 for a lone feature."""
    g = feats.grouped
    rarity = np.zeros(len(g.kind), np.float64)
    for k, sigma in ATTR_SIGMA.items():
        idx = np.flatnonzero(g.kind == k)
        if len(idx) == 0:
            continue
        active = sigma < 100
        attrs = g.attrs[idx].astype(np.float64)
        log_prior = _log_background_density(k, attrs)
        rarity[idx] = log_prior - log_image_density(attrs[:, active], sigma[active], log_prior)
    return rarity


def _pairings(index: ModelIndex, feats: ImageFeatures, config: AlignConfig) -> tuple[
    NDArray[np.int64], NDArray[np.int64], F64
]:
    """All plausible (image feature, model feature) pairings and their log weight."""
    g = feats.grouped
    ks_all, js_all, ws_all = [], [], []
    for k, (tree, model_idx) in index.trees.items():
        img_idx = np.flatnonzero(g.kind == k)
        if len(img_idx) == 0:
            continue
        sigma = ATTR_SIGMA[k]
        img_attrs = g.attrs[img_idx].astype(np.float64)
        img_tree = cKDTree(img_attrs / sigma)
        pairs = img_tree.sparse_distance_matrix(tree, config.attr_gate, output_type="ndarray")
        if len(pairs) == 0:
            continue
        ki = img_idx[pairs["i"]]
        mj = model_idx[pairs["j"]]
        d2 = pairs["v"] ** 2
        active = sigma < 100
        log_f = -0.5 * d2 - float(np.sum(np.log(sigma[active] * np.sqrt(2 * np.pi))))
        # Per image feature, not per pairing: a busy image pairs millions of times.
        log_bg = _log_background_density(k, img_attrs)
        w = index.log_presence[mj] + log_f - log_bg[pairs["i"]]
        ks_all.append(ki)
        js_all.append(mj)
        ws_all.append(w)
    if not ks_all:
        empty = np.zeros(0, np.int64)
        return empty, empty, np.zeros(0)
    return np.concatenate(ks_all), np.concatenate(js_all), np.concatenate(ws_all)


def _seeds(index: ModelIndex, feats: ImageFeatures, k: NDArray[np.int64], j: NDArray[np.int64],
           config: AlignConfig) -> tuple[F64, NDArray[np.int64]]:
    """Similarity (M, 4) implied by each pairing whose scale is in range, and
    the pairing each came from; parallel pairs give two (α, α+π)."""
    g = feats.grouped
    return seed_similarities(
        g.xy, g.theta, g.scale, index.xy, index.theta, index.scale,
        index.kind == KIND_PARALLEL, np.ascontiguousarray(k, np.int64),
        np.ascontiguousarray(j, np.int64), config.min_scale, config.max_scale)


def coverage(
    feats: ImageFeatures, sim: F64, pts: F64, bins: NDArray[np.int64]
) -> float:
    """Fraction of edge samples that land on an image edge of similar orientation
    (the one-hypothesis case of :func:`coverage_many`).

    Parameters
    ----------
    feats : ImageFeatures
        Image with its spread orientation map.
    sim : (4,) array
        Model frame -> image.
    pts : (P, 2) array
        Edge samples, model frame.
    bins : (P,) int
        Their orientation bins (model frame).

    Returns
    -------
    float in [0, 1]; samples outside the image count as missing.
    """
    if len(pts) == 0:
        return 0.0
    p = np.asarray(pts, np.float64)
    return float(coverage_many(feats, np.asarray(sim, np.float64)[None], p[None],
                               np.asarray(bins, np.int64)[None], np.ones((1, len(p)), bool))[0])


def extend(
    feats: ImageFeatures, sim: F64, pts: F64, theta: F64, config: AlignConfig
) -> F64:
    """Greedy extension: pair edge samples under ``sim`` and re-fit, shrinking the gate.

    Parameters
    ----------
    feats : ImageFeatures
    sim : (4,) array
        Initial model -> image similarity.
    pts : (P, 2) array
        Model edge samples.
    theta : (P,) array
        Their orientations modulo π.
    config : AlignConfig

    Returns
    -------
    (4,) float64
        The re-fitted similarity (the input when the fit degenerates).
    """
    p = np.asarray(pts, np.float64)
    return extend_many(feats, np.asarray(sim, np.float64)[None], p[None],
                       np.asarray(theta, np.float64)[None], np.ones((1, len(p)), bool),
                       config.icp_radii_px, config.orientation_tol_deg, robust=True)[0]


def _bin_keys(views: NDArray[np.int64], sims: F64, config: AlignConfig,
              with_position: bool) -> NDArray[np.int64]:
    """One int64 key per seed for its (view, [x, y,] α, s) vote bin.

    Each field is offset to be non-negative and clipped below 2^12, so the
    packed key stays below 2^63 with all five fields.
    """
    fields = []
    if with_position:
        fields += [np.floor(sims[:, 0] / config.vote_xy_px).astype(np.int64) + 2048,
                   np.floor(sims[:, 1] / config.vote_xy_px).astype(np.int64) + 2048]
    fields += [
        np.floor((sims[:, 2] + np.pi) / np.radians(config.vote_angle_deg)).astype(np.int64),
        np.floor(np.log2(sims[:, 3]) / config.vote_log2_scale).astype(np.int64) + 2048,
    ]
    key = views.astype(np.int64)
    for f in fields:
        key = key * 4096 + np.clip(f, 0, 4095)
    return key


def _strongest_seeds_of_best_bins(keys: NDArray[np.int64], vote: F64,
                                  n_bins: int) -> NDArray[np.int64]:
    """Index of the strongest seed in each of the ``n_bins`` best-supported bins, best first."""
    support, strongest = bin_supports(np.ascontiguousarray(keys, np.int64),
                                      np.ascontiguousarray(vote, np.float64),
                                      np.arange(len(keys), dtype=np.int64))
    return strongest[np.argsort(-support)[:n_bins]]


def _vote_bins(views: NDArray[np.int64], sims: F64, vote: F64, config: AlignConfig
               ) -> tuple[NDArray[np.int64], F64]:
    """Hypotheses from the ``max_bins`` best-supported (view, x, y, α, s) bins.

    Parameters and returns as :func:`_vote_hypotheses`.
    """
    best = _strongest_seeds_of_best_bins(_bin_keys(views, sims, config, True), vote,
                                         config.max_bins)
    return views[best], sims[best]


def _vote_hypotheses(views: NDArray[np.int64], sims: F64, vote: F64,
                     shape: tuple[int, int], config: AlignConfig
                     ) -> tuple[NDArray[np.int64], F64]:
    """Hypotheses (model view, similarity) from seed votes, location first.

    Seeds first vote for where the object's reference point is, pooled over
    model views, angles and scales: neighbouring model views describe the same
    object, so the evidence of all of them adds up at the true location even
    when each view alone has only a few consistent seeds. At each peak of
    that location map the seeds nearby then vote for (view, angle, scale),
    and the best-supported combinations become hypotheses.

    Parameters
    ----------
    views : (N,) int
        Model view of each seed.
    sims : (N, 4) float
        Seed similarities model view -> image.
    vote : (N,) float
        Vote of each seed (> 0).
    shape : (int, int)
        Image height and width (px).
    config : AlignConfig

    Returns
    -------
    views : (H,) int64
    sims : (H, 4) float64
    """
    cell = config.vote_xy_px / 2.0
    h, w = shape
    gx = np.floor(sims[:, 0] / cell).astype(np.int64) + 2
    gy = np.floor(sims[:, 1] / cell).astype(np.int64) + 2
    gw, gh = int(np.ceil(w / cell)) + 4, int(np.ceil(h / cell)) + 4
    inside = (gx >= 0) & (gx < gw) & (gy >= 0) & (gy < gh)
    # bincount on flat cell indices: the same sums as np.add.at, far faster.
    raw = np.bincount(gy[inside] * gw + gx[inside], weights=vote[inside],
                      minlength=gh * gw).reshape(gh, gw).astype(np.float32)
    acc = np.asarray(cv2.GaussianBlur(raw, (0, 0), 1.0), dtype=np.float32)
    peaks = (acc >= cv2.dilate(acc, np.ones((5, 5), np.uint8))) & (acc > 0)
    py, px = np.nonzero(peaks)
    order = np.argsort(-acc[py, px])[: config.max_peaks]
    centres = np.stack([(px[order] - 2 + 0.5) * cell, (py[order] - 2 + 0.5) * cell], axis=1)
    # A peak, at the centre of column p, is within reach of seeds in columns
    # p-2..p+2 only (the reach of two cells ends mid-column, far from rounding).
    support, strongest, bins_per_peak = peak_bins(
        np.ascontiguousarray(sims[:, 0]), np.ascontiguousarray(sims[:, 1]),
        np.clip(gx, -3, gw + 2), _bin_keys(views, sims, config, False),
        np.ascontiguousarray(vote, np.float64), np.ascontiguousarray(centres, np.float64),
        px[order].astype(np.int64), 2.0 * cell)
    picked = []
    start = 0
    for count in bins_per_peak.tolist():
        if count:
            peak = slice(start, start + count)
            picked.append(strongest[peak][np.argsort(-support[peak])
                                          [: config.hypotheses_per_peak]])
        start += count
    best = np.concatenate(picked) if picked else np.zeros(0, np.int64)
    return views[best], sims[best]


def coverage_many(feats: ImageFeatures, sims: F64, pts: F64, bins: NDArray[np.int64],
                   valid: NDArray[np.bool_]) -> F64:
    """``coverage`` for H hypotheses at once; pts (H, P, 2), bins/valid (H, P)."""
    uv = sim2.apply_many(sims, pts)
    h, w = feats.shape
    u = np.rint(uv[..., 0]).astype(np.int64)
    v = np.rint(uv[..., 1]).astype(np.int64)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h) & valid
    b = (bins + orientation_turn(sims[:, 2])[:, None]) % ORIENTATION_BINS
    want = wanted_bits(b)
    got = np.zeros(u.shape, np.int64)
    got[inside] = feats.orientation_bits[v[inside], u[inside]]
    hit = (got & want) != 0
    return hit.sum(axis=1) / np.maximum(valid.sum(axis=1), 1)


def extend_many(feats: ImageFeatures, sims: F64, pts: F64, theta: F64,
                valid: NDArray[np.bool_], radii: tuple[float, ...], tol_deg: float,
                robust: bool = False) -> F64:
    """Greedy extension of H hypotheses (:mod:`viewloc_core.similarity_fit`).

    Each step pairs every valid edge sample with the nearest image edge
    within the step's radius and of similar orientation, and re-fits the
    similarity to minimise the point-to-line distances.

    Parameters
    ----------
    feats : ImageFeatures
    sims : (H, 4) array
        Initial model -> image similarities.
    pts : (H, P, 2) array
        Model edge samples of each hypothesis (padded to one length).
    theta : (H, P) array
        Their orientations modulo π.
    valid : (H, P) bool
        Which samples are real (not padding).
    radii : tuple of float
        Pairing radius of each step, pixels.
    tol_deg : float
        Largest orientation difference of a pairing.
    robust : bool
        The final fit (:func:`extend`): Huber weights on the residuals (far
        pairings are likely clutter), a relative test for degenerate
        systems, and a hypothesis stops at its first failed step. Without,
        the quick screen: unweighted, and a failed step is skipped.

    Returns
    -------
    (H, 4) float64
        The re-fitted similarities (a hypothesis keeps its last good one).
    """
    if len(feats.edge_xy) == 0:
        return sims
    return fit_similarities(
        np.ascontiguousarray(sims, np.float64), np.ascontiguousarray(pts, np.float64),
        np.ascontiguousarray(theta, np.float64), np.ascontiguousarray(valid, np.bool_),
        feats.nearest_edge, feats.edge_distance, feats.edge_xy, feats.edge_theta,
        np.asarray(radii, np.float64), float(np.radians(tol_deg)), robust)


def log_probability(view_data: ModelView, feats: ImageFeatures, sim: F64) -> tuple[float, int]:
    """g(E, T) of a hypothesis, pairing model features to image features under T.

    Each model feature pairs with the image feature of its kind that adds the
    most to g (if that beats leaving it unmatched).

    Returns
    -------
    g : float
        ``Σ_unmatched log(1 − p_j) + Σ_pairs [log p_j + log f_j/f_bg
        + log N(b_k; T μ_j, T Σ_j Tᵀ) + log A]`` (the prior log P(H) is the
        same for every hypothesis and left out).
    n_pairs : int
    """
    g, n_pairs = log_probability_many([view_data], feats, np.asarray(sim, np.float64)[None])
    return float(g[0]), int(n_pairs[0])


def log_probability_many(views: Sequence[ModelView], feats: ImageFeatures, sims: F64
                         ) -> tuple[F64, NDArray[np.int64]]:
    """:func:`log_probability` of H hypotheses at once.

    The model features of all hypotheses are stacked, each with its own
    similarity, and paired with the image features as one (model features x
    image features) table per kind, so the cost is a few array operations
    whatever H.

    Parameters
    ----------
    views : sequence of H ModelView
        The model view of each hypothesis.
    feats : ImageFeatures
    sims : (H, 4) array
        Model view -> image similarity of each hypothesis.

    Returns
    -------
    g : (H,) float64
    n_pairs : (H,) int64
    """
    g = feats.grouped
    n_hyp = len(views)
    if n_hyp == 0:
        return np.zeros(0), np.zeros(0, np.int64)
    area = float(feats.shape[0] * feats.shape[1])
    hyp = np.repeat(np.arange(n_hyp), [len(v.kind) for v in views])
    p = np.minimum(np.concatenate([v.presence for v in views]).astype(np.float64), 0.999)
    log_miss = np.log1p(-p)
    total = np.bincount(hyp, weights=log_miss, minlength=n_hyp).astype(np.float64)
    if len(hyp) == 0 or len(g) == 0:
        return total, np.zeros(n_hyp, np.int64)
    kind = np.concatenate([v.kind for v in views])
    theta = np.concatenate([v.theta for v in views])
    attrs = np.concatenate([v.attrs for v in views])
    row_sim = np.asarray(sims, np.float64)[hyp]
    mu = sim2.apply_many(row_sim, np.concatenate([v.xy for v in views])[:, None, :])[:, 0]
    var = row_sim[:, 3] ** 2 * np.concatenate([v.pos_var for v in views]).astype(np.float64) + 1.0
    gxy = g.xy.astype(np.float64)
    # Pairs only form within a kind: one (model x image) distance table per kind.
    jj_all, gain_all = [], []
    for k, sigma in ATTR_SIGMA.items():
        jk = np.flatnonzero(kind == k)
        gk = np.flatnonzero(g.kind == k)
        if len(jk) == 0 or len(gk) == 0:
            continue
        dx = mu[jk, 0, None] - gxy[None, gk, 0]
        dy = mu[jk, 1, None] - gxy[None, gk, 1]
        d2 = dx * dx + dy * dy
        a, c = np.nonzero(d2 <= 9.0 * var[jk, None])
        if len(a) == 0:
            continue
        jj, kk = jk[a], gk[c]
        period = np.pi if k == KIND_PARALLEL else 2 * np.pi
        dth = np.abs(
            np.mod(g.theta[kk] - theta[jj] - row_sim[jj, 2] + period / 2, period) - period / 2
        )
        ok = dth <= np.radians(25.0)
        jj, kk, d2_ok = jj[ok], kk[ok], d2[a[ok], c[ok]]
        if len(jj) == 0:
            continue
        active = sigma < 100
        da = (g.attrs[kk].astype(np.float64) - attrs[jj]) / sigma
        log_f = -0.5 * (da[:, active] ** 2).sum(axis=1) - float(
            np.sum(np.log(sigma[active] * np.sqrt(2 * np.pi)))
        )
        log_bg = _log_background_density(k, g.attrs[kk].astype(np.float64))
        v = var[jj]
        log_pos = -0.5 * d2_ok / v - np.log(2 * np.pi * v)
        term = np.log(p[jj]) + log_f - log_bg + log_pos + np.log(area)
        jj_all.append(jj)
        gain_all.append(term - log_miss[jj])
    if not jj_all:
        return total, np.zeros(n_hyp, np.int64)
    jj = np.concatenate(jj_all)
    gain = np.concatenate(gain_all)
    best = np.full(len(p), 0.0)
    np.maximum.at(best, jj, gain)
    paired = best > 0
    g_sum = total + np.bincount(hyp[paired], weights=best[paired], minlength=n_hyp).astype(
        np.float64)
    return g_sum, np.bincount(hyp[paired], minlength=n_hyp).astype(np.int64)


def align(
    model: ObjectModel,
    index: ModelIndex,
    feats: ImageFeatures,
    config: AlignConfig = AlignConfig(),
    max_matches: int = 5,
) -> list[Match2D]:
    """Find model views in an image.

    Parameters
    ----------
    model : ObjectModel
    index : ModelIndex
        ``build_index(model)``.
    feats : ImageFeatures
        Features of the image.
    config : AlignConfig
    max_matches : int
        Most matches returned (distinct image locations).

    Returns
    -------
    list of Match2D
        Best first by coverage, then g; empty when nothing plausible is found.
    """
    k, j, w = _pairings(index, feats, config)
    if len(k) == 0:
        return []
    if len(k) > config.max_pairings:
        # A model with many views in a busy image pairs millions of times;
        # the weakest pairings cost seconds and almost never seed the answer.
        # Weakest here means least likely under the model and most common in
        # this image (a checkerboard's junctions pair with every right angle
        # of the model): hard bench set, 38 -> 34 of 80 missed. The votes
        # keep the fixed clutter density: the image's estimate decides only
        # what the budget is spent on (voting by it in every image lost 2 of
        # 100 paper images and 5 clean hard ones).
        keep = np.argpartition(-(w + _log_rarity(feats)[k]), config.max_pairings)
        keep = keep[: config.max_pairings]
        k, j, w = k[keep], j[keep], w[keep]
    sims, pairing = _seeds(index, feats, k, j, config)
    j2, w2 = j[pairing], w[pairing]
    if len(sims) == 0:
        return []
    # Two votes, united: per location pooled over views (finds objects whose
    # evidence is spread over neighbouring views) and per (view, x, y, α, s)
    # bin (finds objects that one view explains with many consistent seeds).
    # A seed's vote is its positive log odds (plus a floor, so any seed counts).
    vote = np.maximum(w2, 0.0) + 0.5
    loc_views, loc_sims = _vote_hypotheses(index.view_of[j2], sims, vote, feats.shape, config)
    bin_views, bin_sims = _vote_bins(index.view_of[j2], sims, vote, config)
    hyp_views = np.concatenate([loc_views, bin_views])
    hyp_sims = np.concatenate([loc_sims, bin_sims])
    if len(hyp_views) == 0:
        return []
    # Quick extension of every voted hypothesis on its view's coarse edge
    # subset, all at once, so that seeds a few pixels off are judged after,
    # not before, they snap in.
    pts = index.coarse_pts[hyp_views]
    bins = index.coarse_bins[hyp_views]
    valid = index.coarse_valid[hyp_views]
    theta_c = np.asarray((bins + 0.5) * (np.pi / ORIENTATION_BINS), dtype=np.float64)
    fitted_all = extend_many(feats, hyp_sims, pts, theta_c, valid, config.coarse_radii_px,
                              config.orientation_tol_deg)
    cov_all = coverage_many(feats, fitted_all, pts, bins, valid)
    order = np.argsort(-cov_all)[: config.max_scored]
    order = order[cov_all[order] >= config.min_coverage]
    g_scored, _ = log_probability_many([model.model_views[v] for v in hyp_views[order]],
                                       feats, fitted_all[order])
    scored = [(float(gval) + config.coverage_weight * cov_all[n], int(hyp_views[n]),
               fitted_all[n], float(cov_all[n])) for gval, n in zip(g_scored, order, strict=True)]
    scored.sort(key=lambda item: -item[0])
    # The best hypotheses extended on all edge samples of their views, at once.
    best_views = np.array([view for _, view, _, _ in scored[: config.max_hypotheses]], np.int64)
    fine_pts, fine_theta, fine_bins, fine_valid = index.fine_samples(best_views)
    fitted_best = extend_many(
        feats, np.reshape([sim for _, _, sim, _ in scored[: config.max_hypotheses]], (-1, 4)),
        fine_pts, fine_theta, fine_valid, config.icp_radii_px, config.orientation_tol_deg,
        robust=True)
    cov_best = coverage_many(feats, fitted_best, fine_pts, fine_bins, fine_valid)
    g_best, n_pairs = log_probability_many([model.model_views[v] for v in best_views], feats,
                                           fitted_best)
    matches = [Match2D(int(v), f, float(gv), float(c), int(n)) for v, f, gv, c, n in zip(
        best_views, fitted_best, g_best, cov_best, n_pairs, strict=True)]
    # Pope & Lowe rank by g; coverage alone prefers small views that match
    # a part of the object (one plate of a barbell) perfectly.
    matches.sort(key=lambda m: -(m.log_probability + config.coverage_weight * m.coverage))
    # Hypotheses not extended on all samples still serve as alternatives.
    rest = [Match2D(view, sim, rank - config.coverage_weight * cov, cov, 0)
            for rank, view, sim, cov in scored[config.max_hypotheses:]]
    return suppress_duplicates(matches + rest, index.view_radius_px, max_matches,
                               config.max_alternatives)


def suppress_duplicates(matches: list[Match2D], view_radius_px: float,
                        max_matches: int, max_alternatives: int = 0) -> list[Match2D]:
    """Non-maximum suppression: keep the best match per image location.

    Matches suppressed by a kept one become its alternatives when they are of
    another model view (up to ``max_alternatives``, in the order given).
    """
    kept: list[Match2D] = []
    alternatives: list[list[Match2D]] = []
    for m in matches:
        radius = 0.5 * view_radius_px * m.sim[3]
        near = [i for i, o in enumerate(kept) if np.hypot(*(m.sim[:2] - o.sim[:2])) <= radius]
        if not near:
            if len(kept) < max_matches:
                kept.append(m)
                alternatives.append([])
            continue
        i = near[0]
        views = {kept[i].model_view} | {a.model_view for a in alternatives[i]}
        if len(alternatives[i]) < max_alternatives and m.model_view not in views:
            alternatives[i].append(m)
    return [replace(m, alternatives=tuple(a)) for m, a in zip(kept, alternatives, strict=True)]


def refine_at_model_scale(
    image: NDArray[np.generic],
    sim: F64,
    pts: F64,
    theta: F64,
    view_radius_px: float,
    config: AlignConfig = AlignConfig(icp_radii_px=(3.0, 2.0, 1.5, 1.0, 1.0)),
) -> tuple[F64, ImageFeatures, F64]:
    """Final 2D fit on a crop resampled so the object appears at training scale.

    Edge positions are not exactly scale-covariant (the smoothing and the
    edge thinning work in pixels, and thin parts merge when small), so a
    model learned at one scale fits best where the object has that scale.
    The crop around the match is warped by ``1/s`` (pre-smoothed when
    shrinking), features are extracted there and the similarity is extended
    on them.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array
        The scene.
    sim : (4,) array
        Model frame -> image similarity to refine.
    pts : (P, 2) array
        Edge samples of the view, model frame.
    theta : (P,) array
        Their orientations modulo π.
    view_radius_px : float
        Object radius in model-view pixels.
    config : AlignConfig
        Gates of the extension.

    Returns
    -------
    sim : (4,) float64
        Refined model -> image similarity.
    crop_features : ImageFeatures
        Features of the crop (for verification).
    crop_from_image : (4,) float64
        Similarity image -> crop.
    """
    from viewloc_core.features import extract_features

    k = 1.0 / float(sim[3])
    half = int(np.ceil(view_radius_px * 1.3)) + 4
    # image -> crop: scale by k about the match centre, which lands at (half, half).
    crop_from_image = np.array([half - k * sim[0], half - k * sim[1], 0.0, k])
    M = np.array([[k, 0.0, crop_from_image[0]], [0.0, k, crop_from_image[1]]])
    src = np.asarray(image)
    if k < 1.0:
        # Shrinking: low-pass first so the resampled crop does not alias.
        src = cv2.GaussianBlur(src, (0, 0), 0.5 / k)
    crop = cv2.warpAffine(src, M, (2 * half + 1, 2 * half + 1), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REPLICATE)
    feats = extract_features(crop)
    in_crop = sim2.compose(crop_from_image, sim)
    fitted = extend(feats, in_crop, pts, theta, config)
    return sim2.compose(sim2.inverse(crop_from_image), fitted), feats, crop_from_image
