"""The HTTP contract against a real uvicorn server: shapes, bad input, auth, operations."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import pytest
import trimesh
from openapi_spec_validator import validate

from model_store import ModelStore
from tests.app.conftest import TEST_TASKS, LiveServer, free_port
from tests.app.helpers import (
    CAMERA,
    FAST_LEARNING,
    assert_problem,
    box_stl,
    jpeg,
    png,
    stored_files,
    upload_mesh,
    wait_job,
)
from viewloc_client import ObjectInfo

SLEEPY = {**TEST_TASKS, "learn_mesh": TEST_TASKS["sleepy"]}


def test_object_and_job_lifecycle(make_server: Callable[..., LiveServer]) -> None:
    srv = make_server(tasks=SLEEPY)
    with httpx.Client(base_url=srv.url, timeout=30) as c:
        r = upload_mesh(c)
        assert r.status_code == 202, r.text
        body = r.json()
        obj, job = body["object"], body["job"]
        assert r.headers["location"] == f"/v1/jobs/{job['job_id']}"
        assert set(obj) >= {"object_id", "name", "state", "source", "diameter_mm",
                            "training_views", "model_views", "created_at", "job_id"}
        assert obj["state"] == "learning" and obj["source"] == "mesh" and obj["name"] == "box"
        assert abs(obj["diameter_mm"] - (40**2 + 20**2 + 10**2) ** 0.5) < 1e-6
        assert set(job) == {"job_id", "object_id", "state", "progress", "stage", "error",
                            "created_at", "started_at", "finished_at"}
        # Not ready while learning: 409.
        r = c.post(f"/v1/objects/{obj['object_id']}/localize",
                   files={"image": ("s.png", png(), "image/png")},
                   data={"camera": json.dumps(CAMERA)})
        assert_problem(r, 409)
        done = wait_job(c, job["job_id"])
        assert done["state"] == "succeeded" and done["progress"] == 1.0 or done["progress"] > 0.9
        assert done["finished_at"] and done["started_at"]
        listed = c.get("/v1/objects").json()["objects"]
        assert [o["object_id"] for o in listed] == [obj["object_id"]]
        assert c.get(f"/v1/objects/{obj['object_id']}").json()["job_id"] == job["job_id"]
        assert c.delete(f"/v1/objects/{obj['object_id']}").status_code == 204
        assert_problem(c.get(f"/v1/objects/{obj['object_id']}"), 404)
        assert_problem(c.delete(f"/v1/objects/{obj['object_id']}"), 404)


def test_delete_cancels_running_job(make_server: Callable[..., LiveServer]) -> None:
    srv = make_server(tasks=SLEEPY)
    with httpx.Client(base_url=srv.url, timeout=30) as c:
        created = upload_mesh(c).json()
        job_id = created["job"]["job_id"]
        wait_job(c, job_id, ("running",))
        assert c.delete(f"/v1/objects/{created['object']['object_id']}").status_code == 204
        assert wait_job(c, job_id)["state"] == "cancelled"
        # and cancelling through /v1/jobs answers the (terminal) job unchanged
        r = c.delete(f"/v1/jobs/{job_id}")
        assert r.status_code == 200 and r.json()["state"] == "cancelled"


#: A multipart Content-Type with a boundary, for bodies written by hand.
MULTIPART_ABC = "multipart/form-data; boundary=abc"


def test_bad_input_is_4xx_problem_json_and_leaves_the_store_intact(
    make_server: Callable[..., LiveServer], tmp_path: Path
) -> None:
    srv = make_server(tasks=SLEEPY, max_mesh_bytes=50_000, max_image_bytes=400_000,
                      max_image_pixels=1_000_000, max_images=3)
    with httpx.Client(base_url=srv.url, timeout=30) as c:
        good = upload_mesh(c).json()
        oid = good["object"]["object_id"]
        # Its (test) job writes only to the database, which the comparison leaves out.
        files_before = sorted(p.relative_to(tmp_path) for p in (tmp_path / "var").rglob("*")
                              if p.is_file() and "sqlite" not in p.name)
        image = ("s.png", png(), "image/png")
        cam = json.dumps(CAMERA)
        view = {"azimuth_deg": 0, "polar_deg": 90, "distance_mm": 500}
        photo_spec = {"camera": CAMERA, "object_diameter_mm": 10, "views": [view]}

        def one_photo(changes: dict[str, object], photo: bytes | None = None) -> httpx.Response:
            """POST /v1/objects/from-images with one photo and the spec changed."""
            return c.post("/v1/objects/from-images",
                          files=[("images", ("a.png", photo or png(), "image/png"))],
                          data={"spec": json.dumps({**photo_spec, **changes})})

        loc = f"/v1/objects/{oid}/localize"
        cases: list[tuple[httpx.Response, int, str | None]] = [
            (upload_mesh(c, b"this is not a mesh at all", filename="x.stl"), 422, "mesh"),
            (upload_mesh(c, b"\x00" * 10, filename="x.bin"), 422, "mesh"),
            (upload_mesh(c, b"", filename="x.stl"), 422, "mesh"),
            (upload_mesh(c, b"v 0 0 0\n" * 20000, filename="big.obj"), 413, "mesh"),
            (c.post("/v1/objects", files={"mesh": ("b.stl", box_stl())},
                    data={"spec": "{not json"}), 422, "spec"),
            (c.post("/v1/objects", files={"mesh": ("b.stl", box_stl())},
                    data={"spec": json.dumps({"units": "furlong"})}), 422, "spec.units"),
            (c.post("/v1/objects", files={"mesh": ("b.stl", box_stl())},
                    data={"spec": json.dumps({"colour": "red"})}), 422, "spec.colour"),
            (c.post("/v1/objects", files={"mesh": ("b.stl", box_stl())},
                    data={"spec": json.dumps({"learning": {"max_faces": 10}})}),
             422, "spec.learning.max_faces"),
            # Each in range, together no training view: the job used to fail.
            (c.post("/v1/objects", files={"mesh": ("b.stl", box_stl())},
                    data={"spec": json.dumps({"learning": {
                        "max_level": 0, "min_level": 0, "max_polar_deg": 30}})}),
             422, "spec.learning.max_polar_deg"),
            (c.post("/v1/objects", files={"mesh": ("far.obj",
                                                  b"v 1e39 0 0\nv 1e39 10 0\nv 1e39 0 10\n"
                                                  b"f 1 2 3\n")}),
             422, "mesh"),
            (c.post("/v1/objects", files={"spec": (None, "{}")}), 422, "mesh"),
            (c.post("/v1/objects", data={"spec": "{}"}), 415, None),
            (c.post("/v1/objects", json={"mesh": "abc"}), 415, None),
            (c.post("/v1/objects", content=b"x" * 10, headers={"content-type": "text/plain"}),
             415, None),
            # Bodies the form parser cannot read name what to mend.
            (c.post("/v1/objects", content=b"x" * 10,
                    headers={"content-type": "multipart/form-data"}), 400, "content-type"),
            (c.post(loc, content=b"garbage", headers={"content-type": MULTIPART_ABC}),
             400, "body"),
            (c.post(loc, content=b"--abc\r\nContent-Disposition: form-data\r\n\r\nx\r\n--abc--\r\n",
                    headers={"content-type": MULTIPART_ABC}), 400, "body"),
            (c.post(loc, files={"image": ("s.png", b"GIF89a not an image", "image/gif")},
                    data={"camera": cam}), 422, "image"),
            (c.post(loc, files={"image": ("s.png", b"\x89PNG\r\n\x1a\n" + b"\x00" * 40)},
                    data={"camera": cam}), 422, "image"),
            (c.post(loc, files={"image": ("s.png", png(2000, 1000, noise=False), "image/png")},
                    data={"camera": cam}), 422, "image"),
            (c.post(loc, files={"image": image}, data={"camera": "{fx: 1"}), 422, "camera"),
            (c.post(loc, files={"image": image},
                    data={"camera": json.dumps({**CAMERA, "fx": -5})}), 422, "camera.fx"),
            (c.post(loc, files={"image": image},
                    data={"camera": json.dumps({"fy": 1, "cx": 1, "cy": 1})}), 422, "camera.fx"),
            (c.post(loc, files={"image": image},
                    data={"camera": json.dumps({**CAMERA, "dist": [0.1, 0.2, 0.3]})}),
             422, "camera.dist"),
            # Finite but beyond any lens: these made the pose arithmetic fail (500).
            (c.post(loc, files={"image": image},
                    data={"camera": json.dumps({**CAMERA, "fx": 1e-10, "fy": 1e-10})}),
             422, "camera.fx"),
            (c.post(loc, files={"image": image},
                    data={"camera": json.dumps({**CAMERA, "cx": 1e200})}), 422, "camera.cx"),
            (c.post(loc, files={"image": image},
                    data={"camera": json.dumps({**CAMERA, "dist": [0, 0, 1e10, 0]})}),
             422, "camera.dist"),
            # Each coefficient within bounds, yet the rational model's
            # denominator reaches 0 in the image: a projected pose was NaN (500).
            (c.post(loc, files={"image": image},
                    data={"camera": json.dumps({**CAMERA, "dist": [1000.0] * 8})}),
             422, "camera.dist"),
            (c.post(loc, files={"image": image},
                    data={"camera": cam, "options": json.dumps({"max_detections": 0})}),
             422, "options.max_detections"),
            (c.post(loc, files={"camera": (None, cam)}), 422, "image"),
            (c.post(loc, files={"image": image}), 422, "camera"),
            (c.post("/v1/objects/" + "0" * 32 + "/localize", files={"image": image},
                    data={"camera": cam}), 404, None),
            (c.post("/v1/objects/..%2F..%2Fetc/localize", files={"image": image},
                    data={"camera": cam}), 404, None),
            (c.get("/v1/objects/not-an-id"), 404, None),
            # The id "/": not sent on to the list of objects.
            (c.get("/v1/objects/%2F"), 404, None),
            (c.delete("/v1/objects/%2F"), 404, None),
            (c.get("/v1/objects//"), 404, None),
            (c.get("/v1/jobs/" + "f" * 32), 404, None),
            (c.delete("/v1/jobs/xyz"), 404, None),
            (c.post("/v1/localize", files={"image": image},
                    data={"camera": cam, "options": json.dumps({"object_ids": ["nope"]})}),
             404, "options.object_ids[0]"),
            # A well-formed id of no object is named by its place in the list.
            (c.post("/v1/localize", files={"image": image},
                    data={"camera": cam,
                          "options": json.dumps({"object_ids": [oid, "0" * 32]})}),
             404, "options.object_ids[1]"),
            # ... in the list as sent, repeats counted.
            (c.post("/v1/localize", files={"image": image},
                    data={"camera": cam,
                          "options": json.dumps({"object_ids": [oid, oid, "0" * 32]})}),
             404, "options.object_ids[2]"),
            (one_photo({"views": []}), 422, "spec.views"),
            (c.post("/v1/objects/from-images",
                    files=[("images", ("a.png", png(), "image/png")),
                           ("masks", ("m.png", png(100, 100, 1), "image/png"))],
                    data={"spec": json.dumps(photo_spec)}), 422, "masks[0]"),
            (c.post("/v1/objects/from-images",
                    files=[("images", ("a.png", png(), "image/png"))] * 4,
                    data={"spec": "{}"}), 413, "images"),
            (one_photo({"object_diameter_mm": -1}), 422, "spec.object_diameter_mm"),
            # Finite but impossible: a part larger than 100 m, a camera inside
            # the part, photos too small to read (all were queued as jobs).
            (one_photo({"object_diameter_mm": 1e308}), 422, "spec.object_diameter_mm"),
            # A diameter in metres given as millimetres.
            (one_photo({"object_diameter_mm": 0.05}), 422, "spec.object_diameter_mm"),
            (one_photo({"object_diameter_mm": 100, "views": [{**view, "distance_mm": 40}]}),
             422, "spec.views[0].distance_mm"),
            (one_photo({"views": [{**view, "azimuth_deg": 1e308}]}), 422,
             "spec.views[0].azimuth_deg"),
            (one_photo({"camera": {**CAMERA, "cx": 3.5, "cy": 3.5}}, png(8, 8)), 422,
             "images[0]"),
        ]
        # An id is not echoed back whole (a 70 kB id made a 70 kB answer).
        long_id = c.get("/v1/objects/" + "a" * 20_000)
        assert_problem(long_id, 404)
        assert len(long_id.content) < 1_000 and "20000 characters" in long_id.text
        for i, (r, status, field) in enumerate(cases):
            try:
                assert_problem(r, status, field)
            except AssertionError as exc:
                raise AssertionError(f"case {i}: {exc}") from exc
        # A decompression bomb whose frame header hides behind a stray byte is
        # refused from its header ("W x H = N pixels"), not after decoding it.
        bomb = jpeg(claimed_size=(30000, 30000), stray=b"\x00")
        r = c.post(loc, files={"image": ("b.jpg", bomb, "image/jpeg")}, data={"camera": cam})
        assert "30000x30000 = 900000000 pixels" in assert_problem(r, 422, "image")["detail"]
        # body far beyond the route limit: refused from Content-Length alone
        r = c.post(loc, files={"image": ("big.png", b"\x89PNG" + b"\x00" * 1_500_000)},
                   data={"camera": cam})
        assert_problem(r, 413)
        files_after = sorted(p.relative_to(tmp_path) for p in (tmp_path / "var").rglob("*")
                             if p.is_file() and "sqlite" not in p.name)
        assert files_after == files_before
        assert [o["object_id"] for o in c.get("/v1/objects").json()["objects"]] == [oid]


def test_a_repeated_mesh_or_spec_part_is_refused_naming_it(
    make_server: Callable[..., LiveServer], tmp_path: Path
) -> None:
    srv = make_server(tasks=SLEEPY)
    box = ("b.stl", box_stl(), "application/octet-stream")
    garbage = ("g.stl", b"this is not a mesh at all", "application/octet-stream")
    spec = json.dumps({"name": "box", "units": "mm"})
    with httpx.Client(base_url=srv.url, timeout=30) as c:
        before = c.get("/v1/objects").json()
        files_before = stored_files(tmp_path / "var")
        # The last part of a name was used and the others dropped: the box
        # followed by garbage was a 422 about the mesh, the other way round
        # a 202 that learned the box and never looked at the garbage.
        for meshes in ([box, garbage], [garbage, box], [box, box]):
            r = c.post("/v1/objects", files=[("mesh", m) for m in meshes], data={"spec": spec})
            assert "send exactly one mesh" in assert_problem(r, 422, "mesh")["detail"]
        # Two specs: the units of the first were ignored (cm, then mm).
        r = c.post("/v1/objects", files={"mesh": box},
                   data={"spec": [json.dumps({"units": "cm"}), spec]})
        assert "send exactly one spec" in assert_problem(r, 422, "spec")["detail"]
        # Sent once as text and once as a file is sent twice.
        assert_problem(c.post("/v1/objects", files=[("mesh", box), ("spec", ("s.json", spec))],
                              data={"spec": spec}), 422, "spec")
        # Refused before anything is stored or a job started.
        assert c.get("/v1/objects").json() == before
        assert stored_files(tmp_path / "var") == files_before
        # One of each is learned.
        r = c.post("/v1/objects", files={"mesh": box}, data={"spec": spec})
        assert r.status_code == 202, r.text


def test_api_keys(make_server: Callable[..., LiveServer]) -> None:
    srv = make_server(api_keys="k-one, k-two")
    with httpx.Client(base_url=srv.url, timeout=30) as c:
        assert c.get("/healthz").status_code == 200
        for path in ("/v1/objects", "/readyz", "/metrics", "/v1/jobs/" + "a" * 32):
            body = assert_problem(c.get(path), 401)
            assert "API key" in body["detail"]
        r = c.get("/v1/objects", headers={"Authorization": "Bearer k-three"})
        assert_problem(r, 401)
        assert r.headers["www-authenticate"] == "Bearer"
        assert_problem(c.get("/v1/objects", headers={"Authorization": "Basic k-one"}), 401)
        for key in ("k-one", "k-two"):
            r = c.get("/v1/objects", headers={"Authorization": f"Bearer {key}"})
            assert r.status_code == 200 and r.json() == {"objects": []}


def test_a_bug_answers_500_problem_json_and_the_connection_stays_usable(
    make_server: Callable[..., LiveServer]
) -> None:
    srv = make_server()

    def broken() -> None:
        raise RuntimeError("a bug")

    srv.app.add_api_route("/v1/broken", broken)
    with httpx.Client(base_url=srv.url, timeout=30) as c:
        r = c.get("/v1/broken")
        assert_problem(r, 500)
        assert "a bug" not in r.text and len(r.headers["x-request-id"]) == 32
        # The same pooled connection answers the next request (the server
        # used to drop it after a 500, failing the client's next call).
        assert c.get("/healthz").status_code == 200
        assert 'route="/v1/broken",status="500"' in c.get("/metrics").text


def test_operations_metrics_request_id_and_openapi(make_server: Callable[..., LiveServer]) -> None:
    srv = make_server()
    with httpx.Client(base_url=srv.url, timeout=30) as c:
        assert c.get("/readyz").json()["checks"] == {"store": True, "job_runner": True,
                                                      "models_prepared": True}
        r = c.get("/v1/objects", headers={"X-Request-ID": "abc-123"})
        assert r.headers["x-request-id"] == "abc-123"
        assert len(c.get("/healthz").headers["x-request-id"]) == 32
        c.get("/v1/objects/" + "0" * 32)
        text = c.get("/metrics").text
        assert 'viewloc_http_requests_total{method="GET",route="/v1/objects/{object_id}",' \
               'status="404"} 1.0' in text
        assert "viewloc_http_request_duration_seconds_bucket" in text
        assert 'viewloc_jobs{state="queued"} 0.0' in text
        assert "viewloc_localization_duration_seconds_count" in text
        spec = c.get("/openapi.json").json()
    validate(spec)
    paths = spec["paths"]
    for path in ("/v1/objects", "/v1/objects/from-images", "/v1/objects/{object_id}",
                 "/v1/objects/{object_id}/localize", "/v1/localize", "/v1/jobs/{job_id}",
                 "/healthz", "/readyz", "/metrics"):
        assert path in paths, path
    for path, item in paths.items():
        for method, op in item.items():
            for code, resp in op["responses"].items():
                if int(code) >= 400:
                    assert list(resp["content"]) == ["application/problem+json"], (path, code)
            if path != "/healthz":
                assert "401" in op["responses"], (path, method)
    loc = paths["/v1/objects/{object_id}/localize"]["post"]["responses"]
    assert {"400", "404", "409", "413", "415", "422"} <= set(loc)
    schemas = spec["components"]["schemas"]
    assert {"Problem", "ObjectOut", "JobOut", "LocalizationOut", "DetectionOut"} <= set(schemas)


def _serve_until_learning(root: Path, job_id: str | None) -> tuple[subprocess.Popen[bytes], str]:
    """A service process on ``root`` once the job (``job_id``, or one made
    by uploading a mesh) is learning: (the process, the job's id)."""
    port = free_port()
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    proc = subprocess.Popen(
        [sys.executable, "-m", "tests.app.serve_for_test", "--port", str(port),
         "--data-dir", str(root)], env=env, cwd=Path(__file__).resolve().parents[2])
    try:
        url = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 30
        while True:
            try:
                if httpx.get(url + "/readyz").status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert time.monotonic() < deadline and proc.poll() is None
            time.sleep(0.1)
        with httpx.Client(base_url=url, timeout=30) as c:
            if job_id is None:
                job_id = str(upload_mesh(c).json()["job"]["job_id"])
            deadline = time.monotonic() + 30
            while c.get(f"/v1/jobs/{job_id}").json()["progress"] <= 0:
                assert time.monotonic() < deadline
                time.sleep(0.05)
    except BaseException:
        proc.kill()
        raise
    return proc, job_id


def test_restart_while_a_job_runs_leaves_nothing_stuck(
    tmp_path: Path, make_server: Callable[..., LiveServer]
) -> None:
    root = tmp_path / "var"
    proc, job_id = _serve_until_learning(root, None)
    try:
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert ModelStore(root).get_job(job_id).state == "running"  # as the dead service left it
    srv = make_server(tasks=SLEEPY)
    with httpx.Client(base_url=srv.url, timeout=30) as c:
        job = wait_job(c, job_id)
        assert job["state"] == "succeeded", job
        assert ModelStore(root).get_job(job_id).attempts == 2


def test_clean_restarts_while_a_job_runs_do_not_fail_it(
    tmp_path: Path, make_server: Callable[..., LiveServer]
) -> None:
    # A deploy stops the service with SIGTERM: the job it stops goes back to
    # the queue without its start counted, however often that happens (a
    # killed service counts it: test_restart_while_a_job_runs_...).
    root = tmp_path / "var"
    job_id = None
    for _ in range(3):
        proc, job_id = _serve_until_learning(root, job_id)
        try:
            proc.send_signal(signal.SIGTERM)
            # uvicorn shuts down, then raises the signal again for its caller.
            assert proc.wait(30) in (0, -signal.SIGTERM)
        finally:
            if proc.poll() is None:
                proc.kill()
        stopped = ModelStore(root).get_job(job_id)
        assert (stopped.state, stopped.attempts) == ("queued", 0)
    srv = make_server(tasks=SLEEPY)
    with httpx.Client(base_url=srv.url, timeout=30) as c:
        job = wait_job(c, str(job_id))
        assert job["state"] == "succeeded", job
        assert ModelStore(root).get_job(str(job_id)).attempts == 1


@pytest.mark.parametrize("units", ["cm"])
def test_units_scale_the_mesh(make_server: Callable[..., LiveServer], units: str) -> None:
    srv = make_server(tasks=SLEEPY)
    with httpx.Client(base_url=srv.url, timeout=30) as c:
        r = c.post("/v1/objects", files={"mesh": ("b.stl", box_stl())},
                   data={"spec": json.dumps({"units": units})})
        assert r.status_code == 202
        assert abs(r.json()["object"]["diameter_mm"] - 10 * (40**2 + 20**2 + 10**2) ** 0.5) < 1e-3



def test_a_ready_object_names_its_model_and_the_same_upload_learns_the_same_model(
    make_server: Callable[..., LiveServer]
) -> None:
    srv = make_server()
    with httpx.Client(base_url=srv.url, timeout=30) as c:
        def learn(name: str, mesh: bytes) -> dict[str, Any]:
            r = c.post("/v1/objects", files={"mesh": ("m.stl", mesh, "application/octet-stream")},
                       data={"spec": json.dumps({"name": name, "learning": FAST_LEARNING})})
            assert r.status_code == 202, r.text
            assert r.json()["object"]["model_sha256"] is None  # learning: no model yet
            job = wait_job(c, r.json()["job"]["job_id"], timeout=120)
            assert job["state"] == "succeeded", job
            obj: dict[str, Any] = c.get(f"/v1/objects/{r.json()['object']['object_id']}").json()
            return obj

        first, again = learn("first", box_stl()), learn("again", box_stl())
        other = learn("other", bytes(trimesh.creation.box((30.0, 20.0, 10.0)).export(
            file_type="stl")))
        assert re.fullmatch("[0-9a-f]{64}", first["model_sha256"])
        assert again["model_sha256"] == first["model_sha256"]
        assert other["model_sha256"] != first["model_sha256"]
        listed = {o["name"]: o["model_sha256"] for o in c.get("/v1/objects").json()["objects"]}
        assert listed == {o["name"]: o["model_sha256"] for o in (first, again, other)}
        assert ObjectInfo.from_json(first).model_sha256 == first["model_sha256"]
