"""The Redis/RQ job backend end to end: real redis-server, real HTTP API, real worker processes."""

from __future__ import annotations

import itertools
import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import httpx
import pytest
from redis import Redis
from rq import Queue

from app.jobs.base import JobRunner
from app.jobs.redis_runner import RedisJobRunner, ViewlocWorker
from model_store import JobRecord, ModelStore
from tests.app.conftest import TEST_TASKS, LiveServer
from tests.app.helpers import upload_mesh, wait_job

REPO = Path(__file__).resolve().parents[2]
STALE_S = 3.0
_db_numbers = itertools.count(1)


@pytest.fixture
def redis_url(redis_server: str) -> str:
    """A Redis database of its own for each test (the session server has 64)."""
    return f"{redis_server}/{next(_db_numbers)}"


@pytest.fixture
def start_worker(tmp_path: Path, redis_url: str) -> Iterator[Callable[[], subprocess.Popen[bytes]]]:
    """Start ``viewloc worker`` processes on the test's store and Redis db."""
    procs: list[subprocess.Popen[bytes]] = []

    def start() -> subprocess.Popen[bytes]:
        env = {**os.environ, "VIEWLOC_REDIS_URL": redis_url,
               "VIEWLOC_DATA_DIR": str(tmp_path / "var"),
               "VIEWLOC_JOB_STALE_AFTER_S": str(STALE_S), "VIEWLOC_JOB_CANCEL_GRACE_S": "1",
               "VIEWLOC_LOG_LEVEL": "WARNING", "PYOPENGL_PLATFORM": "egl"}
        log = open(tmp_path / f"worker{len(procs)}.log", "wb")  # noqa: SIM115 (closed by the OS)
        proc = subprocess.Popen([sys.executable, "-m", "viewloc_cli", "worker"], cwd=REPO,
                                env=env, stdout=log, stderr=subprocess.STDOUT)
        procs.append(proc)
        return proc

    yield start
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)  # warm shutdown: the worker unregisters
    for proc in procs:
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


def _wait(pred: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


def _pid_gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    # A zombie is gone for our purpose; it is reaped by its parent or init.
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(") ", 1)[1].startswith("Z")
    except OSError:
        return True


def _redis_server(make_server: Callable[..., LiveServer], redis_url: str,
                  tasks: dict[str, str]) -> LiveServer:
    srv = make_server(tasks=tasks, job_backend="redis", redis_url=redis_url,
                      job_stale_after_s=STALE_S, job_cancel_grace_s=1.0)
    assert isinstance(srv.app.state.runner, RedisJobRunner)
    assert isinstance(srv.app.state.runner, JobRunner)
    return srv


def _queue(srv: LiveServer, kind: str) -> JobRecord:
    """Queue a job of a test kind in the store and hand it to the API's runner."""
    store: ModelStore = srv.app.state.store
    _, job = store.create_object(name=kind, source="mesh", kind=kind, upload=b"x",
                                 upload_suffix="bin", upload_meta={})
    srv.app.state.runner.submit(job)
    return job


def test_worker_learns_through_the_api_cancels_and_records_dead_horses(
    make_server: Callable[..., LiveServer], redis_url: str,
    start_worker: Callable[[], subprocess.Popen[bytes]],
) -> None:
    srv = _redis_server(make_server, redis_url, TEST_TASKS)
    store: ModelStore = srv.app.state.store
    with httpx.Client(base_url=srv.url, timeout=30) as client:
        assert client.get("/readyz").status_code == 200
        # Enqueued before any worker exists: it waits in the queue.
        spec = {"name": "box", "units": "mm",
                "learning": {"max_level": 0, "min_level": 0, "contour_level": 1,
                             "object_px": 64}}
        r = client.post("/v1/objects", files={"mesh": ("box.stl", _box(), "model/stl")},
                        data={"spec": json.dumps(spec)})
        assert r.status_code == 202, r.text
        job_id, object_id = r.json()["job"]["job_id"], r.json()["object"]["object_id"]
        time.sleep(0.3)
        assert client.get(f"/v1/jobs/{job_id}").json()["state"] == "queued"
        # Redis loses its messages (restart without persistence): the store is
        # the truth, and the API's reconciliation enqueues the job again.
        queue = srv.app.state.runner.bridge.queue
        assert queue.count == 1
        srv.app.state.runner.connection.flushdb()
        _wait(lambda: queue.count == 1, 3 * STALE_S, "the job to be enqueued again")

        start_worker()
        job = wait_job(client, job_id, timeout=40)
        assert job["state"] == "succeeded", job
        obj = client.get(f"/v1/objects/{object_id}").json()
        assert obj["state"] == "ready" and obj["model_views"] > 0, obj
        assert store.get_job(job_id).owner is not None  # claimed by the worker's runner id

        # A job that ignores cancellation: the worker kills its horse after the grace.
        ignoring = _queue(srv, "ignores_cancel")
        _wait(lambda: store.get_job(ignoring.job_id).stage == "busy in C", 20, "ignoring start")
        t0 = time.monotonic()
        assert client.delete(f"/v1/jobs/{ignoring.job_id}").status_code == 200
        done = wait_job(client, ignoring.job_id, timeout=15)
        assert done["state"] == "cancelled", done
        assert time.monotonic() - t0 < 10

        # A horse that dies without a word: failed with the reason, not running forever.
        crash = _queue(srv, "crash")
        done = wait_job(client, crash.job_id, timeout=20)
        assert done["state"] == "failed"
        assert "exited unexpectedly with code 7" in done["error"], done
        assert client.get(f"/v1/objects/{crash.object_id}").json()["state"] == "failed"

        # A horse killed from outside (OOM killer, operator).
        sleepy = _queue(srv, "sleepy")
        _wait(lambda: store.get_job(sleepy.job_id).progress > 0, 20, "sleepy progress")
        pid = store.get_job(sleepy.job_id).pid
        assert pid is not None
        os.kill(pid, signal.SIGKILL)
        done = wait_job(client, sleepy.job_id, timeout=15)
        assert done["state"] == "failed" and "killed by signal 9" in done["error"], done

        # Cancelled right after queueing: it ends cancelled whether or not the
        # worker had already taken it.
        quick = _queue(srv, "sleepy")
        srv.app.state.runner.cancel(quick.job_id)
        assert wait_job(client, quick.job_id, timeout=15)["state"] == "cancelled"


def test_killed_worker_job_is_requeued_and_finished_by_another_worker(
    make_server: Callable[..., LiveServer], redis_url: str,
    start_worker: Callable[[], subprocess.Popen[bytes]],
) -> None:
    srv = _redis_server(make_server, redis_url, {**TEST_TASKS, "learn_mesh": TEST_TASKS["sleepy"]})
    store: ModelStore = srv.app.state.store
    first = start_worker()
    with httpx.Client(base_url=srv.url, timeout=30) as client:
        r = upload_mesh(client)
        assert r.status_code == 202, r.text
        job_id = r.json()["job"]["job_id"]
        _wait(lambda: store.get_job(job_id).progress > 0, 25, "the job to run")
        horse = store.get_job(job_id).pid
        assert horse is not None and horse != first.pid

        first.send_signal(signal.SIGKILL)
        first.wait(5)
        # The horse notices its worker is gone and exits, so it cannot race
        # with whoever takes the job next.
        _wait(lambda: _pid_gone(horse), 5, "the orphaned horse to exit")
        # The API's reconciliation sees the dead runner and re-queues the job.
        _wait(lambda: store.get_job(job_id).state == "queued", 3 * STALE_S, "re-queue")
        assert "re-queued" in client.get(f"/v1/jobs/{job_id}").json()["stage"]

        start_worker()
        job = wait_job(client, job_id, timeout=30)
        assert job["state"] == "succeeded", job
        assert store.get_job(job_id).attempts == 2
        assert store.job_counts()["running"] == 0


def test_unreachable_redis_keeps_jobs_queued_and_the_service_unready(
    make_server: Callable[..., LiveServer],
) -> None:
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        dead_url = f"redis://127.0.0.1:{s.getsockname()[1]}/0"
    srv = _redis_server(make_server, dead_url, TEST_TASKS)
    with httpx.Client(base_url=srv.url, timeout=30) as client:
        assert client.get("/healthz").status_code == 200
        assert client.get("/readyz").status_code == 503
        r = upload_mesh(client)
        assert r.status_code == 202, r.text
        assert client.get(f"/v1/jobs/{r.json()['job']['job_id']}").json()["state"] == "queued"


def test_idle_worker_fails_a_job_left_running_under_its_name(tmp_path: Path,
                                                             redis_url: str) -> None:
    store = ModelStore(tmp_path)
    connection = Redis.from_url(redis_url)
    worker = ViewlocWorker([Queue("viewloc", connection=connection)], connection=connection)
    worker.attach(store, "f" * 32, cancel_grace_s=1.0)
    _, job = store.create_object(name="x", source="mesh", kind="sleepy", upload=b"x",
                                 upload_suffix="bin", upload_meta={})
    _, other = store.create_object(name="y", source="mesh", kind="sleepy", upload=b"x",
                                   upload_suffix="bin", upload_meta={})
    assert store.claim_job(job.job_id, worker.owner) is not None
    assert store.claim_job(other.job_id, "e" * 32) is not None
    worker.settle_strays()
    left = store.get_job(job.job_id)
    assert left.state == "failed" and "without recording a result" in (left.error or "")
    assert store.get_job(other.job_id).state == "running"  # another runner's job
    connection.close()


def test_worker_process_imports_neither_fastapi_nor_gl() -> None:
    code = ("import sys, app.jobs.redis_runner, viewloc_cli.main, tests.app.job_funcs\n"
            "bad = [m for m in ('fastapi', 'starlette', 'pyrender', 'OpenGL', 'uvicorn')"
            " if m in sys.modules]\n"
            "assert not bad, bad\n")
    subprocess.run([sys.executable, "-c", code], cwd=REPO, check=True, timeout=60)


def _box() -> bytes:
    import trimesh

    return bytes(trimesh.creation.box((40.0, 20.0, 10.0)).export(file_type="stl"))
