"""One exception tree for bad input to the core.

Expected failures (nothing found, a degenerate fit) are values, not
exceptions. These exceptions mean the caller handed over something unusable;
the service maps every one of them to a 4xx problem+json answer.
"""

from __future__ import annotations


class ViewlocError(Exception):
    """Base of every error the core raises on purpose.

    Parameters
    ----------
    message : str
        What is wrong, in words a user can act on.
    field : str or None
        Name of the offending input (e.g. ``"camera.fx"``), when there is one.
    """

    def __init__(self, message: str, field: str | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.field = field


class InvalidInputError(ViewlocError):
    """An argument has the wrong shape, type, range or content."""


class InvalidImageError(InvalidInputError):
    """An image cannot be decoded or has an unusable size or dtype."""


class InvalidMeshError(InvalidInputError):
    """A mesh cannot be parsed or is degenerate (no faces, zero extent)."""


class InvalidCameraError(InvalidInputError):
    """Camera intrinsics are not finite, not positive, or inconsistent."""


class ModelFormatError(ViewlocError):
    """A stored model file is corrupt or has an unknown schema version."""


class Cancelled(ViewlocError):  # noqa: N818  (a state, not a fault: "learning was Cancelled")
    """A long computation was asked to stop (``should_stop()`` returned True)."""
