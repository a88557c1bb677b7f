"""Pairs of points nearer than a reach of their own, compiled.

The feature grouping pairs segments whose ends, or midpoints, lie within a
distance set by the segments' own lengths (:func:`viewloc_core.features._junctions`,
:func:`viewloc_core.features._parallel_pairs`). A k-d tree's pair query takes
one radius for every point, the longest segment's: on a cluttered 640x480
image (1,500-2,000 segments of median length 9-14 px, the longest 130-400 px)
that radius pairs 0.6-1.2 million midpoints, of which the per-segment reach
keeps 30,000-65,000, and most of the grouping's time went into the rest.
Here each point searches its own reach, on the points sorted by x.

The pairs come back in an order fixed by the points alone, independent of
any tree's traversal.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: Relative slack on a reach: the pairs are candidates for an exact test
#: that follows, so one on the boundary must not be lost to rounding.
_REACH_SLACK = 1e-9


@njit(cache=True, nogil=True)
def _pairs_by_x(x: F64, y: F64, reach: F64, index: I64,
                within_both: bool) -> tuple[I64, I64]:  # pragma: no cover - compiled
    """:func:`pairs_within` on points sorted by ``x``; ``index`` maps them
    back to their rows."""
    n = len(x)
    capacity = 4 * n + 16
    first = np.empty(capacity, np.int64)
    second = np.empty(capacity, np.int64)
    k = 0
    for s in range(n):
        reach_s = reach[s] * (1.0 + _REACH_SLACK)
        lo = np.searchsorted(x, x[s] - reach_s, side="left")
        hi = np.searchsorted(x, x[s] + reach_s, side="right")
        a = index[s]
        for t in range(lo, hi):
            dx = x[t] - x[s]
            dy = y[t] - y[s]
            d2 = dx * dx + dy * dy
            if d2 > reach_s * reach_s:
                continue
            b = index[t]
            if within_both:
                # Found from the lower row's side; the pair must lie within
                # the other's reach too.
                reach_t = reach[t] * (1.0 + _REACH_SLACK)
                if b <= a or d2 > reach_t * reach_t:
                    continue
            elif reach[t] > reach[s] or (reach[t] == reach[s] and b <= a):
                # Found from the side with the larger reach (ties: the lower
                # row), which alone sees every pair within it.
                continue
            if k == capacity:
                capacity *= 2
                first = _grown(first, k, capacity)
                second = _grown(second, k, capacity)
            first[k] = min(a, b)
            second[k] = max(a, b)
            k += 1
    return first[:k], second[:k]


@njit(cache=True, nogil=True)
def _grown(values: I64, used: int, capacity: int) -> I64:  # pragma: no cover - compiled
    """A copy of ``values[:used]`` with room for ``capacity``."""
    grown = np.empty(capacity, np.int64)
    grown[:used] = values[:used]
    return grown


def pairs_within(xy: F64, reach: F64, within_both: bool) -> tuple[I64, I64]:
    """Every pair of points within reach of each other.

    Parameters
    ----------
    xy : (N, 2) float64
        Points, pixels.
    reach : (N,) float64
        Each point's reach, pixels (non-negative).
    within_both : bool
        True: the pairs whose distance is within both points' reach (the
        smaller one); False: within either's (the larger one).

    Returns
    -------
    first, second : (P,) int64
        Rows of the two points of each pair, ``first < second``; a pair at
        exactly the reach may be included (they are candidates for an exact
        test). The order is fixed by the points alone: by the x rank of the
        point whose search found the pair, then of the other.
    """
    points = np.asarray(xy, np.float64).reshape(-1, 2)
    reaches = np.asarray(reach, np.float64).reshape(-1)
    if len(points) != len(reaches):
        raise ValueError(f"{len(points)} points but {len(reaches)} reaches")
    order = np.argsort(points[:, 0], kind="stable").astype(np.int64)
    return _pairs_by_x(np.ascontiguousarray(points[order, 0]),
                       np.ascontiguousarray(points[order, 1]),
                       np.ascontiguousarray(reaches[order]), order, within_both)


def warm_up() -> None:
    """Compile the kernel for the types the grouping passes."""
    pairs_within(np.zeros((2, 2)), np.ones(2), True)
    pairs_within(np.zeros((2, 2)), np.ones(2), False)
