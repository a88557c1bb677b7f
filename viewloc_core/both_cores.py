"""Independent per-hypothesis work split over the machine's two cores.

The alignment and the view search score and fit thousands of hypotheses,
each on its own, with compiled kernels that release the GIL. While they run,
the other core has little to do (the refinement's edge pyramid, built there
meanwhile, takes about a quarter of the time), so the hypotheses are cut in
two halves: one goes to a worker thread, the calling thread does the other.
Results are the same as one call over all of them, in the same order.

A few items of uneven cost (a localization's pose fits, the bands of a
large image's gradient) are instead taken in turn by the two threads
(:func:`each_on_both`), so that neither waits while the other has two.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

#: One worker: the calling thread is the other half. Concurrent requests
#: share it and at worst wait for each other's halves.
_POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="viewloc-halves")

#: The worker of :func:`each_on_both`, apart from ``_POOL``: an item's work
#: may itself split its hypotheses in halves, and a single worker waiting
#: for a task queued behind itself would wait for ever (see also the
#: cancel in :func:`each_on_both`).
_ITEM_POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="viewloc-items")

Item = TypeVar("Item")
Result = TypeVar("Result")


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


def each_on_both(work: Callable[[Item], Result], items: Sequence[Item]) -> list[Result]:
    """``[work(x) for x in items]``, the items taken in turn by the calling
    thread and a worker thread.

    For a few items of uneven cost (the pose fits of a localization: one
    may take ten times another), where halves would leave a core idle. The
    work must release the GIL for the threads to overlap.

    Parameters
    ----------
    work : callable
        Called once per item; its exceptions reach the caller.
    items : sequence

    Returns
    -------
    list
        The results in the items' order.
    """
    if len(items) < 2:
        return [work(x) for x in items]
    results: list[Result | None] = [None] * len(items)
    # next() of an itertools.count is atomic under the GIL: each index is
    # handed out once.
    turns = itertools.count()

    def drain() -> None:
        for i in turns:
            if i >= len(items):
                return
            results[i] = work(items[i])

    other = _ITEM_POOL.submit(drain)
    try:
        drain()
    finally:
        # Every item is done or being done. A worker that never started is
        # not waited for: it may be this very thread (a call made from an
        # item of another call), which would wait for itself.
        if not other.cancel():
            other.result()
    return results  # type: ignore[return-value]  # every slot was filled
