"""Job functions for the runner tests (resolved by name in spawned workers)."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import Any

from model_store import JobRecord, ModelStore
from viewloc_core.errors import InvalidInputError


def sleepy(
    store: ModelStore, job: JobRecord, progress: Callable[[str, float], None],
    should_stop: Callable[[], bool],
) -> Any:
    """Reports progress for about 3 s, stopping early when asked."""
    for k in range(30):
        if should_stop():
            raise RuntimeError("stopped")
        progress(f"step {k + 1} of 30", k / 30)
        time.sleep(0.1)
    return None


def crash(store: ModelStore, job: JobRecord, progress: Callable[[str, float], None],
          should_stop: Callable[[], bool]) -> Any:
    """Dies like a segfaulting driver would: no exception, no cleanup."""
    progress("about to crash", 0.5)
    os._exit(7)


def bad_input(store: ModelStore, job: JobRecord, progress: Callable[[str, float], None],
              should_stop: Callable[[], bool]) -> Any:
    """Fails the way the engine does on unusable input."""
    raise InvalidInputError("the mesh has no faces", "mesh")


def ignores_cancel(store: ModelStore, job: JobRecord, progress: Callable[[str, float], None],
                   should_stop: Callable[[], bool]) -> Any:
    """Ignores cancellation (a long C call); the runner must kill it."""
    progress("busy in C", 0.1)
    time.sleep(60)
    return None
