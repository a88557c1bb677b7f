"""``/v1/objects``: learn from a mesh or from images, list, get, delete."""

from __future__ import annotations

import threading
from collections import OrderedDict
from pathlib import PurePath
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Depends, File, Form, Path, Response, UploadFile

from app.deps import RunnerDep, SettingsDep, StoreDep, require_multipart, single_parts
from app.imaging import decode_image
from app.openapi_doc import errors
from app.problems import ProblemError
from app.routers.common import check_learning_spec, parse_json_field, read_limited
from app.schemas import (
    ImagesSpec,
    MeshSpec,
    ObjectCreated,
    ObjectList,
    ObjectOut,
    SymmetriesIn,
)
from app.serialize import job_dict, object_dict, symmetries_dict
from model_store import ModelStore, ObjectRecord
from model_store.errors import CorruptModelError, ObjectNotFoundError, ObjectNotReadyError
from model_store.files import encode_arrays
from viewloc_core.camera import Camera
from viewloc_core.errors import InvalidCameraError, InvalidInputError
from viewloc_core.features import MIN_IMAGE_SIDE_PX

router = APIRouter(prefix="/v1/objects", tags=["objects"])

ObjectId = Annotated[str, Path(description="Object id (32 hex digits).")]

_MESH_TYPES = ("stl", "obj", "ply", "off", "glb", "gltf")

#: The form parts of an upload that a client may send once only; a
#: from-images upload's images and masks are one part per photo.
_MESH_SINGLE_PARTS = single_parts("mesh", "spec")
_IMAGES_SINGLE_PARTS = single_parts("spec")


def mesh_file_type(filename: str | None, data: bytes) -> str:
    """Mesh format from the upload's file name suffix, else from magic bytes.

    The file name is used for nothing else (never as a path).
    """
    suffix = PurePath(filename or "").suffix.lower().lstrip(".")
    if suffix in _MESH_TYPES:
        return suffix
    head = data[:512]
    if head.startswith(b"glTF"):
        return "glb"
    if head.startswith(b"ply"):
        return "ply"
    if head.lstrip().startswith(b"OFF"):
        return "off"
    if head.lstrip().startswith(b"{") and b'"asset"' in data[:4096]:
        return "gltf"
    if head.lstrip().startswith(b"solid") or (
        len(data) >= 84 and 84 + 50 * int.from_bytes(data[80:84], "little") == len(data)
    ):
        return "stl"
    raise ProblemError(
        422, "cannot tell the mesh format: name the file with a suffix "
        ".stl, .obj, .ply, .off, .glb or .gltf", "validation",
        [("mesh", "unknown mesh format")],
    )


def declared_symmetries_meta(
    declared: SymmetriesIn, units: str, diameter_mm: float, reach_mm: float
) -> dict[str, Any]:
    """The declared group checked and completed, in BOP form and mm, as the job reads it.

    422 naming the entry (``spec.symmetries.symmetries_discrete[1]``) when
    it is no rigid motion, moves the continuous axis, the transforms
    generate no finite group, or one would move the part off itself
    (``reach_mm``: how far the part reaches from its origin, mm; see
    :func:`viewloc_core.symmetry.declared_symmetries`).
    """
    from viewloc_core.mesh import UNIT_TO_MM
    from viewloc_core.symmetry import declared_symmetries

    try:
        sym = declared_symmetries(declared.model_dump(), to_mm=UNIT_TO_MM[units],
                                  diameter_mm=diameter_mm, reach_mm=reach_mm)
    except InvalidInputError as exc:
        raise ProblemError(422, f"the declared symmetries are not valid: {exc.message}",
                           "validation",
                           [(f"spec.symmetries.{exc.field or ''}".rstrip("."), exc.message)],
                           ) from exc
    return symmetries_dict(sym)


#: BOP form of each ready model's symmetries by (object_id, model checksum): a
#: listing then reads each model once per process, not at every request.
_SYMMETRIES: OrderedDict[tuple[str, str], dict[str, Any]] = OrderedDict()
_SYMMETRIES_LOCK = threading.Lock()
_SYMMETRIES_MAX = 4096


def _object_out(store: ModelStore, rec: ObjectRecord) -> dict[str, Any]:
    """API ``Object`` with the model's symmetry group once it is ready."""
    if rec.state != "ready" or rec.model_sha256 is None:
        return object_dict(rec)
    key = (rec.object_id, rec.model_sha256)
    with _SYMMETRIES_LOCK:
        cached = _SYMMETRIES.get(key)
    if cached is None:
        try:
            model = store.load_model(rec.object_id)
        except (CorruptModelError, ObjectNotReadyError):
            # A corrupt model has just been marked failed; show the object as it now is.
            return object_dict(store.get_object(rec.object_id))
        cached = symmetries_dict(model.symmetry_group())
        with _SYMMETRIES_LOCK:
            _SYMMETRIES[key] = cached
            while len(_SYMMETRIES) > _SYMMETRIES_MAX:
                _SYMMETRIES.popitem(last=False)
    return object_dict(rec, cached)


def _created(store_obj: Any, store_job: Any, response: Response) -> dict[str, Any]:
    response.headers["Location"] = f"/v1/jobs/{store_job.job_id}"
    return {"object": object_dict(store_obj), "job": job_dict(store_job)}


@router.post(
    "",
    status_code=202,
    response_model=ObjectCreated,
    dependencies=[Depends(require_multipart), Depends(_MESH_SINGLE_PARTS)],
    responses=errors(400, 413, 415, 422, 503),
    summary="Learn an object from a CAD mesh",
)
def create_object(
    mesh: Annotated[UploadFile, File(description="STL, OBJ, PLY, OFF, GLB or glTF file.")],
    store: StoreDep,
    runner: RunnerDep,
    settings: SettingsDep,
    response: Response,
    spec: Annotated[
        str | None,
        Form(description='JSON: {"name": str, "units": "mm"|"cm"|"m"|"in", "learning": {...}, '
             '"symmetries": {"symmetries_discrete": [[16 numbers], ...], '
             '"symmetries_continuous": [{"axis": [3], "offset": [3]}]}} (all optional)'),
    ] = None,
) -> dict[str, Any]:
    """Store the mesh and queue a learning job. Answers 202 with ``Location: /v1/jobs/{id}``."""
    parsed = parse_json_field(spec, MeshSpec, "spec")
    data = read_limited(mesh, settings.max_mesh_bytes, "mesh")
    if not data:
        raise ProblemError(422, "the mesh file is empty", "validation", [("mesh", "empty file")])
    file_type = mesh_file_type(mesh.filename, data)
    check_learning_spec(parsed.learning)
    from viewloc_core.mesh import load_mesh

    # Parse now so a corrupt mesh is a 422 here, not a failed job later.
    loaded = load_mesh(data, file_type, parsed.units)
    name = parsed.name or PurePath(mesh.filename or "object").stem[:200]
    from viewloc_core.mesh import mesh_diameter_mm, mesh_reach_mm

    diameter_mm = float(mesh_diameter_mm(loaded))
    meta: dict[str, Any] = {
        "file_type": file_type,
        "units": parsed.units,
        "learning": parsed.learning or {},
    }
    if parsed.symmetries is not None:
        meta["symmetries"] = declared_symmetries_meta(parsed.symmetries, parsed.units,
                                                      diameter_mm, mesh_reach_mm(loaded))
    obj, job = store.create_object(
        name=name,
        source="mesh",
        kind="learn_mesh",
        upload=data,
        upload_suffix="bin",
        upload_meta=meta,
        diameter_mm=diameter_mm,
    )
    runner.submit(job)
    return _created(obj, job, response)


@router.post(
    "/from-images",
    status_code=202,
    response_model=ObjectCreated,
    dependencies=[Depends(require_multipart), Depends(_IMAGES_SINGLE_PARTS)],
    responses=errors(400, 413, 415, 422, 503),
    summary="Learn an object from real images with known viewing angles",
)
def create_object_from_images(
    images: Annotated[
        list[UploadFile], File(description="PNG, JPEG, TIFF or BMP; 8/16-bit; grey or colour.")
    ],
    spec: Annotated[
        str,
        Form(description='JSON: {"name", "camera": Camera, "object_diameter_mm", '
             '"views": [{"azimuth_deg", "polar_deg", "distance_mm", "inplane_deg"}, ...], '
             '"symmetries" (optional, as for a mesh, mm)}'),
    ],
    store: StoreDep,
    runner: RunnerDep,
    settings: SettingsDep,
    response: Response,
    masks: Annotated[
        list[UploadFile] | None,
        File(description="Optional, one per image, same size; non-zero = object."),
    ] = None,
) -> dict[str, Any]:
    """Store the decoded images and queue a learning job (paper's real-image path)."""
    if len(images) > settings.max_images:
        raise ProblemError(
            413, f"{len(images)} images, more than the limit of {settings.max_images}",
            "too-large", [("images", f"at most {settings.max_images} images")],
        )
    parsed = parse_json_field(spec, ImagesSpec, "spec")
    masks = masks or []
    problems: list[tuple[str, str]] = []
    if len(parsed.views) != len(images):
        problems.append(("spec.views", f"{len(parsed.views)} views for {len(images)} images"))
    if masks and len(masks) != len(images):
        problems.append(("masks", f"{len(masks)} masks for {len(images)} images"))
    if problems:
        raise ProblemError(422, "the counts of images, masks and views differ", "validation",
                           problems)
    # A camera within the part's own radius sees it from inside.
    inside = [(f"spec.views[{i}].distance_mm", f"{v.distance_mm:g} mm is within the part's "
               f"radius ({parsed.object_diameter_mm / 2:g} mm)")
              for i, v in enumerate(parsed.views)
              if v.distance_mm <= parsed.object_diameter_mm / 2]
    if inside:
        raise ProblemError(422, "a view's camera lies within the part", "validation", inside)
    check_learning_spec(parsed.learning)
    arrays: dict[str, np.ndarray] = {}
    size: tuple[int, int] | None = None
    decoded = 0

    def count(field: str, nbytes: int) -> None:
        # Compressed files can be small and their pixels huge: bound what is kept.
        nonlocal decoded
        decoded += nbytes
        if decoded > settings.max_images_decoded_bytes:
            raise ProblemError(
                413, f"the decoded images exceed {settings.max_images_decoded_bytes} bytes",
                "too-large", [(field, "decoded images larger than "
                               f"{settings.max_images_decoded_bytes} bytes in total")],
            )

    for i, upload in enumerate(images):
        field = f"images[{i}]"
        img = decode_image(read_limited(upload, settings.max_image_bytes, field), field,
                           settings.max_image_pixels)
        count(field, img.nbytes)
        if min(img.shape[:2]) < MIN_IMAGE_SIDE_PX:
            raise ProblemError(422, "image too small", "validation", [(
                field, f"{img.shape[1]}x{img.shape[0]} pixels; at least {MIN_IMAGE_SIDE_PX} "
                "on each side")])
        if size is None:
            size = (img.shape[1], img.shape[0])
        elif (img.shape[1], img.shape[0]) != size:
            raise ProblemError(422, "all images must have the same size (one camera)",
                               "validation", [(field, f"size {img.shape[1]}x{img.shape[0]}, "
                                               f"expected {size[0]}x{size[1]}")])
        arrays[f"image_{i:04d}"] = img
    for i, upload in enumerate(masks):
        field = f"masks[{i}]"
        m = decode_image(read_limited(upload, settings.max_image_bytes, field), field,
                         settings.max_image_pixels)
        if (m.shape[1], m.shape[0]) != size:
            raise ProblemError(422, "each mask must have the size of its image", "validation",
                               [(field, f"size {m.shape[1]}x{m.shape[0]}, expected "
                                 f"{size[0]}x{size[1]}" if size else "bad size")])
        arrays[f"mask_{i:04d}"] = (m.reshape(m.shape[0], m.shape[1], -1).max(axis=2) > 0).astype(
            np.uint8)
        count(field, arrays[f"mask_{i:04d}"].nbytes)
    assert size is not None  # FastAPI requires at least one image
    cam = parsed.camera
    if (cam.width is not None and cam.width != size[0]) or (
        cam.height is not None and cam.height != size[1]
    ):
        raise ProblemError(422, "camera size does not match the images", "validation",
                           [("spec.camera", f"images are {size[0]}x{size[1]}")])
    # The photos' origin is the point their optical axes meet, on the part:
    # no point of the part lies farther from it than the part's diameter.
    symmetries_meta = None if parsed.symmetries is None else declared_symmetries_meta(
        parsed.symmetries, "mm", parsed.object_diameter_mm, parsed.object_diameter_mm)
    camera_meta = {
        "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
        "dist": list(cam.dist or []), "width": size[0], "height": size[1],
    }
    try:
        Camera(cam.fx, cam.fy, cam.cx, cam.cy, size[0], size[1], tuple(cam.dist or ()))
    except InvalidCameraError as exc:
        raise ProblemError(422, exc.message, "validation",
                           [(f"spec.camera.{exc.field or ''}".rstrip("."), exc.message)]) from exc
    meta: dict[str, Any] = {
        "count": len(images),
        "has_masks": bool(masks),
        "camera": camera_meta,
        "views": [v.model_dump() for v in parsed.views],
        "diameter_mm": parsed.object_diameter_mm,
        "learning": parsed.learning or {},
    }
    if symmetries_meta is not None:
        meta["symmetries"] = symmetries_meta
    obj, job = store.create_object(
        name=parsed.name or "object",
        source="images",
        kind="learn_images",
        upload=encode_arrays(arrays),
        upload_suffix="npz",
        upload_meta=meta,
        diameter_mm=parsed.object_diameter_mm,
        training_views=len(images),
    )
    runner.submit(job)
    return _created(obj, job, response)


@router.get("", response_model=ObjectList, responses=errors(503), summary="List objects")
def list_objects(store: StoreDep) -> dict[str, Any]:
    """All objects, oldest first."""
    out = []
    for rec in store.list_objects():
        try:
            out.append(_object_out(store, rec))
        except ObjectNotFoundError:  # deleted while listing
            continue
    return {"objects": out}


@router.get("/{object_id}", response_model=ObjectOut, responses=errors(404, 503),
            summary="Get an object")
def get_object(object_id: ObjectId, store: StoreDep) -> dict[str, Any]:
    """One object's metadata and state."""
    return _object_out(store, store.get_object(object_id))


@router.delete("/{object_id}", status_code=204, responses=errors(404, 503),
               summary="Delete an object (cancels its running job)")
def delete_object(object_id: ObjectId, store: StoreDep, runner: RunnerDep) -> Response:
    """Remove the object, its files and model; a running learning job is cancelled."""
    running = store.delete_object(object_id)
    if running is not None:
        runner.cancel(running.job_id)
    return Response(status_code=204)
