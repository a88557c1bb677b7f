"""Runner smoke tests with an oracle-plus-noise localizer (a test double for the method)."""

import hashlib
import json
import socket
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from viewloc_bench import cli, runner, sets
from viewloc_bench.localizers import CoreBackend, HttpBackend, LearnedObject, detection_from_json
from viewloc_core.camera import Camera
from viewloc_core.detection import Detection, Similarity2D
from viewloc_core.pose import Pose


class OracleBackend:
    """Knows the truth of each image (by its pixels) and answers it with a little noise."""

    label = "oracle"

    def __init__(self, bench: sets.BenchSet, miss: str, fp: bool) -> None:
        self.truth: dict[str, Pose | None] = {}
        for im in bench.images:
            key = self._key(np.asarray(_load(im.path)))
            self.truth[key] = im.targets[0].pose
            if im.path.name == miss:
                self.truth[key] = "miss"  # type: ignore[assignment]
        self.fp = fp
        self.rng = np.random.default_rng(0)

    @staticmethod
    def _key(image: np.ndarray) -> str:
        return hashlib.sha1(image.tobytes()).hexdigest()

    def check(self) -> None:
        pass

    def learn(self, obj: sets.BenchObject) -> LearnedObject:
        def run(image: np.ndarray, camera: Camera) -> list[Detection]:
            pose = self.truth[self._key(image)]
            if pose == "miss" or (pose is None and not self.fp):
                return []
            if pose is None:
                pose = Pose(np.eye(3), np.array([0.0, 0.0, 800.0]))
            noise = Rotation.from_rotvec(self.rng.normal(size=3) * np.radians(0.5)).as_matrix()
            est = Pose(noise @ pose.R_m2c, pose.t_m2c + self.rng.normal(size=3))
            uv = camera.project(est.t_m2c[None])[0]
            return [Detection(0.9, -10.0, 0, 0.0, 90.0, Similarity2D(uv[0], uv[1], 0.0, 1.0), est)]

        return LearnedObject(obj.name, run, 0.01, 130, 18)


def _load(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"), dtype=np.uint8)


def test_oracle_run_table_and_json(tiny_paper_set: Path, tmp_path: Path) -> None:
    bench = sets.load_generated(tiny_paper_set)
    miss = next(im.path.name for im in bench.images if im.targets[0].group == "N=4")
    res = runner.evaluate_set(bench, OracleBackend(bench, miss, fp=True), log=lambda s: None)
    groups = {g["group"]: g for g in res["groups"]}
    assert set(groups) == {"N=0", "N=4", "N=9"}
    assert groups["N=0"]["recognition_2d"] == 1.0 and groups["N=0"]["recognition_6d"] == 1.0
    assert groups["N=4"]["recognition_2d"] == 0.0 and groups["N=4"]["mean_g"] is None
    o = res["overall"]
    assert o["targets"] == 3
    assert o["recognition_2d"] == pytest.approx(2 / 3, abs=1e-3)
    assert 0.99 < o["mean_g"] <= 1.0
    # The missed target is a miss at every threshold: AR is at most 2/3.
    assert o["ar_mssd"] <= 0.6667 and o["ar_mspd"] <= 0.6667
    assert o["ar_mssd"] > 0.6 and o["adds_recall"] == pytest.approx(2 / 3, abs=1e-3)
    assert o["worst_group_recognition_2d"] == 0.0
    gt_images = json.loads((tiny_paper_set / "gt.json").read_text())["images"]
    neg_bg = next(str(e["background"]) for e in gt_images if not e["present"])
    assert res["negatives"] == {"images": 1, "images_with_false_positive": 1, "false_positives": 1,
                                "by_background": {neg_bg: [1, 1]}}
    assert res["objects"]["barbell"]["model_views"] == 18
    table = runner.format_table("paper", bench, res, "oracle")
    assert "N=9" in table and "overall" in table and "false positives: 1 in 1/1" in table
    out = tmp_path / "results.json"
    runner.write_json({"sets": {"paper": res}}, out)
    back = json.loads(out.read_text())
    assert back["sets"]["paper"]["overall"]["targets"] == 3
    missed = [r for r in back["sets"]["paper"]["records"] if not r["detected"]]
    assert len(missed) == 1 and missed[0]["image"] == miss
    runner.plot_fig2(res, tmp_path / "fig2.png")
    assert (tmp_path / "fig2.png").read_bytes()[:4] == b"\x89PNG"


def test_results_broken_down_by_scene_condition(tiny_paper_set: Path) -> None:
    bench = sets.load_generated(tiny_paper_set)
    present = [im for im in bench.images if im.targets[0].pose is not None]
    missed = present[0]
    res = runner.evaluate_set(bench, OracleBackend(bench, missed.path.name, fp=False),
                              log=lambda s: None)
    gt = {e["file"]: e for e in json.loads((tiny_paper_set / "gt.json").read_text())["images"]}
    by = res["by_condition"]
    assert set(by) == set(sets.CONDITION_KEYS)
    for key, rows in by.items():
        # Every target is counted once under its own value of each condition.
        assert sum(r["targets"] for r in rows) == len(present)
        expected = {str(gt[im.path.name][key]) for im in present}
        assert [r["value"] for r in rows] == sorted(expected)
        miss_value = str(gt[missed.path.name][key])
        for r in rows:
            same = [im for im in present if str(gt[im.path.name][key]) == r["value"]]
            hits = sum(1 for im in same if im is not missed)
            assert r["recognition_2d"] == pytest.approx(hits / len(same), abs=1e-3)
            assert (r["value"] == miss_value) == (r["recognition_2d"] < 1.0)
    table = runner.format_table("paper", bench, res, "oracle")
    assert "rec2D by background: " in table
    neg_bg = next(str(e["background"]) for e in gt.values() if not e["present"])
    assert res["negatives"]["by_background"] == {neg_bg: [0, 1]}
    assert f"false positive by background: {neg_bg} 0/1" in table


def test_cli_without_a_service_prints_the_table_and_exits_0(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again: nothing listens there
    code = cli.main([
        "--sets", "paper", "--url", f"http://127.0.0.1:{port}", "--images-per-n", "1",
        "--scale", "0.25", "--out", str(tmp_path), "--seed", "3",
    ])
    out = capsys.readouterr().out
    assert code == 0
    assert "engine not available" in out
    assert "N=9" in out
    res = json.loads((tmp_path / "results.json").read_text())
    assert res["sets"]["paper"]["status"] == "engine not available"
    assert res["sets"]["paper"]["images"] == 11
    # The fingerprint of the images the figures were measured on.
    bench = sets.load_generated(Path(res["sets"]["paper"]["folder"]))
    assert res["sets"]["paper"]["images_sha256"] == sets.images_digest(bench.images)


def test_detection_from_api_json() -> None:
    d = detection_from_json({
        "score": 0.93, "log_probability": -12.4, "model_view": 7,
        "view": {"azimuth_deg": 30.0, "polar_deg": 60.0},
        "similarity": {"x": 301.2, "y": 188.7, "angle_deg": 12.5, "scale": 1.07},
        "pose": {"R": np.eye(3).tolist(), "t_mm": [1.0, 2.0, 500.0],
                 "quaternion_wxyz": [1, 0, 0, 0], "euler_xyz_deg": [0, 0, 0]},
        "refined": True,
    })
    assert d.similarity.x == 301.2 and d.model_view == 7 and d.refined
    assert np.allclose(d.pose.t_m2c, [1.0, 2.0, 500.0]) and d.polar_deg == 60.0


@pytest.mark.parametrize("url", [None, "http://127.0.0.1:9"])
def test_learn_seed_sets_the_models_seed_not_the_scenes(url: str | None) -> None:
    base = ["--seed", "3"] + (["--url", url] if url else [])
    args = cli.parse_args([*base, "--learn-seed", "7"])
    backend = cli.make_backend(args)
    assert isinstance(backend, HttpBackend if url else CoreBackend)
    assert args.seed == 3  # the scenes are generated from --seed
    assert backend.seed == 7
    if isinstance(backend, HttpBackend):
        assert backend.learning["seed"] == 7  # what the upload asks the service for
    # Without --learn-seed, learning follows --seed as before.
    default = cli.make_backend(cli.parse_args(base))
    assert isinstance(default, HttpBackend if url else CoreBackend)
    assert default.seed == 3


def _detection_at(camera: Camera, pose: Pose, score: float) -> Detection:
    """A detection with ``pose`` whose reference point is the pose's projected origin."""
    uv = camera.project(pose.t_m2c[None])[0]
    return Detection(score, -10.0, 0, 0.0, 90.0, Similarity2D(uv[0], uv[1], 0.0, 1.0), pose)


class MultiOracleBackend:
    """Answers each multi image with the truth of its instances, as scripted per image.

    ``script[i]`` lists what the detections of image ``i`` are: an instance
    index (its true pose), ``"elsewhere"`` (a place far from every instance),
    each with a score; images without a script get every instance exactly.
    """

    label = "multi oracle"

    def __init__(self, bench: sets.BenchSet,
                 script: dict[int, list[tuple[int | str, float]]]) -> None:
        self.images: dict[str, tuple[int, sets.BenchImage]] = {}
        for i, im in enumerate(bench.images):
            self.images[OracleBackend._key(np.asarray(_load(im.path)))] = (i, im)
        self.script = script
        self.calls: list[tuple[str, int]] = []

    def check(self) -> None:
        pass

    def learn(self, obj: sets.BenchObject) -> LearnedObject:
        def run(image: np.ndarray, camera: Camera, max_detections: int = 1) -> list[Detection]:
            i, im = self.images[OracleBackend._key(image)]
            self.calls.append((im.path.name, max_detections))
            poses = [t.pose for t in im.targets if t.pose is not None]
            answers = self.script.get(i, [(k, 0.9 - 0.1 * k) for k in range(len(poses))])
            dets = []
            for what, score in answers:
                if what == "elsewhere":
                    # The image corner farthest from every instance.
                    corners = [np.array([u, v]) for u in (0.0, camera.width - 1.0)
                               for v in (0.0, camera.height - 1.0)]
                    origins = [camera.project(p.t_m2c[None])[0] for p in poses]
                    uv = max(corners, key=lambda c: min(np.linalg.norm(c - o) for o in origins))
                    t = camera.ray(uv[None])[0] * 800.0
                    dets.append(_detection_at(camera, Pose(np.eye(3), t), score))
                else:
                    assert isinstance(what, int)
                    dets.append(_detection_at(camera, poses[what], score))
            return dets[:max_detections]

        return LearnedObject(obj.name, run, 0.01, 130, 18)


def test_multi_images_pair_detections_with_instances(tiny_multi_set: Path) -> None:
    bench = sets.load_generated(tiny_multi_set)
    assert [len(im.targets) for im in bench.images] == [3, 3]
    # Image 0: the worse of two fits of instance 0 is a duplicate (listed first,
    # to show the pairing goes by score), instance 2 is missed. Image 1: one
    # detection lies elsewhere, instance 0 is missed.
    script: dict[int, list[tuple[int | str, float]]] = {
        0: [(0, 0.6), (0, 0.9), (1, 0.7)],
        1: [(2, 0.8), ("elsewhere", 0.7), (1, 0.5)],
    }
    backend = MultiOracleBackend(bench, script)
    res = runner.evaluate_set(bench, backend, log=lambda s: None)
    assert sorted(backend.calls) == sorted((im.path.name, 3) for im in bench.images)
    assert res["copies"] == {"images": 2, "per_image": [3], "targets": 6, "found_2d": 4,
                             "detections": 6, "duplicates": 1, "elsewhere": 1}
    records = res["records"]
    assert len(records) == 6 and all(r["copies"] == 3 for r in records)
    by_image = {im.path.name: [r for r in records if r["image"] == im.path.name]
                for im in bench.images}
    first, second = (by_image[im.path.name] for im in bench.images)
    assert [r["detected"] for r in first] == [True, True, False]
    assert [r["detected"] for r in second] == [False, True, True]
    # Each instance is scored with its own detection: the best one for instance 0.
    assert first[0]["score"] == 0.9 and first[1]["score"] == 0.7
    assert second[1]["score"] == 0.5 and second[2]["score"] == 0.8
    found = [r for r in records if r["detected"]]
    assert all(r["recognized_2d"] and r["recognized_6d"] and r["ref_err_px"] < 1e-6
               for r in found)
    assert res["overall"]["recognition_2d"] == pytest.approx(4 / 6, abs=1e-3)
    table = runner.format_table("multi", bench, res, "oracle")
    assert "copies: 3 per image, 2 images: 4/6 found in 2D, 1 duplicates, 1 elsewhere" in table


def test_single_instance_sets_have_no_copies_summary(tiny_paper_set: Path) -> None:
    bench = sets.load_generated(tiny_paper_set)
    res = runner.evaluate_set(bench, OracleBackend(bench, "", fp=False), log=lambda s: None)
    assert "copies" not in res and all("copies" not in r for r in res["records"])
    assert "copies:" not in runner.format_table("paper", bench, res, "oracle")


def test_a_detection_goes_to_the_nearest_free_instance_it_recognizes() -> None:
    cam = Camera(500.0, 500.0, 320.0, 240.0, 640, 480)
    obj = sets.BenchObject("part", Path("part.ply"), 200.0, np.eye(4)[None], np.zeros((1, 3)))
    # Two instances 10 px apart at 500 mm: each recognizes within 0.1 x 200 px = 20 px.
    targets = [
        sets.Target("part", Pose(np.eye(3), np.array([0.0, 0.0, 500.0])), "N=0"),
        sets.Target("part", Pose(np.eye(3), np.array([10.0, 0.0, 500.0])), "N=0"),
    ]

    def at(u: float, score: float) -> Detection:
        return Detection(score, 0.0, 0, 0.0, 0.0, Similarity2D(320.0 + u, 240.0, 0.0, 1.0),
                         Pose(np.eye(3), np.array([0.0, 0.0, 500.0])))

    # Best first: 8 px goes to the nearer instance 1; 9 px recognizes both but
    # only instance 0 is free; 5 px finds both taken; 100 px recognizes none.
    dets = [at(100.0, 0.95), at(5.0, 0.7), at(9.0, 0.8), at(8.0, 0.9)]
    assigned, duplicates, elsewhere = runner.assign_detections(dets, targets, obj, cam)
    assert [d.score if d else None for d in assigned] == [0.8, 0.9]
    assert (duplicates, elsewhere) == (1, 1)
    assert runner.assign_detections([], targets, obj, cam) == ([None, None], 0, 0)


class _TimedOracle:
    """The oracle's answers, each call leaving a stage breakdown as the
    core's and the HTTP localizers do (``last_timing_ms``)."""

    def __init__(self, answer: object) -> None:
        self.answer = answer
        self.calls = 0
        self.last_timing_ms: dict[str, float] = {}

    def __call__(self, image: np.ndarray, camera: Camera) -> list[Detection]:
        self.calls += 1
        self.last_timing_ms = {"features": 10.0 * self.calls, "pose": 1.0, "total": 20.0}
        return self.answer(image, camera)  # type: ignore[operator, no-any-return]


def test_stage_medians_are_summarised_and_printed(tiny_paper_set: Path) -> None:
    bench = sets.load_generated(tiny_paper_set)

    class Timed(OracleBackend):
        def learn(self, obj: sets.BenchObject) -> LearnedObject:
            learned = super().learn(obj)
            return LearnedObject(obj.name, _TimedOracle(learned.localize), 0.01, 130, 18)

    res = runner.evaluate_set(bench, Timed(bench, "", fp=False), log=lambda s: None)
    posed = [im for im in bench.images if im.targets[0].pose is not None]
    # The calls are numbered in image order; the records are the posed images'.
    calls = [i + 1 for i, im in enumerate(bench.images) if im.targets[0].pose is not None]
    assert len(res["records"]) == len(posed)
    stages = res["overall"]["stage_median_ms"]
    assert list(stages) == ["features", "pose", "total"]
    assert stages["features"] == pytest.approx(float(np.median(10.0 * np.array(calls))))
    assert stages["pose"] == 1.0 and stages["total"] == 20.0
    table = runner.format_table("paper", bench, res, "oracle")
    assert f"stage medians: features {stages['features']:.1f}, pose 1.0, total 20.0 ms" in table


def test_records_without_a_breakdown_have_no_stage_medians(tiny_paper_set: Path) -> None:
    bench = sets.load_generated(tiny_paper_set)
    res = runner.evaluate_set(bench, OracleBackend(bench, "", fp=False), log=lambda s: None)
    assert "stage_median_ms" not in res["overall"]
    assert "stage medians" not in runner.format_table("paper", bench, res, "oracle")
    assert runner.stage_medians_ms([{"timing_ms": {"a": 1.0}}, {"timing_ms": {"a": 3.0, "b": 2.0}},
                                    {}]) == {"a": 2.0, "b": 2.0}


def test_the_core_localizer_leaves_its_stage_times() -> None:
    import trimesh

    from viewloc_bench.localizers import CoreLocalizer
    from viewloc_core.learn import LearningConfig, learn_from_mesh

    model = learn_from_mesh(trimesh.creation.box((60.0, 40.0, 20.0)),
                            LearningConfig(max_level=1, min_level=1))
    localizer = CoreLocalizer(model)
    cam = Camera(300.0, 300.0, 80.0, 60.0, 160, 120)
    image = np.full((120, 160, 3), 128, np.uint8)
    image[40:80, 50:110] = 200  # something to find: edges
    localizer(image, cam)
    assert {"features", "total"} <= set(localizer.last_timing_ms)
    assert localizer.last_timed_out is False  # no budget
    assert all(ms >= 0.0 for ms in localizer.last_timing_ms.values())
    # Asked for more detections than its own default, it still answers.
    assert isinstance(localizer(image, cam, max_detections=2), list)


class _TurnedOracle(OracleBackend):
    """The truth's place for every image, 2 % farther along its line of
    sight, and in one image turned by ``turn`` (object frame)."""

    def __init__(self, bench: sets.BenchSet, turned_image: str, turn: np.ndarray) -> None:
        super().__init__(bench, "", fp=False)
        self.turned = {self._key(_load(im.path)) for im in bench.images
                       if im.path.name == turned_image}
        self.turn = turn

    def learn(self, obj: sets.BenchObject) -> LearnedObject:
        def run(image: np.ndarray, camera: Camera) -> list[Detection]:
            key = self._key(image)
            pose = self.truth[key]
            if pose is None:
                return []
            R = pose.R_m2c @ self.turn if key in self.turned else pose.R_m2c
            uv = camera.project(pose.t_m2c[None])[0]
            return [Detection(0.9, -10.0, 0, 0.0, 90.0, Similarity2D(uv[0], uv[1], 0.0, 1.0),
                              Pose(R, 1.02 * pose.t_m2c))]

        return LearnedObject(obj.name, run, 0.01, 130, 18)


def test_right_place_detections_turned_and_their_depth_error_are_reported(
    tiny_paper_set: Path,
) -> None:
    from viewloc_core import metrics as vm

    bench = sets.load_generated(tiny_paper_set)
    symmetries = bench.objects["barbell"].symmetries
    # A quarter turn about the object axis across the bar that is furthest
    # from a symmetry of the barbell (a turn about the bar is none at all).
    quarter = max((Rotation.from_rotvec(np.radians(90.0) * axis).as_matrix() for axis in np.eye(3)),
                  key=lambda R: vm.paper_deltas(Pose(R, np.zeros(3)), Pose(np.eye(3), np.zeros(3)),
                                                symmetries)[2])
    posed = [im for im in bench.images if im.targets[0].pose is not None]
    res = runner.evaluate_set(bench, _TurnedOracle(bench, posed[0].path.name, quarter),
                              log=lambda s: None)
    records = {r["image"]: r for r in res["records"]}
    assert all(r["recognized_2d"] for r in records.values())
    assert records[posed[0].path.name]["dalpha_deg"] > runner.TURNED_DEG
    o = res["overall"]
    assert o["turned_share"] == pytest.approx(1 / len(posed), abs=1e-4)
    assert o["median_depth_error_rel"] == pytest.approx(0.02, abs=1e-4)
    table = runner.format_table("paper", bench, res, "oracle")
    assert (f"right place: {100 / len(posed):.0f}% turned over 30 deg, "
            "median depth error 2.00%") in table
    # Nothing at the right place: nothing to report.
    assert runner.right_place_errors([{"recognized_2d": False}]) == {}


def test_results_broken_down_by_visible_fraction(tiny_paper_set: Path) -> None:
    bench = sets.load_generated(tiny_paper_set)
    posed = [im for im in bench.images if im.targets[0].pose is not None]
    res = runner.evaluate_set(bench, OracleBackend(bench, posed[0].path.name, fp=False),
                              log=lambda s: None)
    records = {r["image"]: r for r in res["records"]}
    # The missed target mostly hidden, the others whole or nearly; a target
    # whose visible fraction is unknown counts in no band.
    fractions = [0.2, 0.95, 1.0]
    for im, fraction in zip(posed, fractions, strict=True):
        records[im.path.name]["visible_fraction"] = fraction
    unknown = dict(records[posed[1].path.name], visible_fraction=None)
    width = posed[0].camera.width
    bands = runner.summarise_visibility([*records.values(), unknown], bench.objects, width)
    assert [(b["from"], b["to"], b["targets"]) for b in bands] == [(0.0, 0.4, 1), (0.9, 1.0, 2)]
    assert bands[0]["recognition_2d"] == 0.0 and bands[1]["recognition_2d"] == 1.0
    assert bands[1]["per_object"]["barbell"]["targets"] == 2
    table = runner.format_table("paper", bench, dict(res, by_visibility=bands), "oracle")
    assert "rec2D by visible fraction: 0-0.4 0.00 (1), 0.9-1 1.00 (2)" in table
    assert "  barbell: 0-0.4 0.00 (1), 0.9-1 1.00 (2)" in table
    # A single band says no more than the overall line: not printed.
    whole = runner.summarise_visibility([records[posed[2].path.name]], bench.objects, width)
    assert len(whole) == 1
    assert "visible fraction" not in runner.format_table("paper", bench,
                                                        dict(res, by_visibility=whole), "oracle")


def test_the_learned_models_checksum_is_reported(tiny_paper_set: Path) -> None:
    bench = sets.load_generated(tiny_paper_set)

    class DigestBackend(OracleBackend):
        def learn(self, obj: sets.BenchObject) -> LearnedObject:
            learned = super().learn(obj)
            learned.info["model_sha256"] = "0123456789abcdef" * 4
            return learned

    lines: list[str] = []
    res = runner.evaluate_set(bench, DigestBackend(bench, "", fp=False), log=lines.append)
    assert res["objects"]["barbell"]["model_sha256"] == "0123456789abcdef" * 4
    expected = ", model sha256 0123456789abcdef"
    assert any(line.endswith(expected) for line in lines)
    table = runner.format_table("paper", bench, res, "oracle").splitlines()
    assert [line for line in table if line.startswith("learned barbell")][0].endswith(expected)
    # A backend that does not know the digest prints nothing for it.
    plain = runner.evaluate_set(bench, OracleBackend(bench, "", fp=False), log=lambda s: None)
    assert "sha256" not in runner.format_table("paper", bench, plain, "oracle")


@pytest.mark.parametrize("url", [None, "http://127.0.0.1:9"])
def test_the_time_budget_reaches_the_localizer(url: str | None) -> None:
    base = ["--url", url] if url else []
    backend = cli.make_backend(cli.parse_args([*base, "--timeout-ms", "80"]))
    assert backend.timeout_ms == 80.0  # type: ignore[union-attr]
    assert cli.make_backend(cli.parse_args(base)).timeout_ms is None  # type: ignore[union-attr]
    if isinstance(backend, CoreBackend):
        from viewloc_bench.localizers import CoreLocalizer

        assert CoreLocalizer(object(), timeout_ms=80.0).timeout_ms == 80.0  # type: ignore[arg-type]


@pytest.mark.parametrize("bad", ["0", "-3", "nan", "inf"])
def test_a_bad_time_budget_is_refused(bad: str, tmp_path: Path,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["--sets", "paper", "--timeout-ms", bad, "--out", str(tmp_path)]) == 2
    assert "--timeout-ms must be a positive number of ms" in capsys.readouterr().err


class _CutShortLocalizer:
    """Answers as ``answer`` does, and says a search was left out for the
    time budget on the images whose key is in ``cut`` (as the core's and
    the service's localizers say it)."""

    def __init__(self, answer: Any, key: Any, cut: set[str]) -> None:
        self.answer, self.key, self.cut = answer, key, cut
        self.last_timed_out = False

    def __call__(self, image: np.ndarray, camera: Camera) -> list[Detection]:
        self.last_timed_out = self.key(image) in self.cut
        return list(self.answer(image, camera))


class _CutShortOracle(OracleBackend):
    """The oracle, its search cut short by the budget on one image."""

    def __init__(self, bench: sets.BenchSet, cut_image: str) -> None:
        super().__init__(bench, "", fp=True)
        self.cut = {self._key(_load(im.path)) for im in bench.images
                    if im.path.name == cut_image}

    def learn(self, obj: sets.BenchObject) -> LearnedObject:
        localizer = _CutShortLocalizer(super().learn(obj).localize, self._key, self.cut)
        return LearnedObject(obj.name, localizer, 0.01, 130, 18)


def test_images_whose_search_the_budget_cut_short_are_marked(tiny_paper_set: Path) -> None:
    bench = sets.load_generated(tiny_paper_set)
    cut = next(im.path.name for im in bench.images if im.targets[0].pose is not None)
    res = runner.evaluate_set(bench, _CutShortOracle(bench, cut), log=lambda s: None)
    assert [r["image"] for r in res["records"] if r.get("timed_out")] == [cut]
    assert not any(r.get("timed_out") for r in res["negative_records"])
    assert res["overall"]["timed_out"] == 1
    table = runner.format_table("paper", bench, res, "oracle")
    assert f"time budget: a search left out for 1 of {res['overall']['targets']} targets" in table
    # Without a budget nothing is marked and the table says nothing of it.
    plain = runner.evaluate_set(bench, OracleBackend(bench, "", fp=True), log=lambda s: None)
    assert "timed_out" not in plain["overall"]
    assert "time budget" not in runner.format_table("paper", bench, plain, "oracle")
