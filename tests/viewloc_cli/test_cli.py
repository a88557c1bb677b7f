"""The command line: learn a mesh into a folder, match it in a rendered image."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_learn_then_match(tmp_path: Path) -> None:
    from viewloc_core.camera import Camera
    from viewloc_core.mesh import load_mesh
    from viewloc_core.pose import Pose
    from viewloc_core.render import Renderer

    env = {**os.environ, "PYOPENGL_PLATFORM": "egl"}
    mesh_path = ROOT / "viewloc_bench" / "assets" / "barbell.stl"
    out = subprocess.run(
        [sys.executable, "-m", "viewloc_cli", "learn", str(mesh_path), "--units", "mm",
         "-o", str(tmp_path / "model"), "--learning",
         '{"max_level": 0, "min_level": 0, "contour_level": 1}'],
        capture_output=True, text=True, env=env, cwd=ROOT, timeout=180, check=True)
    summary = json.loads(out.stdout.strip().splitlines()[-1])
    assert summary["training_views"] == 12 and len(summary["sha256"]) == 64
    assert "learning" in out.stderr or "%" in out.stderr or "‰" in out.stderr  # tqdm bar
    cam = Camera(600.0, 600.0, 191.5, 143.5, 384, 288)
    truth = Pose.from_euler_xyz_deg(np.array([90.0, 0.0, 0.0]), np.array([0.0, 0.0, 650.0]))
    with Renderer() as r:
        img = r.render(load_mesh(mesh_path), cam, truth, background_rgb=(40, 40, 40)).color
    cv2.imwrite(str(tmp_path / "scene.png"), img[:, :, ::-1])
    out = subprocess.run(
        [sys.executable, "-m", "viewloc_cli", "match", str(tmp_path / "model"),
         str(tmp_path / "scene.png"), "--camera",
         json.dumps({"fx": 600, "fy": 600, "cx": 191.5, "cy": 143.5})],
        capture_output=True, text=True, env=env, cwd=ROOT, timeout=180, check=True)
    answer = json.loads(out.stdout)
    assert answer["image"] == {"width": 384, "height": 288} and answer["timed_out"] is False
    det = answer["detections"][0]
    assert set(det) >= {"score", "log_probability", "model_view", "view", "similarity", "pose",
                        "refined"}
    assert abs(det["pose"]["t_mm"][2] - 650.0) < 0.1 * 650


@pytest.mark.parametrize("bad", ["0", "-1", "nan", "soon"])
def test_match_refuses_a_bad_time_budget(bad: str, capsys: pytest.CaptureFixture[str]) -> None:
    from viewloc_cli.main import build_parser

    with pytest.raises(SystemExit) as exit_info:
        build_parser().parse_args(["match", "model", "scene.png", "--camera", "{}",
                                   "--timeout-ms", bad])
    assert exit_info.value.code == 2
    assert "--timeout-ms: must be a positive number of ms" in capsys.readouterr().err
    assert build_parser().parse_args(["match", "m", "s.png", "--camera", "{}",
                                      "--timeout-ms", "80"]).timeout_ms == 80.0
