"""Rendered training photos for the ``-photos`` sets: photos whose masks and stated
views agree, and both backends learning from them."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import httpx
import numpy as np
import pytest
import trimesh

from tests.app.conftest import LiveServer, make_server
from viewloc_bench import cli
from viewloc_bench.localizers import CoreBackend, HttpBackend, LearnedObject
from viewloc_bench.photos import (
    PART_SPAN_PX,
    PhotoBackend,
    TrainingPhotos,
    render_photos,
)
from viewloc_bench.sets import BenchObject
from viewloc_core.mesh import mesh_diameter_mm

__all__ = ["make_server"]

BRACKET = Path(__file__).resolve().parents[2] / "viewloc_bench" / "assets" / "bracket.stl"


def _bracket() -> BenchObject:
    mesh = trimesh.load(BRACKET, force="mesh")
    return BenchObject("bracket", BRACKET, mesh_diameter_mm(mesh), np.eye(4)[None],
                       np.asarray(mesh.vertices))


def test_photos_show_the_part_where_their_views_say() -> None:
    obj = _bracket()
    photos = render_photos(obj, 8, seed=1)
    assert len(photos.images) == len(photos.masks) == len(photos.views) == 8
    cam = photos.camera
    for image, mask, view in zip(photos.images, photos.masks, photos.views, strict=True):
        assert image.shape == (cam.height, cam.width, 3) and image.dtype == np.uint8
        assert set(np.unique(mask)) == {0, 255}
        # The stated view, read as learning reads it, puts the mesh on the mask.
        pose = view.pose()
        uv = cam.project(obj.pts_obj @ pose.R_m2c.T + pose.t_m2c)
        ij = np.rint(uv).astype(int)
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < cam.width) & (ij[:, 1] >= 0) & (
            ij[:, 1] < cam.height)
        assert inside.all()
        near = np.zeros_like(mask)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                near |= np.roll(mask, (dy, dx), axis=(0, 1))
        assert np.mean(near[ij[:, 1], ij[:, 0]] > 0) > 0.99
        # The part is about as large as asked: no wider than its diameter.
        assert np.ptp(uv, axis=0).max() <= PART_SPAN_PX[1] + 2
        # The backdrop is one colour with sensor noise.
        assert image[mask == 0].std(axis=0).max() < 4.0
    # A seed gives the same photos; another seed others.
    assert render_photos(obj, 8, seed=1).digest() == photos.digest()
    assert render_photos(obj, 8, seed=2).digest() != photos.digest()


class _Recording:
    """Records the photos it is asked to learn from (a stand-in for the method)."""

    label = "recording"

    def __init__(self) -> None:
        self.photos: list[TrainingPhotos] = []

    def check(self) -> None:
        pass

    def learn(self, obj: BenchObject) -> LearnedObject:
        raise AssertionError("a -photos set must not learn from the mesh")

    def learn_photos(self, obj: BenchObject, photos: TrainingPhotos) -> LearnedObject:
        self.photos.append(photos)
        return LearnedObject(obj.name, lambda image, camera, max_detections=1: [], 0.5, 12, 9)


def test_photo_backend_learns_from_photos_not_the_mesh() -> None:
    inner = _Recording()
    backend = PhotoBackend(inner, count=5, seed=3)
    assert backend.label == "recording, parts learned from 5 masked photos"
    learned = backend.learn(_bracket())
    assert len(inner.photos) == 1 and len(inner.photos[0].images) == 5
    assert learned.info["photos"] == 5 and learned.info["photos_render_s"] > 0
    assert inner.photos[0].digest() == render_photos(_bracket(), 5, seed=3).digest()


def test_cli_knows_the_photos_sets_and_refuses_no_photos(
        capsys: pytest.CaptureFixture[str]) -> None:
    assert "hard-photos" in cli.ALL_SETS
    assert cli.main(["--sets", "hard-photos", "--photos", "0"]) == 2
    assert "--photos must be at least 1" in capsys.readouterr().err


def test_both_backends_learn_a_part_from_its_photos(
        make_server: Callable[..., LiveServer]) -> None:
    """The core and the service learn the same model from the same photos, and the
    service reuses it for the same photos."""
    obj = _bracket()
    photos = render_photos(obj, 12, seed=0)
    core = CoreBackend().learn_photos(obj, photos)
    assert core.training_views == 12 and core.info["refinable"] is False
    # The same photos learn the same model.
    assert CoreBackend().learn_photos(obj, photos).info["model_sha256"] == core.info["model_sha256"]

    srv = make_server()
    backend = HttpBackend(srv.url)
    first = backend.learn_photos(obj, photos)
    assert first.info["reused"] is False
    # The service's model is the core's, byte for byte.
    assert first.info["model_sha256"] == core.info["model_sha256"]
    assert (first.training_views, first.model_views) == (core.training_views, core.model_views)
    objects = httpx.get(f"{srv.url}/v1/objects").json()["objects"]
    assert [(o["source"], o["name"].endswith(":photos")) for o in objects] == [("images", True)]
    again = backend.learn_photos(obj, photos)
    assert again.info == {"object_id": first.info["object_id"], "reused": True,
                          "model_sha256": first.info["model_sha256"]}
    # Other photos are another object.
    other = backend.learn_photos(obj, render_photos(obj, 12, seed=1))
    assert other.info["reused"] is False

    # Both find the part in a photo like their own (12 photos: no hull, not refined).
    scene = render_photos(obj, 13, seed=5)
    for learned in (core, first):
        dets = learned.localize(scene.images[4], scene.camera)
        assert dets, learned
        truth = scene.views[4].pose()
        uv = scene.camera.project(truth.t_m2c[None])[0]
        assert np.hypot(dets[0].similarity.x - uv[0], dets[0].similarity.y - uv[1]) < 0.1 * max(
            PART_SPAN_PX)
