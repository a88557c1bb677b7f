"""Symmetries declared in the spec of ``POST /v1/objects`` and shown on the ``Object``."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import trimesh

from model_store import ModelStore
from tests.app.conftest import TEST_TASKS, LiveServer
from tests.app.helpers import FAST_LEARNING, assert_problem, box_stl, wait_job
from tests.app.learned import LearnedStore, learned_barbell
from viewloc_client import ViewlocClient

__all__ = ["learned_barbell"]

SLEEPY = {**TEST_TASKS, "learn_mesh": TEST_TASKS["sleepy"]}
FLIP_X = [1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1]
TURN_Z_90 = [0, -1, 0, 0, 1, 0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]
MIRROR_X = [-1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]
Z_AXIS = {"axis": [0, 0, 1], "offset": [0, 0, 0]}


def _box_cm_off_centre() -> bytes:
    """A 4 x 2 x 1 cm box centred at (1 cm, 0, 0), as STL in cm."""
    box = trimesh.creation.box((4.0, 2.0, 1.0))
    box.apply_translation([1.0, 0.0, 0.0])
    return bytes(box.export(file_type="stl"))


def _upload(c: httpx.Client, spec: dict[str, Any] | str, mesh: bytes | None = None,
            ) -> httpx.Response:
    return c.post("/v1/objects",
                  files={"mesh": ("part.stl", mesh if mesh is not None else box_stl(),
                                  "application/octet-stream")},
                  data={"spec": spec if isinstance(spec, str) else json.dumps(spec)})


def _ready(c: httpx.Client, uploads: dict[str, httpx.Response]) -> dict[str, dict[str, Any]]:
    """The objects once learned, by name (all jobs queued before waiting for any)."""
    out = {}
    for name, r in uploads.items():
        assert r.status_code == 202, r.text
        created = r.json()
        assert created["object"]["symmetries"] is None  # learning: no model yet
        job = wait_job(c, created["job"]["job_id"], timeout=120)
        assert job["state"] == "succeeded", job
        obj: dict[str, Any] = c.get(f"/v1/objects/{created['object']['object_id']}").json()
        assert obj["state"] == "ready"
        out[name] = obj
    return out


def _group(sym: dict[str, Any]) -> list[np.ndarray]:
    return [np.asarray(t, float).reshape(4, 4) for t in sym["symmetries_discrete"]]


def test_declared_symmetries_replace_the_detected_ones(
    learned_barbell: LearnedStore, make_server: Callable[..., LiveServer], tmp_path: Path
) -> None:
    learned_barbell.copy_to(tmp_path / "var")
    srv = make_server()
    with httpx.Client(base_url=srv.url, timeout=30) as c:
        # Undeclared: the detector's group (the barbell turns about its bar and flips).
        detected = c.get(f"/v1/objects/{learned_barbell.object_id}").json()["symmetries"]
        assert len(detected["symmetries_continuous"]) == 1
        assert len(detected["symmetries_discrete"]) == 1

        # Declared in cm: 180° about the z-parallel line through the box centre
        # (1 cm, 0, 0) only; the box's other two flips (which the detector
        # would find) are left out, as a mark tells them apart.
        turn = [-1, 0, 0, 2, 0, -1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]
        learned = _ready(c, {
            "half": _upload(c, {"name": "half", "units": "cm", "learning": FAST_LEARNING,
                                "symmetries": {"symmetries_discrete": [turn]}},
                            _box_cm_off_centre()),
            # A 90° turn is completed into its group.
            "quarter": _upload(c, {"name": "quarter", "learning": FAST_LEARNING,
                                   "symmetries": {"symmetries_discrete": [TURN_Z_90]}}),
            # A continuous axis (which no detector would accept on a box) is
            # stored with its offset in mm.
            "axis": _upload(c, {"name": "axis", "units": "cm", "learning": FAST_LEARNING,
                                "symmetries": {"symmetries_discrete": [FLIP_X],
                                               "symmetries_continuous": [
                                                   {"axis": [0, 0, 3], "offset": [0, 0, 0.5]}]}}),
            # Declared as asymmetric: nothing but the identity.
            "none": _upload(c, {"name": "none", "learning": FAST_LEARNING, "symmetries": {}}),
        })
        half, quarter, axis, none = (learned[k] for k in ("half", "quarter", "axis", "none"))
        (T,) = _group(half["symmetries"])
        np.testing.assert_allclose(T[:3, :3], np.diag([-1.0, -1.0, 1.0]), atol=1e-12)
        np.testing.assert_allclose(T[:3, 3], [20.0, 0.0, 0.0], atol=1e-9)
        assert half["symmetries"]["symmetries_continuous"] == []

        assert len(quarter["symmetries"]["symmetries_discrete"]) == 3
        assert axis["symmetries"]["symmetries_continuous"] == [
            {"axis": [0.0, 0.0, 1.0], "offset": [0.0, 0.0, 5.0]}]
        np.testing.assert_allclose(_group(axis["symmetries"])[0],
                                   np.asarray(FLIP_X, float).reshape(4, 4), atol=1e-12)
        assert none["symmetries"] == {"symmetries_discrete": [], "symmetries_continuous": []}

        listed = {o["name"]: o for o in c.get("/v1/objects").json()["objects"]}
        assert listed["half"]["symmetries"] == half["symmetries"]
        assert listed["none"]["symmetries"] == none["symmetries"]
    with ViewlocClient(srv.url) as client:
        assert client.get_object(axis["object_id"]).symmetries == axis["symmetries"]

    # What the Object shows is what the stored model (used by localize) holds.
    model = ModelStore(tmp_path / "var").load_model(half["object_id"])
    assert model.symmetries.shape == (2, 4, 4) and model.symmetry_axis is None
    np.testing.assert_allclose(model.symmetries[1], T, atol=1e-12)


def test_bad_declarations_are_422_naming_the_entry_and_store_nothing(
    make_server: Callable[..., LiveServer], tmp_path: Path
) -> None:
    srv = make_server(tasks=SLEEPY)
    with ViewlocClient(srv.url) as client:
        good, _ = client.learn_mesh(box_stl(), filename="box.stl", name="good", units="cm",
                                    # 180° about the x-parallel line y = 2.5 mm.
                                    symmetries={"symmetries_discrete": [FLIP_X[:7] + [0.5]
                                                                        + FLIP_X[8:]]})
    oid = good.object_id
    with httpx.Client(base_url=srv.url, timeout=30) as c:
        files_before = sorted(p.relative_to(tmp_path) for p in (tmp_path / "var").rglob("*")
                              if p.is_file() and "sqlite" not in p.name)
        field = "spec.symmetries"
        d = f"{field}.symmetries_discrete"
        cont = f"{field}.symmetries_continuous"
        cases: list[tuple[dict[str, Any] | str, str]] = [
            ({"symmetries_discrete": [FLIP_X, [1, 2, 3]]}, f"{d}[1]"),  # not 16 numbers
            ({"symmetries_discrete": [[2, *FLIP_X[1:]]]}, f"{d}[0]"),  # not orthonormal
            ({"symmetries_discrete": [FLIP_X, MIRROR_X]}, f"{d}[1]"),  # det -1
            ({"symmetries_discrete": [[*FLIP_X[:12], 0, 0, 1, 1]]}, f"{d}[0]"),  # last row
            ({"symmetries_discrete": [[*FLIP_X[:3], math.nan, *FLIP_X[4:]]]}, f"{d}[0][3]"),
            ({"symmetries_discrete": [[1, 0, 0, 0, 0, math.cos(1), -math.sin(1), 0,
                                       0, math.sin(1), math.cos(1), 0, 0, 0, 0, 1]]}, d),
            ({"symmetries_continuous": [Z_AXIS, {"axis": [1, 0, 0]}]}, cont),
            ({"symmetries_continuous": [{"axis": [0, 0, 0], "offset": [0, 0, 0]}]},
             f"{cont}[0].axis"),
            ({"symmetries_continuous": [{"axis": [0, 1], "offset": [0, 0, 0]}]},
             f"{cont}[0].axis"),
            ({"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, math.inf]}]},
             f"{cont}[0].offset[2]"),
            # A 90° turn about x moves a continuous z axis: no finite part has both.
            ({"symmetries_discrete": [[1, 0, 0, 0, 0, 0, -1, 0, 0, 1, 0, 0, 0, 0, 0, 1]],
              "symmetries_continuous": [Z_AXIS]}, f"{d}[0]"),
            # The box reaches 22.9 mm from its origin: no symmetry's axis runs
            # a metre from it, or moves it by more than twice that.
            ({"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [1000, 0, 0]}]},
             f"{cont}[0].offset"),
            ({"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [1.7e308, 1.7e308, 0]}]},
             f"{cont}[0].offset"),
            ({"symmetries_discrete": [[-1, 0, 0, 2e300, 0, -1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]]},
             f"{d}[0]"),
            ({"symmetries_discrete": [[-1, 0, 0, 46, 0, -1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]]},
             f"{d}[0]"),
            ({"symmetries_discret": [FLIP_X]}, f"{field}.symmetries_discret"),
            ('{"symmetries": [1, 2]}', field),
            ('{"symmetries": {"symmetries_discrete": [[1e999' + ", 0" * 15 + "]]}}", f"{d}[0][0]"),
        ]
        for i, (sym, name) in enumerate(cases):
            spec = sym if isinstance(sym, str) else {"name": "bad", "symmetries": sym}
            try:
                assert_problem(_upload(c, spec), 422, name)
            except AssertionError as exc:
                raise AssertionError(f"case {i}: {exc}") from exc
        files_after = sorted(p.relative_to(tmp_path) for p in (tmp_path / "var").rglob("*")
                             if p.is_file() and "sqlite" not in p.name)
        assert files_after == files_before
        assert [o["object_id"] for o in c.get("/v1/objects").json()["objects"]] == [oid]
    # The accepted declaration is kept for the job, checked and in mm.
    meta = ModelStore(tmp_path / "var").get_object(oid).upload_meta
    assert meta["symmetries"] == {"symmetries_discrete": [[float(v) for v in FLIP_X[:7]] + [5.0]
                                                          + [float(v) for v in FLIP_X[8:]]],
                                  "symmetries_continuous": []}


def _photo() -> bytes:
    """A bright plate with a hole on a dark ground, 160 x 120 PNG."""
    img = np.full((120, 160), 30, np.uint8)
    cv2.rectangle(img, (50, 35), (110, 85), 220, -1)
    cv2.circle(img, (95, 50), 8, 30, -1)
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return bytes(buf.tobytes())


def test_from_images_takes_declared_symmetries(
    make_server: Callable[..., LiveServer], tmp_path: Path
) -> None:
    # No mesh, so nothing is detected: a declaration is the only way to say it.
    srv = make_server()
    views = [{"azimuth_deg": 30.0 * i, "polar_deg": 60.0, "distance_mm": 400.0}
             for i in range(4)]
    camera = {"fx": 300.0, "fy": 300.0, "cx": 79.5, "cy": 59.5}
    images = [("images", (f"v{i}.png", _photo(), "image/png")) for i in range(4)]

    def post(symmetries: Any) -> httpx.Response:
        spec = {"name": "plate", "camera": camera, "object_diameter_mm": 80.0, "views": views,
                "learning": {"max_level": 0, "min_level": 0}, "symmetries": symmetries}
        return c.post("/v1/objects/from-images", files=images, data={"spec": json.dumps(spec)})

    with httpx.Client(base_url=srv.url, timeout=30) as c:
        assert_problem(post({"symmetries_continuous": [{"axis": [0, 0, 0]}]}), 422,
                       "spec.symmetries.symmetries_continuous[0].axis")
        assert_problem(post({"symmetries_discrete": [MIRROR_X]}), 422,
                       "spec.symmetries.symmetries_discrete[0]")
        # The photos look at a point on the part, 80 mm across: an axis 81 mm
        # from it misses the part.
        assert_problem(post({"symmetries_continuous": [{"axis": [0, 0, 1],
                                                        "offset": [81.0, 0, 0]}]}), 422,
                       "spec.symmetries.symmetries_continuous[0].offset")
        assert c.get("/v1/objects").json()["objects"] == []
        obj = _ready(c, {"plate": post({"symmetries_discrete": [TURN_Z_90]})})["plate"]
    assert obj["source"] == "images"
    assert len(obj["symmetries"]["symmetries_discrete"]) == 3
    model = ModelStore(tmp_path / "var").load_model(obj["object_id"])
    assert model.symmetries.shape == (4, 4, 4)
