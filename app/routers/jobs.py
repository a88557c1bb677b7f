"""``/v1/jobs``: state and progress of learning jobs, cancellation."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Path

from app.deps import RunnerDep, StoreDep
from app.openapi_doc import errors
from app.schemas import JobOut
from app.serialize import job_dict

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])

JobId = Annotated[str, Path(description="Job id (32 hex digits).")]


@router.get("/{job_id}", response_model=JobOut, responses=errors(404, 503), summary="Get a job")
def get_job(job_id: JobId, store: StoreDep) -> dict[str, Any]:
    """State, progress (0..1) and stage of a learning job."""
    return job_dict(store.get_job(job_id))


@router.delete("/{job_id}", response_model=JobOut, responses=errors(404, 503),
               summary="Cancel a job")
def cancel_job(job_id: JobId, store: StoreDep, runner: RunnerDep) -> dict[str, Any]:
    """Cancel a queued job (it never starts) or a running one (it is stopped).

    A job that already finished is answered unchanged. The answer shows the
    state right after the request: a running job may still read ``running``
    for a moment before it becomes ``cancelled``.
    """
    store.get_job(job_id)
    runner.cancel(job_id)
    return job_dict(store.get_job(job_id))
