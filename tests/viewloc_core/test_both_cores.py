"""Per-hypothesis work split over two threads gives what one call gives."""

import threading

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from viewloc_core.both_cores import over_halves


@given(n_items=st.integers(0, 50), min_items=st.integers(0, 60))
def test_halves_join_into_the_whole_in_order(n_items: int, min_items: int) -> None:
    values = np.arange(n_items) * 3.5
    calls: list[tuple[int, int]] = []

    def work(lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
        calls.append((lo, hi))
        return values[lo:hi] ** 2, np.arange(lo, hi)

    squares, index = over_halves(n_items, work, min_items)
    assert np.array_equal(squares, values**2)
    assert np.array_equal(index, np.arange(n_items))
    # Split exactly when there is enough work, into two halves that tile it.
    if n_items >= max(min_items, 2):
        assert sorted(calls) == [(0, n_items // 2), (n_items // 2, n_items)]
    else:
        assert calls == [(0, n_items)]


def test_the_second_half_runs_on_another_thread() -> None:
    threads: dict[int, int] = {}

    def work(lo: int, hi: int) -> tuple[np.ndarray]:
        threads[lo] = threading.get_ident()
        return (np.arange(lo, hi),)

    over_halves(10, work, 2)
    assert threads[0] == threading.get_ident()
    assert threads[5] != threading.get_ident()
