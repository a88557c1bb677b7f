"""Request ids, structured JSON logs, Prometheus metrics and request body limits.

One pure ASGI middleware does all four, so each request is timed, counted
and logged once under its route template (``/v1/objects/{object_id}``, not
the concrete id, which would blow up the metric cardinality).
"""

from __future__ import annotations

import contextvars
import json
import logging
import re
import sys
import time
import uuid
from collections.abc import Callable, Iterable
from typing import Any

from fastapi import HTTPException
from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import GaugeMetricFamily, Metric
from prometheus_client.registry import Collector
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.problems import problem_response

request_id_var: contextvars.ContextVar[str] = contextvars.ContextVar("request_id", default="-")
_REQUEST_ID_OK = re.compile(r"^[A-Za-z0-9._:-]{1,128}$")

log = logging.getLogger("viewloc.access")
error_log = logging.getLogger("viewloc.app")


class JsonFormatter(logging.Formatter):
    """One JSON object per line: time, level, logger, message, request_id, extras."""

    _STD = set(vars(logging.LogRecord("", 0, "", 0, "", None, None))) | {"message", "asctime"}

    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {
            "time": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created))
            + f".{int(record.msecs):03d}Z",
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
            "request_id": request_id_var.get(),
        }
        for key, value in vars(record).items():
            if key not in self._STD and not key.startswith("_"):
                out[key] = value
        if record.exc_info:
            out["exc_info"] = self.formatException(record.exc_info)
        return json.dumps(out, default=str)


def configure_logging(level: str, as_json: bool) -> None:
    """Send the service's loggers to stderr (JSON lines when ``as_json``)."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(
        JsonFormatter() if as_json else logging.Formatter("%(asctime)s %(levelname)s %(message)s")
    )
    root = logging.getLogger("viewloc")
    for h in list(root.handlers):
        if getattr(h, "_viewloc", False):
            root.removeHandler(h)
    handler._viewloc = True  # type: ignore[attr-defined]
    root.addHandler(handler)
    root.setLevel(level.upper())
    root.propagate = False


class Metrics:
    """The service's Prometheus metrics, in a registry of its own per app."""

    def __init__(self, job_counts: Callable[[], dict[str, int]]) -> None:
        self.registry = CollectorRegistry()
        self.requests = Counter(
            "viewloc_http_requests", "HTTP requests by route template, method and status.",
            ["route", "method", "status"], registry=self.registry,
        )
        self.latency = Histogram(
            "viewloc_http_request_duration_seconds", "HTTP request latency by route template.",
            ["route", "method"], registry=self.registry,
            buckets=(0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30),
        )
        self.localize_seconds = Histogram(
            "viewloc_localization_duration_seconds",
            "Time spent in the core's localization (per object searched).",
            registry=self.registry,
            buckets=(0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30),
        )
        self.registry.register(_JobCollector(job_counts))


class _JobCollector(Collector):
    """Job counts by state, read from the store at scrape time (it is shared)."""

    def __init__(self, job_counts: Callable[[], dict[str, int]]) -> None:
        self._job_counts = job_counts

    def collect(self) -> Iterable[Metric]:
        family = GaugeMetricFamily("viewloc_jobs", "Learning jobs by state.", labels=["state"])
        try:
            counts = self._job_counts()
        except Exception:  # a scrape must not fail because the store is busy
            counts = {}
        for state, n in sorted(counts.items()):
            family.add_metric([state], float(n))
        yield family


class ServiceMiddleware:
    """Request id, body limit, metrics and access log for every HTTP request.

    Parameters
    ----------
    app : ASGI app
    metrics : Metrics
    body_limit : callable(path) -> int
        Largest accepted request body for a path, bytes.
    """

    def __init__(self, app: ASGIApp, metrics: Metrics, body_limit: Callable[[str], int]) -> None:
        self.app = app
        self.metrics = metrics
        self.body_limit = body_limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = dict(scope.get("headers") or [])
        given = headers.get(b"x-request-id", b"").decode("latin-1")
        rid = given if _REQUEST_ID_OK.fullmatch(given) else uuid.uuid4().hex
        token = request_id_var.set(rid)
        start = time.perf_counter()
        status_holder = {"status": 500}
        started = False

        async def send_wrapped(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
                status_holder["status"] = int(message["status"])
                message.setdefault("headers", [])
                message["headers"] = [
                    *message["headers"], (b"x-request-id", rid.encode("latin-1"))
                ]
            await send(message)

        try:
            limit = self.body_limit(scope["path"])
            declared = headers.get(b"content-length")
            too_big = False
            if declared is not None:
                try:
                    too_big = int(declared) > limit
                except ValueError:
                    too_big = False
            if too_big:
                response = problem_response(
                    413, f"request body larger than the limit of {limit} bytes for this route",
                    "too-large", headers={"Connection": "close"},
                )
                await response(scope, receive, send_wrapped)
            else:
                await self.app(scope, _limited(receive, limit), send_wrapped)
        except _BodyTooLarge:
            response = problem_response(
                413, f"request body larger than the limit of {limit} bytes for this route",
                "too-large",
            )
            await response(scope, receive, send_wrapped)
        except Exception:
            # A bug answers 500 in problem+json here rather than in the app's
            # handler for Exception: Starlette's outermost middleware re-raises
            # after that handler has answered, and the server then drops the
            # connection, so a client's next request on it failed as well.
            if started:
                raise
            error_log.exception("unhandled error on %s %s", scope["method"], scope["path"])
            await problem_response(500, "internal error; it has been logged", "internal")(
                scope, receive, send_wrapped)
        finally:
            elapsed = time.perf_counter() - start
            route = scope.get("route")
            template = getattr(route, "path", None) or "unmatched"
            status = status_holder["status"]
            self.metrics.requests.labels(template, scope["method"], str(status)).inc()
            self.metrics.latency.labels(template, scope["method"]).observe(elapsed)
            log.info(
                "%s %s %s", scope["method"], scope["path"], status,
                extra={"route": template, "status": status,
                       "duration_ms": round(elapsed * 1000, 2)},
            )
            request_id_var.reset(token)


class _BodyTooLarge(HTTPException):
    """Raised from ``receive``; FastAPI's body parsing passes its own
    HTTPException on (any other error becomes a 400), so the answer is 413."""

    def __init__(self, limit: int) -> None:
        super().__init__(413, f"request body larger than the limit of {limit} bytes")


def _limited(receive: Receive, limit: int) -> Receive:
    """``receive`` that stops a chunked body exceeding ``limit`` bytes."""
    seen = 0

    async def inner() -> Message:
        nonlocal seen
        message = await receive()
        if message["type"] == "http.request":
            seen += len(message.get("body", b""))
            if seen > limit:
                raise _BodyTooLarge(limit)
        return message

    return inner
