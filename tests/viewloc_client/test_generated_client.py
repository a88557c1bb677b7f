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


def test_generated_client_learns_and_localizes(
    make_server: Callable[..., LiveServer], tmp_path: Path
) -> None:
    srv = make_server(tasks={**TEST_TASKS, "learn_mesh": TEST_TASKS["sleepy"]}, api_keys="gen-key")
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
        bad = gen.AuthenticatedClient(base_url=srv.url, token="wrong")
        assert create.sync_detailed(client=bad, body=body).status_code == 401
    finally:
        sys.path.remove(str(tmp_path))
        for name in [m for m in sys.modules if m.startswith("viewloc_generated")]:
            del sys.modules[name]
