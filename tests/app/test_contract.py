"""API.md, endpoint by endpoint, against a served store with the barbell learned."""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import pytest

from model_store import ModelStore
from tests.app.conftest import LiveServer
from tests.app.helpers import CAMERA, assert_problem, png
from tests.app.learned import BARBELL, LearnedStore, another_barbell, learned_barbell
from viewloc_client import ViewlocClient
from viewloc_core.pose import Pose

__all__ = ["learned_barbell"]

DETECTION_KEYS = {"score", "log_probability", "model_view", "view", "similarity", "pose",
                  "refined"}


def _scene(pose: Pose) -> bytes:
    from viewloc_core.camera import Camera
    from viewloc_core.mesh import load_mesh
    from viewloc_core.render import Renderer

    cam = Camera(CAMERA["fx"], CAMERA["fy"], CAMERA["cx"], CAMERA["cy"], 320, 240)
    with Renderer() as renderer:
        color = renderer.render(load_mesh(BARBELL), cam, pose, background_rgb=(40, 40, 40)).color
    ok, buf = cv2.imencode(".png", color[:, :, ::-1])
    assert ok
    return bytes(buf.tobytes())


def _rfc3339(text: str) -> datetime:
    stamp = datetime.fromisoformat(text.replace("Z", "+00:00"))
    assert stamp.tzinfo is not None and "T" in text, text
    return stamp


def _check_detection(det: dict[str, object]) -> None:
    assert set(det) >= DETECTION_KEYS, det
    assert 0.0 <= float(str(det["score"])) <= 1.0
    pose = det["pose"]
    assert isinstance(pose, dict) and set(pose) == {"R", "t_mm", "quaternion_wxyz",
                                                    "euler_xyz_deg"}
    R = np.array(pose["R"])
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-6)
    assert abs(np.linalg.det(R) - 1.0) < 1e-6
    q = np.array(pose["quaternion_wxyz"])
    assert abs(np.linalg.norm(q) - 1.0) < 1e-6 and q[0] >= 0.0
    t = np.array(pose["t_mm"])
    np.testing.assert_allclose(Pose.from_quaternion(q, t).R_m2c, R, atol=1e-6)
    np.testing.assert_allclose(
        Pose.from_euler_xyz_deg(np.array(pose["euler_xyz_deg"]), t).R_m2c, R, atol=1e-6)
    view, sim = det["view"], det["similarity"]
    assert isinstance(view, dict) and set(view) >= {"azimuth_deg", "polar_deg"}
    assert isinstance(sim, dict) and set(sim) >= {"x", "y", "angle_deg", "scale"}
    assert float(sim["scale"]) > 0


#: Where the served scenes show the barbell: 5 mm right of the optical axis, 600 mm away.
SCENE_TRUTH = Pose.from_euler_xyz_deg(np.array([30.0, -15.0, 10.0]), np.array([5.0, 0.0, 600.0]))


def _served_scene(learned_barbell: LearnedStore, make_server: Callable[..., LiveServer],
                  tmp_path: Path) -> tuple[LiveServer, str, tuple[str, bytes, str], str]:
    """A server of a store with the barbell learned, its object id, a scene
    of it at SCENE_TRUTH as an upload, and the camera as its form field."""
    learned_barbell.copy_to(tmp_path / "var")
    scene = ("s.png", _scene(SCENE_TRUTH), "image/png")
    return make_server(), learned_barbell.object_id, scene, json.dumps(CAMERA)


def test_every_endpoint_answers_as_api_md_says(
    learned_barbell: LearnedStore, make_server: Callable[..., LiveServer], tmp_path: Path
) -> None:
    srv, oid, scene, cam = _served_scene(learned_barbell, make_server, tmp_path)
    truth = SCENE_TRUTH
    with httpx.Client(base_url=srv.url, timeout=60) as c:
        # Objects and jobs: shapes and RFC 3339 times.
        obj = c.get(f"/v1/objects/{oid}").json()
        assert obj["state"] == "ready" and obj["source"] == "mesh" and obj["error"] is None
        _rfc3339(obj["created_at"])
        assert c.get("/v1/objects").json() == {"objects": [obj]}
        job = c.get(f"/v1/jobs/{obj['job_id']}").json()
        assert job["object_id"] == oid and job["state"] == "succeeded" and job["error"] is None
        created, started, finished = (_rfc3339(job[k]) for k in
                                      ("created_at", "started_at", "finished_at"))
        assert created <= started <= finished
        # Cancelling a finished job changes nothing.
        assert c.delete(f"/v1/jobs/{obj['job_id']}").json() == job

        # One object: image size, detections best first, consistent pose forms, timings.
        r = c.post(f"/v1/objects/{oid}/localize", files={"image": scene},
                   data={"camera": cam, "options": json.dumps({"max_detections": 3})})
        assert r.status_code == 200, r.text
        body = r.json()
        assert body["object_id"] == oid and body["image"] == {"width": 320, "height": 240}
        assert 1 <= len(body["detections"]) <= 3 and "overlay_png_base64" in body
        scores = [d["score"] for d in body["detections"]]
        assert scores == sorted(scores, reverse=True)
        for det in body["detections"]:
            _check_detection(det)
            assert det["object_id"] == oid
        best = body["detections"][0]
        assert np.linalg.norm(np.array(best["pose"]["t_mm"]) - truth.t_m2c) < 0.05 * 600
        timing = body["timing_ms"]
        assert {"total", "decode", "localize"} <= set(timing)
        assert timing["total"] >= timing["decode"] + timing["localize"] - 1.0

        # Defaults: one detection, refinement on (it may still decline a fit).
        default = c.post(f"/v1/objects/{oid}/localize", files={"image": scene},
                         data={"camera": cam}).json()
        assert len(default["detections"]) == 1
        no_refine = c.post(f"/v1/objects/{oid}/localize", files={"image": scene},
                           data={"camera": cam, "options": json.dumps({"refine": False})}).json()
        assert no_refine["detections"][0]["refined"] is False

        # Nothing there is a normal answer.
        for image, options in ((png(320, 240, noise=False), {}),
                               (scene[1], {"min_score": 1.0, "max_detections": 5})):
            r = c.post(f"/v1/objects/{oid}/localize", files={"image": ("x.png", image)},
                       data={"camera": cam, "options": json.dumps(options)})
            assert r.status_code == 200, r.text
            assert all(d["score"] >= 1.0 for d in r.json()["detections"])
            if not options:
                assert r.json()["detections"] == []

        # Several objects: the searched ids, and each detection names its object.
        many = c.post("/v1/localize", files={"image": scene},
                      data={"camera": cam, "options": json.dumps({"object_ids": [oid]})}).json()
        assert many["object_ids"] == [oid] and many["image"] == {"width": 320, "height": 240}
        assert [d["object_id"] for d in many["detections"]] == [oid]
        _check_detection(many["detections"][0])
        # The same answer as the object's own endpoint gives (the scene's
        # features are shared between objects, not changed).
        assert many["detections"][0]["pose"] == default["detections"][0]["pose"]
        assert {"features", "localize"} <= set(many["timing_ms"])
        everything = c.post("/v1/localize", files={"image": scene}, data={"camera": cam}).json()
        assert everything["object_ids"] == [oid]

        # The camera's optional size must match the image.
        r = c.post(f"/v1/objects/{oid}/localize", files={"image": scene},
                   data={"camera": json.dumps({**CAMERA, "width": 640, "height": 480})})
        assert_problem(r, 422, "camera")

        # Delete: 204, then gone everywhere (404 problem+json).
        assert c.delete(f"/v1/objects/{oid}").status_code == 204
        assert c.get("/v1/objects").json() == {"objects": []}
        assert_problem(c.post(f"/v1/objects/{oid}/localize", files={"image": scene},
                              data={"camera": cam}), 404)
        assert_problem(c.post("/v1/localize", files={"image": scene},
                              data={"camera": cam, "options": json.dumps({"object_ids": [oid]})}),
                       404)
        none_left = c.post("/v1/localize", files={"image": scene}, data={"camera": cam}).json()
        assert none_left["object_ids"] == [] and none_left["detections"] == []


def test_a_region_and_a_depth_range_bound_where_the_part_is_looked_for(
    learned_barbell: LearnedStore, make_server: Callable[..., LiveServer], tmp_path: Path
) -> None:
    srv, oid, scene, cam = _served_scene(learned_barbell, make_server, tmp_path)
    truth = SCENE_TRUTH
    u = CAMERA["fx"] * 5.0 / 600.0 + CAMERA["cx"]
    v = CAMERA["cy"]

    def ask(options: dict[str, object], path: str = f"/v1/objects/{oid}/localize",
            ) -> httpx.Response:
        return c.post(path, files={"image": scene},
                      data={"camera": cam, "options": json.dumps(options)})

    with httpx.Client(base_url=srv.url, timeout=60) as c:
        around = {"x": int(u) - 60, "y": int(v) - 50, "width": 120, "height": 100}
        found = ask({"roi": around, "depth_mm": {"min": 500, "max": 700}})
        assert found.status_code == 200, found.text
        dets = found.json()["detections"]
        assert len(dets) == 1
        assert np.linalg.norm(np.array(dets[0]["pose"]["t_mm"]) - truth.t_m2c) < 0.05 * 600
        # Image positions stay in the whole image's pixels.
        assert abs(dets[0]["similarity"]["x"] - u) < 10 and abs(dets[0]["similarity"]["y"] - v) < 10
        # The multi-object endpoint reads the same options the same way.
        many = ask({"object_ids": [oid], "roi": around, "depth_mm": {"min": 500, "max": 700}},
                   "/v1/localize").json()
        assert [d["pose"] for d in many["detections"]] == [dets[0]["pose"]]

        # Where the part is not: no detection of it there.
        corner = ask({"roi": {"x": 0, "y": 0, "width": 60, "height": 50}, "max_detections": 3})
        assert corner.status_code == 200, corner.text
        assert all(d["similarity"]["y"] < 60 for d in corner.json()["detections"])
        farther = ask({"depth_mm": {"min": 900, "max": 1500}, "max_detections": 3}).json()
        assert all(900 <= d["pose"]["t_mm"][2] <= 1500 for d in farther["detections"])
        assert all(np.linalg.norm(np.array(d["pose"]["t_mm"]) - truth.t_m2c) > 100
                   for d in farther["detections"])

        # Bad options: 422 naming the field, nothing else changed.
        assert_problem(ask({"roi": {"x": 300, "y": 0, "width": 40, "height": 10}}), 422,
                       "options.roi")
        assert_problem(ask({"roi": {"x": -1, "y": 0, "width": 40, "height": 10}}), 422,
                       "options.roi.x")
        assert_problem(ask({"roi": {"x": 0, "y": 0, "width": 40}}), 422, "options.roi.height")
        assert_problem(ask({"depth_mm": {"min": 700, "max": 500}}), 422, "options.depth_mm.max")
        assert_problem(ask({"depth_mm": {"min": 0, "max": 500}}), 422, "options.depth_mm.min")
        assert_problem(ask({"max_rotation_std_deg": 0}), 422, "options.max_rotation_std_deg")
        assert_problem(ask({"max_rotation_std_deg": "x"}), 422, "options.max_rotation_std_deg")
        # The barbell's pose is pinned down to well under the limits asked.
        for limit in (5.0, 360.0):
            pinned = ask({"max_rotation_std_deg": limit})
            assert pinned.status_code == 200, pinned.text
            assert [d["pose"] for d in pinned.json()["detections"]] == [dets[0]["pose"]]
        # No refined pose is known to a thousandth of a degree: nothing is reported.
        assert ask({"max_rotation_std_deg": 1e-3}).json()["detections"] == []
        assert_problem(ask({"roi": {"x": 300, "y": 0, "width": 40, "height": 10}},
                           "/v1/localize"), 422, "options.roi")
        assert c.get(f"/v1/objects/{oid}").json()["state"] == "ready"


def test_a_part_sent_twice_is_refused_naming_it(
    learned_barbell: LearnedStore, make_server: Callable[..., LiveServer], tmp_path: Path
) -> None:
    srv, oid, scene, cam = _served_scene(learned_barbell, make_server, tmp_path)
    garbage = ("g.png", b"not an image", "image/png")
    with httpx.Client(base_url=srv.url, timeout=60) as c:
        for path in (f"/v1/objects/{oid}/localize", "/v1/localize"):
            # The last part of a name was used and the others dropped: the
            # scene followed by garbage was a 422 about the image, the other
            # way round a 200 that never looked at the garbage.
            for images in ([scene, garbage], [garbage, scene], [scene, scene]):
                r = c.post(path, files=[("image", f) for f in images], data={"camera": cam})
                assert "send exactly one image" in assert_problem(r, 422, "image")["detail"]
            assert_problem(c.post(path, files={"image": scene}, data={"camera": [cam, cam]}),
                           422, "camera")
            # Sent once as text and once as a file is sent twice.
            assert_problem(c.post(path, files=[("image", scene), ("camera", ("c.json", cam))],
                                  data={"camera": cam}), 422, "camera")
            assert_problem(c.post(path, files={"image": scene},
                                  data={"camera": cam, "options": ["{}", "{}"]}),
                           422, "options")
            # One of each is localized.
            r = c.post(path, files={"image": scene}, data={"camera": cam, "options": "{}"})
            assert r.status_code == 200, r.text
            assert len(r.json()["detections"]) == 1


def test_an_object_deleted_while_several_are_localized(
    learned_barbell: LearnedStore, make_server: Callable[..., LiveServer], tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    first = learned_barbell.object_id
    second = another_barbell(learned_barbell.copy_to(tmp_path / "var"), first)
    # No warmer: only the requests load models, so only they delete.
    srv = make_server(prepare_models=False)
    store: ModelStore = srv.app.state.store
    load_model = store.load_model
    doomed: set[str] = set()

    def deleted_first(object_id: str) -> Any:
        """The store's load_model, after deleting a doomed object: deleted
        after the request listed or checked it, before its model was loaded."""
        if object_id in doomed:
            doomed.discard(object_id)
            store.delete_object(object_id)
        return load_model(object_id)

    monkeypatch.setattr(store, "load_model", deleted_first)
    scene = ("s.png", _scene(SCENE_TRUTH), "image/png")
    cam = json.dumps(CAMERA)
    with httpx.Client(base_url=srv.url, timeout=60) as c:
        # Named by no one: skipped, and the other object is still searched.
        doomed.add(first)
        r = c.post("/v1/localize", files={"image": scene}, data={"camera": cam})
        assert r.status_code == 200, r.text
        assert r.json()["object_ids"] == [second]
        assert [d["object_id"] for d in r.json()["detections"]] == [second]
        # ... and the answer says so.
        [gone] = r.json()["skipped"]
        assert gone["object_id"] == first and gone["reason"] == "deleted", gone
        # Named by the client: 404 naming its entry in the list.
        doomed.add(second)
        r = c.post("/v1/localize", files={"image": scene},
                   data={"camera": cam, "options": json.dumps({"object_ids": [second]})})
        assert_problem(r, 404, "options.object_ids[0]")
        assert not doomed and c.get("/v1/objects").json() == {"objects": []}


def _inf_vertex(model: Any) -> Any:
    """``model`` as an older version could store it: a vertex of an upload far
    from the origin overflowed float32 to inf (uploads like it are now
    refused), yet the files' checksums are right."""
    vertices = np.array(model.mesh_vertices_mm, copy=True)
    vertices[0, 0] = np.inf
    return dataclasses.replace(model, mesh_vertices_mm=vertices)


def test_a_stored_model_holding_inf_is_corrupt(
    learned_barbell: LearnedStore, make_server: Callable[..., LiveServer], tmp_path: Path,
) -> None:
    good = learned_barbell.object_id
    root = learned_barbell.copy_to(tmp_path / "var")
    asked, listed = (another_barbell(root, good, _inf_vertex) for _ in range(2))
    # No warmer: the requests below are the first to load the models.
    srv = make_server(prepare_models=False)
    scene = ("s.png", _scene(SCENE_TRUTH), "image/png")
    cam = json.dumps(CAMERA)
    with httpx.Client(base_url=srv.url, timeout=60) as c:
        # Localized: 409 naming what is not finite (it was a 500).
        r = c.post(f"/v1/objects/{asked}/localize", files={"image": scene},
                   data={"camera": cam})
        body = assert_problem(r, 409)
        assert body["type"].endswith("/model-corrupt") and "mesh_vertices_mm" in body["detail"]
        failed = c.get(f"/v1/objects/{asked}").json()
        assert failed["state"] == "failed" and "mesh_vertices_mm" in failed["error"], failed
        # Listed before anything loaded it: shown failed, as a corrupt file is.
        r = c.get("/v1/objects")
        assert r.status_code == 200, r.text
        states = {o["object_id"]: (o["state"], o["error"]) for o in r.json()["objects"]}
        assert states[good] == ("ready", None)
        assert states[listed][0] == "failed" and "mesh_vertices_mm" in states[listed][1]
        # The others are still searched.
        r = c.post("/v1/localize", files={"image": scene}, data={"camera": cam})
        assert r.status_code == 200, r.text
        assert r.json()["object_ids"] == [good]


class _Records(logging.Handler):
    """The records a logger emits (the service's loggers do not propagate to
    pytest's handler)."""

    def __init__(self) -> None:
        super().__init__()
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def test_objects_unusable_at_load_are_skipped_unless_named(
    learned_barbell: LearnedStore, make_server: Callable[..., LiveServer], tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    good = learned_barbell.object_id
    root = learned_barbell.copy_to(tmp_path / "var")
    corrupt, corrupt_named = (another_barbell(root, good, _inf_vertex) for _ in range(2))
    stale, stale_named = (another_barbell(root, good) for _ in range(2))
    srv = make_server(prepare_models=False)
    store: ModelStore = srv.app.state.store
    load_model = store.load_model

    def failed_first(object_id: str) -> Any:
        """The store's load_model, after the stale objects stopped being ready
        (after the request listed or checked them)."""
        if object_id in (stale, stale_named):
            store.mark_object_failed(object_id, "relearning failed")
        return load_model(object_id)

    monkeypatch.setattr(store, "load_model", failed_first)
    records = _Records()
    logging.getLogger("viewloc.app").addHandler(records)
    scene = ("s.png", _scene(SCENE_TRUTH), "image/png")
    cam = json.dumps(CAMERA)
    try:
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            def many(options: dict[str, Any]) -> httpx.Response:
                return c.post("/v1/localize", files={"image": scene},
                              data={"camera": cam, "options": json.dumps(options)})

            # Named by the client: the errors of the object's own endpoint.
            body = assert_problem(many({"object_ids": [corrupt_named]}), 409)
            assert body["type"].endswith("/model-corrupt"), body
            body = assert_problem(many({"object_ids": [good, stale_named]}), 409)
            assert body["type"].endswith("/object-not-ready"), body
            # Named by no one: skipped, said why, and the good object is searched
            # (one corrupt model made every such request a 500, then a 409).
            with ViewlocClient(srv.url) as client:
                found = client.localize(None, scene[1], CAMERA)
            assert found.object_ids == [good]
            assert [d["object_id"] for d in found.detections] == [good]
            assert [(s["object_id"], s["reason"]) for s in found.skipped] == [
                (corrupt, "corrupt"), (stale, "not-ready")]
            assert "mesh_vertices_mm" in found.skipped[0]["detail"]
            assert "relearning failed" in found.skipped[1]["detail"]
            # A corrupt model is logged for an operator, as a 409 about it is.
            assert any(r.levelno == logging.ERROR and corrupt in r.getMessage()
                       and "mesh_vertices_mm" in r.getMessage() for r in records.records)
            # They are failed now: not listed, not skipped again.
            again = many({}).json()
            assert again["object_ids"] == [good] and again["skipped"] == []
    finally:
        logging.getLogger("viewloc.app").removeHandler(records)
