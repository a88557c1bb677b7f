"""Localization throughput of a running service: requests/s and latency per client concurrency.

``python -m viewloc_bench.load --url http://127.0.0.1:8000 --concurrency 1 2 4 --requests 40``

Each level sends ``--requests`` localize requests from that many client
threads (one keep-alive connection each) and reports successful requests per
second of wall time and the p50/p95 of the full round trip (upload, server
work, answer). Images are sent as their stored PNG bytes, so the client does
no encoding on the measured path. The object is ``--object-id``, or the
barbell of the paper set learned through the API (reused when the service
already has it, under the same name ``make bench --url`` uses).

Bounded and loopback only: the URL must name this machine, at most
:data:`MAX_REQUESTS` requests and :data:`MAX_CONCURRENCY` clients per level,
and a level stops after ``--max-seconds``. Client and server share the
machine's cores, so the figures are a floor for a dedicated server.
"""

from __future__ import annotations

import argparse
import ipaddress
import json
import statistics
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import httpx
import numpy as np

MAX_REQUESTS = 5000
MAX_CONCURRENCY = 32


@dataclass(frozen=True, slots=True)
class LevelResult:
    """Measurements at one client concurrency.

    Attributes
    ----------
    concurrency : int
        Client threads sending at once.
    requests : int
        Requests sent (successful + failed).
    ok : int
        Answers 200.
    errors : int
        Other answers and transport errors.
    wall_s : float
        Time from the first request to the last answer, s.
    rps : float
        ``ok / wall_s``.
    p50_ms, p95_ms, mean_ms : float
        Round-trip latency of the successful requests, ms (NaN when none).
    server_ms : float
        Mean of the server's own ``timing_ms.total``, ms (NaN when absent).
    detections : float
        Mean number of detections per successful answer.
    """

    concurrency: int
    requests: int
    ok: int
    errors: int
    wall_s: float
    rps: float
    p50_ms: float
    p95_ms: float
    mean_ms: float
    server_ms: float
    detections: float


def require_loopback(url: str) -> str:
    """The URL without a trailing slash; ValueError unless it names this machine."""
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ValueError(f"not an http(s) URL: {url!r}")
    host = parts.hostname
    if host != "localhost":
        try:
            loopback = ipaddress.ip_address(host).is_loopback
        except ValueError:
            loopback = False
        if not loopback:
            raise ValueError(f"the load test only targets this machine (loopback), not {host!r}")
    return url.rstrip("/")


def _client(url: str, api_key: str | None, timeout_s: float) -> httpx.Client:
    headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
    return httpx.Client(base_url=url, timeout=timeout_s, headers=headers)


def run_level(
    url: str,
    object_id: str,
    images: Sequence[bytes],
    camera: dict[str, Any],
    concurrency: int,
    requests: int,
    *,
    options: dict[str, Any] | None = None,
    api_key: str | None = None,
    max_seconds: float = 300.0,
    timeout_s: float = 120.0,
) -> LevelResult:
    """Send ``requests`` localize requests from ``concurrency`` threads and measure them.

    Parameters
    ----------
    url : str
        Service base URL (loopback).
    object_id : str
        A ready object.
    images : sequence of bytes
        Encoded images, used round robin.
    camera : dict
        API.md ``Camera`` JSON object (fx, fy, cx, cy, optional dist).
    concurrency, requests : int
        Client threads and total requests of this level.
    options : dict, optional
        Localize options JSON (default ``{"max_detections": 1}``).
    max_seconds : float
        No request starts after this much time.
    """
    url = require_loopback(url)
    if not 1 <= concurrency <= MAX_CONCURRENCY:
        raise ValueError(f"concurrency must be in 1..{MAX_CONCURRENCY}")
    if not 1 <= requests <= MAX_REQUESTS:
        raise ValueError(f"requests must be in 1..{MAX_REQUESTS}")
    if not images:
        raise ValueError("no images")
    form = {"camera": json.dumps(camera), "options": json.dumps(options or {"max_detections": 1})}
    path = f"/v1/objects/{object_id}/localize"
    lock = threading.Lock()
    counter = iter(range(requests))
    latencies_ms: list[float] = []
    server_ms: list[float] = []
    detections: list[int] = []
    errors: list[str] = []
    start_gate = threading.Barrier(concurrency + 1)
    deadline = [0.0]

    def client_thread() -> None:
        with _client(url, api_key, timeout_s) as client:
            start_gate.wait()
            while True:
                with lock:
                    k = next(counter, None)
                if k is None or time.perf_counter() > deadline[0]:
                    return
                t0 = time.perf_counter()
                try:
                    r = client.post(path, files={"image": ("image.png", images[k % len(images)],
                                                           "image/png")}, data=form)
                except httpx.HTTPError as exc:
                    with lock:
                        errors.append(type(exc).__name__)
                    continue
                dt = (time.perf_counter() - t0) * 1000.0
                with lock:
                    if r.status_code == 200:
                        body = r.json()
                        latencies_ms.append(dt)
                        detections.append(len(body.get("detections", [])))
                        total = (body.get("timing_ms") or {}).get("total")
                        if total is not None:
                            server_ms.append(float(total))
                    else:
                        errors.append(f"HTTP {r.status_code}")

    threads = [threading.Thread(target=client_thread, daemon=True) for _ in range(concurrency)]
    for t in threads:
        t.start()
    t_start = time.perf_counter()
    deadline[0] = t_start + max_seconds
    start_gate.wait()
    for t in threads:
        t.join(max_seconds + timeout_s + 10)
    wall = time.perf_counter() - t_start
    nan = float("nan")
    lat = np.asarray(latencies_ms)
    return LevelResult(
        concurrency=concurrency,
        requests=len(latencies_ms) + len(errors),
        ok=len(latencies_ms),
        errors=len(errors),
        wall_s=wall,
        rps=len(latencies_ms) / wall if wall > 0 else nan,
        p50_ms=float(np.percentile(lat, 50)) if lat.size else nan,
        p95_ms=float(np.percentile(lat, 95)) if lat.size else nan,
        mean_ms=float(lat.mean()) if lat.size else nan,
        server_ms=statistics.fmean(server_ms) if server_ms else nan,
        detections=statistics.fmean(detections) if detections else nan,
    )


def paper_set_folder(root: Path = Path("bench_out/sets")) -> Path:
    """The newest generated paper set under ``root`` (``make bench`` writes it)."""
    folders = sorted((p for p in root.glob("paper-*") if (p / "gt.json").is_file()),
                     key=lambda p: p.stat().st_mtime)
    if not folders:
        raise FileNotFoundError(f"no generated paper set under {root}; run `make bench` first")
    return folders[-1]


def set_images(folder: Path, object_name: str | None = None,
               limit: int = 32) -> tuple[list[bytes], dict[str, Any]]:
    """PNG bytes of up to ``limit`` images of a generated set where the object is
    present, and the set's camera as API.md ``Camera``."""
    gt = json.loads((folder / "gt.json").read_text())
    cam = gt["camera"]
    entries = [e for e in gt["images"] if e.get("present")
               and (object_name is None or e["object"] == object_name)]
    images = [(folder / e["file"]).read_bytes() for e in entries[:limit]]
    return images, {k: float(cam[k]) for k in ("fx", "fy", "cx", "cy")}


def learned_barbell(url: str, folder: Path, api_key: str | None) -> str:
    """Object id of the paper set's barbell on the service, learning it if needed."""
    from viewloc_bench.localizers import HttpBackend
    from viewloc_bench.sets import load_generated

    bench_set = load_generated(folder)
    backend = HttpBackend(url, api_key=api_key, seed=int(bench_set.meta.get("seed", 0)))
    backend.check()
    learned = backend.learn(bench_set.objects["barbell"])
    return str(learned.info["object_id"])


def format_table(results: Sequence[LevelResult]) -> str:
    """A plain-text table of the results."""
    lines = [f"{'clients':>7} {'ok':>5} {'err':>4} {'req/s':>7} {'p50 ms':>8} {'p95 ms':>8} "
             f"{'server ms':>9} {'dets':>5}"]
    for r in results:
        lines.append(f"{r.concurrency:>7d} {r.ok:>5d} {r.errors:>4d} {r.rps:>7.2f} "
                     f"{r.p50_ms:>8.1f} {r.p95_ms:>8.1f} {r.server_ms:>9.1f} "
                     f"{r.detections:>5.2f}")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m viewloc_bench.load", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--url", default="http://127.0.0.1:8000", help="service (loopback only)")
    p.add_argument("--concurrency", type=int, nargs="+", default=[1, 2, 4])
    p.add_argument("--requests", type=int, default=40, help="requests per concurrency level")
    p.add_argument("--warmup", type=int, default=4,
                   help="unmeasured requests first (each HTTP worker loads the model once)")
    p.add_argument("--object-id", default=None,
                   help="a ready object (default: the paper set's barbell, learned if missing)")
    p.add_argument("--set", type=Path, default=None,
                   help="generated set folder with gt.json (default: newest paper set)")
    p.add_argument("--images", type=Path, nargs="+", default=None,
                   help="image files instead of a set (needs --camera)")
    p.add_argument("--camera", default=None, help='JSON {"fx", "fy", "cx", "cy"} for --images')
    p.add_argument("--max-detections", type=int, default=1)
    p.add_argument("--no-refine", action="store_true")
    p.add_argument("--max-seconds", type=float, default=300.0, help="time bound per level")
    p.add_argument("--api-key", default=None)
    p.add_argument("--json", type=Path, default=None, help="also write the results here")
    return p


def main(argv: list[str] | None = None) -> int:
    """Run the load test; prints a table (and writes JSON with ``--json``)."""
    args = build_parser().parse_args(argv)
    try:
        url = require_loopback(args.url)
    except ValueError as exc:
        print(f"load: {exc}", file=sys.stderr)
        return 2
    if args.images:
        if not args.camera:
            print("load: --images needs --camera", file=sys.stderr)
            return 2
        images = [p.read_bytes() for p in args.images]
        camera = {k: float(v) for k, v in json.loads(args.camera).items()}
        folder = None
    else:
        folder = args.set or paper_set_folder()
        images, camera = set_images(folder, "barbell" if args.object_id is None else None)
    object_id = args.object_id or learned_barbell(url, folder or paper_set_folder(), args.api_key)
    options = {"max_detections": args.max_detections, "refine": not args.no_refine}
    if args.warmup > 0:
        run_level(url, object_id, images, camera, min(4, args.warmup), args.warmup,
                  options=options, api_key=args.api_key, max_seconds=args.max_seconds)
    results = [run_level(url, object_id, images, camera, c, args.requests, options=options,
                         api_key=args.api_key, max_seconds=args.max_seconds)
               for c in args.concurrency]
    print(f"load test of {url}, object {object_id}, {len(images)} images, "
          f"{args.requests} requests per level")
    print(format_table(results))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({
            "url": url, "object_id": object_id, "images": len(images),
            "options": options, "levels": [asdict(r) for r in results]}, indent=1))
    return 0 if all(r.errors == 0 for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
