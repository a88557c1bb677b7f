"""The load test against `viewloc serve --workers 2` (local job runner in each HTTP worker)."""

from __future__ import annotations

import json
import math
import os
import signal
import socket
import sqlite3
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest
import trimesh

from viewloc_bench.load import (
    LevelResult,
    format_table,
    main,
    require_loopback,
    run_level,
    set_images,
)

REPO = Path(__file__).resolve().parents[2]
CAMERA = {"fx": 500.0, "fy": 500.0, "cx": 159.5, "cy": 119.5}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def served(tmp_path: Path) -> Iterator[tuple[str, Path]]:
    """`viewloc serve` with two HTTP worker processes on a fresh store."""
    port = _free_port()
    data = tmp_path / "var"
    env = {**os.environ, "VIEWLOC_DATA_DIR": str(data), "VIEWLOC_HTTP_WORKERS": "2",
           "VIEWLOC_LOG_LEVEL": "WARNING", "VIEWLOC_JOB_BACKEND": "local",
           "PYOPENGL_PLATFORM": "egl"}
    log = open(tmp_path / "serve.log", "wb")  # noqa: SIM115 (closed after the server)
    proc = subprocess.Popen([sys.executable, "-m", "viewloc_cli", "serve", "--host", "127.0.0.1",
                             "--port", str(port)], cwd=REPO, env=env, stdout=log,
                            stderr=subprocess.STDOUT, start_new_session=True)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                if httpx.get(f"{url}/readyz", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            assert proc.poll() is None and time.monotonic() < deadline, "serve did not start"
            time.sleep(0.1)
        yield url, data
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(5)
        log.close()


def _runner_count(data: Path) -> int:
    with sqlite3.connect(data / "store.sqlite") as conn:
        return int(conn.execute("SELECT count(*) FROM runners").fetchone()[0])


def _png(width: int = 320, height: int = 240) -> bytes:
    img = np.full((height, width, 3), 40, np.uint8)
    cv2.rectangle(img, (110, 80), (210, 160), (220, 220, 220), -1)
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return bytes(buf.tobytes())


def test_serve_with_two_workers_learns_once_and_measures(
    served: tuple[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    url, data = served
    mesh = bytes(trimesh.creation.box((40.0, 20.0, 10.0)).export(file_type="stl"))
    spec = {"name": "box", "units": "mm",
            "learning": {"max_level": 0, "min_level": 0, "contour_level": 1,
                         "object_px": 64}}
    with httpx.Client(base_url=url, timeout=30) as client:
        r = client.post("/v1/objects", files={"mesh": ("box.stl", mesh, "model/stl")},
                        data={"spec": json.dumps(spec)})
        assert r.status_code == 202, r.text
        object_id, job_id = r.json()["object"]["object_id"], r.json()["job"]["job_id"]
        deadline = time.monotonic() + 60
        while (job := client.get(f"/v1/jobs/{job_id}").json())["state"] not in (
                "succeeded", "failed", "cancelled"):
            assert time.monotonic() < deadline, job
            time.sleep(0.2)
        assert job["state"] == "succeeded", job
    # Both HTTP processes run a job runner; they share the queue through the
    # store, so the job ran exactly once and neither took the other's work.
    assert _runner_count(data) == 2
    with sqlite3.connect(data / "store.sqlite") as conn:
        attempts = conn.execute("SELECT attempts FROM jobs WHERE job_id=?", (job_id,)).fetchone()
    assert attempts[0] == 1

    # Two clients at once: concurrent requests share one process's thread pool.
    result = run_level(url, object_id, [_png()], CAMERA, concurrency=2, requests=6,
                       options={"max_detections": 1, "refine": False})
    assert isinstance(result, LevelResult)
    assert (result.requests, result.ok, result.errors) == (6, 6, 0)
    assert 0 < result.p50_ms <= result.p95_ms and result.rps > 0
    assert math.isfinite(result.server_ms) and result.server_ms <= result.p95_ms
    assert "req/s" in format_table([result])

    image = tmp_path / "scene.png"
    image.write_bytes(_png())
    out = tmp_path / "load.json"
    code = main(["--url", url, "--object-id", object_id, "--images", str(image),
                 "--camera", json.dumps(CAMERA), "--concurrency", "1", "--requests", "3",
                 "--warmup", "1", "--no-refine", "--json", str(out)])
    assert code == 0
    report = json.loads(out.read_text())
    assert [lvl["concurrency"] for lvl in report["levels"]] == [1]
    assert report["levels"][0]["ok"] == 3
    assert "req/s" in capsys.readouterr().out


def test_load_refuses_remote_targets_and_unbounded_runs() -> None:
    assert require_loopback("http://127.0.0.1:8000/") == "http://127.0.0.1:8000"
    assert require_loopback("http://localhost:9") == "http://localhost:9"
    assert require_loopback("http://[::1]:8000") == "http://[::1]:8000"
    for bad in ("http://10.0.0.5:8000", "http://example.com", "ftp://127.0.0.1"):
        with pytest.raises(ValueError):
            require_loopback(bad)
    assert main(["--url", "http://192.0.2.1:8000"]) == 2
    with pytest.raises(ValueError, match="requests"):
        run_level("http://127.0.0.1:1", "x", [b"x"], CAMERA, concurrency=1, requests=10**6)
    with pytest.raises(ValueError, match="concurrency"):
        run_level("http://127.0.0.1:1", "x", [b"x"], CAMERA, concurrency=0, requests=1)


def test_set_images_reads_present_targets_and_camera(tmp_path: Path) -> None:
    (tmp_path / "a.png").write_bytes(b"A")
    (tmp_path / "b.png").write_bytes(b"B")
    gt = {"camera": {"fx": 1.0, "fy": 2.0, "cx": 3.0, "cy": 4.0, "width": 8, "height": 6},
          "images": [{"file": "a.png", "object": "barbell", "present": True},
                     {"file": "b.png", "object": "barbell", "present": False}]}
    (tmp_path / "gt.json").write_text(json.dumps(gt))
    images, camera = set_images(tmp_path, "barbell")
    assert images == [b"A"]
    assert camera == {"fx": 1.0, "fy": 2.0, "cx": 3.0, "cy": 4.0}
