"""POV-Ray scenes in OpenCV camera conventions.

POV-Ray's world is left-handed with y up. We model every scene directly in
the OpenCV camera frame (x right, y down, z forward, mm) and hand POV-Ray the
points ``F @ p`` with ``F = diag(1, -1, 1)``: flipping y turns a right-handed
frame with y down into a left-handed one with y up, so POV-Ray's camera at
the origin looking along +z sees exactly what the pinhole ``K`` sees, without
mirroring. The camera is built from ``K`` explicitly: ``direction`` has length
fx (pixels) and points at the principal point, ``right`` spans the image
width in pixels and ``up`` its height scaled by fx / fy, so that POV-Ray's
ray through pixel centre ``(u, v)`` (OpenCV coordinates) is
``(u - cx, v - cy) / (fx, fy)``. ``tests/viewloc_bench/test_povray.py``
checks this to 0.5 px and against pyrender's mask.
"""

from __future__ import annotations

import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from PIL import Image

from viewloc_core.camera import Camera
from viewloc_core.pose import Pose

Array = NDArray[np.float64]

FLIP_Y = np.diag([1.0, -1.0, 1.0])


class PovRayError(RuntimeError):
    """POV-Ray is missing or failed to render a scene."""


def povray_executable() -> str | None:
    """Path of the ``povray`` program, or None when it is not installed."""
    return shutil.which("povray")


def vec(p: NDArray[np.floating] | tuple[float, ...] | list[float]) -> str:
    """SDL vector ``<a, b, c>``."""
    return "<" + ", ".join(f"{float(c):.6f}" for c in np.asarray(p).reshape(-1)) + ">"


def cam_point(p_cam: NDArray[np.floating]) -> str:
    """SDL vector of a point given in the OpenCV camera frame (mm)."""
    return vec(FLIP_Y @ np.asarray(p_cam, dtype=np.float64).reshape(3))


def camera_sdl(camera: Camera) -> str:
    """POV-Ray perspective camera equivalent to the pinhole ``camera`` (no distortion).

    POV-Ray shoots the ray of pixel column ``i`` through
    ``direction + ((i + 0.5) / W - 0.5) * right``, and of row ``j`` through
    ``(0.5 - (j + 0.5) / H) * up``. With ``right = <W, 0, 0>`` and
    ``up = <0, H fx / fy, 0>``, the offsets of ``direction`` below make that
    ray proportional to ``((i - cx) / fx, -(j - cy) / fy, 1)`` in POV-Ray's
    y-up frame, i.e. OpenCV's ray through ``(i, j)``.
    """
    W, H = camera.width, camera.height
    dx = W / 2.0 - 0.5 - camera.cx
    dy = (camera.cy - H / 2.0 + 0.5) * camera.fx / camera.fy
    return (
        "camera {\n perspective\n location <0, 0, 0>\n"
        f" direction {vec((dx, dy, camera.fx))}\n"
        f" right {vec((W, 0.0, 0.0))}\n"
        f" up {vec((0.0, H * camera.fx / camera.fy, 0.0))}\n}}"
    )


def pose_matrix_sdl(pose: Pose) -> str:
    """SDL ``matrix`` placing an object given in its own frame at ``pose`` (object -> camera).

    POV-Ray applies ``matrix <m00..m32>`` to row vectors, ``p' = p @ M[:3] + M[3]``,
    so the 3x3 block is the transpose of the column-vector map ``F @ R``.
    """
    A = FLIP_Y @ pose.R_m2c
    t = FLIP_Y @ pose.t_m2c
    vals = list(A.T.reshape(-1)) + list(t)
    return "matrix <" + ", ".join(f"{v:.9f}" for v in vals) + ">"


def scene_header(camera: Camera, background_rgb: tuple[float, float, float] = (0, 0, 0)) -> str:
    """Version, linear gamma, background and camera."""
    return (
        "#version 3.7;\n"
        "global_settings { assumed_gamma 1.0 max_trace_level 6 }\n"
        f"background {{ rgb {vec(background_rgb)} }}\n"
        f"{camera_sdl(camera)}\n"
    )


def render(
    sdl: str,
    width: int,
    height: int,
    antialias: float | None = 0.3,
    quality: int = 9,
    threads: int = 2,
    timeout_s: float = 300.0,
) -> NDArray[np.uint8]:
    """Ray-trace a scene and return the image.

    Parameters
    ----------
    sdl : str
        Complete scene description.
    width, height : int
        Image size in pixels.
    antialias : float or None
        Adaptive anti-aliasing threshold (POV-Ray ``+A``); None renders one
        ray per pixel centre (for label images).
    quality : int
        POV-Ray quality 0..11 (``+Q``).
    threads : int
        Render threads (``+WT``); keep it small on a shared machine.
    timeout_s : float
        Kill POV-Ray after this long.

    Returns
    -------
    (height, width, 3) uint8
        RGB image, sRGB encoded.
    """
    exe = povray_executable()
    if exe is None:
        raise PovRayError("povray is not installed (scripts/setup.sh installs it)")
    with tempfile.TemporaryDirectory(prefix="viewloc-pov-") as tmp:
        scene = Path(tmp) / "scene.pov"
        out = Path(tmp) / "out.png"
        scene.write_text(sdl)
        args = [
            exe,
            f"+I{scene.name}",
            f"+O{out.name}",
            f"+W{width}",
            f"+H{height}",
            "-D",
            "+FN8",
            f"+Q{quality}",
            f"+WT{max(1, threads)}",
            "-GA",
            "-P",
        ]
        args += [f"+A{antialias}", "+AM2", "+R3"] if antialias is not None else ["-A"]
        try:
            proc = subprocess.run(
                args, cwd=tmp, capture_output=True, text=True, timeout=timeout_s, check=False
            )
        except subprocess.TimeoutExpired as exc:
            raise PovRayError(f"povray timed out after {timeout_s} s") from exc
        if proc.returncode != 0 or not out.exists():
            raise PovRayError(f"povray failed ({proc.returncode}): {proc.stderr[-2000:]}")
        with Image.open(out) as im:
            return np.asarray(im.convert("RGB"), dtype=np.uint8).copy()
