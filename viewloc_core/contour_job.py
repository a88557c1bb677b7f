"""The contour model of a mesh, built in a child process while learning
renders the training views.

Learning from a mesh renders its training views one after another (Mesa's
llvmpipe keeps about 1.2 of the 2 cores busy), then the contour model's
views (:func:`viewloc_core.learn.contour_of`: 642 depth renders and their
contour points, about a third of the time). The contour model needs
nothing the training views give, so a child process builds it meanwhile on
the core they leave idle. A process, not a thread: two renderers on two
threads of one process, with OpenCV running beside them, crashed it now and
then (see ``learn_from_mesh``).

The child is the same Python running this module (``_main``); the mesh and
the settings go to it in a file, the contour model comes back in another
(a temporary folder). When it fails, :meth:`ContourJob.result` says why and
returns None, and the caller builds the model itself: learning never
depends on the child.
"""

from __future__ import annotations

import os
import pickle
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING

import trimesh

if TYPE_CHECKING:
    from viewloc_core.contour_model import ContourModel
    from viewloc_core.learn import LearningConfig

#: Characters of the child's error output quoted when it fails.
_ERROR_TAIL_CHARS = 2000

#: The package's folder, first on the child's path: the child runs the same
#: code as this process, whatever the working folder holds.
_PACKAGE_ROOT = str(Path(__file__).resolve().parent.parent)

#: How often the child checks that its parent still runs, seconds.
_PARENT_POLL_S = 0.5

#: The child's program: import this module from the same place and run it.
_CHILD_CODE = ("import sys; sys.path.insert(0, sys.argv[1]); "
               "from viewloc_core.contour_job import _main; _main()")


class ContourJob:
    """A contour model being built by a child process.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The part, centred as the training views see it, mm.
    config : LearningConfig
    d0_mm, f_px : float
        Distance and focal length of the training camera.
    size_px : int
        Side of the training views, pixels.
    python : str
        The interpreter to run; this one by default.
    """

    def __init__(self, mesh: trimesh.Trimesh, config: LearningConfig, d0_mm: float,
                 f_px: float, size_px: int, python: str = sys.executable) -> None:
        self.process: subprocess.Popen[bytes] | None = None
        self.failure: str | None = None
        self._folder: tempfile.TemporaryDirectory[str] | None = None
        try:
            # Files, not pipes: the parent goes on rendering at once instead
            # of waiting for the child to start and read.
            self._folder = tempfile.TemporaryDirectory(prefix="viewloc-contour-")
            folder = Path(self._folder.name)
            (folder / "job.pkl").write_bytes(pickle.dumps(
                (mesh, config, d0_mm, f_px, size_px), protocol=pickle.HIGHEST_PROTOCOL))
            with (folder / "errors.txt").open("wb") as errors:
                self.process = subprocess.Popen(
                    [python, "-c", _CHILD_CODE, _PACKAGE_ROOT, str(folder / "job.pkl"),
                     str(folder / "contour.pkl"), str(os.getpid())],
                    stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=errors)
        except OSError as exc:  # no temporary folder, no such interpreter
            self.failure = f"the contour process did not start: {exc}"
            self._close()

    def __enter__(self) -> ContourJob:
        return self

    def __exit__(self, *exc: object) -> None:
        self.cancel()

    def result(self) -> ContourModel | None:
        """The contour model, once the child is done; None when it failed
        (``failure`` says why)."""
        if self.process is None or self._folder is None:
            return None
        folder = Path(self._folder.name)
        code = self.process.wait()
        try:
            if code != 0:
                tail = (folder / "errors.txt").read_text(errors="replace")
                self.failure = (f"the contour process exited with {code}: "
                                f"{tail[-_ERROR_TAIL_CHARS:]}")
                return None
            model: ContourModel = pickle.loads((folder / "contour.pkl").read_bytes())
            return model
        finally:
            self._close()

    def cancel(self) -> None:
        """Stop the child (learning was cancelled or failed) and remove its files."""
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait()
        self._close()

    def _close(self) -> None:
        if self._folder is not None:
            self._folder.cleanup()
            self._folder = None


def _main() -> None:
    """The child: read the mesh and settings from the file ``argv[2]``, write
    the contour model to the file ``argv[3]``; stop when the process
    ``argv[4]`` (the parent) is gone."""
    job_path, out_path, parent_pid = Path(sys.argv[2]), Path(sys.argv[3]), int(sys.argv[4])
    threading.Thread(target=_exit_with_parent, args=(parent_pid, job_path.parent),
                     daemon=True).start()
    from viewloc_core.learn import contour_of
    from viewloc_core.render import Renderer

    mesh, config, d0_mm, f_px, size_px = pickle.loads(job_path.read_bytes())
    with Renderer() as renderer:
        model = contour_of(mesh, config, renderer, d0_mm, f_px, size_px)
    out_path.write_bytes(pickle.dumps(model, protocol=pickle.HIGHEST_PROTOCOL))


def _exit_with_parent(parent_pid: int, folder: Path) -> None:
    """Wait for the parent to end, then remove the job's files and exit.

    A learning job killed from outside (the job runner's terminate or kill
    on a stop or an ignored cancellation) cannot stop its child: without
    this the child would finish the model for no one and leave its files.
    """
    while os.getppid() == parent_pid:
        time.sleep(_PARENT_POLL_S)
    shutil.rmtree(folder, ignore_errors=True)
    os._exit(1)
