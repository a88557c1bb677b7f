"""Execute one job in the current process, recording everything in the store.

This module is what a worker process imports, so it stays free of FastAPI
and of anything that opens a rendering context at import time.
"""

from __future__ import annotations

import importlib
import logging
import os
import threading
import time
import traceback
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Protocol

from model_store import JobRecord, ModelStore, StoreError
from viewloc_core.errors import ViewlocError

log = logging.getLogger("viewloc.jobs")

#: Job kinds the service creates, mapped to "module:function".
DEFAULT_TASKS: dict[str, str] = {
    "learn_mesh": "app.jobs.tasks:learn_mesh",
    "learn_images": "app.jobs.tasks:learn_images",
}


class Task(Protocol):
    """A job function: returns a learned model to store, or None."""

    def __call__(
        self,
        store: ModelStore,
        job: JobRecord,
        progress: Callable[[str, float], None],
        should_stop: Callable[[], bool],
    ) -> Any: ...


def resolve_task(kind: str, tasks: Mapping[str, str] | None = None) -> Task:
    """Look a job kind up in the fixed table (never an import path from outside)."""
    table = {**DEFAULT_TASKS, **(tasks or {})}
    if kind not in table:
        raise StoreError(f"unknown job kind {kind!r}")
    module_name, _, func_name = table[kind].partition(":")
    func: Task = getattr(importlib.import_module(module_name), func_name)
    return func


class _Progress:
    """Progress callback that writes to the store at most every ``min_interval_s``
    (the engine may report thousands of times) but always on a new stage."""

    def __init__(self, store: ModelStore, job_id: str, min_interval_s: float = 0.25) -> None:
        self.store, self.job_id, self.min_interval_s = store, job_id, min_interval_s
        self._last_t = 0.0
        self._last_stage = ""

    def __call__(self, stage: str, fraction: float) -> None:
        now = time.monotonic()
        if stage != self._last_stage or now - self._last_t >= self.min_interval_s:
            self._last_t, self._last_stage = now, stage
            self.store.update_progress(self.job_id, fraction, stage)


class _StopFlag:
    """``should_stop`` for the engine: asks the store at most every ``interval_s``."""

    def __init__(self, store: ModelStore, job_id: str, interval_s: float = 0.5) -> None:
        self.store, self.job_id, self.interval_s = store, job_id, interval_s
        self._last_t = 0.0
        self._stop = False

    def __call__(self) -> bool:
        now = time.monotonic()
        if not self._stop and now - self._last_t >= self.interval_s:
            self._last_t = now
            self._stop = self.store.should_stop(self.job_id)
        return self._stop


def execute_job(
    data_dir: str | Path,
    job_id: str,
    tasks: Mapping[str, str] | None = None,
    owner: str | None = None,
) -> str:
    """Run one job to a terminal state; returns that state.

    Parameters
    ----------
    data_dir : path
        Store root.
    job_id : str
        A job that is ``running`` (claimed by the caller) or, when ``owner``
        is given, ``queued`` (claimed here for ``owner``).
    tasks : mapping, optional
        Extra job kinds ("kind" -> "module:function"), for tests and plugins.
    owner : str, optional
        Runner id to claim a queued job for (backends without a dispatcher).
    """
    store = ModelStore(data_dir)
    job = store.get_job(job_id)
    if job.state == "queued" and owner is not None:
        claimed = store.claim_job(job_id, owner)
        if claimed is None:
            return store.get_job(job_id).state
        job = claimed
    if job.state != "running":
        return job.state
    store.set_job_pid(job_id, os.getpid())
    should_stop = _StopFlag(store, job_id)
    try:
        task = resolve_task(job.kind, tasks)
        store.update_progress(job_id, 0.0, "starting")
        model = task(store, job, _Progress(store, job_id), should_stop)
    except BaseException as exc:
        if store.should_stop(job_id) or type(exc).__name__ == "Cancelled":
            store.finish_job(job_id, "cancelled", "cancelled on request")
            return "cancelled"
        if isinstance(exc, (ViewlocError, StoreError)):
            message = exc.message
        else:
            log.error("job %s crashed:\n%s", job_id, traceback.format_exc())
            message = f"internal error during learning: {type(exc).__name__}: {exc}"
        store.finish_job(job_id, "failed", message)
        if not isinstance(exc, Exception):
            raise
        return "failed"
    if model is None:
        store.finish_job(job_id, "succeeded", None)
        return "succeeded"
    if store.save_model(job.object_id, job_id, model):
        return "succeeded"
    store.finish_job(job_id, "cancelled", "the object was deleted or the job cancelled")
    return store.get_job(job_id).state


def watch_parent(poll_s: float = 1.0) -> None:
    """Exit this worker when the process that started it dies.

    Without it a job would keep running after its service was killed and race
    with the restarted service, which re-queues the job.
    """
    parent = os.getppid()

    def _watch() -> None:
        while True:
            time.sleep(poll_s)
            if os.getppid() != parent:
                os._exit(3)

    threading.Thread(target=_watch, name="viewloc-parent-watch", daemon=True).start()


def child_main(data_dir: str, job_id: str, tasks: dict[str, str] | None) -> None:
    """Entry point of a worker process started by the local runner."""
    logging.basicConfig(level=logging.INFO)
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    watch_parent()
    execute_job(data_dir, job_id, tasks)
