"""Probabilistic alignment of model views to an image (Pope & Lowe 2000; DESIGN.md §2 step 6).

1. *Pairings.* Every image feature is paired with the model features of the
   same kind whose attributes are likely under the model's attribute density;
   each pairing is ranked by ``log p_j + log f_j(a_k) − log f_bg(a_k)``.
2. *Seeds.* A junction or parallel-pair pairing fixes a whole similarity
   ``(x, y, α, s)``.
3. *Verification.* Every seed is checked against the image's spread
   orientation map with its model view's dense edge samples (LINE-2D's
   trick, cheap enough for tens of thousands of seeds), scored as a
   log-likelihood ratio object vs. clutter (:mod:`viewloc_core.edge_evidence`):
   the seeds are ranked by what they explain in the image, not by how many
   agree. The best few hundred are snapped onto the edges and judged again;
   the best per image location are kept.
4. *Extension.* The kept hypotheses are extended greedily: model edge samples
   pair with image edges under the current similarity and the similarity is
   re-fitted by weighted least squares (point-to-line), shrinking the gate.
5. *Quality.* ``g(E, T) ≈ log P(H | E, T)`` over the feature pairings E
   (matched terms, unmatched ``log(1 − p_j)``, Gaussian position term times
   the image area for the uniform background), and the fraction of dense edge
   samples confirmed by the image (the ``coverage``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from viewloc_core import similarity as sim2
from viewloc_core.both_cores import over_halves
from viewloc_core.clutter_density import log_image_density
from viewloc_core.edge_evidence import (
    ChanceRates,
    chance_rates,
    lay_over_templates,
    object_strong_share,
    outline_samples,
)
from viewloc_core.features import (
    KIND_ARC,
    KIND_JUNCTION,
    KIND_PARALLEL,
    KIND_U_JUNCTION,
    ORIENTATION_BINS,
    FeatureConfig,
    ImageFeatures,
    orientation_bin,
    orientation_turn,
    wanted_bits,
)
from viewloc_core.line_crossing import (
    chance_crossed_rate,
    crossing_evidence,
    crossing_log_ratios,
    edge_at,
)
from viewloc_core.model import ModelView, ObjectModel
from viewloc_core.pairing import PairingSet, strongest_pairings
from viewloc_core.search_space import within_bounds
from viewloc_core.seeding import seed_similarities
from viewloc_core.similarity_fit import fit_similarities

F64 = NDArray[np.float64]

#: Attribute standard deviations per feature kind (junction: opening angle rad,
#: log arm ratio; parallel pair: log overlap/separation, unused; arc: angular
#: span rad, unused; spans vary with occlusion and where the chain splits;
#: U-junction: mean and half difference of two opening angles, each the
#: junction's 0.12 over √2).
ATTR_SIGMA = {KIND_JUNCTION: np.array([0.12, 0.7]), KIND_PARALLEL: np.array([0.5, 1e3]),
              KIND_ARC: np.array([0.6, 1e3]), KIND_U_JUNCTION: np.array([0.09, 0.09])}


@dataclass(frozen=True, slots=True)
class AlignConfig:
    """Tuning of the alignment search.

    Attributes
    ----------
    min_scale, max_scale : float
        Range of image scale relative to the training views.
    attr_gate : float
        Pairings further than this many attribute sigmas are not formed.
    max_pairings : int
        Most (image feature, model feature) pairings kept, strongest first
        (a paper-set image makes about 12,000; a 160-view textured model in
        a 400x300 real photo 1.8 million).
    screen_samples : int
        Coarse edge samples per view of the first screen of the seeds.
    max_screened : int
        Seeds (by the first screen) judged on all coarse samples.
    max_extended : int
        Seeds (by their evidence) given the quick extension and judged again.
    max_alternatives : int
        Other hypotheses kept per image location for the 6D verification
        (see :func:`suppress_duplicates`).
    icp_radii_px : tuple of float
        Pairing gates of the successive extension steps (fine edge samples).
    coarse_radii_px : tuple of float
        The same for the quick extension of the best seeds.
    orientation_tol_deg : float
        Largest orientation difference of paired edge samples.
    """

    min_scale: float = 0.3
    max_scale: float = 3.0
    attr_gate: float = 2.5
    max_pairings: int = 40000
    screen_samples: int = 12
    max_screened: int = 1500
    max_extended: int = 300
    max_alternatives: int = 2
    icp_radii_px: tuple[float, ...] = (4.0, 2.5, 1.5, 1.5)
    coarse_radii_px: tuple[float, ...] = (8.0, 4.0)
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
    evidence : float
        Log-likelihood ratio object vs. clutter of the view's edge samples
        (:func:`outline_evidence`), estimated for the whole outline from the
        coarse subset: how the match was ranked.
    alternatives : tuple of Match2D
        Other model views that fit about the same image location, best
        first, with their quick fit and evidence (their ``log_probability``,
        ``coverage`` and ``n_pairs`` are not measured, 0; their
        ``alternatives`` are empty). A 2D similarity cannot tell some views
        apart (a barbell's plate seen end-on or a plate of a side view), the
        6D verification can.
    """

    model_view: int
    sim: F64
    log_probability: float
    coverage: float
    n_pairs: int
    evidence: float = 0.0
    alternatives: tuple[Match2D, ...] = ()


@dataclass(frozen=True, slots=True)
class ModelIndex:
    """Model features stacked over all views, their attributes ready to pair.

    ``attr_z`` holds per feature kind the attributes of the model features in
    units of their pairing standard deviations (:data:`ATTR_SIGMA`) and the
    rows of those features.

    The edge samples of every view are padded to one length twice: a
    well-spread subset (``coarse_*``, screening) and all of them (``fine_*``,
    the final extension), so hypotheses of different views batch together.
    ``coarse_px``, ``coarse_py`` and ``coarse_bins8`` are the coarse subset
    in the types :func:`viewloc_core.edge_evidence.lay_over_templates` reads;
    ``outline_px`` is the edge length of each view's whole outline at scale 1
    (pixels), which its coarse evidence is scaled to.
    """

    view_of: NDArray[np.int64]
    kind: NDArray[np.int8]
    xy: F64
    theta: F64
    scale: F64
    attrs: F64
    log_presence: F64
    attr_z: dict[int, tuple[F64, NDArray[np.int64]]]
    coarse_pts: F64
    coarse_bins: NDArray[np.int64]
    coarse_valid: NDArray[np.bool_]
    coarse_px: NDArray[np.float32]
    coarse_py: NDArray[np.float32]
    coarse_bins8: NDArray[np.uint8]
    outline_px: F64
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
    """Precompute the pairing attributes and edge subsets of a model (once per model)."""
    views = model.model_views
    view_of = np.concatenate([np.full(len(v.kind), i, np.int64) for i, v in enumerate(views)])
    kind = np.concatenate([v.kind for v in views])
    xy = np.concatenate([v.xy for v in views]).astype(np.float64)
    theta = np.concatenate([v.theta for v in views]).astype(np.float64)
    scale = np.concatenate([v.scale for v in views]).astype(np.float64)
    attrs = np.concatenate([v.attrs for v in views]).astype(np.float64)
    log_presence = np.log(np.concatenate([v.presence for v in views]).astype(np.float64))
    attr_z = {}
    for k, sigma in ATTR_SIGMA.items():
        idx = np.flatnonzero(kind == k)
        z = attrs[idx] / sigma
        # A feature with an undefined attribute or never present pairs with nothing.
        ok = np.isfinite(z).all(axis=1) & np.isfinite(log_presence[idx])
        idx, z = idx[ok], z[ok]
        if len(idx):
            # Sorted by the first attribute, as pairing.strongest_pairings reads them.
            order = np.argsort(z[:, 0], kind="stable")
            attr_z[k] = (np.ascontiguousarray(z[order]), idx[order])
    rng = np.random.default_rng(0)
    # Coarse edge subsets padded to one length so hypotheses batch together.
    coarse_pts = np.zeros((len(views), coarse_points, 2))
    coarse_bins = np.zeros((len(views), coarse_points), np.int64)
    coarse_valid = np.zeros((len(views), coarse_points), bool)
    n_fine = max((len(v.edge_theta) for v in views), default=0)
    fine_pts = np.zeros((len(views), n_fine, 2))
    fine_theta = np.zeros((len(views), n_fine))
    fine_valid = np.zeros((len(views), n_fine), bool)
    outline_px = np.zeros(len(views))
    for i, v in enumerate(views):
        exy = v.edge_xy.astype(np.float64)
        eth = v.edge_theta.astype(np.float64)
        fine_pts[i, : len(eth)], fine_theta[i, : len(eth)], fine_valid[i, : len(eth)] = (
            exy, eth, True)
        pick = spread_subset(exy, coarse_points, rng)
        coarse_pts[i, : len(pick)] = exy[pick]
        coarse_bins[i, : len(pick)] = orientation_bin(eth[pick])
        coarse_valid[i, : len(pick)] = True
        outline_px[i] = len(exy) * sample_spacing_px(exy)
    radius = model.f_train_px * model.diameter_mm / model.d0_mm / 2.0
    return ModelIndex(
        view_of, kind, xy, theta, scale, attrs, log_presence, attr_z,
        coarse_pts, coarse_bins, coarse_valid,
        np.ascontiguousarray(coarse_pts[..., 0], np.float32),
        np.ascontiguousarray(coarse_pts[..., 1], np.float32), coarse_bins.astype(np.uint8),
        outline_px, fine_pts, fine_theta, orientation_bin(fine_theta), fine_valid, radius,
    )


def sample_spacing_px(edge_xy: F64) -> float:
    """Spacing (pixels) of edge samples (N, 2) spread evenly along the edges:
    the edge length each one stands for (1 when there are fewer than 2)."""
    if len(edge_xy) < 2:
        return 1.0
    nn_dist, _ = cKDTree(edge_xy).query(edge_xy, k=2)
    return float(np.median(nn_dist[:, 1]))


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


#: Width of the range of junction opening angles the features accept, rad.
_OPENING_SPAN = np.pi - 2 * np.radians(FeatureConfig().min_junction_angle_deg)


def _log_background_density(kind: int, attrs: F64) -> F64:
    """log f_bg(a): attribute density of clutter features.

    Junction opening angles are about uniform over the accepted range and arm
    ratios about log-normal; parallel-pair overlap ratios about log-normal.
    Clutter arcs are mostly short (on the paper set their spans fall off
    about exponentially from the 80° minimum, scale ~75°) and rarely closed
    (~1%): a closed circle counts as a 2% chance spread over 0.5 rad.
    A U-junction's two interior angles, each uniform over the accepted
    range of width L, make its (mean, half difference) uniform with density
    4 / L² over the half of the square they can reach.
    """
    if kind == KIND_U_JUNCTION:
        return np.full(len(attrs), np.log(4.0 / _OPENING_SPAN**2))
    if kind == KIND_JUNCTION:
        return (-np.log(_OPENING_SPAN) - 0.5 * (attrs[:, 1] / 1.2) ** 2
                - np.log(1.2 * np.sqrt(2 * np.pi)))
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


def _on_strong_edges(feats: ImageFeatures) -> NDArray[np.bool_]:
    """Per image feature: whether its edges are strong
    (:attr:`viewloc_core.features.ImageFeatures.strong_bits`), looked up at
    points on them: a junction's vertex, the middles of a parallel pair's two
    lines (both strong), the middle of an arc; (F,) bool."""
    g = feats.grouped
    xy = g.xy.astype(np.float64)
    theta = g.theta.astype(np.float64)
    reach = g.scale.astype(np.float64)[:, None]
    # A parallel pair's position is midway between its lines (its scale is
    # their separation, its angle theirs); an arc's is its circle's centre
    # (its scale the radius, its angle towards the arc's middle).
    across = np.stack([-np.sin(theta), np.cos(theta)], axis=1)
    outward = np.stack([np.cos(theta), np.sin(theta)], axis=1)
    parallel = (g.kind == KIND_PARALLEL)[:, None]
    first = np.where(parallel, xy + 0.5 * reach * across,
                     np.where((g.kind == KIND_ARC)[:, None], xy + reach * outward, xy))
    second = np.where(parallel, xy - 0.5 * reach * across, first)
    h, w = feats.shape

    def strong_at(points: F64) -> NDArray[np.bool_]:
        u = np.clip(np.rint(points[:, 0]).astype(np.int64), 0, w - 1)
        v = np.clip(np.rint(points[:, 1]).astype(np.int64), 0, h - 1)
        return np.asarray(feats.strong_bits[v, u] != 0)

    return strong_at(first) & strong_at(second)


def _log_contrast(feats: ImageFeatures) -> F64:
    """Per image feature: how much likelier its edges' contrast is on the
    part than in this image's clutter, (F,) float64.

    The pairing side of :mod:`viewloc_core.edge_evidence`'s strong hits: the
    image's features lie on strong edges at its own share, the part's at the
    odds :data:`viewloc_core.edge_evidence.STRONG_EDGE_ODDS_RATIO` times as
    high. About 0 wherever nearly every feature is strong (a clean
    background, a rendered training view) or none is.
    """
    strong = _on_strong_edges(feats)
    if len(strong) == 0:
        return np.zeros(0, np.float64)
    # The share stays off 0 and 1: its ratios must only stay finite.
    share = float(np.clip(strong.mean(), 1e-3, 1.0 - 1e-3))
    object_share = float(object_strong_share(share))
    gain = math.log(object_share / share)
    loss = math.log((1.0 - object_share) / (1.0 - share))
    return np.where(strong, gain, loss).astype(np.float64)


def _pairings(index: ModelIndex, feats: ImageFeatures, config: AlignConfig) -> tuple[
    NDArray[np.int64], NDArray[np.int64]
]:
    """All plausible (image feature, model feature) pairings, the
    ``config.max_pairings`` strongest when there are more.

    A model with many views in a busy image pairs millions of times; the
    weakest pairings cost seconds and almost never seed the answer. Weakest
    here means least likely under the model and most common in this image
    (a checkerboard's junctions pair with every right angle of the model):
    hard bench set, 38 -> 34 of 80 missed. The strength of a pairing is the
    log likelihood of its attribute difference plus the model feature's log
    presence, less the image feature's log clutter density and plus its
    rarity in this image (:func:`_log_rarity`) and its contrast
    (:func:`_log_contrast`: a small part's few features among a textured
    background's thousand otherwise lose the budget to the texture's; novel
    bench set, AR_MSSD mean over learning seeds 0-2 0.741 -> 0.776; hard set,
    seeds 0-4, 0.877 -> 0.873).
    """
    g = feats.grouped
    rarity = _log_rarity(feats) + _log_contrast(feats)
    sets = []
    for k, (model_z, model_rows) in index.attr_z.items():
        img_rows = np.flatnonzero(g.kind == k)
        sigma = ATTR_SIGMA[k]
        img_attrs = g.attrs[img_rows].astype(np.float64)
        active = sigma < 100
        log_norm = float(np.sum(np.log(sigma[active] * np.sqrt(2 * np.pi))))
        img_term = rarity[img_rows] - _log_background_density(k, img_attrs) - log_norm
        img_z = img_attrs / sigma
        # A feature with an undefined attribute pairs with nothing.
        ok = np.isfinite(img_z).all(axis=1) & np.isfinite(img_term)
        sets.append(PairingSet(img_rows[ok], model_rows, np.ascontiguousarray(img_z[ok]),
                               model_z, img_term[ok], index.log_presence[model_rows]))
    return strongest_pairings(sets, config.attr_gate, config.max_pairings)


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


def outline_evidence(index: ModelIndex, feats: ImageFeatures, views: NDArray[np.int64],
                     sims: F64, chance: ChanceRates, n_samples: int | None = None) -> F64:
    """Evidence of H hypotheses (model view, similarity) for their whole outline.

    The log-likelihood ratio object vs. clutter of each view's coarse edge
    samples (:func:`viewloc_core.edge_evidence.lay_over_templates`), per
    sample, times the number of samples its whole outline makes in the image
    (the outline's length over the sample spacing), so a view that explains
    the whole object beats one that explains a part of it as well. The
    length grows with the hypothesis's scale only as
    ``scale ** OUTLINE_SCALE_EXPONENT``
    (:func:`viewloc_core.edge_evidence.outline_samples`).

    Parameters
    ----------
    index : ModelIndex
    feats : ImageFeatures
        The image, with its spread orientation map.
    views : (H,) int
        Model view of each hypothesis.
    sims : (H, 4) float64
        Model view -> image similarities.
    chance : ChanceRates
        :func:`viewloc_core.edge_evidence.chance_rates` of the image.
    n_samples : int, optional
        Use only the first this many coarse samples (still spread over the
        outline: the subset is in farthest-point order); all when None.

    Returns
    -------
    (H,) float64
    """
    n = index.coarse_px.shape[1] if n_samples is None else n_samples
    # Contiguous copies of the first n columns ((V, n), small): the kernel is
    # compiled (and warmed up) for C-ordered templates only, and a column
    # slice would make numba compile a second version at the first request.
    llr, _, n_valid, _ = lay_over_templates(
        feats, np.ascontiguousarray(index.coarse_px[:, :n]),
        np.ascontiguousarray(index.coarse_py[:, :n]),
        np.ascontiguousarray(index.coarse_bins8[:, :n]),
        np.ascontiguousarray(index.coarse_valid[:, :n]), views, sims, chance)
    return llr / np.maximum(n_valid, 1) * outline_samples(index.outline_px[views], sims[:, 3])


def outline_crossing_evidence(index: ModelIndex, feats: ImageFeatures, views: NDArray[np.int64],
                              sims: F64, chance_rate: float) -> F64:
    """Evidence of H hypotheses against lines of the image that run across
    their coarse edge samples (:mod:`viewloc_core.line_crossing`), for their
    whole outline as :func:`outline_evidence` counts it.

    Parameters
    ----------
    index : ModelIndex
    feats : ImageFeatures
    views : (H,) int
    sims : (H, 4) float64
        Model view -> image similarities.
    chance_rate : float
        :func:`viewloc_core.line_crossing.chance_crossed_rate` of the image.

    Returns
    -------
    (H,) float64
        At most 0 where the samples are crossed more often than a part's.
    """
    if crossing_log_ratios(chance_rate)[0] == 0.0:
        # The image's lines seldom cross: nothing to tell apart.
        return np.zeros(len(views))
    uv = sim2.apply_many(sims, index.coarse_pts[views])
    tangent_rad = (index.coarse_bins[views] + 0.5) * (np.pi / ORIENTATION_BINS) + sims[:, 2:3]
    turned = (index.coarse_bins[views] + orientation_turn(sims[:, 2])[:, None]) % ORIENTATION_BINS
    found = edge_at(feats, uv, wanted_bits(turned))
    per_sample = crossing_evidence(feats, uv, tangent_rad, found, index.coarse_valid[views],
                                   chance_rate)
    return per_sample * outline_samples(index.outline_px[views], sims[:, 3])


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
    sims = np.ascontiguousarray(sims, np.float64)
    pts = np.ascontiguousarray(pts, np.float64)
    theta = np.ascontiguousarray(theta, np.float64)
    valid = np.ascontiguousarray(valid, np.bool_)
    radii_px = np.asarray(radii, np.float64)
    tol_rad = float(np.radians(tol_deg))

    def fit_some(lo: int, hi: int) -> tuple[F64]:
        return (fit_similarities(sims[lo:hi], pts[lo:hi], theta[lo:hi], valid[lo:hi],
                                 feats.nearest_edge, feats.edge_distance, feats.edge_xy,
                                 feats.edge_theta, radii_px, tol_rad, robust),)

    # About 100 ns per sample and step: split from about half a millisecond.
    (fitted,) = over_halves(len(sims), fit_some, 5000 // max(pts.shape[1] * len(radii_px), 1))
    return np.asarray(fitted, np.float64)


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
    chance: ChanceRates | None = None,
    within: NDArray[np.floating] | None = None,
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
    chance : ChanceRates, optional
        :func:`viewloc_core.edge_evidence.chance_rates` of ``feats``, when
        the caller has them already (the view search needs them too);
        computed here when None.
    within : (4,) array, optional
        ``x0, y0, x1, y1``, image pixels: only hypotheses that place the
        model view's origin in this rectangle are searched.

    Returns
    -------
    list of Match2D
        Best first by evidence; empty when nothing plausible is found.
    """
    k, j = _pairings(index, feats, config)
    if len(k) == 0:
        return []
    sims, pairing = _seeds(index, feats, k, j, config)
    if within is not None:
        inside = within_bounds(sims[:, :2], within)
        sims, pairing = sims[inside], pairing[inside]
    if len(sims) == 0:
        return []
    views = index.view_of[j[pairing]]
    # Every seed is judged by what its view's edge samples find in the image,
    # against how often edges occur there by chance. In textured scenes the
    # true location's seeds are a few hundred among tens of thousands and
    # agree too loosely in view, angle and scale to win a vote (hard bench
    # set, 640x480: the first location was right in 46 of 80 images with a
    # (view, x, y, angle, scale) vote and edge coverage, 64 with this).
    if chance is None:
        chance = chance_rates(feats)
    if len(sims) > config.max_screened:
        # A first screen on a few samples of each view's outline: the seeds
        # that miss most of them miss most of the rest too (hard bench set:
        # the same locations found with 12 samples as with all 48, at a
        # third of the cost).
        evidence = outline_evidence(index, feats, views, sims, chance, config.screen_samples)
        best = np.argpartition(-evidence, config.max_screened)[: config.max_screened]
        views, sims = views[best], sims[best]
    evidence = outline_evidence(index, feats, views, sims, chance)
    best = np.argsort(-evidence, kind="stable")[: config.max_extended]
    views, sims = views[best], sims[best]
    # The best seeds snap onto the edges (a seed is a few pixels and degrees
    # off) and are judged again.
    bins = index.coarse_bins[views]
    theta_c = np.asarray((bins + 0.5) * (np.pi / ORIENTATION_BINS), dtype=np.float64)
    fitted = extend_many(feats, sims, index.coarse_pts[views], theta_c, index.coarse_valid[views],
                         config.coarse_radii_px, config.orientation_tol_deg)
    # A place snapped onto a grid of background lines (a checkerboard, tiles)
    # finds its edges as well as the part does, but those lines run on
    # across it where the part's outline would end them
    # (:mod:`viewloc_core.line_crossing`).
    evidence = outline_evidence(index, feats, views, fitted, chance) + outline_crossing_evidence(
        index, feats, views, fitted, chance_crossed_rate(feats))
    # No more likely object than clutter (or wholly outside the image): no match.
    order = np.argsort(-evidence, kind="stable")
    order = order[evidence[order] > 0]
    views, fitted, evidence = views[order], fitted[order], evidence[order]

    def match(n: int) -> Match2D:
        return Match2D(int(views[n]), fitted[n], 0.0, 0.0, 0, float(evidence[n]))

    kept = [replace(match(i), alternatives=tuple(match(a) for a in alts))
            for i, alts in _suppress(fitted, views, index.view_radius_px, max_matches,
                                     config.max_alternatives)]
    return _with_quality(model, index, feats, kept, config)


def _with_quality(model: ObjectModel, index: ModelIndex, feats: ImageFeatures,
                  matches: list[Match2D], config: AlignConfig) -> list[Match2D]:
    """The matches extended on all their view's edge samples, with g and
    coverage (their alternatives keep their quick fit and evidence only)."""
    if not matches:
        return []
    views = np.array([m.model_view for m in matches], np.int64)
    fine_pts, fine_theta, fine_bins, fine_valid = index.fine_samples(views)
    fitted = extend_many(feats, np.array([m.sim for m in matches]), fine_pts, fine_theta,
                         fine_valid, config.icp_radii_px, config.orientation_tol_deg,
                         robust=True)
    cov = coverage_many(feats, fitted, fine_pts, fine_bins, fine_valid)
    g, n_pairs = log_probability_many([model.model_views[v] for v in views], feats, fitted)
    return [replace(m, sim=fitted[i], log_probability=float(g[i]), coverage=float(cov[i]),
                    n_pairs=int(n_pairs[i])) for i, m in enumerate(matches)]


#: Hypotheses of one model view at one location differing in in-plane angle
#: by more than this are different alternatives (an outline that fits
#: turned by 180° as well as upright is two hypotheses, not one).
DISTINCT_ANGLE_RAD = math.radians(30.0)


def suppress_duplicates(matches: list[Match2D], view_radius_px: float,
                        max_matches: int, max_alternatives: int = 0) -> list[Match2D]:
    """Non-maximum suppression: keep the best match per image location.

    Matches suppressed by a kept one become its alternatives when they are of
    another model view, or of the same at an angle more than
    ``DISTINCT_ANGLE_RAD`` from each one already there (up to
    ``max_alternatives``, in the order given).
    """
    if not matches:
        return []
    groups = _suppress(np.array([m.sim for m in matches]),
                       np.array([m.model_view for m in matches]), view_radius_px,
                       max_matches, max_alternatives)
    return [replace(matches[i], alternatives=tuple(matches[a] for a in alts))
            for i, alts in groups]


def _suppress(sims: F64, views: NDArray[np.int64], view_radius_px: float, max_matches: int,
              max_alternatives: int) -> list[tuple[int, list[int]]]:
    """:func:`suppress_duplicates` on arrays: (index kept, indices of its
    alternatives) per location, for hypotheses (H, 4) given best first.

    A hypothesis within half a view radius (at its own scale) of a kept one
    belongs to the first such, which is earlier in the order; the first one
    that belongs to none is kept next.
    """
    radius = 0.5 * view_radius_px * sims[:, 3]
    owner = np.full(len(sims), -1, np.int64)
    kept: list[int] = []
    while len(kept) < max_matches:
        free = np.flatnonzero(owner < 0)
        if len(free) == 0:
            break
        i, rest = int(free[0]), free[1:]
        kept.append(i)
        owner[i] = i
        near = np.hypot(sims[rest, 0] - sims[i, 0], sims[rest, 1] - sims[i, 1]) <= radius[rest]
        owner[rest[near]] = i
    groups = []
    for i in kept:
        alts: list[int] = []
        for n in np.flatnonzero(owner == i)[1:].tolist():
            if len(alts) == max_alternatives:
                break
            if all(views[n] != views[o]
                   or abs(math.remainder(sims[n, 2] - sims[o, 2], 2 * math.pi))
                   > DISTINCT_ANGLE_RAD for o in (i, *alts)):
                alts.append(n)
        groups.append((i, alts))
    return groups


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
