"""Errors of the model store.

Missing and busy records are not bad input to the core, so they live beside
``viewloc_core.errors`` rather than inside it; a corrupt model file is a
``ModelFormatError`` so the one exception handler of the service treats it
like any other unusable model.
"""

from __future__ import annotations

from viewloc_core.errors import ModelFormatError

#: The most characters of an id an error message repeats back.
SHOWN_ID_CHARS = 64


def shown_id(value: str) -> str:
    """``value`` quoted for an error message, cut to SHOWN_ID_CHARS (an
    answer should not echo a 70 kB id back)."""
    if len(value) <= SHOWN_ID_CHARS:
        return repr(value)
    return f"{value[:SHOWN_ID_CHARS]!r}... ({len(value)} characters)"


class StoreError(Exception):
    """Base of the store's own errors (not bad input to the core)."""

    def __init__(self, message: str, field: str | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.field = field


class ObjectNotFoundError(StoreError):
    """No object with that id (or the id is not a well-formed object id)."""


class JobNotFoundError(StoreError):
    """No job with that id (or the id is not a well-formed job id)."""


class ObjectNotReadyError(StoreError):
    """The object exists but its model is not (yet, or ever) usable."""


class CorruptModelError(ModelFormatError):
    """A stored file does not match its recorded checksum or cannot be parsed."""
