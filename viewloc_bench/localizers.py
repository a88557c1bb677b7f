"""The method under test, as one function ``(image, camera) -> list[Detection]`` per object.

Two backends learn an object and hand back that function: :class:`CoreBackend`
calls ``viewloc_core`` directly, :class:`HttpBackend` goes through the HTTP
API of API.md (``--url``). Anything with a ``learn`` method of the same
shape plugs in (the tests use an oracle with noise).
"""

from __future__ import annotations

import io
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray
from PIL import Image

from viewloc_bench.sets import BenchObject
from viewloc_core.camera import Camera
from viewloc_core.detection import Detection, Similarity2D
from viewloc_core.pose import Pose

Localizer = Callable[[NDArray[np.uint8], Camera], list[Detection]]


class EngineUnavailableError(RuntimeError):
    """The localization engine (or the service) is not there yet."""


@dataclass(slots=True)
class LearnedObject:
    """A learned object and the function that finds it.

    Attributes
    ----------
    name : str
    localize : Localizer
        ``(image (H, W, 3) uint8 RGB, camera) -> detections``, best first.
    learn_s : float
        Wall time of learning (for HTTP: upload until the job succeeded).
    training_views, model_views : int or None
    info : dict
        Anything else worth reporting.
    """

    name: str
    localize: Localizer
    learn_s: float
    training_views: int | None = None
    model_views: int | None = None
    info: dict[str, Any] = field(default_factory=dict)


class Backend(Protocol):
    """Learns objects; ``label`` names it in the report."""

    label: str

    def check(self) -> None:
        """Raise :class:`EngineUnavailableError` when the method cannot run."""

    def learn(self, obj: BenchObject) -> LearnedObject:
        """Learn ``obj`` from its mesh and return its localizer."""
        ...


class CoreBackend:
    """``viewloc_core.learn.learn_from_mesh`` and ``viewloc_core.localize.localize`` in-process."""

    def __init__(self, refine: bool = True, seed: int = 0, max_detections: int = 1) -> None:
        self.refine = refine
        self.seed = seed
        self.max_detections = max_detections
        self.label = "core"

    def check(self) -> None:
        try:
            import viewloc_core.learn  # noqa: F401
            import viewloc_core.localize  # noqa: F401
        except ImportError as exc:
            raise EngineUnavailableError(f"engine not available ({exc})") from exc

    def learn(self, obj: BenchObject) -> LearnedObject:
        import trimesh

        self.check()
        from viewloc_core.learn import LearningConfig, learn_from_mesh
        from viewloc_core.localize import LocalizeOptions, localize

        mesh = trimesh.load(obj.mesh_path, force="mesh")
        assert isinstance(mesh, trimesh.Trimesh)
        t0 = time.perf_counter()
        model = learn_from_mesh(mesh, LearningConfig(), None, rng=self.seed)
        learn_s = time.perf_counter() - t0
        options = LocalizeOptions(max_detections=self.max_detections, refine=self.refine)

        def run(image: NDArray[np.uint8], camera: Camera) -> list[Detection]:
            return list(localize(model, image, camera, options).detections)

        return LearnedObject(
            obj.name,
            run,
            learn_s,
            _int_or_none(getattr(model, "training_views", None)),
            _int_or_none(getattr(model, "model_views", None)),
        )


def _int_or_none(v: object) -> int | None:
    if v is None:
        return None
    if isinstance(v, int | np.integer):
        return int(v)
    try:
        return len(v)  # type: ignore[arg-type]
    except TypeError:
        return None


def detection_from_json(d: dict[str, Any]) -> Detection:
    """A Detection from one element of API.md's ``detections`` list."""
    sim = d["similarity"]
    view = d.get("view", {})
    std = d.get("pose_std")
    return Detection(
        score=float(d["score"]),
        log_probability=float(d.get("log_probability", 0.0)),
        model_view=int(d.get("model_view", -1)),
        azimuth_deg=float(view.get("azimuth_deg", 0.0)),
        polar_deg=float(view.get("polar_deg", 0.0)),
        similarity=Similarity2D(
            float(sim["x"]), float(sim["y"]), float(sim["angle_deg"]), float(sim["scale"])
        ),
        pose=Pose(
            np.asarray(d["pose"]["R"], dtype=np.float64),
            np.asarray(d["pose"]["t_mm"], dtype=np.float64),
        ),
        refined=bool(d.get("refined", False)),
        pose_std=None if std is None else np.asarray(std, dtype=np.float64),
        object_id=d.get("object_id"),
    )


def encode_png(image: NDArray[np.uint8]) -> bytes:
    """PNG bytes of an RGB image (fast compression: it is on the latency path)."""
    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="PNG", compress_level=1)
    return buf.getvalue()


class HttpBackend:
    """The same through the HTTP API (API.md): upload the mesh, wait for the job, localize."""

    def __init__(
        self,
        url: str,
        refine: bool = True,
        max_detections: int = 1,
        learn_timeout_s: float = 1800.0,
        api_key: str | None = None,
    ) -> None:
        import httpx

        headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
        self.url = url.rstrip("/")
        self.client = httpx.Client(base_url=self.url, timeout=120.0, headers=headers)
        self.refine = refine
        self.max_detections = max_detections
        self.learn_timeout_s = learn_timeout_s
        self.label = f"http {self.url}"

    def check(self) -> None:
        import httpx

        try:
            r = self.client.get("/healthz")
        except httpx.HTTPError as exc:
            raise EngineUnavailableError(f"service at {self.url} not reachable ({exc})") from exc
        if r.status_code != 200:
            raise EngineUnavailableError(
                f"service at {self.url}: /healthz answered {r.status_code}"
            )

    def learn(self, obj: BenchObject) -> LearnedObject:
        mesh_bytes = obj.mesh_path.read_bytes()
        t0 = time.perf_counter()
        r = self.client.post(
            "/v1/objects",
            files={"mesh": (obj.mesh_path.name, mesh_bytes, "application/octet-stream")},
            data={"spec": json.dumps({"name": obj.name, "units": "mm"})},
        )
        if r.status_code != 202:
            raise RuntimeError(f"POST /v1/objects answered {r.status_code}: {r.text[:500]}")
        body = r.json()
        object_id = body["object"]["object_id"]
        job_id = body["job"]["job_id"]
        while True:
            job = self.client.get(f"/v1/jobs/{job_id}").json()
            if job["state"] in ("succeeded", "failed", "cancelled"):
                break
            if time.perf_counter() - t0 > self.learn_timeout_s:
                raise RuntimeError(f"learning {obj.name} took longer than {self.learn_timeout_s} s")
            time.sleep(0.5)
        learn_s = time.perf_counter() - t0
        if job["state"] != "succeeded":
            raise RuntimeError(f"learning {obj.name} {job['state']}: {job.get('error')}")
        info = self.client.get(f"/v1/objects/{object_id}").json()
        options = json.dumps({"max_detections": self.max_detections, "refine": self.refine})

        def run(image: NDArray[np.uint8], camera: Camera) -> list[Detection]:
            cam = {"fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy}
            if camera.dist:
                cam["dist"] = list(camera.dist)  # type: ignore[assignment]
            resp = self.client.post(
                f"/v1/objects/{object_id}/localize",
                files={"image": ("image.png", encode_png(image), "image/png")},
                data={"camera": json.dumps(cam), "options": options},
            )
            if resp.status_code != 200:
                raise RuntimeError(f"localize answered {resp.status_code}: {resp.text[:500]}")
            return [detection_from_json(d) for d in resp.json()["detections"]]

        return LearnedObject(
            obj.name,
            run,
            learn_s,
            info.get("training_views"),
            info.get("model_views"),
            {"object_id": object_id},
        )
