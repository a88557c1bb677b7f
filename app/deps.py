"""Dependencies handed to the routers (store, runner, settings, auth).

They are ``async def`` although they never wait: they only read the app's
state and the request's headers, and FastAPI would run a plain ``def`` in
its thread pool, one hand-over and back per dependency (a localization
request has five; together about 1 ms of its round trip).
"""

from __future__ import annotations

import hmac
from collections.abc import Awaitable, Callable
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from app.jobs.base import JobRunner
from app.observability import Metrics
from app.problems import ProblemError
from app.settings import Settings
from model_store import ModelStore


async def get_settings(request: Request) -> Settings:
    """The settings the app was built with."""
    settings: Settings = request.app.state.settings
    return settings


async def get_store(request: Request) -> ModelStore:
    """The store opened in the lifespan."""
    store: ModelStore | None = getattr(request.app.state, "store", None)
    if store is None:
        raise ProblemError(503, "the model store is not open", "unavailable")
    return store


async def get_runner(request: Request) -> JobRunner:
    """The job runner started in the lifespan."""
    runner: JobRunner | None = getattr(request.app.state, "runner", None)
    if runner is None:
        raise ProblemError(503, "the job runner is not running", "unavailable")
    return runner


async def get_metrics(request: Request) -> Metrics:
    """The app's Prometheus metrics."""
    metrics: Metrics = request.app.state.metrics
    return metrics


SettingsDep = Annotated[Settings, Depends(get_settings)]
StoreDep = Annotated[ModelStore, Depends(get_store)]
RunnerDep = Annotated[JobRunner, Depends(get_runner)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]

_bearer = HTTPBearer(auto_error=False, description="An API key from VIEWLOC_API_KEYS.")


async def require_api_key(
    settings: SettingsDep,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> None:
    """Check ``Authorization: Bearer <key>`` when API keys are configured.

    Every configured key is compared (in constant time each), so the answer
    time does not tell which key, or which prefix, came close.
    """
    keys = settings.api_key_list
    if not keys:
        return
    given = credentials.credentials.encode() if credentials is not None else b""
    ok = False
    for key in keys:
        ok |= hmac.compare_digest(given, key.encode())
    if not ok:
        raise ProblemError(
            401, "a valid API key is required: Authorization: Bearer <key>", "unauthorized",
            headers={"WWW-Authenticate": "Bearer"},
        )


async def require_multipart(request: Request) -> None:
    """Uploads are multipart/form-data; anything else is answered 415 up front."""
    ctype = request.headers.get("content-type", "")
    if not ctype.lower().startswith("multipart/form-data"):
        raise ProblemError(
            415, f"expected multipart/form-data, got {ctype or 'no content type'}",
            "unsupported-media-type",
        )


def single_parts(*names: str) -> Callable[[Request], Awaitable[None]]:
    """A dependency answering 422, naming the part, when the form sends one
    of ``names`` more than once.

    A route's form parameter gets one part of its name, the last one sent,
    and the others were dropped without a word: with two ``image`` parts the
    second image was searched. The form is the one FastAPI has already
    parsed for the route (the request keeps it), so nothing is read twice.
    """

    async def require_single(request: Request) -> None:
        form = await request.form()
        for name in names:
            sent = len(form.getlist(name))
            if sent > 1:
                message = f"send exactly one {name} ({sent} parts named {name!r} were sent)"
                raise ProblemError(422, message, "validation", [(name, message)])

    return require_single
