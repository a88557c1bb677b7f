"""Operations: liveness, readiness, Prometheus metrics."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from app.deps import MetricsDep
from app.openapi_doc import errors
from app.problems import problem_response
from app.schemas import Health

#: Open to everyone (no API key): liveness probes of orchestrators.
public_router = APIRouter(tags=["operations"])
#: Behind the API key when keys are configured.
router = APIRouter(tags=["operations"])


@public_router.get("/healthz", response_model=Health, summary="Process alive")
def healthz() -> dict[str, Any]:
    """Always 200 while the process answers (never needs an API key)."""
    return {"status": "ok"}


@router.get(
    "/readyz",
    response_model=Health,
    responses=errors(503),
    summary="Store readable, job runner up, stored models prepared",
)
def readyz(request: Request) -> Any:
    """200 when the store answers, the job runner runs and the models stored
    at start-up are loaded and prepared (:mod:`app.model_warmer`), else 503."""
    store = getattr(request.app.state, "store", None)
    runner = getattr(request.app.state, "runner", None)
    warmer = getattr(request.app.state, "warmer", None)
    checks = {
        "store": bool(store is not None and store.readable()),
        "job_runner": bool(runner is not None and runner.is_running()),
        "models_prepared": bool(warmer is not None and warmer.warm),
    }
    if all(checks.values()):
        return {"status": "ok", "checks": checks}
    down = [f"{name} not available" for name in ("store", "job_runner") if not checks[name]]
    if not checks["models_prepared"]:
        down.append("the stored models are still being prepared")
    return problem_response(503, f"not ready: {', '.join(down)}", "unavailable")


@router.get(
    "/metrics",
    response_class=Response,
    responses={**errors(), 200: {"content": {"text/plain": {"schema": {"type": "string"}}},
                                 "description": "Prometheus text exposition format."}},
    summary="Prometheus metrics",
)
def metrics(metrics: MetricsDep) -> Response:
    """Request counts and latency per route, job counts by state, localization time."""
    return Response(generate_latest(metrics.registry), media_type=CONTENT_TYPE_LATEST)
