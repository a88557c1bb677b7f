"""Scale-out job runner on RQ (Redis): the API enqueues, ``viewloc worker`` processes learn.

The store stays the truth about every job; Redis only carries "job X should
run now" messages. That split decides the design:

* An RQ job's id is ``<store job id>-<attempts>``. A job the store re-queues
  after a dead runner gets a fresh RQ id, so a late message about the old
  attempt can never be confused with the new one, and whether the queue holds
  a store job can be answered from the store row alone.
* :class:`QueueBridge` reconciles both sides: it re-queues jobs of dead runners
  in the store (heartbeats, :meth:`ModelStore.recover_orphaned_jobs`) and makes
  sure every ``queued`` store job has a live RQ job (a Redis restart without
  persistence, or an API killed between the store write and the enqueue, loses
  messages; the store does not). The API and every worker run it at start and
  periodically, so a killed worker's job is picked up whichever survives.
* A worker (:class:`ViewlocWorker`) registers in the store's ``runners`` table
  and heartbeats from a thread of its own. Each job runs in a freshly spawned
  work horse (``posix_spawn``, not ``fork``: the same reason the local runner
  uses 'spawn' -- EGL state does not survive a fork, and forking a threaded
  process is unsafe), which calls :func:`app.jobs.execute.execute_job` and
  exits when its worker dies. When a horse ends without recording an outcome
  (killed, crashed) the worker records one; when a job is cancelled and does
  not stop within the grace period the worker kills its horse.

Nothing here imports FastAPI or opens a rendering context at import: the work
horse imports this module.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from redis import Redis
from redis.exceptions import RedisError
from rq import Queue, SpawnWorker
from rq.exceptions import DuplicateJobError, InvalidJobOperation, NoSuchJobError
from rq.job import Job, JobStatus

from app.jobs.execute import execute_job, watch_parent
from app.periodic import Periodic
from app.settings import Settings
from model_store import JobNotFoundError, JobRecord, ModelStore, new_id

log = logging.getLogger("viewloc.jobs")

#: RQ queue the API fills and the workers drain.
QUEUE_NAME = "viewloc"
#: What a work horse calls (a dotted path, so the API never pickles code).
JOB_FUNC = "app.jobs.redis_runner.run_job"
#: Environment of a work horse: the store runner id of the worker that spawned it.
OWNER_ENV = "VIEWLOC_WORKER_OWNER"
#: RQ keeps a finished job's record this long (the store keeps the real one).
RESULT_TTL_S = 3600
FAILURE_TTL_S = 7 * 24 * 3600
#: RQ states after which a message will not be executed any more.
_DONE_STATES = {JobStatus.FINISHED, JobStatus.FAILED, JobStatus.STOPPED, JobStatus.CANCELED}


def rq_job_id(job: JobRecord) -> str:
    """The RQ id of the current attempt of a store job."""
    return f"{job.job_id}-{job.attempts}"


def connect(redis_url: str) -> Redis:
    """A Redis client with bounded timeouts (an unreachable Redis must not hang a request)."""
    client: Redis = Redis.from_url(redis_url, socket_connect_timeout=5, socket_timeout=10,
                                   health_check_interval=30)
    return client


class QueueBridge:
    """Keeps the RQ queue in step with the store's queued jobs.

    Parameters
    ----------
    store : ModelStore
        The shared store (truth about jobs).
    connection : Redis
        Client of the Redis the workers listen to.
    tasks : mapping, optional
        Extra job kinds ("kind" -> "module:function") handed to the workers
        with each job (a fixed table of the server, never user input).
    queue_name : str
        RQ queue name.
    """

    def __init__(self, store: ModelStore, connection: Redis,
                 tasks: Mapping[str, str] | None = None, queue_name: str = QUEUE_NAME) -> None:
        self.store = store
        self.connection = connection
        self.tasks = dict(tasks or {})
        self.queue = Queue(queue_name, connection=connection)

    def enqueue(self, job: JobRecord) -> bool:
        """Put the current attempt of a queued store job on the RQ queue.

        Returns True when a message was enqueued, False when one is already
        live (another API replica or worker got there first).
        """
        rq_id = rq_job_id(job)
        try:
            existing = Job.fetch(rq_id, connection=self.connection)
        except NoSuchJobError:
            existing = None
        if existing is not None:
            if existing.get_status(refresh=False) not in _DONE_STATES:
                return False
            # A finished or failed message of this attempt (e.g. its worker
            # was not a viewloc worker); the store still says queued.
            existing.delete()
        try:
            self.queue.enqueue_call(
                JOB_FUNC, args=(job.job_id, self.tasks or None), job_id=rq_id,
                timeout=-1,  # learning time grows with the mesh; cancellation is the bound
                result_ttl=RESULT_TTL_S, failure_ttl=FAILURE_TTL_S,
                description=f"viewloc {job.kind} job {job.job_id} attempt {job.attempts}",
                unique=True,
            )
        except DuplicateJobError:
            return False
        return True

    def cancel_queued(self, job_id: str) -> None:
        """Drop the RQ message of a store job that was cancelled before it ran."""
        job = self.store.get_job(job_id)
        # Already gone or cancelled is fine: a worker skips a cancelled job anyway.
        with contextlib.suppress(NoSuchJobError, InvalidJobOperation):
            Job.fetch(rq_job_id(job), connection=self.connection).cancel()

    def reconcile(self, stale_after_s: float) -> list[tuple[str, str]]:
        """Re-queue jobs of dead runners, then enqueue every queued store job
        that has no live RQ message. Returns the store's recovery actions."""
        actions = self.store.recover_orphaned_jobs(stale_after_s)
        for job_id, action in actions:
            log.warning("job %s was running on a runner that stopped: %s", job_id, action)
        for job in self.store.list_jobs("queued"):
            if self.enqueue(job):
                log.info("job %s enqueued (attempt %d)", job.job_id, job.attempts)
        return actions


class RedisJobRunner:
    """The API side of the Redis backend: enqueues, cancels, watches for dead workers.

    It executes nothing itself, so several API replicas can each run one.

    Parameters
    ----------
    store : ModelStore
        The shared store.
    redis_url : str
        ``redis://host:port/db`` of the queue.
    tasks : mapping, optional
        Extra job kinds handed to the workers.
    stale_after_s : float
        Heartbeat age after which a worker counts as dead.
    queue_name : str
        RQ queue name.
    """

    def __init__(self, store: ModelStore, redis_url: str,
                 tasks: Mapping[str, str] | None = None, stale_after_s: float = 30.0,
                 queue_name: str = QUEUE_NAME) -> None:
        self.store = store
        self.redis_url = redis_url
        self.stale_after_s = stale_after_s
        self.connection = connect(redis_url)
        self.bridge = QueueBridge(store, self.connection, tasks, queue_name)
        self._loop: Periodic | None = None
        self._redis_ok = False

    def _maintain(self) -> None:
        try:
            self.connection.ping()
            self.bridge.reconcile(self.stale_after_s)
            self._redis_ok = True
        except RedisError as exc:
            if self._redis_ok:
                log.error("Redis at %s unreachable: %s", _safe_url(self.redis_url), exc)
            self._redis_ok = False

    # -- JobRunner ---------------------------------------------------------
    def start(self) -> None:
        """Reconcile store and queue once, then keep doing it in the background.

        A Redis that is down at start does not stop the service: jobs stay
        queued in the store, ``/readyz`` answers 503, and they are enqueued
        once Redis answers.
        """
        if self._loop is not None:
            return
        self._maintain()
        self._loop = Periodic("viewloc-redis-bridge", max(0.5, self.stale_after_s / 3),
                               self._maintain)
        self._loop.start()

    def stop(self) -> None:
        """Stop the background reconciliation (workers keep running their jobs)."""
        if self._loop is None:
            return
        self._loop.stop()
        self._loop = None
        self.connection.close()

    def submit(self, job: JobRecord) -> None:
        """Enqueue a job the store just queued (retried by reconciliation on failure)."""
        try:
            self.bridge.enqueue(self.store.get_job(job.job_id))
            self._redis_ok = True
        except RedisError as exc:
            self._redis_ok = False
            log.error("job %s stays queued until Redis answers: %s", job.job_id, exc)

    def cancel(self, job_id: str) -> None:
        """Cancel in the store; a queued job's message is dropped, a running
        job's worker stops it (cooperatively, else by killing its horse)."""
        job = self.store.request_cancel(job_id)
        if job.state == "cancelled":
            try:
                self.bridge.cancel_queued(job_id)
            except RedisError as exc:  # harmless: the worker skips a cancelled job
                log.warning("could not drop the message of cancelled job %s: %s", job_id, exc)

    def is_running(self) -> bool:
        """True while reconciliation runs and Redis answered the last time."""
        return self._loop is not None and self._loop.is_alive() and self._redis_ok


def build(store: ModelStore, settings: Settings,
          tasks: Mapping[str, str] | None = None) -> RedisJobRunner:
    """Factory named in :data:`app.jobs.factory.BACKENDS`."""
    return RedisJobRunner(store, settings.redis_url, tasks,
                          stale_after_s=settings.job_stale_after_s)


def _safe_url(url: str) -> str:
    """The Redis URL without a password, for logs."""
    scheme, sep, rest = url.partition("://")
    if "@" in rest:
        rest = "***@" + rest.rsplit("@", 1)[1]
    return scheme + sep + rest


# -- work horse ----------------------------------------------------------------
def run_job(job_id: str, tasks: dict[str, str] | None = None) -> str:
    """Entry point of a work horse: execute one store job, return its final state.

    Run by a :class:`ViewlocWorker`, the job is claimed for that worker (which
    heartbeats for it) and the horse exits if the worker dies. Run by a plain
    ``rq worker``, the horse registers and heartbeats as a runner of its own,
    so a killed horse is still detected.
    """
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    data_dir = Settings().data_dir
    owner = os.environ.get(OWNER_ENV)
    if owner:
        watch_parent()
        return execute_job(data_dir, job_id, tasks, owner=owner)
    store = ModelStore(data_dir)
    owner = new_id()
    store.heartbeat(owner)
    beat = Periodic("viewloc-horse-heartbeat", 2.0, lambda: store.heartbeat(owner))
    beat.start()
    try:
        return execute_job(data_dir, job_id, tasks, owner=owner)
    finally:
        beat.stop()
        store.unregister_runner(owner)


def _exit_reason(status: int | None) -> str:
    if status is not None and os.WIFSIGNALED(status):
        return f"the learning process was killed by signal {os.WTERMSIG(status)}"
    if status is not None and os.WIFEXITED(status):
        return f"the learning process exited unexpectedly with code {os.WEXITSTATUS(status)}"
    return "the learning process ended without recording a result"


class ViewlocWorker(SpawnWorker):
    """An RQ worker that is also a runner of the store.

    The parent process never runs a job: it heartbeats in the store, enforces
    cancellation and records the outcome of horses that die without doing so.
    Configure with :meth:`attach` before :meth:`work`.
    """

    store: ModelStore
    owner: str
    cancel_grace_s: float = 5.0
    _store_job_id: str | None = None
    _cancel_seen_at: float | None = None
    _horse_status: int | None = None

    def attach(self, store: ModelStore, owner: str, cancel_grace_s: float) -> None:
        """Bind the worker to the store under runner id ``owner``."""
        self.store, self.owner, self.cancel_grace_s = store, owner, cancel_grace_s
        self._store_job_id = None
        self._cancel_seen_at = None
        # Held while the current job changes and while strays are looked for,
        # so a job that is just starting is never taken for a stray.
        self._job_lock = threading.Lock()

    def handle_work_horse_killed(self, job: Job, retpid: Any, ret_val: Any, rusage: Any) -> None:
        self._horse_status = ret_val
        super().handle_work_horse_killed(job, retpid, ret_val, rusage)

    def execute_job(self, job: Job, queue: Queue) -> None:
        with self._job_lock:
            self._store_job_id = str(job.args[0]) if job.args else None
            self._horse_status, self._cancel_seen_at = None, None
        try:
            super().execute_job(job, queue)
        finally:
            with self._job_lock:
                store_job_id, self._store_job_id = self._store_job_id, None
                if store_job_id is not None:
                    try:
                        self._settle(store_job_id, _exit_reason(self._horse_status))
                    except Exception:  # settle_strays retries from the maintenance thread
                        log.exception("could not record the outcome of job %s", store_job_id)

    def _settle(self, job_id: str, reason: str) -> None:
        """Record an outcome for a job of ours still ``running`` although its horse ended."""
        try:
            record = self.store.get_job(job_id)
        except JobNotFoundError:  # a message of another store
            return
        if record.state != "running" or record.owner != self.owner:
            return
        if record.cancel_requested:
            self.store.finish_job(job_id, "cancelled", "cancelled on request")
            return
        if self.store.finish_job(job_id, "failed", reason):
            log.error("job %s: %s", job_id, reason)

    def settle_strays(self) -> None:
        """Between jobs, no job may be ``running`` for this worker: fail any that is.

        Our heartbeat keeps the store's recovery away from our jobs, so one
        whose outcome could not be recorded when its horse ended would
        otherwise stay running for as long as this worker lives.
        """
        with self._job_lock:
            if self._store_job_id is not None:
                return
            for record in self.store.list_jobs("running"):
                if record.owner == self.owner:
                    self._settle(record.job_id, "the learning process ended without "
                                                "recording a result")

    def enforce_cancellation(self) -> None:
        """Kill the horse of a cancelled job once its grace period is over."""
        job_id = self._store_job_id
        if job_id is None:
            return
        record = self.store.get_job(job_id)
        if record.state != "running" or record.owner != self.owner or not record.cancel_requested:
            return
        now = time.monotonic()
        if self._cancel_seen_at is None:
            self._cancel_seen_at = now
        elif now - self._cancel_seen_at > self.cancel_grace_s and self.horse_pid:
            log.warning("job %s ignored cancellation; killing its process", job_id)
            self.kill_horse(signal.SIGKILL)


def run_worker(settings: Settings, *, burst: bool = False, name: str | None = None,
               queue_name: str = QUEUE_NAME) -> int:
    """Run one worker until SIGTERM/SIGINT (or, with ``burst``, an empty queue).

    Parameters
    ----------
    settings : Settings
        ``redis_url``, ``data_dir``, ``job_stale_after_s``, ``job_cancel_grace_s``
        and ``log_level`` are used.
    burst : bool
        Exit once the queue is empty.
    name : str, optional
        RQ worker name (default: derived from the store runner id).
    """
    logging.basicConfig(level=settings.log_level.upper(),
                        format="%(asctime)s %(levelname)s %(name)s %(message)s")
    data_dir = Path(settings.data_dir).resolve()
    store = ModelStore(data_dir)
    connection = connect(settings.redis_url)
    owner = new_id()
    # The horse is spawned with this environment: it claims jobs for us and
    # reads the same store even when the root came from a command line.
    os.environ[OWNER_ENV] = owner
    os.environ["VIEWLOC_DATA_DIR"] = str(data_dir)
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    worker = ViewlocWorker([Queue(queue_name, connection=connection)], connection=connection,
                           name=name or f"viewloc-{owner[:12]}")
    worker.attach(store, owner, settings.job_cancel_grace_s)
    bridge = QueueBridge(store, connection, queue_name=queue_name)
    stale = settings.job_stale_after_s
    store.heartbeat(owner)
    bridge.reconcile(stale)

    last = {"beat": time.monotonic(), "reconcile": time.monotonic()}

    def step() -> None:
        now = time.monotonic()
        if now - last["beat"] >= min(2.0, stale / 4):
            store.heartbeat(owner)
            last["beat"] = now
        worker.enforce_cancellation()
        if now - last["reconcile"] >= stale / 2:
            last["reconcile"] = now
            worker.settle_strays()
            bridge.reconcile(stale)

    loop = Periodic("viewloc-worker-maintenance", 0.25, step)
    loop.start()
    log.info("viewloc worker %s on %s, store %s", worker.name, _safe_url(settings.redis_url),
             data_dir)
    try:
        worker.work(burst=burst, logging_level=settings.log_level.upper(),
                    with_scheduler=False)
    finally:
        loop.stop()
        store.unregister_runner(owner)
        # A job of ours still running (cold shutdown) goes back to the queue now
        # rather than after the stale timeout.
        try:
            bridge.reconcile(stale)
        except RedisError as exc:
            log.warning("could not hand jobs back to the queue on exit: %s", exc)
    return 0
