"""Set generation: deterministic from the seed, cached, and its ground truth is sane."""

import json
from pathlib import Path

import numpy as np
from PIL import Image

from tests.viewloc_bench.conftest import tiny_paper_spec
from viewloc_bench import cli, sets, shapes


def _gt_without_timing(folder: Path) -> dict[str, object]:
    gt = json.loads((folder / "gt.json").read_text())
    gt.pop("generation_s")
    return gt


def test_same_seed_same_set_other_seed_other_set(tiny_paper_set: Path, tmp_path: Path) -> None:
    again = sets.generate(tiny_paper_spec(), 7, tmp_path, workers=2, log=None)
    assert again.name == tiny_paper_set.name  # the hash names the content
    assert _gt_without_timing(again) == _gt_without_timing(tiny_paper_set)
    for f in sorted(tiny_paper_set.glob("*.png")):
        assert (again / f.name).read_bytes() == f.read_bytes()
    # Reused, not regenerated, when present.
    stamp = (again / "gt.json").stat().st_mtime_ns
    assert sets.generate(tiny_paper_spec(), 7, tmp_path, log=None) == again
    assert (again / "gt.json").stat().st_mtime_ns == stamp
    assert sets.spec_hash(tiny_paper_spec(), 8) != sets.spec_hash(tiny_paper_spec(), 7)


def test_quick_subset_images_equal_the_full_sets_first_images() -> None:
    spec = tiny_paper_spec()
    jobs_small = sets._jobs(spec)
    jobs_big = sets._jobs(sets.paper_spec(3, 2, scale=0.25))
    assert set(jobs_small) <= set(jobs_big)
    import dataclasses

    a = sets._image_rng(7, spec, 0, 4, 0).uniform(size=3)
    b = sets._image_rng(7, dataclasses.replace(spec, images_per_n=5), 0, 4, 0).uniform(size=3)
    assert np.array_equal(a, b)


def test_ground_truth_is_sane(tiny_paper_set: Path) -> None:
    gt = json.loads((tiny_paper_set / "gt.json").read_text())
    bench = sets.load_generated(tiny_paper_set)
    cam = bench.images[0].camera
    assert (cam.width, cam.height) == (96, 72)
    assert np.allclose(gt["camera"]["K"], cam.K)
    barbell = bench.objects["barbell"]
    assert abs(barbell.diameter_mm - np.hypot(180.0, 15.0)) < 1e-6
    assert len(barbell.symmetries) == 720  # continuous about x every 1 deg, times the end swap
    hull = np.asarray(shapes.to_trimesh(shapes.barbell()).convex_hull.vertices)
    present = [e for e in gt["images"] if e["present"]]
    assert [e["n_clutter"] for e in present] == [0, 4, 9]
    assert len(gt["images"]) - len(present) == 1
    for e in present:
        R = np.asarray(e["R"])
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-9)
        assert np.linalg.det(R) > 0.999
        assert 500.0 <= e["distance_mm"] <= 1100.0
        uv = cam.project(hull @ R.T + np.asarray(e["t_mm"]))
        assert uv.min() >= 0
        assert uv[:, 0].max() <= cam.width - 1 and uv[:, 1].max() <= cam.height - 1
        assert e["visible_fraction"] >= 0.6
        if e["n_clutter"] == 0:
            assert e["visible_fraction"] == 1.0
        assert (tiny_paper_set / e["file"]).exists()
        assert (tiny_paper_set / "mask_visib" / e["file"]).exists()
    assert {i.targets[0].group for i in bench.images} == {"N=0", "N=4", "N=9", "negative"}


def test_paper_and_hard_sets_keep_their_cached_folders() -> None:
    # The folders in bench_out/sets/ are named by these hashes: adding a set must
    # not regenerate the others (change the pins only when that is the intent).
    assert sets.spec_hash(sets.paper_spec(), 0) == "f0d27aeac2b8"
    assert sets.spec_hash(sets.hard_spec(), 0) == "69c2dbb56efe"
    assert sets.spec_hash(sets.paper_spec(2, 2), 0) == "aa8eabbc3708"  # --quick
    assert sets.spec_hash(sets.hard_spec(2, 2), 0) == "866a203a9bf3"


def test_novel_spec_is_the_hard_scenes_with_new_objects() -> None:
    novel, hard = sets.novel_spec(), sets.hard_spec()
    assert novel.objects == ("tee", "clamp", "knob")
    assert not set(novel.objects) & set(hard.objects + sets.paper_spec().objects)
    assert (novel.images_per_n, novel.negatives, novel.n_values) == (10, 4, (0, 2, 4, 6))
    assert novel.camera == hard.camera and novel.scene == hard.scene
    assert len(set(sets.SET_CODES.values())) == len(sets.SET_CODES)
    assert set(sets.SPECS) <= set(cli.ALL_SETS) <= set(sets.SPECS) | {"lmo"}
    assert cli.ALL_SETS.index("novel") == cli.ALL_SETS.index("hard") + 1


def test_novel_set_ground_truth_is_sane(tiny_novel_set: Path) -> None:
    gt = json.loads((tiny_novel_set / "gt.json").read_text())
    bench = sets.load_generated(tiny_novel_set)
    cam = bench.images[0].camera
    assert (cam.width, cam.height) == (160, 120)
    assert list(bench.objects) == ["tee", "clamp", "knob"]
    # The tee keeps its half turn about y; clamp and knob have only the identity.
    assert [len(bench.objects[n].symmetries) for n in ("tee", "clamp", "knob")] == [2, 1, 1]
    for name, obj in bench.objects.items():
        assert obj.mesh_path.name == shapes.ASSET_FILES[name]
        assert 100.0 <= obj.diameter_mm <= 140.0
        hull = np.asarray(shapes.to_trimesh(shapes.SHAPES[name]()).convex_hull.vertices)
        present = [e for e in gt["images"] if e["present"] and e["object"] == name]
        assert len(present) == 1
        for e in present:
            assert 450.0 <= e["distance_mm"] <= 1000.0
            assert e["n_clutter"] == 2 and e["visible_fraction"] >= 0.6
            uv = cam.project(hull @ np.asarray(e["R"]).T + np.asarray(e["t_mm"]))
            assert uv.min() >= 0
            assert uv[:, 0].max() <= cam.width - 1 and uv[:, 1].max() <= cam.height - 1
            # The object is in the picture: its visible mask is not empty.
            mask = np.asarray(Image.open(tiny_novel_set / "mask_visib" / e["file"]))
            assert mask.any()
    negatives = [e for e in gt["images"] if not e["present"]]
    assert sorted(e["object"] for e in negatives) == ["clamp", "knob", "tee"]
