"""Evidence against outlines that the image's lines run across.

A part's outline ends the background's lines: a line of the background that
meets the part stops at its outline (the part hides the rest of it), and the
part's own edges seldom carry on across its outline either. A place made of
the background's own lines (a checkerboard, tiles, a grid of boxes) is
different: its lines cross each other, so along a phantom outline snapped
onto them, edges at right angles to the outline run on to both sides of it.

An edge sample of a hypothesis that finds its edge in the image is
*crossed* when an edge at right angles to it lies on both sides of it, at
:data:`CROSSING_OFFSETS_PX` along its normal (beyond the orientation map's
spreading, so the outline's own edge does not count). The true part's samples
are crossed at :data:`OBJECT_CROSSED_RATE`; by chance, at the share of the
image's own edge pixels that are crossed (:func:`chance_crossed_rate`). A
crossed sample adds ``log(p_o / p_c)``, one not crossed
``log((1 - p_o) / (1 - p_c))``. Where the image's edges are no more often
crossed than the part's (a plain or a softly textured background), the term is
zero.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from viewloc_core.features import ImageFeatures, orientation_bin, wanted_bits

F64 = NDArray[np.float64]

#: Distances along a sample's normal, both ways, at which an edge at right
#: angles to it must lie for the sample to count as crossed, pixels (all of
#: them: a line through the sample, not a corner or a line ending at it).
#: Beyond the orientation map's spreading (2 px) and the outline's own blur.
CROSSING_OFFSETS_PX = (4.0, 6.0)

#: Share of the true part's edge samples, where they find their edge, that
#: the image's lines run across. Hard and novel bench sets, learning seed 0,
#: the right place's fit: median 0.0 and 0.02 of all samples, 97th
#: percentile 0.05 and 0.07; phantoms snapped onto a checkerboard's lines
#: 0.2-0.35. With the term in the alignment, AR_MSSD: novel set, learning
#: seeds 0 and 1, 0.8058 -> 0.8142 and 0.8033 -> 0.81 (checker images);
#: hard set, seeds 0 and 1, paper set, LM-O (every second photo) unchanged.
OBJECT_CROSSED_RATE = 0.05

#: Most of the image's edge pixels examined for the chance rate.
_MAX_CHANCE_PIXELS = 2000


def edge_at(feats: ImageFeatures, uv: F64, want: NDArray[np.int64]) -> NDArray[np.bool_]:
    """Whether the spread orientation map holds any of the ``want`` bits at
    each point's nearest pixel.

    Parameters
    ----------
    feats : ImageFeatures
    uv : (..., 2) float64
        Points in the image, pixels.
    want : (...) int64
        Orientation bits wanted at each point (:func:`wanted_bits`).

    Returns
    -------
    (...) bool
        False for points outside the image.
    """
    h, w = feats.shape
    u = np.rint(uv[..., 0]).astype(np.int64)
    v = np.rint(uv[..., 1]).astype(np.int64)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    bits = feats.orientation_bits[np.clip(v, 0, h - 1), np.clip(u, 0, w - 1)]
    return np.asarray(inside & ((bits.astype(np.int64) & want) != 0), np.bool_)


def crossed(feats: ImageFeatures, uv: F64, tangent_rad: F64) -> NDArray[np.bool_]:
    """Whether an image edge at right angles to each point's tangent lies on
    both sides of it at every :data:`CROSSING_OFFSETS_PX`.

    Parameters
    ----------
    feats : ImageFeatures
        The image, with its spread orientation map.
    uv : (..., 2) float64
        Points in the image, pixels.
    tangent_rad : (...) float64
        Tangent orientation at each point, radians (modulo π).

    Returns
    -------
    (...) bool
        False where any of the looked-at pixels is outside the image.
    """
    normal = np.stack([-np.sin(tangent_rad), np.cos(tangent_rad)], axis=-1)
    # The crossing edge runs along the normal: its orientation is the
    # normal's.
    want = wanted_bits(orientation_bin(np.mod(tangent_rad + np.pi / 2, np.pi)))
    result = np.ones(tangent_rad.shape, bool)
    for offset in CROSSING_OFFSETS_PX:
        for side in (1.0, -1.0):
            result &= edge_at(feats, uv + side * offset * normal, want)
    return result


def chance_crossed_rate(feats: ImageFeatures, rng: np.random.Generator | None = None) -> float:
    """Share of the image's edge pixels that its lines run across.

    Parameters
    ----------
    feats : ImageFeatures
    rng : numpy.random.Generator, optional
        Picks the examined pixels when there are more than a few thousand
        (a fixed seed when None, so an image always gets the same rate).

    Returns
    -------
    float
        In [0, 1]; 0 for an image without edges.
    """
    n = len(feats.edge_xy)
    if n == 0:
        return 0.0
    pick = np.arange(n)
    if n > _MAX_CHANCE_PIXELS:
        pick = (rng or np.random.default_rng(0)).choice(n, _MAX_CHANCE_PIXELS, replace=False)
    return float(crossed(feats, feats.edge_xy[pick].astype(np.float64),
                         feats.edge_theta[pick].astype(np.float64)).mean())


def crossing_log_ratios(chance_rate: float) -> tuple[float, float]:
    """Log-likelihood ratios object vs. clutter of a crossed sample and of
    one not crossed.

    Parameters
    ----------
    chance_rate : float
        :func:`chance_crossed_rate` of the image.

    Returns
    -------
    crossed_llr, not_crossed_llr : float
        Both 0 when the image's edges are crossed no more often than the
        part's (:data:`OBJECT_CROSSED_RATE`).
    """
    p_clutter = min(max(chance_rate, OBJECT_CROSSED_RATE), 0.95)
    return (float(np.log(OBJECT_CROSSED_RATE / p_clutter)),
            float(np.log((1.0 - OBJECT_CROSSED_RATE) / (1.0 - p_clutter))))


def crossing_evidence(feats: ImageFeatures, uv: F64, tangent_rad: F64, found: NDArray[np.bool_],
                      valid: NDArray[np.bool_], chance_rate: float) -> F64:
    """Mean log-likelihood ratio per sample of H hypotheses' crossings.

    Parameters
    ----------
    feats : ImageFeatures
    uv : (H, P, 2) float64
        Edge samples mapped into the image, pixels.
    tangent_rad : (H, P) float64
        Their tangent orientations in the image, radians.
    found : (H, P) bool
        Which samples find an image edge of their orientation (only those
        are judged: a missed sample has no line of its own to be crossed).
    valid : (H, P) bool
        Which samples are real (not padding).
    chance_rate : float
        :func:`chance_crossed_rate` of the image.

    Returns
    -------
    (H,) float64
        Sum over the found samples, over the number of valid ones (the
        same normalisation as :func:`viewloc_core.align.outline_evidence`).
    """
    crossed_llr, not_crossed_llr = crossing_log_ratios(chance_rate)
    if crossed_llr == 0.0:
        return np.zeros(len(uv))
    judged = found & valid
    # Only the judged samples are looked at (a third to a half of them).
    is_crossed = np.zeros(judged.shape, bool)
    is_crossed[judged] = crossed(feats, uv[judged], tangent_rad[judged])
    total = (crossed_llr * is_crossed.sum(axis=1)
             + not_crossed_llr * (judged & ~is_crossed).sum(axis=1))
    return np.asarray(total / np.maximum(valid.sum(axis=1), 1), np.float64)
