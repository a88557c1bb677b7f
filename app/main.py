"""Application factory: settings are read when the app is built, never at import."""

from __future__ import annotations

from fastapi import FastAPI


def create_app() -> FastAPI:
    """Build the viewloc FastAPI application."""
    application = FastAPI(title="viewloc", version="1.0.0")

    @application.get("/healthz", tags=["operations"])
    def healthz() -> dict[str, str]:
        """Process is alive."""
        return {"status": "ok"}

    return application
