"""RFC 9457 problem details: one place that turns every error into problem+json.

Bad input never becomes a 500: core errors (``viewloc_core.errors``), store
errors, FastAPI's request validation and HTTP errors are all mapped here.
"""

from __future__ import annotations

import logging
from http import HTTPStatus
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException

from model_store.errors import (
    CorruptModelError,
    JobNotFoundError,
    ObjectNotFoundError,
    ObjectNotReadyError,
    StoreError,
)
from viewloc_core.errors import ModelFormatError, ViewlocError

PROBLEM_JSON = "application/problem+json"
PROBLEM_BASE = "https://viewloc.invalid/problems/"

log = logging.getLogger("viewloc.app")


class ProblemError(Exception):
    """Raised by the routers to answer with a problem document.

    Parameters
    ----------
    status : int
        HTTP status code.
    detail : str
        Human-readable explanation of this occurrence.
    kind : str
        Last segment of the problem ``type`` URI (e.g. ``"validation"``).
    errors : list of (field, message), optional
        Field-level problems.
    headers : dict, optional
        Extra response headers.
    """

    def __init__(
        self,
        status: int,
        detail: str,
        kind: str | None = None,
        errors: list[tuple[str, str]] | None = None,
        headers: dict[str, str] | None = None,
    ) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail
        self.kind = kind or _default_kind(status)
        self.errors = errors or []
        self.headers = headers or {}


def _default_kind(status: int) -> str:
    return {
        400: "bad-request", 401: "unauthorized", 403: "forbidden", 404: "not-found",
        405: "method-not-allowed", 409: "conflict", 413: "too-large",
        415: "unsupported-media-type", 422: "validation", 500: "internal", 503: "unavailable",
    }.get(status, "error")


def problem_response(
    status: int,
    detail: str,
    kind: str | None = None,
    errors: list[tuple[str, str]] | None = None,
    headers: dict[str, str] | None = None,
) -> JSONResponse:
    """A problem+json response."""
    try:
        title = HTTPStatus(status).phrase
    except ValueError:
        title = "Error"
    body: dict[str, Any] = {
        "type": PROBLEM_BASE + (kind or _default_kind(status)),
        "title": title,
        "status": status,
        "detail": detail,
    }
    if errors:
        body["errors"] = [{"field": f, "message": m} for f, m in errors]
    return JSONResponse(body, status_code=status, media_type=PROBLEM_JSON, headers=headers)


def validation_errors(exc: ValidationError, prefix: str) -> list[tuple[str, str]]:
    """Field-level messages of a pydantic error, fields written ``prefix.a.b``."""
    out: list[tuple[str, str]] = []
    for err in exc.errors():
        loc = [p for p in err.get("loc", ()) if p != "__root__"]
        field = field_name([prefix, *loc] if prefix else loc)
        out.append((field or prefix, str(err.get("msg", "invalid"))))
    return out


def field_name(loc: Any) -> str:
    """``("spec", "views", 0, "polar_deg")`` -> ``"spec.views[0].polar_deg"``.

    List positions are written as indices, as the routes and the core name
    them (``images[2]``, ``spec.views[0].distance_mm``), so a client sees one
    spelling whichever layer found the problem.
    """
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += f".{part}" if out else str(part)
    return out


def _core_status(exc: ViewlocError) -> int:
    return 409 if isinstance(exc, ModelFormatError) else 422


def _unreadable_form(request: Request, status: int, detail: str) -> tuple[str, str] | None:
    """(field, message) for a multipart/form-data body the form parser could
    not read, None for any other error.

    Starlette's parser answers 400 with its own words ("Missing boundary in
    multipart.", "Invalid multipart data.") before any route sees a field;
    the answer names what to mend: the Content-Type header when it gives no
    boundary, else the body.
    """
    content_type = request.headers.get("content-type", "").lower()
    if status != 400 or not content_type.startswith("multipart/form-data"):
        return None
    field = "content-type" if "boundary=" not in content_type else "body"
    return field, f"the multipart/form-data body could not be read: {detail}"


def install_problem_handlers(app: FastAPI) -> None:
    """Register the exception handlers that produce problem+json."""

    @app.exception_handler(ProblemError)
    async def _problem(_: Request, exc: ProblemError) -> JSONResponse:
        return problem_response(exc.status, exc.detail, exc.kind, exc.errors, exc.headers)

    @app.exception_handler(CorruptModelError)
    async def _corrupt(_: Request, exc: CorruptModelError) -> JSONResponse:
        log.error("corrupt stored model: %s", exc.message)
        return problem_response(
            409, f"the object's stored model is unusable: {exc.message}", "model-corrupt"
        )

    @app.exception_handler(ViewlocError)
    async def _core(_: Request, exc: ViewlocError) -> JSONResponse:
        status = _core_status(exc)
        errors = [(exc.field, exc.message)] if exc.field else None
        kind = "model-format" if status == 409 else "validation"
        return problem_response(status, exc.message, kind, errors)

    @app.exception_handler(StoreError)
    async def _store(_: Request, exc: StoreError) -> JSONResponse:
        if isinstance(exc, (ObjectNotFoundError, JobNotFoundError)):
            return problem_response(404, exc.message, "not-found",
                                    [(exc.field, exc.message)] if exc.field else None)
        if isinstance(exc, ObjectNotReadyError):
            return problem_response(409, exc.message, "object-not-ready")
        log.error("store error: %s", exc.message)
        return problem_response(503, exc.message, "store-unavailable")

    @app.exception_handler(RequestValidationError)
    async def _request_validation(_: Request, exc: RequestValidationError) -> JSONResponse:
        errors: list[tuple[str, str]] = []
        for err in exc.errors():
            loc = list(err.get("loc", ()))
            # FastAPI prefixes body/query/path; the field name is what a client knows.
            if loc and loc[0] in ("body", "query", "path", "header", "cookie"):
                loc = loc[1:]
            errors.append((field_name(loc) or "request", str(err.get("msg", "invalid"))))
        return problem_response(422, "the request is not valid", "validation", errors)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        detail = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
        headers = dict(exc.headers or {})
        unreadable = _unreadable_form(request, exc.status_code, detail)
        if unreadable is not None:
            field, message = unreadable
            return problem_response(400, message, errors=[(field, message)], headers=headers)
        return problem_response(exc.status_code, detail, headers=headers)


def install_fallback_handler(app: FastAPI) -> None:
    """A bug still answers in problem+json (status 500), without internals.

    The last resort: the app's own errors are answered by
    :class:`app.observability.ServiceMiddleware`, which keeps the connection
    usable; this handler sees only what goes wrong outside it.
    """

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return problem_response(500, "internal error; it has been logged", "internal")
