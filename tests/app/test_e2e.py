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
from tests.app.learned import BARBELL, LearnedStore, learned_barbell
from viewloc_client import ConflictError, ViewlocClient
from viewloc_core.camera import Camera
from viewloc_core.pose import Pose

__all__ = ["learned_barbell"]


@pytest.mark.slow
def test_learn_and_localize_barbell_through_http(
    learned_barbell: LearnedStore, make_server: Callable[..., LiveServer], tmp_path: Path
) -> None:
    from viewloc_core.localize import LocalizeOptions, localize
    from viewloc_core.mesh import load_mesh
    from viewloc_core.render import Renderer

    # The barbell was uploaded and learned through the service once per session.
    created_obj, created_job = learned_barbell.created
    assert created_obj.state == "learning" and created_job.state in ("queued", "running")
    assert any(0 < p < 1 and stage.startswith("rendering view") for p, stage in
               learned_barbell.progress_seen)
    done = learned_barbell.job
    assert done["state"] == "succeeded" and done["progress"] == 1.0 and done["stage"] == "done"
    ready = learned_barbell.obj
    assert ready["state"] == "ready" and ready["training_views"] == 42
    assert ready["model_views"] > 1 and ready["source"] == "mesh"

    learned_barbell.copy_to(tmp_path / "var")
    srv = make_server()
    object_id = learned_barbell.object_id
    mesh = load_mesh(BARBELL)
    cam = Camera(600.0, 600.0, 191.5, 143.5, 384, 288)
    truth = Pose.from_euler_xyz_deg(np.array([35.0, -20.0, 15.0]), np.array([15.0, -10.0, 700.0]))
    with Renderer() as renderer:
        scene = renderer.render(mesh, cam, truth, background_rgb=(40, 40, 40)).color
    ok, buf = cv2.imencode(".png", scene[:, :, ::-1])
    assert ok
    with ViewlocClient(srv.url) as client:
        assert client.get_object(object_id).state == "ready"
        loc = client.localize(object_id, buf.tobytes(), cam, overlay=True)
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
        # The frame as pixels (sent as BMP) is the same image to the service,
        # colour order included; a 16-bit grey frame (sent as TIFF) finds the part too.
        as_array = client.localize(object_id, scene, cam)
        assert as_array.detections[0]["pose"] == det["pose"]
        assert as_array.detections[0]["score"] == det["score"]
        grey16 = cv2.cvtColor(scene, cv2.COLOR_RGB2GRAY).astype(np.uint16) * 257
        det16 = client.localize(object_id, grey16, cam).detections[0]
        assert np.linalg.norm(np.array(det16["pose"]["t_mm"]) - truth.t_m2c) < 0.05 * 700
        many = client.localize(None, buf.tobytes(), cam)
        assert many.object_ids == [object_id]
        assert many.detections[0]["object_id"] == object_id
        # Where the part is and is not (the client's roi and depth_mm).
        u, v = cam.project(truth.t_m2c[None])[0]
        there = client.localize(object_id, buf.tobytes(), cam,
                                roi=(int(u) - 50, int(v) - 40, 100, 80), depth_mm=(600.0, 800.0))
        assert there.detections[0]["pose"] == det["pose"]
        farther = client.localize(object_id, buf.tobytes(), cam, depth_mm=(1000.0, 2000.0),
                                  max_detections=3).detections
        assert all(1000.0 <= d["pose"]["t_mm"][2] <= 2000.0 for d in farther)

        # Latency: the same localization directly on the core vs through HTTP.
        model = ModelStore(tmp_path / "var").load_model(object_id)
        t = time.perf_counter()
        localize(model, scene, cam, LocalizeOptions())
        direct_ms = (time.perf_counter() - t) * 1000
        t = time.perf_counter()
        client.localize(object_id, buf.tobytes(), cam)
        http_ms = (time.perf_counter() - t) * 1000
        print(f"\nlocalization latency: direct {direct_ms:.0f} ms, HTTP {http_ms:.0f} ms")

        # A corrupted model file is reported (409), never half-used, and the store says why.
        npz = tmp_path / "var" / "objects" / object_id / "model.npz"
        data = bytearray(npz.read_bytes())
        data[len(data) // 2] ^= 0xFF
        npz.write_bytes(bytes(data))
        srv.app.state.store._evict(object_id)
        with pytest.raises(ConflictError, match="corrupt|checksum"):
            client.localize(object_id, buf.tobytes(), cam)
        failed = client.get_object(object_id)
        assert failed.state == "failed" and "checksum" in (failed.error or "")
