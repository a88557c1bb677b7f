"""Vote bins of the alignment's seeds: best-supported bins and their strongest
seed, overall and around each peak of the location vote, compiled.

:func:`viewloc_core.align._vote_hypotheses` and ``_vote_bins`` turn tens of
thousands of seeds into a few dozen hypotheses: seeds fall into (view, [x, y,]
angle, scale) bins, a bin's support is the sum of its seeds' votes, and each of
the best-supported bins contributes its strongest seed. Around each of a dozen
location peaks this runs on the seeds within reach. In array form every peak
cost a sort, a gather and a dozen small passes; here a peak is one pass over
the seeds and a sort of its own few.

Within a bin the strongest seed is the first (lowest index) of equal votes.
Ranking the bins by support is left to the caller (numpy's sort, whose order
of equal supports the hypotheses were measured with).
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@njit(cache=True, nogil=True)
def bin_supports(keys: I64, vote: F64, members: I64) -> tuple[F64, I64]:  # pragma: no cover
    """Support and strongest seed of every bin the ``members`` fall into.

    Parameters
    ----------
    keys : (N,) int64
        Bin key of every seed.
    vote : (N,) float64
        Vote of every seed (> 0).
    members : (M,) int64
        The seeds taking part, in increasing order.

    Returns
    -------
    support : (B,) float64
        Summed votes per bin, bins in key order.
    strongest : (B,) int64
        Seed index (into ``keys``) of each bin's strongest seed.
    """
    m = len(members)
    member_keys = keys[members]
    order = np.argsort(member_keys)
    bin_of = np.empty(m, np.int64)
    n_distinct = 0
    for r in range(m):
        if r > 0 and member_keys[order[r]] != member_keys[order[r - 1]]:
            n_distinct += 1
        bin_of[order[r]] = n_distinct
    if m > 0:
        n_distinct += 1
    support = np.zeros(n_distinct)
    top = np.full(n_distinct, -np.inf)
    strongest = np.zeros(n_distinct, np.int64)
    # In seed order: supports add up as a bincount would, and the first of
    # equal votes stays the strongest.
    for r in range(m):
        b = bin_of[r]
        v = vote[members[r]]
        support[b] += v
        if v > top[b]:
            top[b] = v
            strongest[b] = members[r]
    return support, strongest


@njit(cache=True, nogil=True)
def peak_bins(
    x: F64, y: F64, column: I64, keys: I64, vote: F64, centres: F64, peak_columns: I64,
    reach: float,
) -> tuple[F64, I64, I64]:  # pragma: no cover - compiled
    """:func:`bin_supports` of the seeds near each peak.

    Parameters
    ----------
    x, y : (N,) float64
        Where each seed puts the object's reference point, pixels.
    column : (N,) int64
        The vote grid column of each seed.
    keys : (N,) int64
        (view, angle, scale) bin key of each seed.
    vote : (N,) float64
        Vote of each seed.
    centres : (K, 2) float64
        Peak centres, pixels.
    peak_columns : (K,) int64
        Grid column of each peak.
    reach : float
        Seeds closer than this to a peak's centre take part (pixels); it
        must not exceed two grid columns.

    Returns
    -------
    support, strongest : (B,) float64, (B,) int64
        Peak after peak, each peak's bins in key order.
    bins_per_peak : (K,) int64
    """
    n = len(x)
    near = np.empty(n, np.int64)
    supports = []
    strongests = []
    counts = np.zeros(len(centres), np.int64)
    for k in range(len(centres)):
        cx, cy = centres[k, 0], centres[k, 1]
        p = peak_columns[k]
        n_near = 0
        for i in range(n):
            if column[i] < p - 2 or column[i] > p + 2:
                continue
            if np.hypot(x[i] - cx, y[i] - cy) < reach:
                near[n_near] = i
                n_near += 1
        support, strongest = bin_supports(keys, vote, near[:n_near])
        supports.append(support)
        strongests.append(strongest)
        counts[k] = len(support)
    total = 0
    for k in range(len(centres)):
        total += counts[k]
    all_support = np.empty(total)
    all_strongest = np.empty(total, np.int64)
    at = 0
    for k in range(len(centres)):
        all_support[at:at + counts[k]] = supports[k]
        all_strongest[at:at + counts[k]] = strongests[k]
        at += counts[k]
    return all_support, all_strongest, counts


def warm_up() -> None:
    """Compile (or load from numba's cache) for the types the alignment passes."""
    one = np.ones(1)
    zero = np.zeros(1, np.int64)
    bin_supports(zero, one, zero)
    peak_bins(one, one, zero, zero, one, np.ones((1, 2)), zero, 1.0)
