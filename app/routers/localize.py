"""Localization: one object (``/v1/objects/{id}/localize``) or several (``/v1/localize``).

Plain ``def`` endpoints: FastAPI runs them in its thread pool, so the
CPU-heavy core never blocks the event loop.
"""

from __future__ import annotations

import base64
import dataclasses
import logging
import time
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Depends, File, Form, Path, Query, UploadFile

from app.deps import MetricsDep, SettingsDep, StoreDep, require_multipart, single_parts
from app.imaging import decode_image, encode_png
from app.openapi_doc import errors
from app.problems import ProblemError
from app.routers.common import parse_json_field, read_limited
from app.schemas import (
    CameraIn,
    LocalizationOut,
    LocalizeOptionsIn,
    MultiLocalizationOut,
    MultiLocalizeOptionsIn,
)
from app.serialize import detection_dict
from model_store import ModelStore
from model_store.errors import (
    CorruptModelError,
    ObjectNotFoundError,
    ObjectNotReadyError,
)
from viewloc_core.camera import Camera
from viewloc_core.detection import Detection
from viewloc_core.errors import InvalidCameraError
from viewloc_core.localize import (
    LocalizeOptions,
    Scene,
    localize,
    localize_in_scene,
    prepare_scene,
    refines,
)
from viewloc_core.search_space import DepthRange, ImageRegion

router = APIRouter(tags=["localization"])

log = logging.getLogger("viewloc.app")

#: The form parts of a localization that a client may send once only.
_SINGLE_PARTS = single_parts("image", "camera", "options")

ImageFile = Annotated[UploadFile, File(description="Scene image: PNG, JPEG, TIFF or BMP.")]
CameraField = Annotated[
    str,
    Form(description='JSON Camera: {"fx", "fy", "cx", "cy", "dist": [k1, k2, p1, p2, k3]}'),
]
Overlay = Annotated[
    bool,
    Query(description="Also return the scene with each detection drawn, as base64 PNG in "
                      "`overlay_png_base64`."),
]


def _camera(text: str, width: int, height: int) -> Camera:
    cam = parse_json_field(text, CameraIn, "camera")
    if (cam.width is not None and cam.width != width) or (
        cam.height is not None and cam.height != height
    ):
        raise ProblemError(422, "camera size does not match the image", "validation",
                           [("camera", f"the image is {width}x{height}")])
    try:
        return Camera(cam.fx, cam.fy, cam.cx, cam.cy, width, height, tuple(cam.dist or ()))
    except InvalidCameraError as exc:
        field = f"camera.{exc.field}" if exc.field else "camera"
        raise ProblemError(422, exc.message, "validation", [(field, exc.message)]) from exc


def _decode(image: UploadFile, settings: Any, timing: dict[str, float]) -> np.ndarray:
    t = time.perf_counter()
    data = read_limited(image, settings.max_image_bytes, "image")
    img = decode_image(data, "image", settings.max_image_pixels)
    timing["decode"] = (time.perf_counter() - t) * 1000
    return img


def _core_options(opts: LocalizeOptionsIn) -> LocalizeOptions:
    roi = (None if opts.roi is None
           else ImageRegion(opts.roi.x, opts.roi.y, opts.roi.width, opts.roi.height))
    depth = None if opts.depth_mm is None else DepthRange(opts.depth_mm.min, opts.depth_mm.max)
    return LocalizeOptions(max_detections=opts.max_detections, min_score=opts.min_score,
                           refine=opts.refine, roi=roi, depth_mm=depth,
                           max_rotation_std_deg=opts.max_rotation_std_deg,
                           timeout_ms=opts.timeout_ms)


def _run(model: Any, img: np.ndarray, camera: Camera, opts: LocalizeOptionsIn,
         metrics: Any, scene: Scene | None = None, deadline: float | None = None,
         ) -> tuple[list[Detection], dict[str, float], bool]:
    """One part's detections, the core's timings (ms) and whether the time
    budget cut its search short; in ``scene`` when given (shared by the
    parts of one request, whose ``deadline`` they share), else in ``img``."""
    t = time.perf_counter()
    core_options = _core_options(opts)
    result = (localize(model, img, camera, core_options) if scene is None
              else localize_in_scene(model, scene, core_options, deadline=deadline))
    metrics.localize_seconds.observe(time.perf_counter() - t)
    return (list(result.detections), {str(k): float(v) for k, v in result.timing_ms.items()},
            result.timed_out)


def _overlay(img: np.ndarray, items: list[tuple[Any, list[Detection]]], camera: Camera) -> str:
    from viewloc_core.overlay import draw_detections, to_rgb8

    canvas = to_rgb8(img)
    for model, dets in items:
        canvas = draw_detections(canvas, dets, camera, getattr(model, "mesh_vertices_mm", None),
                                 getattr(model, "mesh_faces", None))
    return base64.b64encode(encode_png(canvas)).decode("ascii")


def _answer(
    head: dict[str, Any],
    img: np.ndarray,
    cam: Camera,
    dets: list[Detection],
    drawn: list[tuple[Any, list[Detection]]],
    overlay: bool,
    timing: dict[str, float],
    t0: float,
) -> dict[str, Any]:
    """The localize answer of API.md: image size, detections, overlay, timings (ms)."""
    out: dict[str, Any] = {
        **head,
        "image": {"width": int(img.shape[1]), "height": int(img.shape[0])},
        "detections": [detection_dict(d) for d in dets],
    }
    if overlay:
        t = time.perf_counter()
        out["overlay_png_base64"] = _overlay(img, drawn, cam)
        timing["overlay"] = (time.perf_counter() - t) * 1000
    timing["total"] = (time.perf_counter() - t0) * 1000
    out["timing_ms"] = timing
    return out


@router.post(
    "/v1/objects/{object_id}/localize",
    response_model=LocalizationOut,
    response_model_exclude_none=False,
    dependencies=[Depends(require_multipart), Depends(_SINGLE_PARTS)],
    responses=errors(400, 404, 409, 413, 415, 422, 503),
    summary="Localize one object in an image (6D pose)",
)
def localize_object(
    object_id: Annotated[str, Path(description="Object id (32 hex digits).")],
    image: ImageFile,
    camera: CameraField,
    store: StoreDep,
    settings: SettingsDep,
    metrics: MetricsDep,
    options: Annotated[
        str | None,
        Form(description='JSON: {"max_detections": 1, "min_score": null, "refine": true, '
                         '"roi": {"x", "y", "width", "height"} (optional), '
                         '"depth_mm": {"min", "max"} (optional), '
                         '"max_rotation_std_deg": 30 (optional), "timeout_ms": null (optional)}'),
    ] = None,
    overlay: Overlay = False,
) -> dict[str, Any]:
    """Find the object; no detection above ``min_score`` answers ``"detections": []``."""
    t0 = time.perf_counter()
    timing: dict[str, float] = {}
    store.get_object(object_id)  # 404 before anything else
    opts = parse_json_field(options, LocalizeOptionsIn, "options")
    img = _decode(image, settings, timing)
    cam = _camera(camera, img.shape[1], img.shape[0])
    # 409 unless ready: the record is read again, as the object may have
    # been deleted or relearned since the check above.
    model = store.load_model(object_id)
    dets, core_timing, timed_out = _run(model, img, cam, opts, metrics)
    # Every detection names its object, as in the multi-object answer (not null).
    dets = [dataclasses.replace(d, object_id=object_id) for d in dets]
    core_total = core_timing.pop("total", None)
    timing.update(core_timing)
    if core_total is not None:
        timing["localize"] = core_total
    return _answer({"object_id": object_id, "timed_out": timed_out}, img, cam, dets,
                   [(model, dets)], overlay, timing, t0)


def _objects_to_search(store: ModelStore, object_ids: list[str] | None) -> dict[str, str | None]:
    """The ids of the objects to search, each with the request field that named it.

    Every ready object when the client named none (no field), else the
    client's list without repeats, each id named by its first entry (the
    index in the list as sent, not in the list without repeats).
    """
    if object_ids is None:
        return {o.object_id: None for o in store.list_objects(state="ready")}
    fields: dict[str, str | None] = {}
    for i, oid in enumerate(object_ids):
        fields.setdefault(oid, f"options.object_ids[{i}]")
    return fields


def _require_named(store: ModelStore, fields: dict[str, str | None]) -> None:
    """404 naming the list entry of the first named id that is no object.

    The ready objects searched when the client named none were just listed:
    one deleted since is skipped when the models are loaded.
    """
    for oid, field in fields.items():
        if field is None:
            continue
        try:
            store.get_object(oid)  # a malformed id is no object either
        except ObjectNotFoundError as exc:
            raise ObjectNotFoundError(exc.message, field) from exc


def _load_models(
    store: ModelStore, fields: dict[str, str | None]
) -> tuple[list[tuple[str, Any]], list[dict[str, str]]]:
    """(id, model) of each object to search, and the listed objects skipped.

    An object the client named keeps its error: 404 naming its list entry
    when it was deleted since it was checked, 409 when it is not ready or its
    stored model turns out corrupt (a client that names an object wants to
    know). When the client named none, an object deleted since it was
    listed, no longer ready, or whose model turns out corrupt (the store has
    just marked it failed) is skipped and reported in ``skipped``: one
    unusable object must not fail the search for all the others, and the
    client cannot act on an error about an object it never asked for.
    """
    models: list[tuple[str, Any]] = []
    skipped: list[dict[str, str]] = []
    for oid, field in fields.items():
        try:
            models.append((oid, store.load_model(oid)))
        except ObjectNotFoundError as exc:
            if field is not None:
                raise ObjectNotFoundError(exc.message, field) from exc
            skipped.append({"object_id": oid, "reason": "deleted", "detail": exc.message})
        except ObjectNotReadyError as exc:
            if field is not None:
                raise
            skipped.append({"object_id": oid, "reason": "not-ready", "detail": exc.message})
        except CorruptModelError as exc:
            if field is not None:
                raise
            # At error level, as when a request that named the object is
            # answered (app.problems): a damaged store is for an operator to
            # see, whichever request met it first.
            log.error("corrupt stored model of %s skipped: %s", oid, exc.message)
            skipped.append({"object_id": oid, "reason": "corrupt", "detail": exc.message})
    return models, skipped


@router.post(
    "/v1/localize",
    response_model=MultiLocalizationOut,
    dependencies=[Depends(require_multipart), Depends(_SINGLE_PARTS)],
    responses=errors(400, 404, 409, 413, 415, 422, 503),
    summary="Localize several (default: all ready) objects in one image",
)
def localize_many(
    image: ImageFile,
    camera: CameraField,
    store: StoreDep,
    settings: SettingsDep,
    metrics: MetricsDep,
    options: Annotated[
        str | None,
        Form(description='JSON: {"object_ids": [...], "max_detections": 1, "min_score": null, '
                         '"roi": {...}, "depth_mm": {...}, "max_rotation_std_deg": 30, '
                         '"timeout_ms": null, "refine": true}'),
    ] = None,
    overlay: Overlay = False,
) -> dict[str, Any]:
    """Each detection carries its ``object_id``; best score first. Without
    ``options.object_ids``, a listed object that cannot be searched is
    reported in ``skipped`` instead of failing the request."""
    t0 = time.perf_counter()
    timing: dict[str, float] = {}
    opts = parse_json_field(options, MultiLocalizeOptionsIn, "options")
    fields = _objects_to_search(store, opts.object_ids)
    _require_named(store, fields)  # 404 before the image is decoded
    img = _decode(image, settings, timing)
    cam = _camera(camera, img.shape[1], img.shape[0])
    models, skipped = _load_models(store, fields)
    ids: list[str] = []  # the objects searched
    all_dets: list[Detection] = []
    drawn: list[tuple[Any, list[Detection]]] = []
    # The image's features and edge pyramid are the same for every part:
    # found once (a colour 640x480 image: about 25 ms a part saved).
    t = time.perf_counter()
    core_options = _core_options(opts)
    # One budget for the request: the objects share it, in their order.
    deadline = core_options.deadline(t)
    timed_out = False
    scene = prepare_scene(img, cam, edges=any(refines(m, core_options) for _, m in models))
    localize_ms = (time.perf_counter() - t) * 1000
    timing["features"] = scene.features_ms
    try:
        for k, (oid, model) in enumerate(models):
            # The first object is always searched, as a single object's
            # search always makes its first fits.
            if k > 0 and time.perf_counter() >= deadline:
                skipped.append({"object_id": oid, "reason": "timed-out",
                                "detail": "the time budget (options.timeout_ms) was spent "
                                          "before its search began"})
                timed_out = True
                continue
            dets, core_timing, cut_short = _run(model, img, cam, opts, metrics, scene,
                                                deadline)
            timed_out |= cut_short
            ids.append(oid)
            localize_ms += core_timing.get("total", 0.0)
            dets = [dataclasses.replace(d, object_id=oid) for d in dets]
            drawn.append((model, dets))
            all_dets.extend(dets)
    finally:
        scene.release()
    all_dets.sort(key=lambda d: -d.score)
    timing["localize"] = localize_ms
    return _answer({"object_ids": ids, "skipped": skipped, "timed_out": timed_out}, img, cam,
                   all_dets, drawn, overlay, timing, t0)
