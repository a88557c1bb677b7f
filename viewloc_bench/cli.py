"""``python -m viewloc_bench``: generate the sets, run the localizer, print and save the results."""

from __future__ import annotations

import argparse
import math
import sys
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from viewloc_bench import dense, lmo, lmo_composite, runner, sets
from viewloc_bench.localizers import (
    Backend,
    CoreBackend,
    EngineUnavailableError,
    HttpBackend,
    PhotoLearningBackend,
)
from viewloc_bench.photos import DEFAULT_PHOTOS, PhotoBackend

ALL_SETS = ("paper", "hard", "novel", "multi", "shop", "hard-mono", "hard-hd", "hard-photos",
            "lmo", "lmo-grey")

#: A generated set's scenes rendered with objects that cast no shadows
#: (:attr:`viewloc_bench.scenes.SceneParams.cast_shadows`): against the set
#: itself, what the cast shadows cost.
UNSHADOWED = "-unshadowed"
UNSHADOWED_SETS = tuple(f"{name}{UNSHADOWED}" for name in sets.SPECS)

#: Diagnostic sets run only when named in ``--sets``: LM-O's targets
#: rendered at their true poses over their photos or over grey
#: (:mod:`viewloc_bench.lmo_composite`), and the generated sets without
#: shadows.
OPT_IN_SETS = lmo_composite.COMPOSITE_SETS + UNSHADOWED_SETS

#: Sets made from a generated one: its images as a monochrome camera sees
#: them (``-mono``, :func:`viewloc_bench.sets.monochrome`), its scenes
#: rendered at twice the resolution, 1280x960 for hard (``-hd``: a
#: megapixel camera, the part twice as many pixels across), or its scenes
#: with each part learned from masked photos instead of its mesh
#: (``-photos``, :mod:`viewloc_bench.photos`).
DERIVED_SUFFIXES = ("-mono", "-hd", "-photos", UNSHADOWED)
HD_SCALE = 2.0
QUICK_IMAGES_PER_N = 2
QUICK_NEGATIVES = 2
QUICK_LMO_IMAGES = 20


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m viewloc_bench", description=__doc__)
    p.add_argument(
        "--sets",
        default=",".join(ALL_SETS),
        help=f"comma-separated subset of {','.join(ALL_SETS)} (default: all), or the "
        f"diagnostic {','.join(OPT_IN_SETS)}",
    )
    p.add_argument(
        "--url", default=None, help="measure the HTTP service at this URL instead of the core"
    )
    p.add_argument(
        "--quick",
        action="store_true",
        help=f"smoke run: {QUICK_IMAGES_PER_N} images per N, {QUICK_LMO_IMAGES} LM-O images",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the generated sets and of learning")
    p.add_argument(
        "--learn-seed",
        type=int,
        default=None,
        help="seed of learning only (default: --seed); the same scenes measured with models "
        "learned from other random lights and edge samples show how much a figure is luck",
    )
    p.add_argument("--out", type=Path, default=Path("bench_out"), help="output folder")
    p.add_argument("--no-refine", action="store_true", help="localize without pose refinement")
    p.add_argument("--timeout-ms", type=float, default=None,
                   help="localize with this time budget per image (options.timeout_ms, ms; "
                   "default none): what a bound on the slow images costs in recognition")
    p.add_argument(
        "--heldout",
        action="store_true",
        help="evaluate LM-O's held-out objects 9, 10, 11, 12 instead of 1, 5, 6, 8",
    )
    p.add_argument("--workers", type=int, default=2, help="POV-Ray processes while generating")
    p.add_argument(
        "--lmo-extra",
        type=Path,
        default=None,
        help="folder with LM-O's models_info.json etc. (default ../shared/data/lmo-bop19-extra)",
    )
    p.add_argument("--api-key", default=None, help="bearer token for --url")
    p.add_argument(
        "--images-per-n", type=int, default=None, help="override images per N (and negatives)"
    )
    p.add_argument(
        "--photos",
        type=int,
        default=DEFAULT_PHOTOS,
        help="masked training photos per part in the -photos sets (default %(default)s)",
    )
    p.add_argument(
        "--scale", type=float, default=1.0, help="shrink generated images (smoke tests only)"
    )
    return p.parse_args(argv)


def set_spec(name: str, per_n: int | None, scale: float) -> sets.SetSpec:
    """A generated set's parameters: full size (``per_n`` None) or ``per_n`` images per N.

    A smaller set keeps at most :data:`QUICK_NEGATIVES` negatives per object,
    and none when the full set has none (the multi set).
    """
    make_spec = sets.SPECS[name]
    if per_n is None:
        return make_spec(scale=scale)
    negatives = min(per_n, QUICK_NEGATIVES, make_spec().negatives)
    return make_spec(per_n, negatives, scale)


def load_sets(args: argparse.Namespace, names: list[str]) -> dict[str, sets.BenchSet]:
    """Generate (or reuse) and load the requested sets, printing the time each took."""
    root = args.out / "sets"
    out: dict[str, sets.BenchSet] = {}
    # None: each set at its own full size (10 images per N).
    per_n = QUICK_IMAGES_PER_N if args.quick else None
    if args.images_per_n is not None:
        per_n = args.images_per_n
    for name in names:
        t0 = time.perf_counter()
        generated, suffix = name, ""
        for derived in DERIVED_SUFFIXES:
            if name.endswith(derived):
                generated, suffix = name.removesuffix(derived), derived
        if generated in sets.SPECS:
            scale = args.scale * (HD_SCALE if suffix == "-hd" else 1.0)
            spec = set_spec(generated, per_n, scale)
            if suffix == UNSHADOWED:
                spec = sets.unshadowed(spec)
            folder = sets.generate(spec, args.seed, root, workers=args.workers)
            bench = sets.load_generated(folder)
            if suffix == "-mono":
                bench = sets.monochrome(bench)
            took = time.perf_counter() - t0
            state = "generated" if took > 1.0 else "cached"
            print(
                f"set {name}: {len(bench.images)} images in {folder} ({state}; "
                f"generation took {bench.generation_s:.1f} s)"
            )
        else:
            folder, took = lmo.prepare(root, args.lmo_extra)
            ids = lmo.HELDOUT_OBJECTS if args.heldout else lmo.DEV_OBJECTS
            # lmo-grey: the same photos, the parts learned from colourless meshes.
            bench = lmo.load(folder, ids, QUICK_LMO_IMAGES if args.quick else None,
                             grey=name == "lmo-grey")
            if name in OPT_IN_SETS:
                plain = name == lmo_composite.PLAIN
                t_paste = time.perf_counter()
                bench = lmo_composite.composite(bench, folder / ("plain" if plain else "composite"),
                                                plain)
                print(f"set {name}: {len(bench.images)} targets rendered and pasted (or read) "
                      f"in {time.perf_counter() - t_paste:.1f} s")
            bench.generation_s = took
            print(
                f"set {name}: {len(bench.images)} images, objects {list(bench.objects)} in "
                f"{folder} ({f'extracted in {took:.1f} s' if took else 'cached'})"
            )
        out[name] = bench
    return out


def _learn_seed(args: argparse.Namespace) -> int:
    """Seed of learning: ``--learn-seed``, else ``--seed``."""
    return int(args.seed if args.learn_seed is None else args.learn_seed)


def make_backend(args: argparse.Namespace) -> PhotoLearningBackend:
    """The method measured: the HTTP service at ``--url``, else the core in-process;
    learning with ``--learn-seed`` (``--seed`` when not given)."""
    refine = not args.no_refine
    learn_seed = _learn_seed(args)
    if args.url:
        return HttpBackend(args.url, refine=refine, api_key=args.api_key, seed=learn_seed,
                           timeout_ms=args.timeout_ms)
    return CoreBackend(refine=refine, seed=learn_seed, timeout_ms=args.timeout_ms)


def _learn_dense(backend: Backend, lmo_set: sets.BenchSet) -> dict[str, Any]:
    """Learn the LM-O driller cut into 1.6 million faces (:mod:`viewloc_bench.dense`)."""
    obj, faces = dense.dense_object(lmo_set.objects["driller"], lmo_set.folder / "models_dense")
    learned = backend.learn(obj)
    print(f"learning a dense mesh: {obj.name}, {faces} faces, {learned.learn_s:.1f} s "
          f"({learned.model_views} model views)")
    return {"object": obj.name, "faces": faces, "learn_s": round(learned.learn_s, 2),
            "model_views": learned.model_views}


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    names = [s.strip() for s in args.sets.split(",") if s.strip()]
    unknown = [n for n in names if n not in ALL_SETS + OPT_IN_SETS]
    if unknown:
        print(f"unknown set(s) {unknown}; choose from {ALL_SETS + OPT_IN_SETS}",
              file=sys.stderr)
        return 2
    if args.photos < 1:
        print(f"--photos must be at least 1, got {args.photos}", file=sys.stderr)
        return 2
    if args.timeout_ms is not None and not (math.isfinite(args.timeout_ms)
                                            and args.timeout_ms > 0):
        print(f"--timeout-ms must be a positive number of ms, got {args.timeout_ms}",
              file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    benches = load_sets(args, names)
    refine = not args.no_refine
    backend = make_backend(args)
    results: dict[str, Any] = {
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "backend": backend.label,
        "args": {
            k: (str(v) if isinstance(v, Path) else v)
            for k, v in vars(args).items()
            if k != "api_key"
        },
        "definitions": {
            "recognized_2d": "top detection's (x, y) within 0.1 x image diameter "
            "(focal_px * diameter_mm / z) of the projected object origin",
            "recognized_6d": "top detection's MSSD < 0.1 x object diameter (symmetry-aware)",
            "g": "paper Eq. 3, fz=1/250000, fxy=1/50000, falpha=1/10000, mm and deg, "
            "min over symmetries; mean/median over 2D-recognized targets",
            "turned_share": "share of the 2D-recognized targets whose top detection's "
            f"rotation is more than {runner.TURNED_DEG:g} deg from the truth (symmetry-aware)",
            "median_depth_error_rel": "median over the 2D-recognized targets of the depth "
            "error of the object origin (symmetry-aware) over the true depth",
        },
        "sets": {},
    }
    try:
        backend.check()
        available = True
    except EngineUnavailableError as exc:
        print(str(exc))
        available = False
    for name, bench in benches.items():
        set_backend: Backend = backend
        if name.endswith("-photos"):
            set_backend = PhotoBackend(backend, args.photos, _learn_seed(args))
        header = f"{set_backend.label}, refine {'on' if refine else 'off'}"
        if args.timeout_ms is not None:
            header += f", time budget {args.timeout_ms:g} ms"
        entry: dict[str, Any] = {
            "folder": str(bench.folder),
            "generation_s": bench.generation_s,
            "images": len(bench.images),
            "images_sha256": sets.images_digest(bench.images),
        }
        # Figures from two machines compare only on the same pixels (images_digest).
        print(f"set {name}: images sha256 {entry['images_sha256'][:16]}")
        if not available:
            print(runner.format_table(name, bench, None, header))
            entry["status"] = "engine not available"
            results["sets"][name] = entry
            continue
        t0 = time.perf_counter()
        res = runner.evaluate_set(bench, set_backend)
        entry.update(res)
        entry["wall_s"] = round(time.perf_counter() - t0, 1)
        results["sets"][name] = entry
        print(runner.format_table(name, bench, res, header))
        if name == "paper":
            runner.plot_fig2(res, args.out / "paper_fig2.png")
            print(f"plot: {args.out / 'paper_fig2.png'}")
        runner.write_json(results, args.out / "results.json")
    lmo_set = benches.get("lmo")
    if available and not args.quick and lmo_set is not None and "driller" in lmo_set.objects:
        results["learning_dense"] = _learn_dense(backend, lmo_set)
    runner.write_json(results, args.out / "results.json")
    print(f"results: {args.out / 'results.json'}")
    return 0
