"""One barbell learned through HTTP per test session, copied into each test's store.

Learning is the slow part of the HTTP tests; every test that needs a ready
object starts its own server on a private copy of a store in which the
barbell was learned once (upload, job, model, all through the service), so
tests stay independent (one may corrupt its copy) without learning again.

Import the fixture into a test module with ``from tests.app.learned import
learned_barbell``; the learning itself is cached here, so modules and folders
that each register the fixture still share one learned model.
"""

from __future__ import annotations

import shutil
import sqlite3
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest

from app.settings import Settings
from model_store import ModelStore
from tests.app.conftest import start_server
from viewloc_bench.localizers import bench_object_name
from viewloc_client import JobInfo, ObjectInfo, ViewlocClient

BARBELL = Path(__file__).resolve().parents[2] / "viewloc_bench" / "assets" / "barbell.stl"
#: Level 1 of the view sphere (42 views) keeps learning to a few seconds.
LEARNING: dict[str, object] = {"max_level": 1, "min_level": 1, "seed": 0}


#: The name the benchmark's HTTP backend gives this mesh with these options, so
#: its reuse of a learned object can be tested on a copy of this store.
BENCH_NAME = bench_object_name("barbell", BARBELL.read_bytes(), LEARNING)


@dataclass(frozen=True)
class LearnedStore:
    """A store root with the barbell learned, and what the service answered while learning.

    Attributes
    ----------
    root : Path
        Store root to copy (never serve it directly).
    object_id : str
    created : (ObjectInfo, JobInfo)
        Answer of ``POST /v1/objects``.
    job : dict
        The finished job as ``GET /v1/jobs/{id}`` showed it.
    obj : dict
        The ready object as ``GET /v1/objects/{id}`` showed it.
    progress_seen : list of (float, str)
        (progress, stage) pairs polled while the job ran.
    """

    root: Path
    object_id: str
    created: tuple[ObjectInfo, JobInfo]
    job: dict[str, Any]
    obj: dict[str, Any]
    progress_seen: list[tuple[float, str]]

    def copy_to(self, dest: Path) -> Path:
        """A private copy of the store at ``dest`` (which must not exist yet)."""
        shutil.copytree(self.root, dest,
                        ignore=shutil.ignore_patterns("store.sqlite*", "store.lock"))
        # The database goes through SQLite's backup API: a WAL database is
        # more than its main file.
        with sqlite3.connect(self.root / "store.sqlite") as src, \
                sqlite3.connect(dest / "store.sqlite") as dst:
            src.backup(dst)
        return dest


_CACHE: dict[str, LearnedStore] = {}


def _learn(root: Path) -> LearnedStore:
    srv = start_server(Settings(data_dir=root, log_json=True, job_stale_after_s=5.0))
    try:
        with ViewlocClient(srv.url) as client:
            created_obj, created_job = client.learn_mesh(BARBELL, name=BENCH_NAME,
                                                         learning=LEARNING)
            seen: list[tuple[float, str]] = []
            deadline = time.monotonic() + 180
            while True:
                job = client.get_job(created_job.job_id)
                seen.append((job.progress, job.stage))
                if job.done:
                    break
                assert time.monotonic() < deadline, f"learning stuck: {job}"
                time.sleep(0.1)
            job_json = httpx.get(f"{srv.url}/v1/jobs/{job.job_id}").json()
            obj_json = httpx.get(f"{srv.url}/v1/objects/{created_obj.object_id}").json()
    finally:
        srv.stop()
    assert job_json["state"] == "succeeded", job_json
    return LearnedStore(root, created_obj.object_id, (created_obj, created_job), job_json,
                        obj_json, seen)


@pytest.fixture(scope="session")
def learned_barbell(tmp_path_factory: pytest.TempPathFactory) -> LearnedStore:
    """A store with the barbell learned through HTTP (copy it with ``copy_to``)."""
    if "barbell" not in _CACHE:
        _CACHE["barbell"] = _learn(tmp_path_factory.mktemp("learned") / "var")
    return _CACHE["barbell"]


def another_barbell(root: Path, object_id: str,
                    change: Callable[[Any], Any] | None = None) -> str:
    """A second ready object in the store at ``root``, with the barbell's
    model (``change(model)`` when given), stored through the steps a learning
    job takes, so its checksum is valid (no server may have the store open
    yet: its runner would claim the job)."""
    store = ModelStore(root)
    model = store.load_model(object_id)
    if change is not None:
        model = change(model)
    obj, job = store.create_object(name="barbell again", source="mesh", kind="learn_mesh",
                                   upload=BARBELL.read_bytes(), upload_suffix="bin",
                                   upload_meta={})
    assert store.claim_job(job.job_id, "f" * 32) is not None
    assert store.save_model(obj.object_id, job.job_id, model)
    return obj.object_id
