"""Model store: records, ids, atomic files, checksums, recovery, two processes."""

from __future__ import annotations

import multiprocessing
import os
import subprocess
import sys
from pathlib import Path

import pytest

from model_store import (
    CorruptModelError,
    JobNotFoundError,
    ModelStore,
    ObjectNotFoundError,
    ObjectNotReadyError,
    StoreError,
)
from model_store.files import atomic_write_bytes, decode_arrays, encode_arrays


def _new(store: ModelStore, upload: bytes = b"solid x\nendsolid x\n"):
    return store.create_object(name="part", source="mesh", kind="learn_mesh", upload=upload,
                               upload_suffix="bin", upload_meta={"units": "mm"})


def test_create_get_list_delete(tmp_path: Path) -> None:
    store = ModelStore(tmp_path)
    obj, job = _new(store)
    assert obj.state == "learning" and job.state == "queued" and obj.job_id == job.job_id
    assert store.get_object(obj.object_id) == obj
    assert [o.object_id for o in store.list_objects()] == [obj.object_id]
    data, rec = store.read_upload(obj.object_id)
    assert data == b"solid x\nendsolid x\n" and rec.upload_meta == {"units": "mm"}
    assert store.delete_object(obj.object_id) is None  # queued job: cancelled, nothing to stop
    assert store.get_job(job.job_id).state == "cancelled"
    assert not (tmp_path / "objects" / obj.object_id).exists()
    with pytest.raises(ObjectNotFoundError):
        store.get_object(obj.object_id)


BAD_IDS = ["../etc", "", "A" * 32, "0" * 31, "../" + "0" * 32, "0" * 32 + "/"]


@pytest.mark.parametrize("bad", BAD_IDS)
def test_malformed_ids_never_reach_the_file_system(tmp_path: Path, bad: str) -> None:
    store = ModelStore(tmp_path)
    with pytest.raises(ObjectNotFoundError):
        store.get_object(bad)
    with pytest.raises(ObjectNotFoundError):
        store.delete_object(bad)
    with pytest.raises(JobNotFoundError):
        store.get_job(bad)


def test_not_ready_object_has_no_model(tmp_path: Path) -> None:
    store = ModelStore(tmp_path)
    obj, _ = _new(store)
    with pytest.raises(ObjectNotReadyError):
        store.load_model(obj.object_id)


def test_corrupt_upload_is_detected(tmp_path: Path) -> None:
    store = ModelStore(tmp_path)
    obj, _ = _new(store)
    path = tmp_path / "objects" / obj.object_id / obj.upload_file
    path.write_bytes(b"solid y\nendsolid y\n")
    with pytest.raises(CorruptModelError, match="checksum"):
        store.read_upload(obj.object_id)


def test_atomic_write_replaces_and_leaves_no_temp_files(tmp_path: Path) -> None:
    target = tmp_path / "f.bin"
    atomic_write_bytes(target, b"old")
    atomic_write_bytes(target, b"new")
    assert target.read_bytes() == b"new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.bin"]


def test_array_archive_round_trip_and_garbage(tmp_path: Path) -> None:
    import numpy as np

    arrays = {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "b": np.array([1, 2], np.int32)}
    back = decode_arrays(encode_arrays(arrays), "x")
    assert set(back) == {"a", "b"} and np.array_equal(back["a"], arrays["a"])
    with pytest.raises(CorruptModelError):
        decode_arrays(b"PK\x03\x04 not really a zip", "x")


def test_schema_version_mismatch_is_refused(tmp_path: Path) -> None:
    ModelStore(tmp_path)
    import sqlite3

    with sqlite3.connect(tmp_path / "store.sqlite") as conn:
        conn.execute("UPDATE meta SET value='99' WHERE key='schema_version'")
    with pytest.raises(StoreError, match="schema version 99"):
        ModelStore(tmp_path)


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_jobs_of_a_dead_runner_are_requeued_then_failed(tmp_path: Path) -> None:
    store = ModelStore(tmp_path)
    obj, job = _new(store)
    import socket
    import sqlite3
    import time

    for attempt in (1, 2):
        claimed = store.claim_next_job("deadbeef" * 4)
        assert claimed is not None and claimed.attempts == attempt
        with sqlite3.connect(tmp_path / "store.sqlite") as conn:
            conn.execute("INSERT OR REPLACE INTO runners VALUES (?,?,?,?)",
                         ("deadbeef" * 4, socket.gethostname(), _dead_pid(), time.time()))
        actions = store.recover_orphaned_jobs(stale_after_s=300)
        expected = "requeued" if attempt == 1 else "failed"
        assert actions == [(job.job_id, expected)]
    final = store.get_job(job.job_id)
    assert final.state == "failed" and "giving up" in (final.error or "")
    assert store.get_object(obj.object_id).state == "failed"


def test_jobs_a_runner_stops_cleanly_go_back_to_the_queue_uncounted(tmp_path: Path) -> None:
    store = ModelStore(tmp_path)
    obj, job = _new(store)
    _, other = _new(store)
    # Three clean restarts in a row (more than recover_orphaned_jobs allows
    # starts) do not fail the job: each start is handed back.
    for _ in range(3):
        claimed = store.claim_next_job("c" * 32)
        assert claimed is not None and claimed.job_id == job.job_id and claimed.attempts == 1
        store.update_progress(job.job_id, 0.6, "rendering")
        assert store.release_jobs("c" * 32) == [job.job_id]
        back = store.get_job(job.job_id)
        assert (back.state, back.attempts, back.progress) == ("queued", 0, 0.0)
        assert store.get_object(obj.object_id).state == "learning"
    # Only the stopping runner's jobs, and not those asked to cancel.
    assert store.claim_next_job("d" * 32) is not None
    assert store.get_job(other.job_id).state == "queued"
    assert store.claim_next_job("c" * 32).job_id == other.job_id  # type: ignore[union-attr]
    store.request_cancel(other.job_id)
    assert store.release_jobs("c" * 32) == []
    assert store.get_job(other.job_id).state == "running"
    assert store.get_job(job.job_id).state == "running"


def test_live_runner_keeps_its_jobs(tmp_path: Path) -> None:
    store = ModelStore(tmp_path)
    _, job = _new(store)
    store.heartbeat("a" * 32)  # this process: alive
    assert store.claim_next_job("a" * 32) is not None
    assert store.recover_orphaned_jobs(stale_after_s=300) == []
    assert store.get_job(job.job_id).state == "running"


def test_cancel_running_job_is_a_flag_until_it_finishes(tmp_path: Path) -> None:
    store = ModelStore(tmp_path)
    obj, job = _new(store)
    store.claim_next_job("b" * 32)
    assert store.should_stop(job.job_id) is False
    assert store.request_cancel(job.job_id).state == "running"
    assert store.should_stop(job.job_id) is True
    assert store.finish_job(job.job_id, "failed", "stopped") is True
    assert store.get_job(job.job_id).state == "cancelled"
    assert store.get_object(obj.object_id).state == "failed"


def _create_many(root: str, n: int) -> None:
    store = ModelStore(root)
    for _ in range(n):
        store.create_object(name="p", source="mesh", kind="learn_mesh", upload=os.urandom(2000),
                            upload_suffix="bin", upload_meta={})
        store.claim_next_job(f"{os.getpid():032x}")


def test_two_processes_share_one_root(tmp_path: Path) -> None:
    ctx = multiprocessing.get_context("spawn")
    procs = [ctx.Process(target=_create_many, args=(str(tmp_path), 15)) for _ in range(2)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(60)
        assert p.exitcode == 0
    store = ModelStore(tmp_path)
    objects = store.list_objects()
    assert len(objects) == 30
    for o in objects:
        store.read_upload(o.object_id)  # every upload verifies
    claimed = store.list_jobs(state="running")
    assert len(claimed) == 30 and len({j.job_id for j in claimed}) == 30


def _read_in_forked_child(store: ModelStore, object_id: str, out: object) -> None:
    # ``store`` crossed a fork: the reader it holds is the parent's.
    inherited = store._readers.conn
    state = store.get_object(object_id).state
    out.put((state, store._readers.conn is not inherited,  # type: ignore[attr-defined]
             any(c is inherited for c in store._inherited)))


def test_kept_read_connection_sees_every_committed_write(tmp_path: Path) -> None:
    reader, writer = ModelStore(tmp_path), ModelStore(tmp_path)
    obj, job = _new(writer)
    assert reader.get_object(obj.object_id).state == "learning"  # opens the reader
    writer.claim_next_job("f" * 32)
    writer.delete_object(obj.object_id)
    with pytest.raises(ObjectNotFoundError):
        reader.get_object(obj.object_id)
    assert reader.get_job(job.job_id).state in ("cancelled", "running")
    # Another process's write, through its own connection.
    ctx = multiprocessing.get_context("spawn")
    proc = ctx.Process(target=_create_many, args=(str(tmp_path), 2))
    proc.start()
    proc.join(60)
    assert proc.exitcode == 0
    assert len(reader.list_objects()) == 2


def test_each_thread_and_forked_child_reads_through_its_own_connection(tmp_path: Path) -> None:
    import threading

    store = ModelStore(tmp_path)
    obj, _ = _new(store)
    store.get_object(obj.object_id)
    mine = store._readers.conn
    seen: list[object] = []

    def read() -> None:
        store.get_object(obj.object_id)
        seen.append(store._readers.conn)

    worker = threading.Thread(target=read)
    worker.start()
    worker.join()
    assert seen and seen[0] is not mine
    store.get_object(obj.object_id)
    assert store._readers.conn is mine  # kept, not reopened
    ctx = multiprocessing.get_context("fork")
    out = ctx.Queue()
    child = ctx.Process(target=_read_in_forked_child, args=(store, obj.object_id, out))
    child.start()
    # The child read through a connection of its own and left the parent's
    # open (closing it there could checkpoint away the parent's WAL).
    assert out.get(timeout=60) == ("learning", True, True)
    child.join(60)
    assert child.exitcode == 0
    # The parent's connection still works after the child went.
    assert store.get_object(obj.object_id).state == "learning"
