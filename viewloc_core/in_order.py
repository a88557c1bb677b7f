"""Work done in the order it is handed over, on one thread behind the caller.

Learning renders its views with Mesa's software rasteriser, which keeps the
second core only partly busy (the 2-core machine: 1.1 cores in use while
the contour views' depth renders run, 1.3 during colour renders), and must
render on the thread that made its GL context. What it does with each view
(feature clustering, contour extraction) depends only on that view and the
ones before it, so it can run on another thread while the next view
renders. One worker takes the tasks one after another in the order given:
state they share (a clustering, a random generator) sees the same sequence
as in a plain loop, and the results are the same to the bit.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from types import TracebackType
from typing import Any


class InOrder:
    """Tasks run one at a time on a worker thread, in the order submitted.

    Use as a context manager: leaving the block waits for the tasks and
    re-raises the first failed one's exception; leaving it by an exception
    drops the tasks not yet started and waits for the running one. A task
    behind a failed one is skipped.

    Parameters
    ----------
    name : str
        Prefix of the worker thread's name.

    Examples
    --------
    >>> out = []
    >>> with InOrder("example") as behind:
    ...     for i in range(3):
    ...         behind.submit(out.append, i)
    >>> out
    [0, 1, 2]
    """

    def __init__(self, name: str) -> None:
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix=name)
        self._pending: list[Future[Any]] = []
        self._failed = False

    def __enter__(self) -> InOrder:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        try:
            if exc_type is None:
                self.drain()
        finally:
            self._pool.shutdown(wait=True, cancel_futures=True)

    def submit(self, task: Callable[..., Any], *args: Any) -> None:
        """Queue ``task(*args)`` behind the tasks already submitted; it is
        skipped if one of them failed (it may rest on that one's work)."""
        self._pending.append(self._pool.submit(self._run, task, args))

    def _run(self, task: Callable[..., Any], args: tuple[Any, ...]) -> None:
        # Only the one worker thread reads and sets the flag.
        if self._failed:
            return
        try:
            task(*args)
        except BaseException:
            self._failed = True
            raise

    def drain(self) -> None:
        """Wait until every submitted task has run.

        Raises
        ------
        Exception
            The first failed task's exception (the tasks behind it were
            skipped).
        """
        pending, self._pending = self._pending, []
        for future in pending:
            future.result()
