"""Edge samples of view templates laid over an image and scored, compiled.

The view search (:mod:`viewloc_core.view_search`) scores thousands of
(training view, similarity) pairs per image location: each edge sample is
mapped into the image, looked up in the spread orientation map and adds the
log-likelihood ratio of a hit on a strong edge, a hit on a weak one or a miss
of its (turned) orientation bin. In
array form that is a dozen passes over (pairs x samples) temporaries; here it
is one pass with no temporaries. Positions are computed in float32 exactly as
the array form did (the rounding to a pixel decides hits).

The outcome of a sample indexes a table of log-likelihood ratios per row
(:data:`MISS`, :data:`WEAK_HIT`, :data:`STRONG_HIT`) rather than choosing
between them by branches: whether a hit is strong is as good as random to
the processor, and the nested branch made the grid kernel 4.6 times slower
(22 against 4.8 ms on 2 million samples; the table lookup takes 7).

A template sample carries a code, ``class * B + bin`` (``B`` orientation
bins): its orientation bin and the class of edge it stands for (outline,
crease, ... : :mod:`viewloc_core.sample_classes`), each class with its own
rate of being found and so its own ``B`` rows of the table. A table of ``B``
rows serves templates of one class (codes below ``B``).
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

F64 = NDArray[np.float64]

#: Columns of the log-likelihood ratio table: a sample that finds no edge of
#: its orientation, one that finds a weak edge, one that finds a strong edge.
MISS, WEAK_HIT, STRONG_HIT = 0, 1, 2


@njit(cache=True, nogil=True, inline="always")
def _laid_template(
    bits: NDArray[np.uint16], strong_bits: NDArray[np.uint16], wanted: NDArray[np.uint16],
    px: NDArray[np.float32], py: NDArray[np.float32], bins: NDArray[np.uint8],
    valid: NDArray[np.bool_], t: np.int64, c: np.float32, s: np.float32, tx: np.float32,
    ty: np.float32, tn: np.uint8, log_ratio: F64,
) -> tuple[float, int, int, float]:  # pragma: no cover - compiled
    """Template row ``t`` laid over the image by one similarity: its llr,
    hits, valid samples and the llr had every sample inside found its edge."""
    h, w = bits.shape
    n_bins = len(wanted)
    acc = 0.0
    acc_best = 0.0
    n_hit = 0
    count = 0
    for p in range(px.shape[1]):
        if not valid[t, p]:
            continue
        count += 1
        u = int(np.rint(c * px[t, p] - s * py[t, p] + tx))
        v = int(np.rint(s * px[t, p] + c * py[t, p] + ty))
        if u < 0 or u >= w or v < 0 or v >= h:
            continue
        code = np.int64(bins[t, p])
        b = (code + tn) & (n_bins - 1)
        # The sample's class picks its rows of the table, its bin the row.
        row = code - (code & (n_bins - 1)) + b
        acc_best += max(log_ratio[row, WEAK_HIT], log_ratio[row, STRONG_HIT])
        hit = (bits[v, u] & wanted[b]) != 0
        # The strong map is a subset of the full one: 0, 1 or 2 is MISS,
        # WEAK_HIT or STRONG_HIT.
        outcome = np.int64(hit) + np.int64((strong_bits[v, u] & wanted[b]) != 0)
        acc += log_ratio[row, outcome]
        n_hit += hit
    return acc, n_hit, count, acc_best


@njit(cache=True, nogil=True)
def lay_over(
    bits: NDArray[np.uint16], strong_bits: NDArray[np.uint16], wanted: NDArray[np.uint16],
    px: NDArray[np.float32], py: NDArray[np.float32], bins: NDArray[np.uint8],
    valid: NDArray[np.bool_], rows: NDArray[np.int64],
    cos_scale: NDArray[np.float32], sin_scale: NDArray[np.float32],
    x: NDArray[np.float32], y: NDArray[np.float32], turn: NDArray[np.uint8],
    log_ratio: F64,
) -> tuple[F64, NDArray[np.int64], NDArray[np.int64], F64]:  # pragma: no cover - compiled
    """Evidence of H template rows laid over an image by H similarities.

    Parameters
    ----------
    bits : (h, w) uint16
        Spread orientation map of the image (bit ``b``: an edge of bin ``b``).
    strong_bits : (h, w) uint16
        The same of its strong edges alone (a subset of ``bits``).
    wanted : (B,) uint16
        Bits that confirm a sample of each orientation bin.
    px, py : (T, P) float32
        Sample positions of the templates, template pixels.
    bins : (T, P) uint8
        Their codes: ``class * B + orientation bin`` (see the module's
        docstring; the orientation bin alone for a table of ``B`` rows).
    valid : (T, P) bool
        Real samples (not padding).
    rows : (H,) int64
        Template row of each pair.
    cos_scale, sin_scale : (H,) float32
        ``s cos α`` and ``s sin α`` of each similarity.
    x, y : (H,) float32
        Its translation, image pixels.
    turn : (H,) uint8
        Orientation bins its angle turns the samples by.
    log_ratio : (C * B, 3) float64
        Log-likelihood ratio per sample class and orientation bin (row
        ``class * B + bin``) of a miss, a hit on a weak edge and a hit on a
        strong one (columns :data:`MISS`, :data:`WEAK_HIT`,
        :data:`STRONG_HIT`); ``B = len(wanted)`` must be a power of two.

    Returns
    -------
    llr : (H,) float64
        Summed over the samples inside the image (outside ones are unknown).
    hits : (H,) int64
        Samples that found an edge of their orientation.
    n_valid : (H,) int64
        Valid samples.
    llr_all_found : (H,) float64
        The llr had every sample inside the image found its edge, of the
        better-scoring kind.
    """
    n_pairs = len(rows)
    llr = np.zeros(n_pairs)
    hits = np.zeros(n_pairs, np.int64)
    n_valid = np.zeros(n_pairs, np.int64)
    best = np.zeros(n_pairs)
    for i in range(n_pairs):
        llr[i], hits[i], n_valid[i], best[i] = _laid_template(
            bits, strong_bits, wanted, px, py, bins, valid, rows[i], cos_scale[i], sin_scale[i],
            x[i], y[i], turn[i], log_ratio)
    return llr, hits, n_valid, best


@njit(cache=True, nogil=True)
def lay_over_grid(
    bits: NDArray[np.uint16], strong_bits: NDArray[np.uint16], wanted: NDArray[np.uint16],
    px: NDArray[np.float32], py: NDArray[np.float32], bins: NDArray[np.uint8],
    valid: NDArray[np.bool_], views: NDArray[np.int64],
    cos_scale: NDArray[np.float32], sin_scale: NDArray[np.float32],
    x: NDArray[np.float32], y: NDArray[np.float32], turn: NDArray[np.uint8],
    log_ratio: F64,
) -> F64:  # pragma: no cover - compiled
    """The llr of :func:`lay_over` for every template row of ``views`` laid
    over the image by every one of S similarities, without the S x V pair
    arrays (a colour location screens about a hundred thousand pairs).

    Parameters
    ----------
    bits, strong_bits, wanted, px, py, bins, valid, log_ratio
        As :func:`lay_over` takes them.
    views : (V,) int64
        Template rows.
    cos_scale, sin_scale, x, y, turn : (S,)
        The similarities, as :func:`lay_over` takes them per pair.

    Returns
    -------
    llr : (S * V,) float64
        Similarity-major: pair ``(s, j)`` at ``s * V + j``, the value
        :func:`lay_over` gives it.
    """
    n_views = len(views)
    llr = np.zeros(len(x) * n_views)
    for k in range(len(x)):
        for j in range(n_views):
            llr[k * n_views + j] = _laid_template(
                bits, strong_bits, wanted, px, py, bins, valid, views[j], cos_scale[k],
                sin_scale[k], x[k], y[k], turn[k], log_ratio)[0]
    return llr


@njit(cache=True, nogil=True)
def similarity_terms(
    sims: F64, n_bins: int,
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32], NDArray[np.float32],
           NDArray[np.uint8]]:  # pragma: no cover - compiled
    """``s cos α``, ``s sin α``, x, y and the orientation turn of (H, 4)
    similarities ``(x, y, α rad, s)``, as :func:`lay_over` takes them.

    One pass instead of numpy's dozen over (H,) temporaries: the alignment's
    first screen lays tens of thousands of seeds over the image on a dozen
    samples each, where preparing the similarities cost as much as the
    scoring. The values are numpy's exactly: products and the cosine in
    float64, rounded once to float32, and the turn
    ``floor(mod(α, π) / π * n_bins + 0.5)`` in ``0..n_bins``
    (:func:`viewloc_core.features.orientation_turn`).
    """
    n = sims.shape[0]
    cos_scale = np.empty(n, np.float32)
    sin_scale = np.empty(n, np.float32)
    x = np.empty(n, np.float32)
    y = np.empty(n, np.float32)
    turn = np.empty(n, np.uint8)
    for i in range(n):
        angle = sims[i, 2]
        cos_scale[i] = np.float32(sims[i, 3] * np.cos(angle))
        sin_scale[i] = np.float32(sims[i, 3] * np.sin(angle))
        x[i] = np.float32(sims[i, 0])
        y[i] = np.float32(sims[i, 1])
        turn[i] = np.uint8(np.floor(np.mod(angle, np.pi) / np.pi * n_bins + 0.5))
    return cos_scale, sin_scale, x, y, turn


def warm_up() -> None:
    """Compile (or load from numba's cache) for the types the view search passes."""
    f32 = np.zeros(1, np.float32)
    bits = np.zeros((1, 1), np.uint16)
    lay_over(bits, bits, np.ones(16, np.uint16), np.zeros((1, 1), np.float32),
             np.zeros((1, 1), np.float32), np.zeros((1, 1), np.uint8), np.ones((1, 1), np.bool_),
             np.zeros(1, np.int64), f32, f32, f32, f32, np.zeros(1, np.uint8),
             np.zeros((16, 3)))
    lay_over_grid(bits, bits, np.ones(16, np.uint16),
                  np.zeros((1, 1), np.float32), np.zeros((1, 1), np.float32),
                  np.zeros((1, 1), np.uint8), np.ones((1, 1), np.bool_), np.zeros(1, np.int64),
                  f32, f32, f32, f32, np.zeros(1, np.uint8), np.zeros((16, 3)))
    similarity_terms(np.zeros((1, 4)), 16)
