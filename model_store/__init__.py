"""On-disk store of objects, uploads, learned models and jobs (see store.py)."""

from model_store.errors import (
    CorruptModelError,
    JobNotFoundError,
    ObjectNotFoundError,
    ObjectNotReadyError,
    StoreError,
)
from model_store.files import STORE_SCHEMA_VERSION, load_model_dir, save_model_dir
from model_store.store import (
    ID_PATTERN,
    JobRecord,
    ModelStore,
    ObjectRecord,
    is_valid_id,
    new_id,
    now_rfc3339,
)

__all__ = [
    "ID_PATTERN",
    "STORE_SCHEMA_VERSION",
    "CorruptModelError",
    "JobNotFoundError",
    "JobRecord",
    "ModelStore",
    "ObjectNotFoundError",
    "ObjectNotReadyError",
    "ObjectRecord",
    "StoreError",
    "is_valid_id",
    "load_model_dir",
    "new_id",
    "now_rfc3339",
    "save_model_dir",
]
