"""End to end through HTTP: learn the barbell, localize a rendered scene, check the pose."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from model_store import ModelStore
from tests.app.conftest import LiveServer
from viewloc_client import ConflictError, ViewlocClient
from viewloc_core.camera import Camera
from viewloc_core.pose import Pose

BARBELL = Path(__file__).resolve().parents[2] / "viewloc_bench" / "assets" / "barbell.stl"


@pytest.mark.slow
def test_learn_and_localize_barbell_through_http(
    make_server: Callable[..., LiveServer], tmp_path: Path
) -> None:
    from viewloc_core.localize import LocalizeOptions, localize
    from viewloc_core.mesh import load_mesh
    from viewloc_core.render import Renderer

    srv = make_server()
    mesh = load_mesh(BARBELL)
    cam = Camera(600.0, 600.0, 191.5, 143.5, 384, 288)
    truth = Pose.from_euler_xyz_deg(np.array([35.0, -20.0, 15.0]), np.array([15.0, -10.0, 700.0]))
    with Renderer() as renderer:
        scene = renderer.render(mesh, cam, truth, background_rgb=(40, 40, 40)).color
    ok, buf = cv2.imencode(".png", scene[:, :, ::-1])
    assert ok
    with ViewlocClient(srv.url) as client:
        obj, job = client.learn_mesh(BARBELL, name="barbell",
                                     learning={"max_level": 1, "min_level": 1})
        done = client.wait_for_job(job.job_id, timeout=120)
        assert done.progress == 1.0 and done.stage == "done"
        ready = client.get_object(obj.object_id)
        assert ready.state == "ready" and ready.training_views == 42 and ready.model_views > 1
        t = time.perf_counter()
        loc = client.localize(obj.object_id, buf.tobytes(), cam, overlay=True)
        http_ms = (time.perf_counter() - t) * 1000
        assert len(loc.detections) == 1 and (loc.width, loc.height) == (384, 288)
        det = loc.detections[0]
        t_mm = np.array(det["pose"]["t_mm"])
        assert np.linalg.norm(t_mm - truth.t_m2c) < 0.05 * 700
        # The barbell is symmetric about its bar: compare the bar axis, up to sign.
        bar = int(np.argmax(mesh.extents))
        R = np.array(det["pose"]["R"])
        cos = abs(float(R[:, bar] @ truth.R_m2c[:, bar]))
        assert np.degrees(np.arccos(min(1.0, cos))) < 10
        assert {"decode", "total"} <= set(loc.timing_ms)
        assert loc.overlay_png is not None
        overlay = cv2.imdecode(np.frombuffer(loc.overlay_png, np.uint8), cv2.IMREAD_COLOR)
        assert overlay.shape == (288, 384, 3)
        assert np.count_nonzero(np.any(overlay != scene[:, :, ::-1], axis=2)) > 200
        many = client.localize(None, buf.tobytes(), cam)
        assert many.object_ids == [obj.object_id]
        assert many.detections[0]["object_id"] == obj.object_id

        # Latency: the same localization directly on the core vs through HTTP.
        model = ModelStore(tmp_path / "var").load_model(obj.object_id)
        t = time.perf_counter()
        localize(model, scene, cam, LocalizeOptions())
        direct_ms = (time.perf_counter() - t) * 1000
        t = time.perf_counter()
        client.localize(obj.object_id, buf.tobytes(), cam)
        http_ms = (time.perf_counter() - t) * 1000
        print(f"\nlocalization latency: direct {direct_ms:.0f} ms, HTTP {http_ms:.0f} ms")

        # A corrupted model file is reported (409), never half-used, and the store says why.
        npz = tmp_path / "var" / "objects" / obj.object_id / "model.npz"
        data = bytearray(npz.read_bytes())
        data[len(data) // 2] ^= 0xFF
        npz.write_bytes(bytes(data))
        srv.app.state.store._evict(obj.object_id)
        with pytest.raises(ConflictError, match="corrupt|checksum"):
            client.localize(obj.object_id, buf.tobytes(), cam)
        failed = client.get_object(obj.object_id)
        assert failed.state == "failed" and "checksum" in (failed.error or "")
