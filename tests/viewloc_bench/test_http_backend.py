"""The benchmark's ``--url`` backend against a real service: reuse, round trip, server timings."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import httpx
import numpy as np

from tests.app.conftest import LiveServer, make_server
from tests.app.learned import BARBELL, BENCH_NAME, LEARNING, LearnedStore, learned_barbell
from viewloc_bench.localizers import HttpBackend, HttpLocalizer
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
    assert learned.info == {"object_id": learned_barbell.object_id, "reused": True}
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
    assert len(dets) == 1
    assert np.linalg.norm(dets[0].pose.t_m2c - truth.t_m2c) < 0.05 * 700
    timing = localizer.last_timing_ms
    assert {"client_encode", "client_request", "server_total", "server_decode",
            "server_localize"} <= set(timing)
    # The round trip contains the server's own time.
    assert timing["client_request"] >= timing["server_total"] > 0

    # Other options (here another seed) are another object: not reused.
    other = HttpBackend(srv.url, seed=1, learning={"max_level": 1, "min_level": 1})
    assert other.object_name(obj, BARBELL.read_bytes()) != BENCH_NAME
