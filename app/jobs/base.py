"""The job runner interface.

Jobs live in the model store (state ``queued`` when created); a runner only
decides where and when they execute. The embedded default is
:class:`app.jobs.local.LocalJobRunner`; a distributed backend (Redis/RQ) is
another class with the same four methods, chosen by ``VIEWLOC_JOB_BACKEND``
through :func:`app.jobs.factory.build_runner`. Whatever runs a job calls
:func:`app.jobs.execute.execute_job`, which writes state, progress and errors
into the store, so the API reads one place regardless of the backend.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from model_store import JobRecord


@runtime_checkable
class JobRunner(Protocol):
    """Executes queued jobs of the store in the background."""

    def start(self) -> None:
        """Begin executing jobs; recovers jobs orphaned by a dead runner first."""
        ...

    def stop(self) -> None:
        """Stop executing; jobs still running are handed back to the queue."""
        ...

    def submit(self, job: JobRecord) -> None:
        """Make a job that was just queued in the store known to the runner."""
        ...

    def cancel(self, job_id: str) -> None:
        """Cancel a job: a queued one never starts, a running one is stopped."""
        ...

    def is_running(self) -> bool:
        """True while the runner accepts and executes jobs (used by /readyz)."""
        ...
