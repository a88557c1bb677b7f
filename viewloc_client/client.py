"""A small typed client of the viewloc HTTP API (API.md), on httpx."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx

from viewloc_client.errors import (
    JobFailedError,
    JobTimeoutError,
    TransportError,
    ViewlocClientError,
    error_for,
)
from viewloc_client.image_upload import ImageInput, file_bytes, upload_file


@dataclass(frozen=True, slots=True)
class ObjectInfo:
    """API ``Object``."""

    object_id: str
    name: str
    state: str
    source: str
    diameter_mm: float
    training_views: int
    model_views: int
    created_at: str
    job_id: str
    error: str | None = None
    #: Symmetry group of the ready model, BOP ``models_info`` form in mm
    #: (``symmetries_discrete``, ``symmetries_continuous``); None while learning.
    symmetries: dict[str, Any] | None = field(default=None, hash=False)
    #: SHA-256 (hex) of the ready model's arrays; None while learning.
    model_sha256: str | None = None

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> ObjectInfo:
        return cls(d["object_id"], d["name"], d["state"], d["source"], float(d["diameter_mm"]),
                   int(d["training_views"]), int(d["model_views"]), d["created_at"],
                   d["job_id"], d.get("error"), d.get("symmetries"), d.get("model_sha256"))


@dataclass(frozen=True, slots=True)
class JobInfo:
    """API ``Job``."""

    job_id: str
    object_id: str
    state: str
    progress: float
    stage: str
    error: str | None
    created_at: str
    started_at: str | None
    finished_at: str | None

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> JobInfo:
        return cls(d["job_id"], d["object_id"], d["state"], float(d["progress"]), d["stage"],
                   d.get("error"), d["created_at"], d.get("started_at"), d.get("finished_at"))

    @property
    def done(self) -> bool:
        """True in a terminal state."""
        return self.state in ("succeeded", "failed", "cancelled")


@dataclass(frozen=True, slots=True)
class Localization:
    """Answer of a localization: detections as the API's JSON dicts."""

    object_ids: list[str]
    width: int
    height: int
    detections: list[dict[str, Any]]
    timing_ms: dict[str, float]
    overlay_png: bytes | None = None
    #: Objects of a several-object localization that could not be searched,
    #: as the API's JSON dicts (``object_id``, ``reason``, ``detail``).
    skipped: list[dict[str, Any]] = field(default_factory=list)
    #: A search was left out for the time budget (``timeout_ms``).
    timed_out: bool = False


def _camera_json(camera: dict[str, Any] | Any) -> str:
    if isinstance(camera, dict):
        return json.dumps(camera)
    fields = {k: float(getattr(camera, k)) for k in ("fx", "fy", "cx", "cy")}
    dist = list(getattr(camera, "dist", ()) or ())
    if dist:
        fields["dist"] = [float(c) for c in dist]  # type: ignore[assignment]
    return json.dumps(fields)


class ViewlocClient:
    """Client of one viewloc service.

    Parameters
    ----------
    base_url : str
        E.g. ``"http://127.0.0.1:8000"``.
    api_key : str, optional
        Sent as ``Authorization: Bearer <key>``.
    timeout : float
        Seconds per request (localization of large images can take a while).
    transport : httpx.BaseTransport, optional
        For custom transports (e.g. retries).
    """

    def __init__(self, base_url: str, api_key: str | None = None, timeout: float = 60.0,
                 transport: httpx.BaseTransport | None = None) -> None:
        headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
        self._http = httpx.Client(base_url=base_url, headers=headers, timeout=timeout,
                                  transport=transport)

    def close(self) -> None:
        """Close the connection pool."""
        self._http.close()

    def __enter__(self) -> ViewlocClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _request(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        try:
            response = self._http.request(method, path, **kwargs)
        except httpx.HTTPError as exc:
            raise TransportError(str(exc)) from exc
        if response.status_code >= 400:
            try:
                problem = response.json()
            except ValueError:
                problem = {"detail": response.text}
            raise error_for(response.status_code, problem if isinstance(problem, dict) else {})
        return response

    # -- objects -----------------------------------------------------------
    def learn_mesh(self, mesh: bytes | str | Path, *, filename: str = "mesh.stl",
                   name: str = "", units: str = "mm",
                   learning: dict[str, Any] | None = None,
                   symmetries: dict[str, Any] | None = None) -> tuple[ObjectInfo, JobInfo]:
        """Upload a mesh (bytes with ``filename`` for its format, or a path).

        ``symmetries`` (BOP ``models_info`` form, lengths in ``units``)
        replaces the group the service would detect; ``{}`` means none.
        """
        spec: dict[str, Any] = {"name": name, "units": units}
        if learning:
            spec["learning"] = learning
        if symmetries is not None:
            spec["symmetries"] = symmetries
        r = self._request("POST", "/v1/objects", files={"mesh": file_bytes(mesh, filename)},
                          data={"spec": json.dumps(spec)})
        body = r.json()
        return ObjectInfo.from_json(body["object"]), JobInfo.from_json(body["job"])

    def learn_images(self, images: list[ImageInput], camera: dict[str, Any] | Any,
                     views: list[dict[str, float]], object_diameter_mm: float, *,
                     masks: list[ImageInput] | None = None, name: str = "",
                     learning: dict[str, Any] | None = None) -> tuple[ObjectInfo, JobInfo]:
        """Upload real images with known viewing angles (paper §4.1, API.md from-images).

        Parameters
        ----------
        images : list of bytes, paths or arrays
            PNG, JPEG, TIFF or BMP files (8/16-bit, grey or colour), one
            camera; or pixel arrays (see
            :func:`viewloc_client.image_upload.upload_file`).
        camera : dict or Camera-like
            ``{fx, fy, cx, cy[, dist]}`` of the camera that took them, pixels.
        views : list of dict
            One per image: ``azimuth_deg``, ``polar_deg``, ``distance_mm`` and
            optionally ``inplane_deg`` (default 0); the object origin is on the
            optical axis at ``distance_mm``.
        object_diameter_mm : float
            The part's largest extent, mm (0.1 mm to 100 m).
        masks : list of bytes, paths or arrays, optional
            Same count and order as ``images``; non-zero = object.
        name, learning
            Object name and optional learning options.
        """
        spec: dict[str, Any] = {"name": name, "camera": json.loads(_camera_json(camera)),
                                "object_diameter_mm": object_diameter_mm, "views": views}
        if learning:
            spec["learning"] = learning
        files = [("images", upload_file(b, f"image_{i}", f"images[{i}]"))
                 for i, b in enumerate(images)]
        files += [("masks", upload_file(b, f"mask_{i}", f"masks[{i}]"))
                  for i, b in enumerate(masks or [])]
        r = self._request("POST", "/v1/objects/from-images", files=files,
                          data={"spec": json.dumps(spec)})
        body = r.json()
        return ObjectInfo.from_json(body["object"]), JobInfo.from_json(body["job"])

    def list_objects(self) -> list[ObjectInfo]:
        """All objects."""
        return [ObjectInfo.from_json(o) for o in self._request("GET", "/v1/objects").json()
                ["objects"]]

    def get_object(self, object_id: str) -> ObjectInfo:
        """One object."""
        return ObjectInfo.from_json(self._request("GET", f"/v1/objects/{object_id}").json())

    def delete_object(self, object_id: str) -> None:
        """Delete an object (cancels its running job)."""
        self._request("DELETE", f"/v1/objects/{object_id}")

    # -- jobs --------------------------------------------------------------
    def get_job(self, job_id: str) -> JobInfo:
        """One job."""
        return JobInfo.from_json(self._request("GET", f"/v1/jobs/{job_id}").json())

    def cancel_job(self, job_id: str) -> JobInfo:
        """Cancel a queued or running job."""
        return JobInfo.from_json(self._request("DELETE", f"/v1/jobs/{job_id}").json())

    def wait_for_job(self, job_id: str, timeout: float = 600.0,
                     poll_interval: float = 0.25) -> JobInfo:
        """Poll until the job finishes; raises :class:`JobFailedError` unless it succeeded."""
        deadline = time.monotonic() + timeout
        while True:
            job = self.get_job(job_id)
            if job.done:
                if job.state != "succeeded":
                    raise JobFailedError(job)
                return job
            if time.monotonic() > deadline:
                raise JobTimeoutError(f"job {job_id} still {job.state} after {timeout} s")
            time.sleep(poll_interval)

    # -- localization ------------------------------------------------------
    def localize(self, object_id: str | None, image: ImageInput,
                 camera: dict[str, Any] | Any, *, max_detections: int = 1,
                 min_score: float | None = None, refine: bool = True,
                 object_ids: list[str] | None = None, overlay: bool = False,
                 roi: tuple[int, int, int, int] | None = None,
                 depth_mm: tuple[float, float] | None = None,
                 max_rotation_std_deg: float | None = None,
                 timeout_ms: float | None = None) -> Localization:
        """Localize one object (``object_id``) or several (``object_id=None``).

        ``image`` is an image file's bytes or path, or the pixels: an
        (H, W) or (H, W, 3) RGB ``uint8`` array is sent as an uncompressed
        BMP, the fastest upload the service decodes (about 25 ms less per
        640x480 frame than PNG; :mod:`viewloc_client.image_upload`).
        ``camera`` is a dict ``{fx, fy, cx, cy[, dist]}`` or any object with
        those attributes (e.g. ``viewloc_core.camera.Camera``). ``roi``
        ``(x, y, width, height)`` (pixels) is where the part's centre lies;
        ``depth_mm`` ``(min, max)`` the depths of its origin;
        ``max_rotation_std_deg`` the most rotation uncertainty a detection
        may have (degrees; the service's default 30 when None);
        ``timeout_ms`` the search's time budget (ms; none when None: see
        :attr:`Localization.timed_out`).
        """
        import base64

        options: dict[str, Any] = {"max_detections": max_detections, "refine": refine}
        if min_score is not None:
            options["min_score"] = min_score
        if roi is not None:
            options["roi"] = dict(zip(("x", "y", "width", "height"), roi, strict=True))
        if depth_mm is not None:
            options["depth_mm"] = {"min": depth_mm[0], "max": depth_mm[1]}
        if max_rotation_std_deg is not None:
            options["max_rotation_std_deg"] = max_rotation_std_deg
        if timeout_ms is not None:
            options["timeout_ms"] = timeout_ms
        if object_id is None:
            path = "/v1/localize"
            if object_ids is not None:
                options["object_ids"] = object_ids
        else:
            path = f"/v1/objects/{object_id}/localize"
        r = self._request("POST", path, params={"overlay": "true"} if overlay else None,
                          files={"image": upload_file(image, "scene.png")},
                          data={"camera": _camera_json(camera), "options": json.dumps(options)})
        body = r.json()
        png = body.get("overlay_png_base64")
        return Localization(
            object_ids=body.get("object_ids") or [body.get("object_id")],
            width=int(body["image"]["width"]), height=int(body["image"]["height"]),
            detections=list(body["detections"]), timing_ms=dict(body["timing_ms"]),
            overlay_png=base64.b64decode(png) if png else None,
            skipped=list(body.get("skipped") or []),
            timed_out=bool(body.get("timed_out", False)),
        )

    # -- operations --------------------------------------------------------
    def ready(self) -> bool:
        """True when /readyz answers 200."""
        try:
            self._request("GET", "/readyz")
        except ViewlocClientError:
            return False
        return True
