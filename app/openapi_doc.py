"""OpenAPI helpers: documented error answers and problem+json everywhere."""

from __future__ import annotations

from typing import Any

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from app.problems import PROBLEM_JSON
from app.schemas import Problem

_DESCRIPTIONS = {
    400: "The multipart/form-data body could not be read; `errors` names the "
         "Content-Type header (no boundary) or the body.",
    401: "Missing or wrong API key (only when VIEWLOC_API_KEYS is set).",
    404: "Unknown object or job id.",
    409: "The object is not ready (still learning, failed, or its model is corrupt).",
    413: "Upload too large (bytes, or number of images).",
    415: "The request is not multipart/form-data.",
    422: "Invalid input; `errors` names each offending field.",
    503: "The store or the job runner is not available.",
}


def errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    """``responses=`` entries for the given error status codes (plus 401)."""
    out: dict[int | str, dict[str, Any]] = {}
    for code in sorted({401, *codes}):
        out[code] = {"model": Problem, "description": _DESCRIPTIONS.get(code, "Error.")}
    return out


def _mark_binary(node: Any) -> None:
    """Add ``format: binary`` beside OpenAPI 3.1's ``contentMediaType`` for uploads.

    Client generators (openapi-python-client among them) recognise a file
    part by ``format: binary``; without it they send the file as a text field.
    """
    if isinstance(node, dict):
        if node.get("contentMediaType") == "application/octet-stream":
            node["format"] = "binary"
        for value in node.values():
            _mark_binary(value)
    elif isinstance(node, list):
        for value in node:
            _mark_binary(value)


def install_openapi(app: FastAPI) -> None:
    """Serve error answers as application/problem+json in the document.

    FastAPI documents every ``responses=`` model as application/json and adds
    its own HTTPValidationError for 422; the service answers errors as
    problem+json with :class:`Problem`, so the document is rewritten to say so.
    """

    def openapi() -> dict[str, Any]:
        if app.openapi_schema:
            return app.openapi_schema
        schema = get_openapi(
            title=app.title, version=app.version, description=app.description,
            routes=app.routes,
        )
        problem_ref = {"$ref": "#/components/schemas/Problem"}
        for item in schema.get("paths", {}).values():
            for op in item.values():
                if not isinstance(op, dict) or "responses" not in op:
                    continue
                for code, resp in op["responses"].items():
                    if code.isdigit() and int(code) >= 400:
                        resp["content"] = {PROBLEM_JSON: {"schema": problem_ref}}
                        if int(code) == 422:
                            resp["description"] = _DESCRIPTIONS[422]
        comps = schema.get("components", {}).get("schemas", {})
        _mark_binary(comps)
        for unused in ("HTTPValidationError", "ValidationError"):
            comps.pop(unused, None)
        app.openapi_schema = schema
        return schema

    app.openapi = openapi  # type: ignore[method-assign]
