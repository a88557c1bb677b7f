"""The method under test, as one function ``(image, camera) -> list[Detection]`` per object.

The function also takes ``max_detections`` when an image holds several
instances of the object (the multi set); without it, the backend's own
setting applies (one detection unless the backend was made otherwise).

Two backends learn an object and hand back that function: :class:`CoreBackend`
calls ``viewloc_core`` directly, :class:`HttpBackend` goes through the HTTP
API of API.md (``--url``). Anything with a ``learn`` method of the same
shape plugs in (the tests use an oracle with noise).
"""

from __future__ import annotations

import hashlib
import io
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import NDArray
from PIL import Image

from viewloc_bench.sets import BenchObject
from viewloc_client.image_upload import upload_file
from viewloc_core.camera import Camera
from viewloc_core.detection import Detection, Similarity2D
from viewloc_core.pose import Pose

if TYPE_CHECKING:
    import httpx

    from viewloc_bench.photos import TrainingPhotos
    from viewloc_core.model import ObjectModel


class Localizer(Protocol):
    """Finds one learned object in an image."""

    def __call__(
        self, image: NDArray[np.uint8], camera: Camera, max_detections: int = 1
    ) -> list[Detection]:
        """Detections, best first.

        Parameters
        ----------
        image : (H, W, 3) uint8
            RGB.
        camera : Camera
        max_detections : int
            Most detections wanted (instances of the object to find).
        """
        ...


class EngineUnavailableError(RuntimeError):
    """The localization engine (or the service) is not there yet."""


@dataclass(slots=True)
class LearnedObject:
    """A learned object and the function that finds it.

    Attributes
    ----------
    name : str
    localize : Localizer
        ``(image (H, W, 3) uint8 RGB, camera[, max_detections]) -> detections``, best first.
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


class PhotoLearningBackend(Backend, Protocol):
    """A backend that can also learn an object from masked training photos."""

    def learn_photos(self, obj: BenchObject, photos: TrainingPhotos) -> LearnedObject:
        """Learn ``obj`` from ``photos`` (not its mesh) and return its localizer."""
        ...


class CoreBackend:
    """``viewloc_core.learn.learn_from_mesh`` and ``viewloc_core.localize.localize`` in-process."""

    def __init__(self, refine: bool = True, seed: int = 0, max_detections: int = 1,
                 timeout_ms: float | None = None) -> None:
        self.refine = refine
        self.seed = seed
        self.max_detections = max_detections
        self.timeout_ms = timeout_ms
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

        mesh = trimesh.load(obj.mesh_path, force="mesh")
        assert isinstance(mesh, trimesh.Trimesh)
        t0 = time.perf_counter()
        model = learn_from_mesh(mesh, LearningConfig(), None, rng=self.seed)
        return self._learned(obj, model, time.perf_counter() - t0)

    def learn_photos(self, obj: BenchObject, photos: TrainingPhotos) -> LearnedObject:
        """Learn ``obj`` from masked photos (``learn_from_images``) and return its localizer."""
        self.check()
        from viewloc_core.learn import LearningConfig, learn_from_images

        t0 = time.perf_counter()
        model = learn_from_images(photos.images, photos.masks, photos.camera, photos.views,
                                  photos.diameter_mm, LearningConfig(), None, rng=self.seed)
        return self._learned(obj, model, time.perf_counter() - t0)

    def _learned(self, obj: BenchObject, model: ObjectModel, learn_s: float) -> LearnedObject:
        from model_store.files import model_sha256
        from viewloc_core.localize import prepare, warm_up
        from viewloc_core.model import ObjectModel as CoreModel

        # As the service does before it says ready (its model warmer), not
        # timed as learning: the first image's latency is then a
        # localization's, not the building of the model's search structures
        # (0.3-0.5 s: it was the hard set's two slowest images of 92).
        warm_up()
        if isinstance(model, CoreModel):
            prepare(model)

        return LearnedObject(
            obj.name,
            CoreLocalizer(model, self.refine, self.max_detections, self.timeout_ms),
            learn_s,
            _int_or_none(getattr(model, "training_views", None)),
            _int_or_none(getattr(model, "model_views", None)),
            # Two runs' figures differ by the models or by the search: the
            # checksum tells which (the service reports the same one).
            {"refinable": getattr(model, "contour", None) is not None,
             "model_sha256": model_sha256(model) if isinstance(model, CoreModel) else None},
        )


class CoreLocalizer:
    """One learned model's localizer in-process (``viewloc_core.localize.localize``).

    Each call leaves the localization's own stage times in
    :attr:`last_timing_ms` (``features``, ``align``, ``views``, ``pose`` and
    ``total``, ms; see ``LocalizationResult.timing_ms``), as
    :class:`HttpLocalizer` leaves the server's: the bench reports their
    medians beside the latency, so that a change of speed shows where it
    came from.
    """

    def __init__(self, model: ObjectModel, refine: bool = True, max_detections: int = 1,
                 timeout_ms: float | None = None) -> None:
        self.model = model
        self.refine = refine
        self.max_detections = max_detections
        #: The localization's time budget (``LocalizeOptions.timeout_ms``).
        self.timeout_ms = timeout_ms
        self.last_timing_ms: dict[str, float] = {}
        #: Whether the last call left a search out for the budget.
        self.last_timed_out = False

    def __call__(
        self, image: NDArray[np.uint8], camera: Camera, max_detections: int | None = None
    ) -> list[Detection]:
        """Detections, best first (``max_detections`` None: the localizer's own)."""
        from viewloc_core.localize import LocalizeOptions, localize

        wanted = self.max_detections if max_detections is None else max_detections
        result = localize(self.model, image, camera,
                          LocalizeOptions(max_detections=wanted, refine=self.refine,
                                          timeout_ms=self.timeout_ms))
        self.last_timing_ms = dict(result.timing_ms)
        self.last_timed_out = result.timed_out
        return list(result.detections)


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
    """PNG bytes of an RGB image (fast compression; the training photos' upload)."""
    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="PNG", compress_level=1)
    return buf.getvalue()


class HttpLocalizer:
    """One learned object's localizer through ``POST /v1/objects/{id}/localize``.

    The bench's latency (measured around the call) is the full round trip:
    encoding, upload, server work, answer and parsing. The image goes as
    the client library sends an array, an uncompressed BMP
    (:func:`viewloc_client.image_upload.upload_file`): what a station
    sending its camera's frames would do for speed. Each call also
    leaves its breakdown in :attr:`last_timing_ms`: ``client_encode`` and
    ``client_request`` (ms, measured here) and the server's own ``timing_ms``
    answer with its keys prefixed ``server_`` (``server_total``, ...).
    """

    def __init__(self, client: Any, object_id: str, options_json: str) -> None:
        self.client = client
        self.object_id = object_id
        self.options_json = options_json
        self.last_timing_ms: dict[str, float] = {}
        #: Whether the last answer said a search was left out for the budget.
        self.last_timed_out = False

    def __call__(
        self, image: NDArray[np.uint8], camera: Camera, max_detections: int | None = None
    ) -> list[Detection]:
        """Detections, best first (``max_detections`` None: as in the options given)."""
        options_json = self.options_json
        if max_detections is not None:
            options = {**json.loads(options_json), "max_detections": max_detections}
            options_json = json.dumps(options)
        cam: dict[str, Any] = {"fx": camera.fx, "fy": camera.fy, "cx": camera.cx,
                               "cy": camera.cy}
        if camera.dist:
            cam["dist"] = list(camera.dist)
        t0 = time.perf_counter()
        upload = upload_file(image, "image")
        t1 = time.perf_counter()
        resp = self.client.post(
            f"/v1/objects/{self.object_id}/localize",
            files={"image": upload},
            data={"camera": json.dumps(cam), "options": options_json},
        )
        t2 = time.perf_counter()
        if resp.status_code != 200:
            raise RuntimeError(f"localize answered {resp.status_code}: {resp.text[:500]}")
        body = resp.json()
        timing = {"client_encode": (t1 - t0) * 1000.0, "client_request": (t2 - t1) * 1000.0}
        for key, value in (body.get("timing_ms") or {}).items():
            timing[f"server_{key}"] = float(value)
        self.last_timing_ms = timing
        self.last_timed_out = bool(body.get("timed_out", False))
        return [detection_from_json(d) for d in body["detections"]]


class HttpBackend:
    """The same through the HTTP API (API.md): upload the mesh, wait for the job, localize.

    An object the service already learned from the same mesh bytes with the
    same seed and learning options (recognised by its name, which carries
    them) is reused instead of learned again, so repeated runs against one
    service measure localization only; ``reuse=False`` always uploads.
    ``learning`` is sent as the upload's ``spec.learning`` (default: the
    service's defaults, which are the core backend's).
    """

    def __init__(
        self,
        url: str,
        refine: bool = True,
        max_detections: int = 1,
        learn_timeout_s: float = 1800.0,
        api_key: str | None = None,
        seed: int = 0,
        reuse: bool = True,
        learning: dict[str, Any] | None = None,
        timeout_ms: float | None = None,
    ) -> None:
        import httpx

        headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
        self.url = url.rstrip("/")
        self.client = httpx.Client(base_url=self.url, timeout=120.0, headers=headers)
        self.refine = refine
        self.max_detections = max_detections
        self.learn_timeout_s = learn_timeout_s
        self.seed = seed
        self.reuse = reuse
        self.learning = {**(learning or {}), "seed": seed}
        self.timeout_ms = timeout_ms
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

    def _get(self, path: str) -> dict[str, Any]:
        r = self.client.get(path)
        if r.status_code != 200:
            raise RuntimeError(f"GET {path} answered {r.status_code}: {r.text[:500]}")
        body: dict[str, Any] = r.json()
        return body

    def object_name(self, obj: BenchObject, mesh_bytes: bytes) -> str:
        """Name under which the service keeps ``obj`` (see :func:`bench_object_name`)."""
        return bench_object_name(obj.name, mesh_bytes, self.learning)

    def _wait(self, obj: BenchObject, job_id: str, t0: float) -> dict[str, Any]:
        while True:
            job = self._get(f"/v1/jobs/{job_id}")
            if job["state"] in ("succeeded", "failed", "cancelled"):
                return job
            if time.perf_counter() - t0 > self.learn_timeout_s:
                raise RuntimeError(f"learning {obj.name} took longer than {self.learn_timeout_s} s")
            time.sleep(0.5)

    def learn(self, obj: BenchObject) -> LearnedObject:
        mesh_bytes = obj.mesh_path.read_bytes()
        name = self.object_name(obj, mesh_bytes)

        def upload() -> httpx.Response:
            return self.client.post(
                "/v1/objects",
                files={"mesh": (obj.mesh_path.name, mesh_bytes, "application/octet-stream")},
                data={"spec": json.dumps({"name": name, "units": "mm",
                                          "learning": self.learning})},
            )

        return self._learn(obj, name, "mesh", upload)

    def learn_photos(self, obj: BenchObject, photos: TrainingPhotos) -> LearnedObject:
        """Learn ``obj`` from masked photos through ``POST /v1/objects/from-images``.

        Reused as :meth:`learn` is, under a name that carries the photos' digest.
        """
        name = bench_object_name(obj.name, photos.digest().encode(), self.learning) + ":photos"

        def upload() -> httpx.Response:
            cam = photos.camera
            spec = {
                "name": name,
                "camera": {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy},
                "object_diameter_mm": photos.diameter_mm,
                "views": [{"azimuth_deg": v.azimuth_deg, "polar_deg": v.polar_deg,
                           "distance_mm": v.distance_mm, "inplane_deg": v.inplane_deg}
                          for v in photos.views],
                "learning": self.learning,
            }
            files = [("images", (f"photo{i:04d}.png", encode_png(image), "image/png"))
                     for i, image in enumerate(photos.images)]
            files += [("masks", (f"mask{i:04d}.png", encode_png(mask), "image/png"))
                      for i, mask in enumerate(photos.masks)]
            return self.client.post("/v1/objects/from-images", files=files,
                                    data={"spec": json.dumps(spec)})

        return self._learn(obj, name, "images", upload)

    def _learn(self, obj: BenchObject, name: str, source: str,
               upload: Callable[[], httpx.Response]) -> LearnedObject:
        """Reuse the object called ``name`` learned from ``source``, else ``upload`` it;
        wait for its job and return its localizer."""
        t0 = time.perf_counter()
        found = [o for o in self._get("/v1/objects")["objects"]
                 if o["name"] == name and o["source"] == source
                 and o["state"] in ("ready", "learning")] if self.reuse else []
        if found:
            # Newest first: a ready one, else the one still learning.
            found.sort(key=lambda o: (o["state"] == "ready", o["created_at"]), reverse=True)
            object_id, job_id = found[0]["object_id"], found[0]["job_id"]
            reused = True
        else:
            r = upload()
            if r.status_code != 202:
                raise RuntimeError(f"learning {obj.name} answered {r.status_code}: {r.text[:500]}")
            body = r.json()
            object_id, job_id = body["object"]["object_id"], body["job"]["job_id"]
            reused = False
        job = self._wait(obj, job_id, t0)
        if job["state"] != "succeeded":
            raise RuntimeError(f"learning {obj.name} {job['state']}: {job.get('error')}")
        learn_s = time.perf_counter() - t0
        if reused:
            # The learning happened earlier: report what the job took then.
            learn_s = _job_seconds(job) or learn_s
        info = self._get(f"/v1/objects/{object_id}")
        options = json.dumps({"max_detections": self.max_detections, "refine": self.refine,
                              **({} if self.timeout_ms is None
                                 else {"timeout_ms": self.timeout_ms})})
        return LearnedObject(
            obj.name,
            HttpLocalizer(self.client, object_id, options),
            learn_s,
            info.get("training_views"),
            info.get("model_views"),
            {"object_id": object_id, "reused": reused,
             "model_sha256": info.get("model_sha256")},
        )


def bench_object_name(name: str, mesh_bytes: bytes, learning: dict[str, Any]) -> str:
    """``bench:<name>:<mesh digest>:seed<seed>[:learning-<digest>]``: equal names mean
    the same mesh learned with the same options (the learning digest only when
    options other than the seed are given)."""
    digest = hashlib.sha256(mesh_bytes).hexdigest()[:16]
    out = f"bench:{name}:{digest}:seed{int(learning.get('seed', 0))}"
    extra = {k: v for k, v in learning.items() if k != "seed"}
    if extra:
        text = json.dumps(extra, sort_keys=True).encode()
        out += f":learning-{hashlib.sha256(text).hexdigest()[:8]}"
    return out


def _job_seconds(job: dict[str, Any]) -> float | None:
    """Run time of a finished job from its RFC 3339 timestamps."""
    from datetime import datetime

    try:
        start = datetime.fromisoformat(str(job["started_at"]).replace("Z", "+00:00"))
        end = datetime.fromisoformat(str(job["finished_at"]).replace("Z", "+00:00"))
    except (KeyError, TypeError, ValueError):
        return None
    return (end - start).total_seconds()
