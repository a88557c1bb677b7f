"""The contour model built by a child process: the same model as built here,
a failed child says why and learning builds the model itself, a cancelled
one stops."""

import logging
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from viewloc_core import contour_job
from viewloc_core.contour_job import ContourJob
from viewloc_core.contour_model import ContourModel
from viewloc_core.errors import Cancelled
from viewloc_core.learn import LearningConfig, _canonical_camera, contour_of, learn_from_mesh
from viewloc_core.mesh import mesh_diameter_mm

#: 42 contour views, one training level: a learning of a few seconds.
QUICK = LearningConfig(max_level=0, min_level=0, contour_level=1)


def _centred(mesh):
    centred = mesh.copy()
    centred.apply_translation(-np.asarray(mesh.bounds).mean(axis=0))
    return centred


def _assert_same(a: ContourModel, b: ContourModel) -> None:
    for key, value in a.to_arrays().items():
        np.testing.assert_array_equal(value, b.to_arrays()[key], err_msg=key)


def test_the_child_builds_the_model_this_process_would(bracket_mesh, renderer):
    part = _centred(bracket_mesh)
    camera = _canonical_camera(QUICK, mesh_diameter_mm(bracket_mesh))
    with ContourJob(part, QUICK, *camera) as job:
        built_there = job.result()
    assert built_there is not None, job.failure
    _assert_same(built_there, contour_of(part, QUICK, renderer, *camera))


def test_a_child_that_fails_says_why(bracket_mesh):
    part = _centred(bracket_mesh)
    camera = _canonical_camera(QUICK, mesh_diameter_mm(bracket_mesh))
    with ContourJob(part, QUICK, *camera, python="/bin/false") as job:
        assert job.result() is None
    assert job.failure is not None and "exited with 1" in job.failure
    with ContourJob(part, QUICK, *camera, python="/no/such/python") as job:
        assert job.result() is None
    assert job.failure is not None and "did not start" in job.failure


def test_learning_builds_the_contour_model_itself_when_the_child_fails(
        bracket_mesh, monkeypatch, caplog):
    normal = learn_from_mesh(bracket_mesh, QUICK)
    monkeypatch.setattr(contour_job, "_CHILD_CODE",
                        "import sys; sys.stderr.write('no GPU here'); sys.exit(3)")
    with caplog.at_level(logging.WARNING, logger="viewloc_core.learn"):
        fallen_back = learn_from_mesh(bracket_mesh, QUICK)
    assert "exited with 3: no GPU here" in caplog.text
    assert normal.contour is not None and fallen_back.contour is not None
    _assert_same(ContourModel.from_arrays(fallen_back.contour),
                 ContourModel.from_arrays(normal.contour))


def test_a_cancelled_job_stops_its_child_and_leaves_no_files(bracket_mesh):
    part = _centred(bracket_mesh)
    camera = _canonical_camera(LearningConfig(), mesh_diameter_mm(bracket_mesh))
    job = ContourJob(part, LearningConfig(), *camera)
    folder = Path(job._folder.name)
    assert job.process is not None and folder.is_dir()
    job.cancel()
    assert job.process.returncode is not None and job.process.returncode < 0  # killed
    assert not folder.exists()


def test_cancelled_learning_stops_the_child(bracket_mesh, monkeypatch):
    jobs: list[ContourJob] = []

    class Recorded(ContourJob):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            jobs.append(self)

    monkeypatch.setattr("viewloc_core.learn.ContourJob", Recorded)
    calls = []

    def stop() -> bool:
        calls.append(1)
        return len(calls) > 3

    with pytest.raises(Cancelled):
        learn_from_mesh(bracket_mesh, LearningConfig(), should_stop=stop)
    assert len(jobs) == 1
    process = jobs[0].process
    # Killed: 642 contour views take longer than three training views.
    assert process is not None and process.returncode is not None and process.returncode < 0


def _running(pid: int) -> bool:
    """Whether process ``pid`` still runs (an exited one nobody reaped is a zombie)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return False
    return "\nState:\tZ" not in status


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads /proc")
def test_the_child_of_a_killed_learning_stops_and_leaves_no_files():
    """A learning job killed from outside (the job runner's SIGKILL) cannot
    stop its child itself: the child notices and ends."""
    parent = subprocess.run(
        [sys.executable, "-c", textwrap.dedent("""
            import os, signal, sys
            import trimesh
            from viewloc_core.contour_job import ContourJob
            from viewloc_core.learn import LearningConfig
            job = ContourJob(trimesh.creation.box((40.0, 30.0, 20.0)), LearningConfig(),
                             240.0, 1500.0, 160)
            print(job.process.pid, job._folder.name, flush=True)
            os.kill(os.getpid(), signal.SIGKILL)
        """)], capture_output=True, text=True, timeout=120)
    assert parent.returncode == -signal.SIGKILL, parent.stderr
    pid_text, folder = parent.stdout.split()
    deadline = time.monotonic() + 30.0
    while _running(int(pid_text)) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not _running(int(pid_text))
    assert not Path(folder).exists()
