"""Entry point of the ``viewloc`` command line."""

from __future__ import annotations

import argparse
import os


def _serve(args: argparse.Namespace) -> int:
    import uvicorn

    uvicorn.run(
        "app.main:create_app",
        factory=True,
        host=args.host,
        port=args.port,
        workers=args.workers,
    )
    return 0


def _worker(args: argparse.Namespace) -> int:
    # Imported here: the worker must not load the HTTP stack or a GL context.
    from app.jobs.redis_runner import run_worker
    from app.settings import Settings

    return run_worker(Settings(), burst=args.burst, name=args.name)


def _learn(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    from tqdm import tqdm

    from model_store import save_model_dir
    from viewloc_core.learn import LearningConfig, learn_from_mesh
    from viewloc_core.mesh import load_mesh

    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    mesh = load_mesh(Path(args.mesh), None, args.units)
    config = LearningConfig.from_dict(json.loads(args.learning) if args.learning else {})
    with tqdm(total=1000, unit="‰", desc="learning", leave=True) as bar:

        def progress(stage: str, fraction: float) -> None:
            bar.set_description(stage[:40])
            bar.n = int(round(1000 * min(1.0, max(0.0, fraction))))
            bar.refresh()

        model = learn_from_mesh(mesh, config, progress=progress, rng=config.seed)
        bar.n = 1000
        bar.refresh()
    digest = save_model_dir(Path(args.output), model)
    print(json.dumps({"model_dir": str(args.output), "sha256": digest,
                      "diameter_mm": float(model.diameter_mm),
                      "training_views": int(model.training_views),
                      "model_views": len(model.model_views)}))
    return 0


def _match(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    from app.imaging import decode_image
    from app.serialize import detection_dict
    from model_store import load_model_dir
    from viewloc_core.camera import Camera
    from viewloc_core.localize import LocalizeOptions, localize

    text = args.camera
    if not text.lstrip().startswith("{"):
        text = Path(text).read_text()
    cam = json.loads(text)
    image = decode_image(Path(args.image).read_bytes(), "image", 1 << 31)
    camera = Camera(float(cam["fx"]), float(cam["fy"]), float(cam["cx"]), float(cam["cy"]),
                    image.shape[1], image.shape[0], tuple(cam.get("dist") or ()))
    model = load_model_dir(Path(args.model_dir))
    result = localize(model, image, camera, LocalizeOptions(
        max_detections=args.max_detections, min_score=args.min_score,
        refine=not args.no_refine, timeout_ms=args.timeout_ms))
    print(json.dumps({
        "image": {"width": image.shape[1], "height": image.shape[0]},
        "detections": [detection_dict(d) for d in result.detections],
        "timing_ms": dict(result.timing_ms),
        "timed_out": result.timed_out,
    }, indent=1))
    return 0


def _positive_ms(text: str) -> float:
    """A positive, finite number of milliseconds (argparse type)."""
    import math

    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number of ms, not {text!r}")
    return value


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with one sub-command per verb."""
    parser = argparse.ArgumentParser(prog="viewloc", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    serve = sub.add_parser("serve", help="start the HTTP service")
    serve.add_argument("--host", default=os.environ.get("HOST", "127.0.0.1"))
    serve.add_argument("--port", type=int, default=int(os.environ.get("PORT", "8000")))
    serve.add_argument(
        "--workers", type=int, default=int(os.environ.get("VIEWLOC_HTTP_WORKERS", "1"))
    )
    serve.set_defaults(func=_serve)

    worker = sub.add_parser(
        "worker",
        help="run learning jobs from the Redis queue (service with VIEWLOC_JOB_BACKEND=redis)",
        description="Configured like the service: VIEWLOC_REDIS_URL, VIEWLOC_DATA_DIR (the "
        "same store as the API), VIEWLOC_JOB_STALE_AFTER_S, VIEWLOC_JOB_CANCEL_GRACE_S.",
    )
    worker.add_argument("--burst", action="store_true", help="exit once the queue is empty")
    worker.add_argument("--name", default=None, help="RQ worker name")
    worker.set_defaults(func=_worker)

    learn = sub.add_parser("learn", help="learn a model from a mesh file into a folder")
    learn.add_argument("mesh", help="STL, OBJ, PLY, OFF, GLB or glTF file")
    learn.add_argument("--units", default="mm", choices=["mm", "cm", "m", "in"])
    learn.add_argument("-o", "--output", required=True, help="model folder to write")
    learn.add_argument("--learning", default="", help="JSON of LearningConfig fields")
    learn.set_defaults(func=_learn)

    match = sub.add_parser("match", help="localize a learned model in an image")
    match.add_argument("model_dir")
    match.add_argument("image")
    match.add_argument("--camera", required=True,
                       help='JSON {"fx", "fy", "cx", "cy", "dist"} or a file holding it')
    match.add_argument("--max-detections", type=int, default=1)
    match.add_argument("--min-score", type=float, default=None)
    match.add_argument("--no-refine", action="store_true")
    match.add_argument("--timeout-ms", type=_positive_ms, default=None,
                       help="time budget of the search, ms (API options.timeout_ms)")
    match.set_defaults(func=_match)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the process exit code."""
    args = build_parser().parse_args(argv)
    return int(args.func(args))
