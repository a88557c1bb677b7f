"""Paths with an empty segment name no resource here."""

from __future__ import annotations

from starlette.types import ASGIApp, Receive, Scope, Send

from app.problems import problem_response


class EmptySegmentGuard:
    """Answers 404 (problem+json) to an HTTP path with an empty segment
    (``//``, or an id given as ``%2F``, which the server decodes to ``/``)
    before the router sees it.

    The router's slash redirect strips every trailing slash: ``GET
    /v1/objects/%2F``, asking for the object ``/``, was sent on (307) to the
    list of objects, and ``DELETE`` there answered 405. A single trailing
    slash still redirects to the path without it.

    Parameters
    ----------
    app : ASGI app
    """

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and "//" in scope["path"]:
            response = problem_response(
                404, "no resource has an empty path segment (an id holds no '/')")
            await response(scope, receive, send)
            return
        await self.app(scope, receive, send)
