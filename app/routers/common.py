"""Small helpers shared by the routers: bounded reads and JSON form fields."""

from __future__ import annotations

from typing import TypeVar

from fastapi import UploadFile
from pydantic import BaseModel, ValidationError

from app.problems import ProblemError, validation_errors

M = TypeVar("M", bound=BaseModel)


def read_limited(upload: UploadFile, limit: int, field: str) -> bytes:
    """The upload's bytes; 413 when it has more than ``limit``."""
    data = upload.file.read(limit + 1)
    if len(data) > limit:
        raise ProblemError(
            413, f"{field} is larger than the limit of {limit} bytes", "too-large",
            [(field, f"larger than {limit} bytes")],
        )
    return data


def parse_json_field(text: str | None, model: type[M], field: str) -> M:
    """Validate a JSON text form field; 422 naming ``field.sub.field`` on error."""
    if text is None or not text.strip():
        text = "{}"
    try:
        return model.model_validate_json(text)
    except ValidationError as exc:
        raise ProblemError(
            422, f"the {field} field is not valid", "validation", validation_errors(exc, field)
        ) from exc


def check_learning_spec(learning: dict[str, object] | None) -> None:
    """Refuse unknown or bad learning options at upload time, not in the job,
    naming the option as the request has it (``spec.learning.max_faces``)."""
    if not learning:
        return
    try:
        from viewloc_core.errors import InvalidInputError
        from viewloc_core.learn import LearningConfig
    except ImportError:  # engine not installed: the job reports it instead
        return
    try:
        LearningConfig.from_dict(dict(learning))
    except InvalidInputError as exc:
        raise ProblemError(422, exc.message, "validation",
                           [(f"spec.{exc.field or 'learning'}", exc.message)]) from exc
