"""A daemon thread that calls a function at a fixed interval until stopped."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

log = logging.getLogger("viewloc.periodic")


class Periodic:
    """A daemon thread calling ``step`` every ``interval_s`` until stopped.

    The first call comes one interval after :meth:`start`, or at once with
    ``immediately``. An exception in ``step`` is logged and the loop goes
    on: a busy database or a Redis hiccup must not end it.
    """

    def __init__(self, name: str, interval_s: float, step: Callable[[], object],
                 immediately: bool = False) -> None:
        self.interval_s, self.step, self.immediately = interval_s, step, immediately
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        self._thread.join(timeout_s)

    def is_alive(self) -> bool:
        return self._thread.is_alive()

    def _run(self) -> None:
        if self.immediately:
            self._call()
        while not self._stop.wait(self.interval_s):
            self._call()

    def _call(self) -> None:
        try:
            self.step()
        except Exception:
            log.exception("periodic %s failed", self._thread.name)
