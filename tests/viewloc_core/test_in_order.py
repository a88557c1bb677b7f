"""InOrder: tasks on one worker thread, in the order given, failures surfaced."""

import threading
import time

import numpy as np
import pytest

from viewloc_core.in_order import InOrder


def test_tasks_run_in_order_on_one_other_thread():
    seen: list[tuple[int, int]] = []

    def task(i: int) -> None:
        # Earlier tasks take longer: only a single ordered worker keeps the order.
        time.sleep(0.002 * (5 - i))
        seen.append((i, threading.get_ident()))

    with InOrder("test") as behind:
        for i in range(5):
            behind.submit(task, i)
    assert [i for i, _ in seen] == list(range(5))
    threads = {t for _, t in seen}
    assert len(threads) == 1 and threading.get_ident() not in threads


def test_a_shared_generator_draws_as_in_a_plain_loop():
    def draws(gen: np.random.Generator, out: list[float]) -> None:
        out.append(float(gen.random()))

    plain: list[float] = []
    gen = np.random.default_rng(7)
    for _ in range(20):
        draws(gen, plain)
    behind_out: list[float] = []
    gen = np.random.default_rng(7)
    with InOrder("test") as behind:
        for _ in range(20):
            behind.submit(draws, gen, behind_out)
    assert behind_out == plain


def test_drain_waits_for_every_task_and_the_block_can_go_on():
    done: list[int] = []
    with InOrder("test") as behind:
        behind.submit(lambda: (time.sleep(0.02), done.append(1)))
        behind.drain()
        assert done == [1]
        behind.submit(done.append, 2)
    assert done == [1, 2]


def test_a_failed_task_is_raised_and_the_tasks_behind_it_are_skipped():
    ran: list[int] = []

    def fail() -> None:
        raise ValueError("broken view")

    with pytest.raises(ValueError, match="broken view"), InOrder("test") as behind:
        behind.submit(ran.append, 0)
        behind.submit(fail)
        for i in range(1, 4):
            behind.submit(ran.append, i)
    assert ran == [0]


def test_leaving_by_an_exception_drops_the_queue():
    ran: list[int] = []
    gate = threading.Event()
    with pytest.raises(KeyError), InOrder("test") as behind:
        behind.submit(gate.wait, 5)
        for i in range(3):
            behind.submit(ran.append, i)
        # The running task ends soon after the block is left.
        threading.Timer(0.2, gate.set).start()
        raise KeyError("cancelled")
    assert ran == []
