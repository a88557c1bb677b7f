"""Set generation: deterministic from the seed, cached, and its ground truth is sane."""

import dataclasses
import hashlib
import json
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from tests.viewloc_bench.conftest import tiny_paper_spec
from viewloc_bench import cli, povray, scenes, sets, shapes


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
    assert sets.spec_hash(sets.novel_spec(), 0) == "6d024278c752"
    assert sets.spec_hash(sets.paper_spec(2, 2), 0) == "aa8eabbc3708"  # --quick
    assert sets.spec_hash(sets.hard_spec(2, 2), 0) == "866a203a9bf3"
    assert sets.spec_hash(sets.novel_spec(2, 2), 0) == "f92c36b87c9b"
    # More than one instance per image is another set, whatever else it shares.
    multi = sets.multi_spec()
    assert sets.spec_hash(multi, 0) != sets.spec_hash(dataclasses.replace(multi, copies=2), 0)
    assert "copies" not in sets.spec_params(sets.hard_spec())
    assert sets.spec_params(multi)["copies"] == 3


def _draws_digest(spec: sets.SetSpec) -> str:
    """Digest of the scenes drawn for the first image of each N and the first negative
    (poses to 1e-6, no rendering), and of where each draw left its generator."""
    h = hashlib.sha256()
    for oi, n, i, present in sets._jobs(spec):
        if i > 0:
            continue
        rng = sets._image_rng(0, spec, oi, n, i)
        shape = shapes.SHAPES[spec.objects[oi]]()
        pts = np.asarray(shapes.to_trimesh(shape).convex_hull.vertices, dtype=np.float64)
        if not present:
            n = int(rng.integers(max(spec.n_values) // 2, max(spec.n_values) + 1))
        scene = scenes.draw_scene(
            rng, spec.camera, shape if present else None, pts if present else None, n, spec.scene
        )
        values = [scene.background_sdl, scene.fog_sdl, scene.material, str(len(scene.clutter))]
        values += [f"{x:.6f}" for _, rgb in scene.lights for x in rgb]
        for o in ([scene.target] if scene.target else []) + scene.clutter:
            values.append(o.texture)
            values += [f"{x:.6f}" for x in [*o.pose.R_m2c.ravel(), *o.pose.t_m2c, o.radius_mm]]
        values.append(str(rng.integers(2**31)))
        h.update("|".join(values).encode())
    return h.hexdigest()[:16]


def test_scenes_without_copies_draw_as_before_copies_existed() -> None:
    # Pinned with the generator before copies were added: scenes of one
    # instance use the random generator exactly as then (same draws, same
    # number of them), so the paper, hard and novel sets stay as they were.
    assert _draws_digest(sets.paper_spec()) == "de297e1d827a0eff"
    assert _draws_digest(sets.hard_spec()) == "9723f8f23f5f2f23"
    assert _draws_digest(sets.novel_spec()) == "dd589d1c1213b7ab"


def test_copies_come_after_target_and_fog_and_keep_apart() -> None:
    spec = sets.multi_spec()
    cam = spec.camera
    shape = shapes.bracket()
    pts = np.asarray(shapes.to_trimesh(shape).convex_hull.vertices, dtype=np.float64)
    for i in range(6):
        one = scenes.draw_scene(sets._image_rng(0, spec, 0, 4, i), cam, shape, pts, 4, spec.scene)
        rng = sets._image_rng(0, spec, 0, 4, i)
        three = scenes.draw_scene(rng, cam, shape, pts, 4, spec.scene, copies=2)
        # Lights, background, fog and target are drawn before the copies.
        assert (three.background_sdl, three.fog_sdl, three.material) == (
            one.background_sdl, one.fog_sdl, one.material)
        assert repr(three.lights) == repr(one.lights)
        assert one.target is not None and three.target is not None
        assert np.array_equal(three.target.pose.t_m2c, one.target.pose.t_m2c)
        assert one.copies == [] and len(three.copies) == 2
        assert three.instances == [three.target, *three.copies]
        for c in three.copies:
            assert c.shape is shape and c.texture == three.target.texture
        circles = [scenes.image_circle(cam, o, pts) for o in three.instances]
        for a in range(3):
            for b in range(a + 1, 3):
                oa, ob = three.instances[a], three.instances[b]
                gap_mm = np.linalg.norm(oa.pose.t_m2c - ob.pose.t_m2c)
                assert gap_mm > oa.radius_mm + ob.radius_mm
                (ca, ra), (cb, rb) = circles[a], circles[b]
                assert np.linalg.norm(ca - cb) > ra + rb
        # Clutter avoids every instance; behind only, it is behind the farthest.
        for o in three.clutter:
            for inst in three.instances:
                assert np.linalg.norm(o.pose.t_m2c - inst.pose.t_m2c) > o.radius_mm + inst.radius_mm
        far = max(inst.pose.t_m2c[2] + inst.radius_mm for inst in three.instances)
        behind = scenes.sample_clutter(rng, cam, 4, spec.scene, three.instances, behind_only=True)
        assert all(o.pose.t_m2c[2] - o.radius_mm > far for o in behind)


def test_copies_that_cannot_lie_apart_are_an_error() -> None:
    # Parts so near that each spans most of the image (~100 of 160 px): no second fits.
    spec = dataclasses.replace(sets.multi_spec(scale=0.25),
                               scene=scenes.SceneParams(distance_mm=(200.0, 220.0)))
    shape = shapes.bracket()
    pts = np.asarray(shapes.to_trimesh(shape).convex_hull.vertices, dtype=np.float64)
    with pytest.raises(RuntimeError, match="could not place copy 1 of 2"):
        scenes.draw_scene(np.random.default_rng(0), spec.camera, shape, pts, 0, spec.scene,
                          copies=2)


def test_label_renders_focus_on_one_instance() -> None:
    spec = sets.multi_spec(scale=0.25)
    shape = shapes.clamp()
    pts = np.asarray(shapes.to_trimesh(shape).convex_hull.vertices, dtype=np.float64)
    scene = scenes.draw_scene(sets._image_rng(0, spec, 1, 4, 0), spec.camera, shape, pts, 4,
                              spec.scene, copies=2)
    red, green = povray.vec(scenes.LABEL_TARGET), povray.vec(scenes.LABEL_CLUTTER)
    for focus, inst in enumerate(scene.instances):
        label = scenes.scene_sdl(scene, "label", focus)
        assert label.count(red) == 1 and label.count(green) == 2 + 4
        # The red object is placed where the focus instance is (the transform
        # follows the texture); the other instances are occluders.
        placed_at = povray.pose_matrix_sdl(inst.pose)
        after_red = label.split(red)[1]
        assert after_red.index(placed_at) < after_red.index(green)
        alone = scenes.scene_sdl(scene, "target", focus)
        assert alone.count(red) == 1 and green not in alone and placed_at in alone
    # The colour image shows every instance in the target's finish, and the clutter.
    assert scene.target is not None
    color = scenes.scene_sdl(scene, "color")
    assert color.count(scene.target.texture) == 3
    assert all(povray.pose_matrix_sdl(o.pose) in color for o in scene.instances + scene.clutter)
    with pytest.raises(ValueError, match="3 instances"):
        scenes.scene_sdl(scene, "label", 3)


def test_novel_spec_is_the_hard_scenes_with_new_objects() -> None:
    novel, hard = sets.novel_spec(), sets.hard_spec()
    assert novel.objects == ("tee", "clamp", "knob")
    assert not set(novel.objects) & set(hard.objects + sets.paper_spec().objects)
    assert (novel.images_per_n, novel.negatives, novel.n_values) == (10, 4, (0, 2, 4, 6))
    assert novel.camera == hard.camera and novel.scene == hard.scene
    assert len(set(sets.SET_CODES.values())) == len(sets.SET_CODES)
    assert set(sets.SPECS) <= set(cli.ALL_SETS) <= set(sets.SPECS) | {
        "hard-mono", "hard-hd", "hard-photos", "lmo", "lmo-grey"}
    assert cli.ALL_SETS.index("novel") == cli.ALL_SETS.index("hard") + 1


def _copied_set(folder: Path, root: Path,
                objects_edit: Callable[[dict[str, dict[str, object]]], object]) -> Path:
    """A copy of a generated set under ``root`` with its gt.json's objects edited."""
    copy = root / folder.name
    shutil.copytree(folder, copy)
    gt = json.loads((copy / "gt.json").read_text())
    objects_edit(gt["objects"])
    (copy / "gt.json").write_text(json.dumps(gt))
    return copy


def test_a_set_drawn_with_another_mesh_is_drawn_anew(tiny_paper_set: Path, tmp_path: Path):
    gt = json.loads((tiny_paper_set / "gt.json").read_text())
    assert gt["objects"]["barbell"]["mesh_sha256"] == sets.asset_digest("barbell")
    copy = _copied_set(tiny_paper_set, tmp_path,
                       lambda objs: objs["barbell"].update(mesh_sha256="0" * 64))
    logged: list[str] = []
    assert sets.generate(tiny_paper_spec(), 7, tmp_path, log=logged.append) == copy
    assert any("drawn with other meshes" in line for line in logged)
    redrawn = json.loads((copy / "gt.json").read_text())
    assert redrawn["objects"]["barbell"]["mesh_sha256"] == sets.asset_digest("barbell")
    assert redrawn["images"] == gt["images"]


def test_a_set_drawn_before_digests_were_recorded_is_kept(tiny_paper_set: Path, tmp_path: Path):
    copy = _copied_set(tiny_paper_set, tmp_path,
                       lambda objs: objs["barbell"].pop("mesh_sha256"))
    before = (copy / "gt.json").read_text()
    logged: list[str] = []
    assert sets.generate(tiny_paper_spec(), 7, tmp_path, log=logged.append) == copy
    assert logged == [] and (copy / "gt.json").read_text() == before


def test_shop_spec_is_the_hard_scenes_with_parts_no_other_set_has() -> None:
    shop, hard = sets.shop_spec(), sets.hard_spec()
    assert shop.objects == ("hexbolt", "shaft", "plate")
    others = {o for name, make in sets.SPECS.items() if name != "shop" for o in make().objects}
    assert not set(shop.objects) & others
    assert (shop.images_per_n, shop.negatives, shop.n_values) == (10, 4, (0, 2, 4, 6))
    assert shop.camera == hard.camera and shop.scene == hard.scene
    assert cli.ALL_SETS.index("shop") == cli.ALL_SETS.index("multi") + 1
    assert cli.set_spec("shop", 2, 1.0) == sets.shop_spec(2, 2)


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


def test_multi_spec_is_the_hard_scenes_with_three_instances() -> None:
    multi, hard = sets.multi_spec(), sets.hard_spec()
    assert (multi.objects, multi.n_values, multi.copies) == (("bracket", "clamp"), (0, 4), 3)
    assert (multi.images_per_n, multi.negatives) == (8, 0)
    assert multi.camera == hard.camera and multi.scene == hard.scene
    assert cli.ALL_SETS.index("multi") == cli.ALL_SETS.index("novel") + 1
    assert cli.ALL_SETS[-5:] == ("hard-mono", "hard-hd", "hard-photos", "lmo", "lmo-grey")
    # Smaller runs (--quick, --images-per-n) keep the others' negatives and add none here.
    assert cli.set_spec("multi", 2, 1.0) == sets.multi_spec(2, 0)
    assert cli.set_spec("paper", 2, 1.0) == sets.paper_spec(2, 2)
    assert cli.set_spec("novel", 1, 0.25) == sets.novel_spec(1, 1, 0.25)
    assert cli.set_spec("hard", None, 1.0) == sets.hard_spec()


def test_multi_set_ground_truth_is_sane(tiny_multi_set: Path) -> None:
    gt = json.loads((tiny_multi_set / "gt.json").read_text())
    assert gt["params"]["copies"] == 3
    bench = sets.load_generated(tiny_multi_set)
    cam = bench.images[0].camera
    assert (cam.width, cam.height) == (160, 120)
    assert [e["object"] for e in gt["images"]] == ["bracket", "clamp"]
    for e, im in zip(gt["images"], bench.images, strict=True):
        assert e["present"] and e["n_clutter"] == 2 and len(e["copies"]) == 2
        hull = np.asarray(shapes.to_trimesh(shapes.SHAPES[e["object"]]()).convex_hull.vertices)
        stem = e["file"][:-4]
        instances = [e, *e["copies"]]
        circles, masks = [], []
        for k, inst in enumerate(instances):
            assert 450.0 <= inst["distance_mm"] <= 1000.0
            assert inst["visible_fraction"] >= 0.6
            uv = cam.project(hull @ np.asarray(inst["R"]).T + np.asarray(inst["t_mm"]))
            assert uv.min() >= 0
            assert uv[:, 0].max() <= cam.width - 1 and uv[:, 1].max() <= cam.height - 1
            centre = cam.project(np.asarray(inst["t_mm"])[None])[0]
            circles.append((centre, np.linalg.norm(uv - centre, axis=1).max()))
            name = f"{stem}.png" if k == 0 else f"{stem}_c{k}.png"
            masks.append(np.asarray(Image.open(tiny_multi_set / "mask_visib" / name)) > 0)
            assert masks[-1].any()
        # The instances lie apart in the image: no two share a pixel or overlap.
        for a in range(3):
            for b in range(a + 1, 3):
                assert not (masks[a] & masks[b]).any()
                assert np.linalg.norm(circles[a][0] - circles[b][0]) > circles[a][1] + circles[b][1]
        # One target per instance, all of the same object, group and conditions.
        assert len(im.targets) == 3
        assert {(t.object_name, t.group, t.n_clutter) for t in im.targets} == {
            (e["object"], "N=2", 2)}
        assert all(t.conditions == im.targets[0].conditions for t in im.targets)
        for t, inst in zip(im.targets, instances, strict=True):
            assert t.pose is not None
            assert np.allclose(t.pose.t_m2c, inst["t_mm"])
            assert t.visible_fraction == inst["visible_fraction"]


def test_images_digest_follows_the_pixels_not_the_files(tiny_paper_set: Path,
                                                        tmp_path: Path) -> None:
    bench = sets.load_generated(tiny_paper_set)
    digest = sets.images_digest(bench.images)
    assert len(digest) == 64 and digest == sets.images_digest(bench.images)
    copy = tmp_path / "copy"
    copy.mkdir()
    for im in bench.images:
        (copy / im.path.name).write_bytes(im.path.read_bytes())
    moved = [dataclasses.replace(im, path=copy / im.path.name) for im in bench.images]
    assert sets.images_digest(moved) == digest  # the folder does not count
    first = moved[0].path
    pixels = np.asarray(Image.open(first)).copy()
    # The same pixels encoded otherwise: the same images.
    Image.fromarray(pixels).save(first, compress_level=0)
    assert first.read_bytes() != bench.images[0].path.read_bytes()
    assert sets.images_digest(moved) == digest
    # One pixel changed by one grey level: other images.
    pixels[0, 0, 0] ^= 1
    Image.fromarray(pixels).save(first)
    assert sets.images_digest(moved) != digest
    # The same images in another order: another fingerprint.
    assert sets.images_digest(bench.images[::-1]) != digest


def test_the_mono_set_is_the_same_targets_in_grey_stored_as_rgb(tiny_paper_set: Path) -> None:
    bench = sets.load_generated(tiny_paper_set)
    mono = sets.monochrome(bench)
    assert mono.name == f"{bench.name}-mono"
    assert mono.objects is bench.objects
    assert len(mono.images) == len(bench.images)
    for colour, grey in zip(bench.images, mono.images, strict=True):
        assert grey.targets == colour.targets and grey.camera == colour.camera
        assert grey.path.parent == tiny_paper_set / sets.MONO_FOLDER
        with Image.open(colour.path) as pil:
            rgb = np.asarray(pil.convert("RGB"), np.float64)
        with Image.open(grey.path) as pil:
            assert pil.mode == "RGB"
            stored = np.asarray(pil, np.int16)
        # Three equal channels holding the luminance of the colours.
        assert (stored == stored[:, :, :1]).all()
        luma = rgb @ np.array([0.299, 0.587, 0.114])
        assert np.abs(stored[:, :, 0] - luma).max() <= 1.0
    # Written once: a second call reuses the files and leaves no temporary one.
    stamps = {p: p.stat().st_mtime_ns for p in (tiny_paper_set / sets.MONO_FOLDER).iterdir()}
    assert [im.path for im in sets.monochrome(bench).images] == [im.path for im in mono.images]
    assert {p: p.stat().st_mtime_ns
            for p in (tiny_paper_set / sets.MONO_FOLDER).iterdir()} == stamps
    assert all(p.suffix == ".png" for p in stamps)


def test_an_hd_set_is_the_same_scenes_at_twice_the_resolution(tmp_path: Path) -> None:
    if povray.povray_executable() is None:
        pytest.skip("povray not installed")
    args = cli.parse_args(["--out", str(tmp_path), "--scale", "0.25", "--images-per-n", "1",
                           "--workers", "2"])
    loaded = cli.load_sets(args, ["paper", "paper-hd"])
    plain, hd = loaded["paper"], loaded["paper-hd"]
    assert len(hd.images) == len(plain.images) > 0
    for a, b in zip(plain.images, hd.images, strict=True):
        assert (b.camera.width, b.camera.height) == (2 * a.camera.width, 2 * a.camera.height)
        assert b.camera.fx == pytest.approx(2 * a.camera.fx)
        assert [(t.object_name, t.group) for t in b.targets] == [
            (t.object_name, t.group) for t in a.targets]
        # The same scene draws: the same conditions. (The part's placement is
        # drawn again where the visible fraction, measured on renders of the
        # image's size, falls otherwise: in tiny images like these, not at
        # full size, where all 80 hard scenes keep their distance.)
        for ta, tb in zip(a.targets, b.targets, strict=True):
            assert ta.conditions == tb.conditions
            assert (ta.pose is None) == (tb.pose is None)
        with Image.open(b.path) as pil:
            assert pil.size == (b.camera.width, b.camera.height)


def test_unshadowed_specs_draw_the_same_scenes_with_objects_that_cast_no_shadow() -> None:
    spec = sets.hard_spec()
    unshadowed = sets.unshadowed(spec)
    # The sets with shadows keep their names (pinned above); without, another.
    assert "cast_shadows" not in sets.spec_params(spec)["scene"]
    assert sets.spec_params(unshadowed)["scene"]["cast_shadows"] is False
    assert sets.spec_hash(unshadowed, 0) != sets.spec_hash(spec, 0)
    assert _draws_digest(unshadowed) == _draws_digest(spec)
    shape = shapes.SHAPES["bracket"]()
    pts = np.asarray(shapes.to_trimesh(shape).convex_hull.vertices, dtype=np.float64)
    drawn = [scenes.draw_scene(sets._image_rng(0, s, 0, 4, 0), s.camera, shape, pts, 4, s.scene)
             for s in (spec, unshadowed)]
    with_shadows, without = (scenes.scene_sdl(scene, "color") for scene in drawn)
    objects = drawn[1].instances + drawn[1].clutter
    assert without.count(" no_shadow") == len(objects) > 1
    assert "no_shadow" not in with_shadows
    assert without.replace(" no_shadow", "") == with_shadows
    # The masks are rendered self-lit: the same with or without shadows.
    assert scenes.scene_sdl(drawn[0], "label") == scenes.scene_sdl(drawn[1], "label")


def test_an_unshadowed_set_is_the_same_scenes_lit_where_shadows_fell(tmp_path: Path) -> None:
    if povray.povray_executable() is None:
        pytest.skip("povray not installed")
    assert "shop-unshadowed" in cli.OPT_IN_SETS and "shop-unshadowed" not in cli.ALL_SETS
    args = cli.parse_args(["--out", str(tmp_path), "--scale", "0.25", "--images-per-n", "1",
                           "--workers", "2"])
    loaded = cli.load_sets(args, ["hard", "hard-unshadowed"])
    plain, unshadowed = loaded["hard"], loaded["hard-unshadowed"]
    assert plain.folder != unshadowed.folder
    assert len(unshadowed.images) == len(plain.images) > 0
    lit_more = 0
    for a, b in zip(plain.images, unshadowed.images, strict=True):
        assert [(t.object_name, t.group, t.conditions) for t in b.targets] == [
            (t.object_name, t.group, t.conditions) for t in a.targets]
        for ta, tb in zip(a.targets, b.targets, strict=True):
            assert (ta.pose is None) == (tb.pose is None)
            if ta.pose is not None and tb.pose is not None:
                np.testing.assert_array_equal(ta.pose.R_m2c, tb.pose.R_m2c)
                np.testing.assert_array_equal(ta.pose.t_m2c, tb.pose.t_m2c)
        shadowed = np.asarray(Image.open(a.path), np.int16)
        lit = np.asarray(Image.open(b.path), np.int16)
        # Without shadows every surface gets all the light it got and more
        # (anti-aliasing samples an edge pixel differently here and there).
        assert np.percentile(lit - shadowed, 0.5) >= -2
        lit_more += int(np.count_nonzero(lit.sum(axis=2) > shadowed.sum(axis=2) + 30))
    assert lit_more > 0
