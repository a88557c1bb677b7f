"""Embedded job runner: each job in its own spawned process, a bounded number at once.

Why one process per job instead of a ``ProcessPoolExecutor``: a pool cannot
stop one task (cancellation of a running job would need killing a pool
worker, which breaks the whole pool), and a worker that dies (segfault in a
GL driver, ``os._exit``) marks every pending future of the pool as failed. A
process per job gives both isolation and a clean kill. Workers are started
with 'spawn' because EGL contexts do not survive ``fork`` of a process that
has rendered. The queue itself is the store's ``jobs`` table, so queued jobs
survive a restart and several services on one root share it.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from multiprocessing.process import BaseProcess

from app.jobs.execute import child_main
from model_store import JobRecord, ModelStore, new_id

log = logging.getLogger("viewloc.jobs")


@dataclass
class _Running:
    job_id: str
    process: BaseProcess
    cancel_seen_at: float | None = field(default=None)


class LocalJobRunner:
    """Runs queued jobs of ``store`` in at most ``workers`` spawned processes.

    Parameters
    ----------
    store : ModelStore
        Where jobs are queued and their state is recorded.
    workers : int
        Maximum number of jobs executing at once; the rest wait queued.
    tasks : mapping, optional
        Extra job kinds ("kind" -> "module:function").
    poll_interval_s : float
        How often the dispatcher looks at the queue without being woken.
    cancel_grace_s : float
        How long a cancelled job may take to stop by itself before its
        process is terminated.
    stale_after_s : float
        Heartbeat age after which another runner counts as dead.
    """

    def __init__(
        self,
        store: ModelStore,
        workers: int = 1,
        tasks: Mapping[str, str] | None = None,
        poll_interval_s: float = 0.5,
        cancel_grace_s: float = 5.0,
        stale_after_s: float = 30.0,
    ) -> None:
        self.store = store
        self.workers = max(1, int(workers))
        self.tasks = dict(tasks or {})
        self.poll_interval_s = poll_interval_s
        self.cancel_grace_s = cancel_grace_s
        self.stale_after_s = stale_after_s
        self.owner = new_id()
        self._ctx = multiprocessing.get_context("spawn")
        self._running: dict[str, _Running] = {}
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None

    # -- JobRunner ---------------------------------------------------------
    def start(self) -> None:
        """Recover orphaned jobs, then start the dispatcher thread."""
        if self._thread is not None:
            return
        self.store.heartbeat(self.owner)
        for job_id, action in self.store.recover_orphaned_jobs(self.stale_after_s):
            log.warning("job %s left running by a stopped runner: %s", job_id, action)
        self._stopping.clear()
        self._thread = threading.Thread(target=self._loop, name="viewloc-jobs", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 10.0) -> None:
        """Stop dispatching, terminate running workers and re-queue their jobs."""
        if self._thread is None:
            return
        self._stopping.set()
        self._wake.set()
        self._thread.join(timeout_s)
        self._thread = None
        with self._lock:
            running = list(self._running.values())
            self._running.clear()
        for r in running:
            if r.process.is_alive():
                r.process.terminate()
        for r in running:
            r.process.join(timeout_s)
        # The jobs stopped here go back to the queue for the next start,
        # their start not counted (a restart is not their failure).
        # Unregistering makes any left running (asked to cancel) orphans,
        # which the recovery below settles.
        for job_id in self.store.release_jobs(self.owner):
            log.info("job %s re-queued: the service stopped", job_id)
        self.store.unregister_runner(self.owner)
        self.store.recover_orphaned_jobs(self.stale_after_s)

    def submit(self, job: JobRecord) -> None:
        """Wake the dispatcher; the job is already queued in the store."""
        self._wake.set()

    def cancel(self, job_id: str) -> None:
        """Cancel in the store; a running worker sees it or is terminated."""
        self.store.request_cancel(job_id)
        self._wake.set()

    def is_running(self) -> bool:
        """True while the dispatcher thread is alive."""
        return self._thread is not None and self._thread.is_alive()

    def running_jobs(self) -> list[str]:
        """Ids of jobs executing in this runner's workers."""
        with self._lock:
            return list(self._running)

    # -- dispatcher --------------------------------------------------------
    def _loop(self) -> None:
        last_beat = last_recover = time.monotonic()
        while not self._stopping.is_set():
            try:
                now = time.monotonic()
                if now - last_beat >= min(2.0, self.stale_after_s / 4):
                    self.store.heartbeat(self.owner)
                    last_beat = now
                if now - last_recover >= self.stale_after_s / 2:
                    self.store.recover_orphaned_jobs(self.stale_after_s)
                    last_recover = now
                self._reap()
                self._enforce_cancellations()
                self._dispatch()
            except Exception:  # the dispatcher must outlive a busy database
                log.exception("job dispatcher iteration failed")
            self._wake.wait(self.poll_interval_s)
            self._wake.clear()

    def _dispatch(self) -> None:
        while not self._stopping.is_set():
            with self._lock:
                if len(self._running) >= self.workers:
                    return
            job = self.store.claim_next_job(self.owner)
            if job is None:
                return
            process = self._ctx.Process(
                target=child_main,
                args=(str(self.store.root), job.job_id, self.tasks or None),
                name=f"viewloc-job-{job.job_id[:8]}",
                daemon=False,
            )
            try:
                process.start()
            except Exception as exc:
                reason = f"could not start a learning process: {exc}"
                log.error("job %s: %s", job.job_id, reason)
                self.store.finish_job(job.job_id, "failed", reason)
                continue
            with self._lock:
                self._running[job.job_id] = _Running(job.job_id, process)
            log.info("job %s started in process %s", job.job_id, process.pid)

    def _reap(self) -> None:
        with self._lock:
            done = [r for r in self._running.values() if not r.process.is_alive()]
            for r in done:
                del self._running[r.job_id]
        for r in done:
            r.process.join(0)
            code = r.process.exitcode
            # The worker records its own outcome; a job still 'running' here
            # means the process died without doing so.
            if r.cancel_seen_at is not None:
                reason = "cancelled on request"
                if self.store.finish_job(r.job_id, "cancelled", reason):
                    log.info("job %s cancelled (process exit code %s)", r.job_id, code)
                continue
            reason = (f"the learning process was killed by signal {-code}" if code and code < 0
                      else f"the learning process exited unexpectedly with code {code}")
            if self.store.finish_job(r.job_id, "failed", reason):
                log.error("job %s: %s", r.job_id, reason)

    def _enforce_cancellations(self) -> None:
        now = time.monotonic()
        with self._lock:
            running = list(self._running.values())
        for r in running:
            if r.cancel_seen_at is None:
                if self.store.should_stop(r.job_id):
                    r.cancel_seen_at = now
            elif now - r.cancel_seen_at > self.cancel_grace_s and r.process.is_alive():
                log.warning("job %s ignored cancellation; terminating its process", r.job_id)
                r.process.terminate()
                with contextlib.suppress(Exception):
                    r.process.join(2.0)
                if r.process.is_alive():
                    r.process.kill()
