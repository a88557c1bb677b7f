"""Crash-safe file primitives: atomic writes, checksums, model directories.

A reader never sees a half-written file: every file is written to a
temporary name in the same directory, flushed to disk, renamed over the
final name and the directory entry flushed too (POSIX rename is atomic within
one file system). Every stored payload carries a SHA-256 that is checked on
load, so a torn or tampered file is reported, never half-used.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import io
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from model_store.errors import CorruptModelError
from viewloc_core.errors import ModelFormatError

if TYPE_CHECKING:
    from viewloc_core.model import ObjectModel

#: Version of the on-disk layout written by this code (files and SQLite schema).
STORE_SCHEMA_VERSION = 1

MODEL_ARRAYS = "model.npz"
MODEL_META = "model.json"


def sha256_hex(data: bytes) -> str:
    """Hex SHA-256 of ``data``."""
    return hashlib.sha256(data).hexdigest()


def fsync_dir(path: Path) -> None:
    """Flush a directory entry so a completed rename survives a power cut."""
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so readers see the old or the new file, never a mix.

    Parameters
    ----------
    path : Path
        Final file name; its directory must exist.
    data : bytes
        Complete new content.
    """
    path = Path(path)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp_name, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp_name)
        raise
    fsync_dir(path.parent)


@contextlib.contextmanager
def file_lock(path: Path, shared: bool = False) -> Iterator[None]:
    """Hold an ``fcntl.flock`` on ``path`` (created if missing) for the block.

    The lock is per open file description, so it serialises threads of one
    process as well as separate processes serving the same store root.
    """
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_SH if shared else fcntl.LOCK_EX)
        yield
    finally:
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)


def encode_arrays(arrays: dict[str, NDArray[Any]]) -> bytes:
    """Serialise named arrays to ``.npz`` bytes (no pickled objects)."""
    buf = io.BytesIO()
    np.savez(buf, allow_pickle=False, **arrays)
    return buf.getvalue()


def decode_arrays(data: bytes, what: str) -> dict[str, NDArray[Any]]:
    """Parse ``.npz`` bytes written by :func:`encode_arrays`.

    Raises
    ------
    CorruptModelError
        When the bytes are not a readable archive of plain arrays.
    """
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            return {name: npz[name] for name in npz.files}
    except Exception as exc:  # numpy raises several unrelated types on garbage
        raise CorruptModelError(f"{what} is not a readable array archive: {exc}") from exc


def model_payload(model: ObjectModel) -> tuple[bytes, dict[str, Any]]:
    """Serialise a learned model to (npz bytes, JSON metadata with checksum)."""
    from viewloc_core.model import model_to_arrays

    arrays, meta = model_to_arrays(model)
    data = encode_arrays(arrays)
    envelope = {
        "store_schema_version": STORE_SCHEMA_VERSION,
        "arrays_file": MODEL_ARRAYS,
        "arrays_sha256": sha256_hex(data),
        "model_meta": meta,
    }
    return data, envelope


def model_sha256(model: ObjectModel) -> str:
    """The checksum :func:`save_model_dir` stores for ``model`` (and the API
    reports as ``Object.model_sha256``), without writing anything: SHA-256 of
    its arrays' ``.npz`` bytes, hex. numpy writes the archive with a fixed
    date, so equal arrays give equal bytes: learning repeats bit for bit on
    one machine, and one upload learned twice gives one checksum."""
    return str(model_payload(model)[1]["arrays_sha256"])


def model_from_payload(data: bytes, envelope: dict[str, Any], expected_sha256: str | None) -> Any:
    """Verify and parse what :func:`model_payload` wrote.

    Parameters
    ----------
    data : bytes
        Content of the arrays file.
    envelope : dict
        Parsed ``model.json``.
    expected_sha256 : str or None
        Checksum recorded elsewhere (the store's database); checked as well
        as the one in the envelope.

    Raises
    ------
    CorruptModelError
        Checksum mismatch, unknown store schema version or unparsable content.
    """
    from viewloc_core.model import model_from_arrays

    version = envelope.get("store_schema_version")
    if version != STORE_SCHEMA_VERSION:
        raise CorruptModelError(f"unknown model file schema version {version!r}")
    digest = sha256_hex(data)
    if digest != envelope.get("arrays_sha256") or (
        expected_sha256 is not None and digest != expected_sha256
    ):
        raise CorruptModelError("model file checksum mismatch: the file is corrupt")
    arrays = decode_arrays(data, "model file")
    meta = envelope.get("model_meta")
    if not isinstance(meta, dict):
        raise CorruptModelError("model metadata is missing")
    try:
        return model_from_arrays(arrays, meta)
    except CorruptModelError:
        raise
    except ModelFormatError as exc:
        raise CorruptModelError(exc.message) from exc


def save_model_dir(directory: Path, model: ObjectModel) -> str:
    """Write a model into ``directory`` (created) atomically; returns its SHA-256.

    The arrays file is replaced before the metadata that names its checksum,
    so a crash between the two leaves a mismatch that :func:`load_model_dir`
    reports instead of a silently mixed model.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    data, envelope = model_payload(model)
    atomic_write_bytes(directory / MODEL_ARRAYS, data)
    atomic_write_bytes(directory / MODEL_META, json.dumps(envelope, indent=1).encode())
    return str(envelope["arrays_sha256"])


def load_model_dir(directory: Path, expected_sha256: str | None = None) -> Any:
    """Read and verify a model written by :func:`save_model_dir`.

    Raises
    ------
    CorruptModelError
        Missing files, checksum mismatch or unparsable content.
    """
    directory = Path(directory)
    try:
        envelope = json.loads((directory / MODEL_META).read_text())
        data = (directory / MODEL_ARRAYS).read_bytes()
    except FileNotFoundError as exc:
        raise CorruptModelError(f"model file missing: {Path(exc.filename).name}") from exc
    except (ValueError, UnicodeDecodeError) as exc:
        raise CorruptModelError(f"model metadata is not valid JSON: {exc}") from exc
    if not isinstance(envelope, dict):
        raise CorruptModelError("model metadata is not a JSON object")
    return model_from_payload(data, envelope, expected_sha256)
