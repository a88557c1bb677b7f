"""Independent per-hypothesis work split over the machine's two cores.

The alignment and the view search score and fit thousands of hypotheses,
each on its own, with compiled kernels that release the GIL. While they run,
the other core has little to do (the refinement's edge pyramid, built there
meanwhile, takes about a quarter of the time), so the hypotheses are cut in
two halves: one goes to a worker thread, the calling thread does the other.
Results are the same as one call over all of them, in the same order.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from numpy.typing import NDArray

#: One worker: the calling thread is the other half. Concurrent requests
#: share it and at worst wait for each other's halves.
_POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="viewloc-halves")


def over_halves(
    n_items: int,
    work: Callable[[int, int], tuple[NDArray[np.generic], ...]],
    min_items: int,
) -> tuple[NDArray[np.generic], ...]:
    """``work(0, n_items)``, computed as two halves on two threads.

    Parameters
    ----------
    n_items : int
        Number of independent items (hypotheses).
    work : callable
        ``work(lo, hi)`` handles items ``lo:hi`` and returns arrays whose
        first axis runs over them. It must release the GIL for the halves to
        overlap (numba ``nogil`` kernels, most of OpenCV).
    min_items : int
        Fewer items than this are done in one call: handing a half to
        another thread costs tens of microseconds.

    Returns
    -------
    tuple of arrays
        As ``work(0, n_items)`` returns them.
    """
    if n_items < max(min_items, 2):
        return work(0, n_items)
    mid = n_items // 2
    second = _POOL.submit(work, mid, n_items)
    first = work(0, mid)
    return tuple(np.concatenate([a, b]) for a, b in zip(first, second.result(), strict=True))
