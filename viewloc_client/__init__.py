"""Typed Python client of the viewloc HTTP API."""

from viewloc_client.client import JobInfo, Localization, ObjectInfo, ViewlocClient
from viewloc_client.errors import (
    APIError,
    AuthenticationError,
    ConflictError,
    JobFailedError,
    JobTimeoutError,
    NotFoundError,
    PayloadTooLargeError,
    TransportError,
    ValidationError,
    ViewlocClientError,
)

__all__ = [
    "APIError",
    "AuthenticationError",
    "ConflictError",
    "JobFailedError",
    "JobInfo",
    "JobTimeoutError",
    "Localization",
    "NotFoundError",
    "ObjectInfo",
    "PayloadTooLargeError",
    "TransportError",
    "ValidationError",
    "ViewlocClient",
    "ViewlocClientError",
]
