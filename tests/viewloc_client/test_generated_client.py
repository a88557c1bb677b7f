"""A client generated from the served /openapi.json by openapi-python-client works."""

from __future__ import annotations

import importlib
import io
import json
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import httpx

from tests.app.conftest import TEST_TASKS, LiveServer
from tests.app.helpers import CAMERA, box_stl, png
from tests.app.learned import LearnedStore, learned_barbell

__all__ = ["learned_barbell"]


def test_generated_client_learns_and_localizes(
    learned_barbell: LearnedStore, make_server: Callable[..., LiveServer], tmp_path: Path
) -> None:
    learned_barbell.copy_to(tmp_path / "var")
    srv = make_server(tasks={**TEST_TASKS, "learn_mesh": TEST_TASKS["sleepy"],
                             "learn_images": TEST_TASKS["sleepy"]}, api_keys="gen-key")
    spec_path = tmp_path / "openapi.json"
    spec_path.write_text(httpx.get(f"{srv.url}/openapi.json",
                                   headers={"Authorization": "Bearer gen-key"}).text)
    out = tmp_path / "viewloc_generated"
    exe = shutil.which("openapi-python-client") or str(
        Path(sys.executable).parent / "openapi-python-client")
    subprocess.run([exe, "generate", "--path", str(spec_path), "--meta", "none",
                    "--output-path", str(out)], check=True, capture_output=True, timeout=120)
    sys.path.insert(0, str(tmp_path))
    try:
        gen = importlib.import_module("viewloc_generated")
        create = importlib.import_module(
            "viewloc_generated.api.objects.create_object_v1_objects_post")
        localize = importlib.import_module(
            "viewloc_generated.api.localization.localize_object_v1_objects_object_id_localize_post")
        models = importlib.import_module("viewloc_generated.models")
        types = importlib.import_module("viewloc_generated.types")
        client = gen.AuthenticatedClient(base_url=srv.url, token="gen-key")
        body = models.BodyCreateObjectV1ObjectsPost(
            mesh=types.File(payload=io.BytesIO(box_stl()), file_name="box.stl"),
            spec=json.dumps({"name": "generated"}))
        created = create.sync_detailed(client=client, body=body)
        assert created.status_code == 202, created.content
        assert isinstance(created.parsed, models.ObjectCreated)
        assert created.parsed.object_.name == "generated"
        object_id = created.parsed.object_.object_id
        loc = localize.sync_detailed(
            object_id, client=client,
            body=models.BodyLocalizeObjectV1ObjectsObjectIdLocalizePost(
                image=types.File(payload=io.BytesIO(png()), file_name="s.png"),
                camera=json.dumps(CAMERA)))
        # Still learning (the test task never makes a model): a well-formed request
        # that passed image and camera validation, answered with a parsed Problem.
        assert loc.status_code == 409, loc.content
        assert isinstance(loc.parsed, models.Problem) and loc.parsed.status == 409
        # From images: a list of files and a JSON spec, as API.md describes.
        from_images = importlib.import_module(
            "viewloc_generated.api.objects.create_object_from_images_v1_objects_from_images_post")
        view = {"azimuth_deg": 10.0, "polar_deg": 80.0, "distance_mm": 500.0}
        images_body = models.BodyCreateObjectFromImagesV1ObjectsFromImagesPost
        made = from_images.sync_detailed(client=client, body=images_body(
            images=[types.File(payload=io.BytesIO(png()), file_name=f"v{i}.png") for i in range(2)],
            masks=[types.File(payload=io.BytesIO(png(channels=1)), file_name=f"m{i}.png")
                   for i in range(2)],
            spec=json.dumps({"name": "photos", "camera": CAMERA, "object_diameter_mm": 60.0,
                             "views": [view, {**view, "inplane_deg": 15.0}]})))
        assert made.status_code == 202, made.content
        assert made.parsed.object_.source == "images" and made.parsed.object_.training_views == 2
        wrong = from_images.sync_detailed(client=client, body=images_body(
            images=[types.File(payload=io.BytesIO(png()), file_name="v.png")],
            spec=json.dumps({"camera": CAMERA, "object_diameter_mm": 60.0, "views": []})))
        assert wrong.status_code == 422 and isinstance(wrong.parsed, models.Problem)
        assert [e.field for e in wrong.parsed.errors] == ["spec.views"]

        # The barbell learned earlier is ready: a real localization, parsed.
        ok = localize.sync_detailed(
            learned_barbell.object_id, client=client,
            body=models.BodyLocalizeObjectV1ObjectsObjectIdLocalizePost(
                image=types.File(payload=io.BytesIO(_barbell_scene()), file_name="s.png"),
                camera=json.dumps(CAMERA), options=json.dumps({"refine": False})))
        assert ok.status_code == 200, ok.content
        assert isinstance(ok.parsed, models.LocalizationOut)
        assert ok.parsed.object_id == learned_barbell.object_id
        assert len(ok.parsed.detections) == 1
        det = ok.parsed.detections[0]
        assert 0 <= det.score <= 1 and len(det.pose.t_mm) == 3 and len(det.pose.r) == 3
        assert abs(det.pose.t_mm[2] - 600.0) < 60.0
        bad = gen.AuthenticatedClient(base_url=srv.url, token="wrong")
        assert create.sync_detailed(client=bad, body=body).status_code == 401
    finally:
        sys.path.remove(str(tmp_path))
        for name in [m for m in sys.modules if m.startswith("viewloc_generated")]:
            del sys.modules[name]


def _barbell_scene() -> bytes:
    """PNG of the barbell 600 mm in front of the helpers' 320x240 camera."""
    import cv2
    import numpy as np

    from tests.app.learned import BARBELL
    from viewloc_core.camera import Camera
    from viewloc_core.mesh import load_mesh
    from viewloc_core.pose import Pose
    from viewloc_core.render import Renderer

    cam = Camera(CAMERA["fx"], CAMERA["fy"], CAMERA["cx"], CAMERA["cy"], 320, 240)
    pose = Pose.from_euler_xyz_deg(np.array([30.0, -15.0, 10.0]), np.array([5.0, 0.0, 600.0]))
    with Renderer() as renderer:
        color = renderer.render(load_mesh(BARBELL), cam, pose, background_rgb=(40, 40, 40)).color
    ok, buf = cv2.imencode(".png", color[:, :, ::-1])
    assert ok
    return bytes(buf.tobytes())
