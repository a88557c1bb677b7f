"""Choose the job runner from the settings (``VIEWLOC_JOB_BACKEND``)."""

from __future__ import annotations

import importlib
from collections.abc import Mapping

from app.jobs.base import JobRunner
from app.jobs.local import LocalJobRunner
from app.settings import Settings
from model_store import ModelStore

#: Backends other than "local", as "module:factory"; the factory is called as
#: ``factory(store, settings, tasks)`` and returns a :class:`JobRunner`.
BACKENDS: dict[str, str] = {"redis": "app.jobs.redis_runner:build"}


def build_runner(
    store: ModelStore, settings: Settings, tasks: Mapping[str, str] | None = None
) -> JobRunner:
    """The runner for ``settings.job_backend``."""
    if settings.job_backend == "local":
        return LocalJobRunner(
            store,
            workers=settings.job_workers,
            tasks=tasks,
            cancel_grace_s=settings.job_cancel_grace_s,
            stale_after_s=settings.job_stale_after_s,
        )
    module_name, _, func = BACKENDS[settings.job_backend].partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise RuntimeError(
            f"job backend {settings.job_backend!r} is not installed ({exc})"
        ) from exc
    runner: JobRunner = getattr(module, func)(store, settings, tasks)
    return runner
