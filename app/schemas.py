"""Pydantic models of the HTTP contract (API.md). Pydantic lives only in ``app``."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field

from viewloc_core.mesh import MAX_DIAMETER_MM, MIN_DIAMETER_MM

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]


class _In(BaseModel):
    """Inputs: unknown keys are errors, so a typo never silently means a default."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


# -- problems --------------------------------------------------------------
class FieldError(BaseModel):
    """One field-level validation problem."""

    field: str = Field(description="Dotted name of the input, e.g. 'camera.fx'.")
    message: str


class Problem(BaseModel):
    """RFC 9457 problem details (media type application/problem+json)."""

    type: str
    title: str
    status: int
    detail: str
    errors: list[FieldError] | None = Field(
        default=None, description="Field-level problems, for validation errors."
    )


# -- inputs given as JSON text in multipart forms ---------------------------
class CameraIn(_In):
    """Pinhole intrinsics in pixels (OpenCV convention); the size comes from the image."""

    fx: FiniteFloat = Field(gt=0, description="Focal length x, pixels.")
    fy: FiniteFloat = Field(gt=0, description="Focal length y, pixels.")
    cx: FiniteFloat = Field(description="Principal point x, pixels.")
    cy: FiniteFloat = Field(description="Principal point y, pixels.")
    dist: list[FiniteFloat] | None = Field(
        default=None, description="OpenCV distortion [k1, k2, p1, p2(, k3(, k4, k5, k6))]."
    )
    width: int | None = Field(default=None, gt=0, description="Optional; must match the image.")
    height: int | None = Field(default=None, gt=0, description="Optional; must match the image.")


Transform16 = Annotated[list[FiniteFloat], Field(min_length=16, max_length=16)]
Vector3 = Annotated[list[FiniteFloat], Field(min_length=3, max_length=3)]


class SymmetryAxisIn(_In):
    """A continuous rotational symmetry (BOP ``symmetries_continuous`` entry)."""

    axis: Vector3 = Field(description="Direction of the axis, object frame; non-zero.")
    offset: Vector3 = Field(default_factory=lambda: [0.0, 0.0, 0.0],
                            description="A point on the axis, in the spec's units.")


class SymmetriesIn(_In):
    """A declared symmetry group in BOP ``models_info`` form (object frame, spec's units)."""

    symmetries_discrete: list[Transform16] = Field(
        default_factory=list, max_length=240,
        description="Row-major 4x4 rigid transforms (last row 0 0 0 1, rotation orthonormal "
        "within 1e-3, det +1, translation in the spec's units); the group they generate "
        "is used, the identity always included.",
    )
    symmetries_continuous: list[SymmetryAxisIn] = Field(
        default_factory=list, max_length=1, description="At most one continuous axis.")


class MeshSpec(_In):
    """The ``spec`` form field of ``POST /v1/objects``."""

    name: str = Field(default="", max_length=200)
    units: Literal["mm", "cm", "m", "in"] = "mm"
    learning: dict[str, object] | None = Field(
        default=None, description="Optional tuning of the learning (LearningConfig fields)."
    )
    symmetries: SymmetriesIn | None = Field(
        default=None,
        description="The part's symmetries, replacing the detected ones (e.g. a near-symmetry "
        "the detector accepts that QA must tell apart: declare {} for none).",
    )


class ViewIn(_In):
    """Known viewing angles of one training image."""

    azimuth_deg: FiniteFloat = Field(
        ge=-36_000, le=36_000,
        description="Degrees; a turntable's count may run on (at most 100 turns).")
    polar_deg: FiniteFloat = Field(ge=0, le=180)
    distance_mm: FiniteFloat = Field(gt=0, le=1_000_000,
                                     description="Camera to object origin, mm (at most 1 km).")
    inplane_deg: FiniteFloat = Field(default=0.0, ge=-36_000, le=36_000)


class ImagesSpec(_In):
    """The ``spec`` form field of ``POST /v1/objects/from-images``."""

    name: str = Field(default="", max_length=200)
    camera: CameraIn
    object_diameter_mm: FiniteFloat = Field(
        ge=MIN_DIAMETER_MM, le=MAX_DIAMETER_MM,
        description="The part's largest extent, mm (0.1 mm to 100 m, as a mesh's).")
    views: list[ViewIn] = Field(min_length=1)
    learning: dict[str, object] | None = None
    symmetries: SymmetriesIn | None = Field(
        default=None, description="The part's symmetries (lengths in mm), in the frame the "
        "views' angles define; without it the model has none (there is no mesh to detect on).",
    )


class RegionIn(_In):
    """An image rectangle, pixels (OpenCV convention: the top-left pixel's centre is 0, 0)."""

    x: int = Field(ge=0, description="Left column.")
    y: int = Field(ge=0, description="Top row.")
    width: int = Field(gt=0)
    height: int = Field(gt=0)


class DepthRangeIn(_In):
    """A range of depths (camera z), mm; ``max`` must be greater than ``min``."""

    min: FiniteFloat = Field(gt=0)
    max: FiniteFloat = Field(gt=0)


class LocalizeOptionsIn(_In):
    """The ``options`` form field of localization."""

    max_detections: int = Field(default=1, ge=1, le=100)
    min_score: FiniteFloat | None = Field(default=None, ge=0, le=1)
    refine: bool = True
    roi: RegionIn | None = Field(
        default=None, description="Search only this region of the image (it must lie inside "
        "it): the part lies within it. Poses and image positions stay in the full image's "
        "frame.",
    )
    depth_mm: DepthRangeIn | None = Field(
        default=None, description="The depths (camera z, mm) the part's origin can have: "
        "sizes outside it are not searched, and no detection outside it is reported.",
    )
    max_rotation_std_deg: FiniteFloat | None = Field(
        default=None, gt=0, le=360,
        description="The most rotation uncertainty a refined detection may have: the largest "
        "standard deviation of its rotation over all axes (a continuous symmetry's turn set "
        "aside), degrees. A fit its contour does not pin down (edges along one side of its "
        "outline only) is not reported. Default 30.",
    )
    timeout_ms: FiniteFloat | None = Field(
        default=None, gt=0, le=3_600_000,
        description="Time budget of the localization, ms, counted once the image is decoded. "
        "A search that only looks further for the part (the finer image level, spare and "
        "further locations) is started only when it is expected to end within it; with "
        "several objects, those not yet searched when it is spent are left out and listed in "
        "'skipped'. A search begun finishes, so the answer can come after the budget when one "
        "took longer than expected. The answer's 'timed_out' says whether anything was left "
        "out. Default: no budget.",
    )


class MultiLocalizeOptionsIn(LocalizeOptionsIn):
    """Options of ``POST /v1/localize``: which objects (default all ready ones)."""

    object_ids: list[str] | None = Field(default=None, max_length=1000)


# -- outputs ---------------------------------------------------------------
class SymmetryAxisOut(BaseModel):
    """A continuous rotational symmetry, object frame, mm."""

    axis: list[float] = Field(min_length=3, max_length=3, description="Unit direction.")
    offset: list[float] = Field(min_length=3, max_length=3, description="A point on it, mm.")


class SymmetriesOut(BaseModel):
    """The model's symmetry group in BOP ``models_info`` form (identity left out), mm."""

    symmetries_discrete: list[list[float]] = Field(
        description="Row-major 4x4 transforms, translation in mm.")
    symmetries_continuous: list[SymmetryAxisOut]


class ObjectOut(BaseModel):
    """An object (API.md ``Object``)."""

    object_id: str
    name: str
    state: Literal["learning", "ready", "failed"]
    source: Literal["mesh", "images"]
    diameter_mm: float
    training_views: int
    model_views: int
    created_at: str = Field(description="RFC 3339 UTC.")
    job_id: str
    error: str | None = Field(default=None, description="Why the object is failed, if it is.")
    symmetries: SymmetriesOut | None = Field(
        default=None, description="Symmetry group of the learned model (declared in the spec "
        "or detected on the mesh); null until the object is ready.",
    )
    model_sha256: str | None = Field(
        default=None, description="SHA-256 (hex) of the learned model's arrays, as stored; "
        "null until the object is ready. Learning repeats bit for bit on one machine: the "
        "same upload (mesh or images, spec and learning options) learns the same model, "
        "so a station can log which model gave a pose and tell a relearned part from "
        "another.",
    )


class JobOut(BaseModel):
    """A background learning job (API.md ``Job``)."""

    job_id: str
    object_id: str
    state: Literal["queued", "running", "succeeded", "failed", "cancelled"]
    progress: float = Field(ge=0, le=1)
    stage: str
    error: str | None
    created_at: str
    started_at: str | None
    finished_at: str | None


class ObjectCreated(BaseModel):
    """Answer of the learning uploads."""

    object: ObjectOut
    job: JobOut


class ObjectList(BaseModel):
    """Answer of ``GET /v1/objects``."""

    objects: list[ObjectOut]


class ViewOut(BaseModel):
    """Viewing angles of the matched training view."""

    azimuth_deg: float
    polar_deg: float


class SimilarityOut(BaseModel):
    """The 2D match r = (x, y, α, s) of paper §4.2."""

    x: float
    y: float
    angle_deg: float
    scale: float


class PoseOut(BaseModel):
    """Object -> camera pose, mm; x_cam = R x_obj + t."""

    R: list[list[float]] = Field(min_length=3, max_length=3)
    t_mm: list[float] = Field(min_length=3, max_length=3)
    quaternion_wxyz: list[float] = Field(min_length=4, max_length=4)
    euler_xyz_deg: list[float] = Field(min_length=3, max_length=3)


class DetectionOut(BaseModel):
    """One localized instance."""

    score: float = Field(ge=0, le=1)
    log_probability: float
    model_view: int
    view: ViewOut
    similarity: SimilarityOut
    pose: PoseOut
    refined: bool
    pose_std: list[float] | None = Field(
        default=None,
        description="Std. dev. of the refined pose: rot x,y,z (deg), trans x,y,z (mm).",
    )
    object_id: str | None = Field(
        default=None, description="The object this detection is of."
    )


class ImageSize(BaseModel):
    """Size of the scene image in pixels."""

    width: int
    height: int


class LocalizationOut(BaseModel):
    """Answer of ``POST /v1/objects/{object_id}/localize``."""

    object_id: str
    image: ImageSize
    detections: list[DetectionOut]
    timing_ms: dict[str, float] = Field(description="Has 'decode' and 'total', ms.")
    timed_out: bool = Field(default=False, description="A search was left out for the time "
                            "budget (options.timeout_ms): it was not expected to end within it. "
                            "The detections are what was found without it.")
    overlay_png_base64: str | None = Field(default=None,
        description="With ?overlay=true: the scene as PNG (base64) with each detection's "
        "projected model contour and axes (x red, y green, z blue) drawn.",
    )


class SkippedObjectOut(BaseModel):
    """A ready object that ``POST /v1/localize`` listed but could not search."""

    object_id: str
    reason: Literal["corrupt", "not-ready", "deleted", "timed-out"] = Field(
        description="'corrupt': its stored model turned out unusable when loaded (the object "
        "is now failed); 'not-ready': it was no longer ready when its model was loaded; "
        "'deleted': it was deleted after it was listed; 'timed-out': the time budget "
        "(options.timeout_ms) was spent before its search began.",
    )
    detail: str = Field(description="What the store said, as a 409 or 404 would.")


class MultiLocalizationOut(BaseModel):
    """Answer of ``POST /v1/localize``."""

    object_ids: list[str] = Field(description="The objects that were searched.")
    skipped: list[SkippedObjectOut] = Field(
        default_factory=list,
        description="The objects that could not be searched, and why (the others were "
        "searched). Without options.object_ids: ready objects whose model could not be used, "
        "or left out by the time budget; with it, only those left out by the time budget "
        "(an object named there that cannot be searched answers 404 or 409).",
    )
    image: ImageSize
    detections: list[DetectionOut]
    timing_ms: dict[str, float]
    timed_out: bool = Field(default=False, description="A search was left out for the time "
                            "budget (options.timeout_ms): an object's (listed in 'skipped') "
                            "or a further search of one.")
    overlay_png_base64: str | None = None


class Health(BaseModel):
    """Answer of the health probes."""

    status: str
    checks: dict[str, bool] | None = None
