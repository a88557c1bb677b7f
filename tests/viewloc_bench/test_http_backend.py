"""The benchmark's backends: ``--url`` against a real service (reuse, round trip, server
timings), and what both ask the method for."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace

import httpx
import numpy as np
import pytest

from tests.app.conftest import LiveServer, make_server
from tests.app.learned import BARBELL, BENCH_NAME, LEARNING, LearnedStore, learned_barbell
from viewloc_bench.localizers import CoreBackend, HttpBackend, HttpLocalizer
from viewloc_bench.sets import BenchObject
from viewloc_core.camera import Camera
from viewloc_core.pose import Pose

__all__ = ["learned_barbell", "make_server"]


def test_http_backend_reuses_the_learned_object_and_records_timings(
    learned_barbell: LearnedStore, make_server: Callable[..., LiveServer], tmp_path: Path
) -> None:
    from viewloc_core.mesh import load_mesh
    from viewloc_core.render import Renderer

    learned_barbell.copy_to(tmp_path / "var")
    srv = make_server()
    obj = BenchObject("barbell", BARBELL, 0.0, np.eye(4)[None], np.zeros((1, 3)))
    backend = HttpBackend(srv.url, learning={k: v for k, v in LEARNING.items() if k != "seed"})
    backend.check()
    assert backend.object_name(obj, BARBELL.read_bytes()) == BENCH_NAME
    learned = backend.learn(obj)
    # Found by name and reused: nothing uploaded, the learning time is the job's.
    assert learned.info == {"object_id": learned_barbell.object_id, "reused": True,
                            "model_sha256": learned_barbell.obj["model_sha256"]}
    assert [o["object_id"] for o in httpx.get(f"{srv.url}/v1/objects").json()["objects"]] == [
        learned_barbell.object_id]
    assert 0 < learned.learn_s < 600 and learned.training_views == 42

    cam = Camera(600.0, 600.0, 191.5, 143.5, 384, 288)
    truth = Pose.from_euler_xyz_deg(np.array([35.0, -20.0, 15.0]), np.array([15.0, -10.0, 700.0]))
    with Renderer() as renderer:
        scene = renderer.render(load_mesh(BARBELL), cam, truth, background_rgb=(40, 40, 40)).color
    localizer = learned.localize
    assert isinstance(localizer, HttpLocalizer)
    dets = localizer(scene, cam)
    assert len(dets) == 1 and localizer.last_timed_out is False
    assert np.linalg.norm(dets[0].pose.t_m2c - truth.t_m2c) < 0.05 * 700
    timing = localizer.last_timing_ms
    assert {"client_encode", "client_request", "server_total", "server_decode",
            "server_localize"} <= set(timing)
    # The round trip contains the server's own time.
    assert timing["client_request"] >= timing["server_total"] > 0

    # The bench's time budget goes with every localization, not into learning.
    budgeted = HttpBackend(srv.url, learning={k: v for k, v in LEARNING.items() if k != "seed"},
                           timeout_ms=40.0).learn(obj).localize
    assert isinstance(budgeted, HttpLocalizer) and budgeted.object_id == learned_barbell.object_id
    assert json.loads(budgeted.options_json)["timeout_ms"] == 40.0
    assert "timeout_ms" not in json.loads(localizer.options_json)

    # Other options (here another seed) are another object: not reused.
    other = HttpBackend(srv.url, seed=1, learning={"max_level": 1, "min_level": 1})
    assert other.object_name(obj, BARBELL.read_bytes()) != BENCH_NAME


class _RecordingClient:
    """Stands in for httpx.Client: keeps each request's form data, answers no detections."""

    def __init__(self) -> None:
        self.forms: list[dict[str, str]] = []

    def post(self, url: str, files: object, data: dict[str, str]) -> httpx.Response:
        self.forms.append(data)
        return httpx.Response(200, json={"detections": [], "timing_ms": {"total": 1.0}})


def test_http_localizer_asks_for_as_many_detections_as_wanted() -> None:
    client = _RecordingClient()
    options = json.dumps({"max_detections": 1, "refine": True})
    localizer = HttpLocalizer(client, "obj-1", options)
    image = np.zeros((8, 8, 3), np.uint8)
    cam = Camera(10.0, 10.0, 4.0, 4.0, 8, 8)
    assert localizer(image, cam) == [] and localizer(image, cam, max_detections=3) == []
    assert client.forms[0]["options"] == options  # as before: the options given
    assert json.loads(client.forms[1]["options"]) == {"max_detections": 3, "refine": True}


def test_core_backend_passes_max_detections_to_the_core(monkeypatch: pytest.MonkeyPatch) -> None:
    import viewloc_core.learn
    import viewloc_core.localize

    wanted: list[tuple[int, bool, float | None]] = []

    def fake_localize(model: object, image: object, camera: object,
                      options: viewloc_core.localize.LocalizeOptions) -> SimpleNamespace:
        wanted.append((options.max_detections, options.refine, options.timeout_ms))
        return SimpleNamespace(detections=(), timing_ms={"total": 1.5}, timed_out=False)

    monkeypatch.setattr(viewloc_core.learn, "learn_from_mesh", lambda *a, **k: SimpleNamespace())
    monkeypatch.setattr(viewloc_core.localize, "localize", fake_localize)
    obj = BenchObject("barbell", BARBELL, 0.0, np.eye(4)[None], np.zeros((1, 3)))
    run = CoreBackend(refine=False).learn(obj).localize
    image = np.zeros((8, 8, 3), np.uint8)
    cam = Camera(10.0, 10.0, 4.0, 4.0, 8, 8)
    assert run(image, cam) == [] and run(image, cam, max_detections=3) == []
    assert wanted == [(1, False, None), (3, False, None)]
    # The bench's time budget is each localization's.
    budgeted = CoreBackend(timeout_ms=50.0).learn(obj).localize
    budgeted(image, cam)
    assert wanted[-1] == (1, True, 50.0)
    # The core's stage times are kept for the bench's breakdown.
    assert run.last_timing_ms == {"total": 1.5}  # type: ignore[attr-defined]


def test_the_core_backend_prepares_each_model_before_its_first_image(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import viewloc_core.learn
    from viewloc_core import view_search

    learn = viewloc_core.learn.learn_from_mesh
    monkeypatch.setattr(viewloc_core.learn, "learn_from_mesh", lambda mesh, config, *a, **k: learn(
        mesh, viewloc_core.learn.LearningConfig(max_level=1, min_level=1), *a, **k))
    obj = BenchObject("barbell", BARBELL, 0.0, np.eye(4)[None], np.zeros((1, 3)))
    learned = CoreBackend().learn(obj)
    # Its search structures are built, as the service's warmer builds them.
    assert learned.localize.model in view_search._TEMPLATES  # type: ignore[attr-defined]
