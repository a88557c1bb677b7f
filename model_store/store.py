"""The model store: objects, uploads, learned models and jobs under one root.

Layout under ``root`` (``VIEWLOC_DATA_DIR``)::

    store.sqlite          metadata of objects, jobs and job runners (WAL mode)
    store.lock            fcntl lock serialising model writes and deletions
    objects/<object_id>/  upload.bin | upload.npz, model.npz, model.json

Object and job ids are made here (uuid4 hex) and every id that arrives from
outside is checked against :data:`ID_PATTERN` before it is used, so no path is
ever built from a user's string. Several processes may serve the same root:
metadata changes are SQLite transactions (``BEGIN IMMEDIATE``), files are
written atomically under the file lock and verified by SHA-256 when read.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import socket
import sqlite3
import threading
import time
import uuid
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

from model_store.errors import (
    CorruptModelError,
    JobNotFoundError,
    ObjectNotFoundError,
    ObjectNotReadyError,
    StoreError,
    shown_id,
)
from model_store.files import (
    STORE_SCHEMA_VERSION,
    atomic_write_bytes,
    file_lock,
    load_model_dir,
    save_model_dir,
    sha256_hex,
)

ID_PATTERN = re.compile(r"^[0-9a-f]{32}$")

ObjectState = Literal["learning", "ready", "failed"]
JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]
TERMINAL_JOB_STATES = ("succeeded", "failed", "cancelled")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS objects (
    object_id TEXT PRIMARY KEY,
    name TEXT NOT NULL,
    state TEXT NOT NULL,
    source TEXT NOT NULL,
    diameter_mm REAL NOT NULL DEFAULT 0,
    training_views INTEGER NOT NULL DEFAULT 0,
    model_views INTEGER NOT NULL DEFAULT 0,
    created_at TEXT NOT NULL,
    job_id TEXT NOT NULL,
    error TEXT,
    upload_file TEXT NOT NULL,
    upload_sha256 TEXT NOT NULL,
    upload_meta TEXT NOT NULL,
    model_sha256 TEXT
);
CREATE TABLE IF NOT EXISTS jobs (
    job_id TEXT PRIMARY KEY,
    object_id TEXT NOT NULL,
    kind TEXT NOT NULL,
    state TEXT NOT NULL,
    progress REAL NOT NULL DEFAULT 0,
    stage TEXT NOT NULL DEFAULT 'queued',
    error TEXT,
    created_at TEXT NOT NULL,
    started_at TEXT,
    finished_at TEXT,
    cancel_requested INTEGER NOT NULL DEFAULT 0,
    owner TEXT,
    pid INTEGER,
    attempts INTEGER NOT NULL DEFAULT 0
);
CREATE INDEX IF NOT EXISTS jobs_state ON jobs (state, created_at);
CREATE TABLE IF NOT EXISTS runners (
    owner TEXT PRIMARY KEY,
    host TEXT NOT NULL,
    pid INTEGER NOT NULL,
    heartbeat_at REAL NOT NULL
);
"""


def now_rfc3339() -> str:
    """Current UTC time as RFC 3339 with milliseconds and a ``Z``."""
    return datetime.now(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def new_id() -> str:
    """A fresh server-made id (uuid4, 32 lowercase hex digits)."""
    return uuid.uuid4().hex


def is_valid_id(value: str) -> bool:
    """True when ``value`` has the exact shape of an id this store makes."""
    return isinstance(value, str) and ID_PATTERN.fullmatch(value) is not None


@dataclass(frozen=True, slots=True)
class ObjectRecord:
    """Metadata of one object (API.md ``Object``)."""

    object_id: str
    name: str
    state: ObjectState
    source: str
    diameter_mm: float
    training_views: int
    model_views: int
    created_at: str
    job_id: str
    error: str | None
    upload_file: str
    upload_sha256: str
    upload_meta: dict[str, Any]
    model_sha256: str | None


@dataclass(frozen=True, slots=True)
class JobRecord:
    """One background job (API.md ``Job``) plus the runner's bookkeeping."""

    job_id: str
    object_id: str
    kind: str
    state: JobState
    progress: float
    stage: str
    error: str | None
    created_at: str
    started_at: str | None
    finished_at: str | None
    cancel_requested: bool
    owner: str | None
    pid: int | None
    attempts: int


def _object_from_row(row: sqlite3.Row) -> ObjectRecord:
    return ObjectRecord(
        object_id=row["object_id"],
        name=row["name"],
        state=row["state"],
        source=row["source"],
        diameter_mm=float(row["diameter_mm"]),
        training_views=int(row["training_views"]),
        model_views=int(row["model_views"]),
        created_at=row["created_at"],
        job_id=row["job_id"],
        error=row["error"],
        upload_file=row["upload_file"],
        upload_sha256=row["upload_sha256"],
        upload_meta=json.loads(row["upload_meta"]),
        model_sha256=row["model_sha256"],
    )


def _job_from_row(row: sqlite3.Row) -> JobRecord:
    return JobRecord(
        job_id=row["job_id"],
        object_id=row["object_id"],
        kind=row["kind"],
        state=row["state"],
        progress=float(row["progress"]),
        stage=row["stage"],
        error=row["error"],
        created_at=row["created_at"],
        started_at=row["started_at"],
        finished_at=row["finished_at"],
        cancel_requested=bool(row["cancel_requested"]),
        owner=row["owner"],
        pid=row["pid"],
        attempts=int(row["attempts"]),
    )


def _count(value: Any) -> int:
    """A model's view count, whether given as a number or as the list itself."""
    return len(value) if hasattr(value, "__len__") else int(value)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class ModelStore:
    """Objects, uploads, learned models and jobs on disk under ``root``.

    Safe to share between threads (each thread reads through a connection
    of its own and writes through one per transaction) and between processes
    on the same root (SQLite transactions + file lock).

    Parameters
    ----------
    root : Path
        Data directory; created when missing.
    cache_size : int
        Number of loaded models kept in memory (least recently used evicted).
    """

    def __init__(self, root: Path | str, cache_size: int = 16) -> None:
        self.root = Path(root).resolve()
        self.objects_dir = self.root / "objects"
        self.db_path = self.root / "store.sqlite"
        self.lock_path = self.root / "store.lock"
        self.objects_dir.mkdir(parents=True, exist_ok=True)
        self._cache: OrderedDict[tuple[str, str], Any] = OrderedDict()
        self._cache_size = max(0, int(cache_size))
        self._cache_lock = threading.Lock()
        # Per thread (and process): the read connection, kept open.
        self._readers = threading.local()
        # Connections a forked child inherited: kept referenced, never
        # closed there (closing one may checkpoint and delete the WAL the
        # parent still reads).
        self._inherited: list[sqlite3.Connection] = []
        self._init_db()

    # -- database plumbing -------------------------------------------------
    def _connect(self) -> sqlite3.Connection:
        conn = sqlite3.connect(self.db_path, timeout=30.0, isolation_level=None)
        conn.row_factory = sqlite3.Row
        conn.execute("PRAGMA busy_timeout = 30000")
        conn.execute("PRAGMA synchronous = NORMAL")
        return conn

    @contextlib.contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        """A write transaction; IMMEDIATE takes the write lock up front so two
        processes cannot both read-then-write the same row."""
        conn = self._connect()
        try:
            conn.execute("BEGIN IMMEDIATE")
            try:
                yield conn
            except BaseException:
                conn.execute("ROLLBACK")
                raise
            conn.execute("COMMIT")
        finally:
            conn.close()

    @contextlib.contextmanager
    def _read(self) -> Iterator[sqlite3.Connection]:
        """This thread's read connection, opened on first use.

        Opening a connection costs about half a millisecond, as much as the
        read itself, and a localization reads the object twice. A kept
        connection in autocommit mode sees every committed write: each
        statement is its own read transaction, ended when its cursor is
        done with. It is never shared: SQLite connections must not cross
        threads, nor a fork (the pid is checked: a forked child opens its
        own).
        """
        conn: sqlite3.Connection | None = getattr(self._readers, "conn", None)
        if conn is not None and self._readers.pid != os.getpid():
            self._inherited.append(conn)
            conn = None
        if conn is None:
            conn = self._connect()
            self._readers.conn, self._readers.pid = conn, os.getpid()
        try:
            yield conn
        except sqlite3.Error:
            # A connection in an unknown state is not kept.
            self._readers.conn = None
            conn.close()
            raise

    def _init_db(self) -> None:
        with file_lock(self.lock_path):
            conn = self._connect()
            try:
                conn.execute("PRAGMA journal_mode = WAL")
                conn.executescript(_SCHEMA)
                row = conn.execute("SELECT value FROM meta WHERE key='schema_version'").fetchone()
                if row is None:
                    conn.execute(
                        "INSERT INTO meta (key, value) VALUES ('schema_version', ?)",
                        (str(STORE_SCHEMA_VERSION),),
                    )
                elif int(row["value"]) != STORE_SCHEMA_VERSION:
                    raise StoreError(
                        f"store at {self.root} has schema version {row['value']}, "
                        f"this code reads version {STORE_SCHEMA_VERSION}"
                    )
            finally:
                conn.close()

    def schema_version(self) -> int:
        """Schema version recorded in the database."""
        with self._read() as conn:
            row = conn.execute("SELECT value FROM meta WHERE key='schema_version'").fetchone()
        return int(row["value"])

    def readable(self) -> bool:
        """True when the database answers and the objects folder is there."""
        try:
            with self._read() as conn:
                conn.execute("SELECT count(*) FROM objects").fetchone()
            return self.objects_dir.is_dir() and os.access(self.objects_dir, os.W_OK)
        except (sqlite3.Error, OSError):
            return False

    def _object_dir(self, object_id: str) -> Path:
        if not is_valid_id(object_id):
            raise ObjectNotFoundError(f"no object {shown_id(object_id)}", "object_id")
        return self.objects_dir / object_id

    # -- objects -----------------------------------------------------------
    def create_object(
        self,
        *,
        name: str,
        source: str,
        kind: str,
        upload: bytes,
        upload_suffix: str,
        upload_meta: dict[str, Any],
        diameter_mm: float = 0.0,
        training_views: int = 0,
    ) -> tuple[ObjectRecord, JobRecord]:
        """Store an upload and queue the job that learns from it.

        Parameters
        ----------
        name : str
            Display name (free text, never used in a path).
        source : {"mesh", "images"}
            Where the model comes from.
        kind : str
            Job kind that the job runner resolves to a function.
        upload : bytes
            The raw upload (mesh file bytes, or an ``.npz`` of images).
        upload_suffix : {"bin", "npz"}
            Fixed suffix of the stored upload file.
        upload_meta : dict
            JSON-able parameters the job needs (units, file type, camera, ...).
        diameter_mm, training_views : float, int
            Known before learning for image sets; 0 until learned otherwise.
        """
        if upload_suffix not in ("bin", "npz"):
            raise ValueError(f"unsupported upload suffix {upload_suffix!r}")
        object_id, job_id = new_id(), new_id()
        directory = self._object_dir(object_id)
        directory.mkdir()
        upload_file = f"upload.{upload_suffix}"
        try:
            atomic_write_bytes(directory / upload_file, upload)
            created = now_rfc3339()
            with self._tx() as conn:
                conn.execute(
                    "INSERT INTO objects (object_id, name, state, source, diameter_mm, "
                    "training_views, model_views, created_at, job_id, upload_file, "
                    "upload_sha256, upload_meta) VALUES (?,?,?,?,?,?,?,?,?,?,?,?)",
                    (object_id, name, "learning", source, float(diameter_mm),
                     int(training_views), 0, created, job_id, upload_file,
                     sha256_hex(upload), json.dumps(upload_meta)),
                )
                conn.execute(
                    "INSERT INTO jobs (job_id, object_id, kind, state, progress, stage, "
                    "created_at) VALUES (?,?,?,?,?,?,?)",
                    (job_id, object_id, kind, "queued", 0.0, "queued", created),
                )
        except BaseException:
            shutil.rmtree(directory, ignore_errors=True)
            raise
        return self.get_object(object_id), self.get_job(job_id)

    def get_object(self, object_id: str) -> ObjectRecord:
        """The object's metadata; :class:`ObjectNotFoundError` when unknown."""
        if not is_valid_id(object_id):
            raise ObjectNotFoundError(f"no object {shown_id(object_id)}", "object_id")
        with self._read() as conn:
            row = conn.execute("SELECT * FROM objects WHERE object_id=?", (object_id,)).fetchone()
        if row is None:
            raise ObjectNotFoundError(f"no object {shown_id(object_id)}", "object_id")
        return _object_from_row(row)

    def list_objects(self, state: ObjectState | None = None) -> list[ObjectRecord]:
        """All objects, oldest first (optionally only those in ``state``)."""
        with self._read() as conn:
            if state is None:
                rows = conn.execute("SELECT * FROM objects ORDER BY created_at, object_id")
            else:
                rows = conn.execute(
                    "SELECT * FROM objects WHERE state=? ORDER BY created_at, object_id", (state,)
                )
            return [_object_from_row(r) for r in rows.fetchall()]

    def delete_object(self, object_id: str) -> JobRecord | None:
        """Remove an object, its files and cached model.

        Its job, when still queued, becomes ``cancelled``; when running, it is
        flagged for cancellation and returned so the caller can stop it.
        """
        directory = self._object_dir(object_id)
        with self._tx() as conn:
            row = conn.execute("SELECT job_id FROM objects WHERE object_id=?",
                               (object_id,)).fetchone()
            if row is None:
                raise ObjectNotFoundError(f"no object {shown_id(object_id)}", "object_id")
            conn.execute("DELETE FROM objects WHERE object_id=?", (object_id,))
            self._cancel_in_tx(conn, row["job_id"], "the object was deleted")
            job_row = conn.execute("SELECT * FROM jobs WHERE job_id=?",
                                   (row["job_id"],)).fetchone()
        with file_lock(self.lock_path):
            shutil.rmtree(directory, ignore_errors=True)
        self._evict(object_id)
        job = _job_from_row(job_row) if job_row is not None else None
        return job if job is not None and job.state == "running" else None

    def mark_object_failed(self, object_id: str, reason: str) -> None:
        """Record that the object's model is unusable (it stays listed)."""
        with self._tx() as conn:
            conn.execute(
                "UPDATE objects SET state='failed', error=? WHERE object_id=?",
                (reason, object_id),
            )
        self._evict(object_id)

    def read_upload(self, object_id: str) -> tuple[bytes, ObjectRecord]:
        """The object's stored upload, verified against its checksum."""
        record = self.get_object(object_id)
        path = self._object_dir(object_id) / record.upload_file
        try:
            data = path.read_bytes()
        except FileNotFoundError as exc:
            raise CorruptModelError("the stored upload is missing") from exc
        if sha256_hex(data) != record.upload_sha256:
            raise CorruptModelError("the stored upload does not match its checksum")
        return data, record

    # -- models ------------------------------------------------------------
    def save_model(self, object_id: str, job_id: str, model: Any) -> bool:
        """Store a learned model and mark the object ready and its job succeeded.

        Returns False (and keeps nothing) when the object was deleted or the
        job cancelled meanwhile.
        """
        directory = self._object_dir(object_id)
        with file_lock(self.lock_path):
            if not directory.is_dir():
                return False
            digest = save_model_dir(directory, model)
        with self._tx() as conn:
            job = conn.execute("SELECT state, cancel_requested FROM jobs WHERE job_id=?",
                               (job_id,)).fetchone()
            obj = conn.execute("SELECT object_id FROM objects WHERE object_id=?",
                               (object_id,)).fetchone()
            if obj is None or job is None or job["state"] != "running" or job["cancel_requested"]:
                return False
            conn.execute(
                "UPDATE objects SET state='ready', error=NULL, model_sha256=?, diameter_mm=?, "
                "training_views=?, model_views=? WHERE object_id=?",
                (digest, float(model.diameter_mm), _count(model.training_views),
                 _count(model.model_views), object_id),
            )
            conn.execute(
                "UPDATE jobs SET state='succeeded', progress=1.0, stage='done', error=NULL, "
                "finished_at=? WHERE job_id=?",
                (now_rfc3339(), job_id),
            )
        self._evict(object_id)
        return True

    def load_model(self, object_id: str) -> Any:
        """The object's learned model (cached after the first load).

        Raises
        ------
        ObjectNotFoundError
            Unknown id.
        ObjectNotReadyError
            The object is still learning or has failed.
        CorruptModelError
            The files do not verify; the object is then marked failed.
        """
        record = self.get_object(object_id)
        if record.state != "ready" or record.model_sha256 is None:
            detail = f": {record.error}" if record.error else ""
            raise ObjectNotReadyError(
                f"object {object_id} is {record.state}, not ready{detail}", "object_id"
            )
        key = (object_id, record.model_sha256)
        with self._cache_lock:
            if key in self._cache:
                self._cache.move_to_end(key)
                return self._cache[key]
        try:
            with file_lock(self.lock_path, shared=True):
                model = load_model_dir(self._object_dir(object_id), record.model_sha256)
        except CorruptModelError as exc:
            self.mark_object_failed(object_id, f"stored model is corrupt: {exc.message}")
            raise
        with self._cache_lock:
            self._cache[key] = model
            while len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
        return model

    def _evict(self, object_id: str) -> None:
        with self._cache_lock:
            for key in [k for k in self._cache if k[0] == object_id]:
                del self._cache[key]

    # -- jobs --------------------------------------------------------------
    def get_job(self, job_id: str) -> JobRecord:
        """The job's record; :class:`JobNotFoundError` when unknown."""
        if not is_valid_id(job_id):
            raise JobNotFoundError(f"no job {shown_id(job_id)}", "job_id")
        with self._read() as conn:
            row = conn.execute("SELECT * FROM jobs WHERE job_id=?", (job_id,)).fetchone()
        if row is None:
            raise JobNotFoundError(f"no job {shown_id(job_id)}", "job_id")
        return _job_from_row(row)

    def list_jobs(self, state: JobState | None = None) -> list[JobRecord]:
        """All jobs, oldest first (optionally only those in ``state``)."""
        with self._read() as conn:
            if state is None:
                rows = conn.execute("SELECT * FROM jobs ORDER BY created_at, job_id")
            else:
                rows = conn.execute(
                    "SELECT * FROM jobs WHERE state=? ORDER BY created_at, job_id", (state,)
                )
            return [_job_from_row(r) for r in rows.fetchall()]

    def job_counts(self) -> dict[str, int]:
        """Number of jobs per state (every state present, zero when none)."""
        counts = dict.fromkeys(("queued", "running", *TERMINAL_JOB_STATES), 0)
        with self._read() as conn:
            for row in conn.execute("SELECT state, count(*) AS n FROM jobs GROUP BY state"):
                counts[row["state"]] = int(row["n"])
        return counts

    def claim_next_job(self, owner: str) -> JobRecord | None:
        """Atomically move the oldest queued job to ``running`` for ``owner``."""
        with self._tx() as conn:
            row = conn.execute(
                "SELECT job_id FROM jobs WHERE state='queued' ORDER BY created_at, job_id LIMIT 1"
            ).fetchone()
            if row is None:
                return None
            conn.execute(
                "UPDATE jobs SET state='running', owner=?, pid=NULL, attempts=attempts+1, "
                "started_at=?, stage='starting', progress=0 WHERE job_id=?",
                (owner, now_rfc3339(), row["job_id"]),
            )
            claimed = conn.execute("SELECT * FROM jobs WHERE job_id=?",
                                   (row["job_id"],)).fetchone()
        return _job_from_row(claimed)

    def claim_job(self, job_id: str, owner: str) -> JobRecord | None:
        """Move one specific queued job to ``running`` for ``owner`` (None if it
        is not queued any more, e.g. cancelled or taken by another runner)."""
        with self._tx() as conn:
            cur = conn.execute(
                "UPDATE jobs SET state='running', owner=?, pid=NULL, attempts=attempts+1, "
                "started_at=?, stage='starting', progress=0 WHERE job_id=? AND state='queued'",
                (owner, now_rfc3339(), job_id),
            )
            if cur.rowcount != 1:
                return None
            row = conn.execute("SELECT * FROM jobs WHERE job_id=?", (job_id,)).fetchone()
        return _job_from_row(row)

    def set_job_pid(self, job_id: str, pid: int) -> None:
        """Record which process executes a running job."""
        with self._tx() as conn:
            conn.execute("UPDATE jobs SET pid=? WHERE job_id=?", (int(pid), job_id))

    def update_progress(self, job_id: str, progress: float, stage: str) -> None:
        """Record progress in [0, 1] and a stage text of a running job."""
        p = min(1.0, max(0.0, float(progress))) if progress == progress else 0.0
        with self._tx() as conn:
            conn.execute(
                "UPDATE jobs SET progress=?, stage=? WHERE job_id=? AND state='running'",
                (p, str(stage)[:200], job_id),
            )

    def should_stop(self, job_id: str) -> bool:
        """True when the job was cancelled, its object deleted, or it left ``running``."""
        with self._read() as conn:
            row = conn.execute(
                "SELECT j.state, j.cancel_requested, o.object_id FROM jobs j "
                "LEFT JOIN objects o ON o.object_id = j.object_id WHERE j.job_id=?",
                (job_id,),
            ).fetchone()
        return (
            row is None or row["state"] != "running" or bool(row["cancel_requested"])
            or row["object_id"] is None
        )

    def _cancel_in_tx(self, conn: sqlite3.Connection, job_id: str, reason: str) -> None:
        row = conn.execute("SELECT state FROM jobs WHERE job_id=?", (job_id,)).fetchone()
        if row is None:
            return
        if row["state"] == "queued":
            conn.execute(
                "UPDATE jobs SET state='cancelled', error=?, stage='cancelled', finished_at=? "
                "WHERE job_id=?",
                (reason, now_rfc3339(), job_id),
            )
            conn.execute(
                "UPDATE objects SET state='failed', error=? WHERE job_id=? AND state='learning'",
                (f"learning cancelled: {reason}", job_id),
            )
        elif row["state"] == "running":
            conn.execute("UPDATE jobs SET cancel_requested=1 WHERE job_id=?", (job_id,))

    def request_cancel(self, job_id: str, reason: str = "cancelled on request") -> JobRecord:
        """Cancel a queued job at once, or flag a running one; terminal jobs stay."""
        self.get_job(job_id)
        with self._tx() as conn:
            self._cancel_in_tx(conn, job_id, reason)
        return self.get_job(job_id)

    def finish_job(self, job_id: str, state: JobState, error: str | None) -> bool:
        """Move a running job to a terminal state; its object becomes failed unless
        the job succeeded. Returns False when the job was not running any more."""
        if state not in TERMINAL_JOB_STATES:
            raise ValueError(f"{state!r} is not a terminal job state")
        with self._tx() as conn:
            row = conn.execute("SELECT state, object_id, cancel_requested FROM jobs "
                               "WHERE job_id=?", (job_id,)).fetchone()
            if row is None or row["state"] != "running":
                return False
            if state == "failed" and row["cancel_requested"]:
                state, error = "cancelled", error or "cancelled on request"
            conn.execute(
                "UPDATE jobs SET state=?, error=?, stage=?, finished_at=? WHERE job_id=?",
                (state, error, state, now_rfc3339(), job_id),
            )
            if state != "succeeded":
                word = "cancelled" if state == "cancelled" else "failed"
                conn.execute(
                    "UPDATE objects SET state='failed', error=? WHERE object_id=? "
                    "AND state='learning'",
                    (f"learning {word}: {error}", row["object_id"]),
                )
        return True

    # -- runners (liveness of whoever executes jobs) -------------------------
    def heartbeat(self, owner: str) -> None:
        """Record that runner ``owner`` (this host, this process) is alive."""
        with self._tx() as conn:
            conn.execute(
                "INSERT INTO runners (owner, host, pid, heartbeat_at) VALUES (?,?,?,?) "
                "ON CONFLICT(owner) DO UPDATE SET heartbeat_at=excluded.heartbeat_at",
                (owner, socket.gethostname(), os.getpid(), time.time()),
            )

    def unregister_runner(self, owner: str) -> None:
        """Forget a runner that shut down cleanly."""
        with self._tx() as conn:
            conn.execute("DELETE FROM runners WHERE owner=?", (owner,))

    def release_jobs(self, owner: str) -> list[str]:
        """Hand the ``running`` jobs of a runner that stops cleanly back to the queue.

        The runner stopped them (a deploy, a restart), not they it: their
        start is not counted against them, so a job is not failed by
        :meth:`recover_orphaned_jobs` for two restarts in a row. Jobs asked
        to cancel are left to that recovery, which cancels them.

        Returns
        -------
        list of str
            The ids of the jobs re-queued.
        """
        with self._tx() as conn:
            rows = conn.execute(
                "SELECT job_id FROM jobs WHERE state='running' AND owner=? "
                "AND NOT cancel_requested", (owner,)).fetchall()
            for row in rows:
                conn.execute(
                    "UPDATE jobs SET state='queued', owner=NULL, pid=NULL, progress=0, "
                    "attempts=max(attempts - 1, 0), "
                    "stage='re-queued: the service stopped' WHERE job_id=?",
                    (row["job_id"],),
                )
        return [row["job_id"] for row in rows]

    def recover_orphaned_jobs(
        self, stale_after_s: float = 30.0, max_attempts: int = 2
    ) -> list[tuple[str, str]]:
        """Re-queue or fail ``running`` jobs whose runner is gone.

        A runner is gone when its heartbeat is older than ``stale_after_s`` or
        when it ran on this host and its process no longer exists. A job is
        re-queued while it has had fewer than ``max_attempts`` starts, so one
        that kills its runner every time cannot loop forever.

        Returns
        -------
        list of (job_id, "requeued" | "failed")
        """
        host, now = socket.gethostname(), time.time()
        actions: list[tuple[str, str]] = []
        with self._tx() as conn:
            runners = {r["owner"]: r for r in conn.execute("SELECT * FROM runners")}
            dead: set[str] = set()
            for owner, r in runners.items():
                if now - float(r["heartbeat_at"]) > stale_after_s or (
                    r["host"] == host and not _pid_alive(int(r["pid"]))
                ):
                    dead.add(owner)
            for row in conn.execute("SELECT * FROM jobs WHERE state='running'").fetchall():
                if row["owner"] in runners and row["owner"] not in dead:
                    continue
                if row["attempts"] < max_attempts and not row["cancel_requested"]:
                    conn.execute(
                        "UPDATE jobs SET state='queued', owner=NULL, pid=NULL, progress=0, "
                        "stage='re-queued after the runner stopped' WHERE job_id=?",
                        (row["job_id"],),
                    )
                    actions.append((row["job_id"], "requeued"))
                else:
                    reason = ("cancelled while its runner was gone" if row["cancel_requested"]
                              else "the learning process stopped with its service "
                                   f"{row['attempts']} times; giving up")
                    state = "cancelled" if row["cancel_requested"] else "failed"
                    conn.execute(
                        "UPDATE jobs SET state=?, error=?, stage=?, finished_at=? "
                        "WHERE job_id=?",
                        (state, reason, state, now_rfc3339(), row["job_id"]),
                    )
                    conn.execute(
                        "UPDATE objects SET state='failed', error=? WHERE object_id=? "
                        "AND state='learning'",
                        (f"learning {state}: {reason}", row["object_id"]),
                    )
                    actions.append((row["job_id"], "failed"))
            for owner in dead:
                conn.execute("DELETE FROM runners WHERE owner=?", (owner,))
        return actions
