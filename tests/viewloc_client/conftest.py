"""Reuse the live-server fixture of the app tests."""

from tests.app.conftest import make_server

__all__ = ["make_server"]
