"""Per-hypothesis work split over two threads gives what one call gives."""

import threading

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from viewloc_core.both_cores import each_on_both, over_halves


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


@given(items=st.lists(st.integers(-1000, 1000), max_size=30))
def test_each_on_both_gives_every_result_in_order(items: list[int]) -> None:
    calls: list[int] = []

    def work(x: int) -> int:
        calls.append(x)
        return 3 * x + 1

    assert each_on_both(work, items) == [3 * x + 1 for x in items]
    assert sorted(calls) == sorted(items)  # each item once


def test_each_on_both_uses_the_other_thread_and_passes_errors_on() -> None:
    release = threading.Event()
    threads: dict[int, int] = {}

    def work(x: int) -> int:
        threads[x] = threading.get_ident()
        if x == 0:
            # Hold the first item until another thread has taken the second.
            assert release.wait(5.0)
        else:
            release.set()
        return x

    assert each_on_both(work, [0, 1]) == [0, 1]
    assert threads[0] != threads[1]

    def fails(x: int) -> int:
        if x == 2:
            raise ValueError("item 2")
        return x

    with pytest.raises(ValueError, match="item 2"):
        each_on_both(fails, [0, 1, 2, 3])


def test_each_on_both_called_from_its_own_worker_does_not_wait_for_itself() -> None:
    # An item's work calls each_on_both again (a refinement given a large
    # image builds its edges in bands): whichever thread runs it, it ends.
    def inner(x: int) -> int:
        return x * 10

    def outer(x: int) -> list[int]:
        return each_on_both(inner, [x, x + 1, x + 2])

    done = threading.Event()
    result: list[list[list[int]]] = []

    def run() -> None:
        result.append(each_on_both(outer, [1, 5]))
        done.set()

    threading.Thread(target=run, daemon=True).start()
    assert done.wait(10.0)
    assert result[0] == [[10, 20, 30], [50, 60, 70]]
