"""Exceptions of the viewloc client.

::

    ViewlocClientError
    ├── TransportError        the service could not be reached (wraps httpx errors)
    ├── APIError              the service answered with a problem+json error
    │   ├── AuthenticationError   401
    │   ├── NotFoundError         404
    │   ├── ConflictError         409 (e.g. object not ready)
    │   ├── PayloadTooLargeError  413
    │   └── ValidationError       415 / 422 (``errors`` names the fields)
    ├── JobFailedError        a waited-for job ended failed or cancelled
    └── JobTimeoutError       a waited-for job did not finish in time
"""

from __future__ import annotations

from typing import Any


class ViewlocClientError(Exception):
    """Base of every error this client raises."""


class TransportError(ViewlocClientError):
    """Connection refused, timeout, or another network failure."""


class APIError(ViewlocClientError):
    """An error answer of the service (RFC 9457 problem details).

    Attributes
    ----------
    status : int
    problem : dict
        The problem document (``type``, ``title``, ``status``, ``detail``, ``errors``).
    """

    def __init__(self, status: int, problem: dict[str, Any]) -> None:
        self.status = status
        self.problem = problem
        self.detail = str(problem.get("detail", ""))
        self.errors: list[dict[str, str]] = list(problem.get("errors") or [])
        super().__init__(f"HTTP {status}: {self.detail}")


class AuthenticationError(APIError):
    """401: missing or wrong API key."""


class NotFoundError(APIError):
    """404: unknown object or job."""


class ConflictError(APIError):
    """409: the object is not ready (learning, failed or corrupt)."""


class PayloadTooLargeError(APIError):
    """413: an upload exceeds the service's limits."""


class ValidationError(APIError):
    """415 / 422: invalid input; ``errors`` lists ``{field, message}``."""


class JobFailedError(ViewlocClientError):
    """The job ended ``failed`` or ``cancelled``; ``job`` is its last state."""

    def __init__(self, job: Any) -> None:
        self.job = job
        super().__init__(f"job {job.job_id} {job.state}: {job.error}")


class JobTimeoutError(ViewlocClientError):
    """The job was still running when the wait ended."""


_BY_STATUS: dict[int, type[APIError]] = {
    401: AuthenticationError, 404: NotFoundError, 409: ConflictError,
    413: PayloadTooLargeError, 415: ValidationError, 422: ValidationError,
}


def error_for(status: int, problem: dict[str, Any]) -> APIError:
    """The most specific :class:`APIError` for a status code."""
    return _BY_STATUS.get(status, APIError)(status, problem)
