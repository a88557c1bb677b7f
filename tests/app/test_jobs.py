"""The embedded job runner: progress, crash isolation, cancellation, bounded concurrency."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

from app.jobs.base import JobRunner
from app.jobs.local import LocalJobRunner
from model_store import JobRecord, ModelStore
from tests.app.conftest import TEST_TASKS


def _queue(store: ModelStore, kind: str) -> JobRecord:
    _, job = store.create_object(name=kind, source="mesh", kind=kind, upload=b"x",
                                 upload_suffix="bin", upload_meta={})
    return job


def _wait(pred: Callable[[], bool], timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


def test_runner_protocol_progress_crash_and_failure(tmp_path: Path) -> None:
    store = ModelStore(tmp_path)
    runner = LocalJobRunner(store, workers=2, tasks=TEST_TASKS, poll_interval_s=0.1)
    assert isinstance(runner, JobRunner)
    runner.start()
    try:
        crash, bad, ok = _queue(store, "crash"), _queue(store, "bad_input"), _queue(store, "sleepy")
        runner.submit(ok)
        seen_progress: list[float] = []

        def done() -> bool:
            seen_progress.append(store.get_job(ok.job_id).progress)
            return all(store.get_job(j.job_id).state in ("succeeded", "failed")
                       for j in (crash, bad, ok))

        _wait(done, 60)
        c = store.get_job(crash.job_id)
        assert c.state == "failed" and "exited unexpectedly with code 7" in (c.error or "")
        b = store.get_job(bad.job_id)
        assert b.state == "failed" and b.error == "the mesh has no faces"
        assert store.get_object(b.object_id).state == "failed"
        assert store.get_job(ok.job_id).state == "succeeded"
        assert max(seen_progress) > 0.1  # progress was written while it ran
        assert runner.is_running()  # a crashing job did not take the runner down
    finally:
        runner.stop()
    assert not runner.is_running()


def test_cancel_queued_running_and_cancel_ignoring_jobs_with_one_worker(tmp_path: Path) -> None:
    store = ModelStore(tmp_path)
    runner = LocalJobRunner(store, workers=1, tasks=TEST_TASKS, poll_interval_s=0.1,
                            cancel_grace_s=0.5)
    runner.start()
    try:
        first, second, third = (_queue(store, "sleepy"), _queue(store, "sleepy"),
                                _queue(store, "ignores_cancel"))
        runner.submit(first)
        _wait(lambda: store.get_job(first.job_id).progress > 0)
        # Bounded concurrency: one worker, so the others wait queued.
        assert store.get_job(second.job_id).state == "queued"
        runner.cancel(second.job_id)
        assert store.get_job(second.job_id).state == "cancelled"
        runner.cancel(first.job_id)
        _wait(lambda: store.get_job(first.job_id).state == "cancelled", 15)
        assert store.get_job(second.job_id).started_at is None
        _wait(lambda: store.get_job(third.job_id).stage == "busy in C")
        t = time.monotonic()
        runner.cancel(third.job_id)
        _wait(lambda: store.get_job(third.job_id).state == "cancelled", 15)
        assert time.monotonic() - t < 10  # killed after the grace, not after its 60 s
        assert runner.running_jobs() == []
    finally:
        runner.stop()
