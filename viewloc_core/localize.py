"""Localize a learned object in a scene image: 2D alignment, 6D pose, refinement.

DESIGN.md §2 steps 6-8: features of the scene (on a pyramid level small enough
to stay fast), probabilistic alignment of the model views, the best-fitting
training view of each matched model view, the 6D pose from the similarity
(paper §4.2) and, when the model has a contour model, the refinement against
image edges (§5.2's scene-based tracking).
"""

from __future__ import annotations

import time
import weakref
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from viewloc_core import similarity as sim2
from viewloc_core.align import (
    AlignConfig,
    Match2D,
    ModelIndex,
    align,
    build_index,
    coverage,
    refine_at_model_scale,
)
from viewloc_core.camera import Camera
from viewloc_core.contour_model import ContourModel
from viewloc_core.detection import Detection, Similarity2D
from viewloc_core.errors import InvalidInputError
from viewloc_core.features import ImageFeatures, extract_features, orientation_bin, to_grey_float
from viewloc_core.model import ObjectModel
from viewloc_core.pose import Pose
from viewloc_core.pose_from_match import pose_from_similarity
from viewloc_core.refine import (
    EdgePyramid,
    RefinementResult,
    RefineOptions,
    prepare_edges,
    refine_pose,
)
from viewloc_core.symmetry import canonical_pose

#: Images larger than this (longest side, px) are searched on a pyramid level.
MAX_SEARCH_SIDE_PX = 700

#: Refinement settings of the quick 6D check that chooses among alternative
#: views at one location: the coarse level only, a few iterations.
QUICK_REFINE = RefineOptions(iterations=(0, 3), shift_search_px=12.0, measure_chance=False)

#: The final refinement; its chance rate is not used here, so not measured.
FINAL_REFINE = RefineOptions(measure_chance=False)

#: Inlier fraction by which an alternative view's quick check must beat the
#: 2D-ranked view to replace it.
ALTERNATIVE_MARGIN = 0.1

#: Locations beyond ``max_detections`` that get the final fit, in case the
#: quick check ranked a true one just below a false one.
SPARE_LOCATIONS = 1

#: Training views closer than this to the chosen one are tried as starts of
#: the final refinement (about one view spacing of level 2).
NEIGHBOUR_VIEW_DEG = 20.0

#: A quick check that confirms this share of the contour needs no other start
#: (true poses: median 0.90 on the paper set).
GOOD_FIT_FRACTION = 0.75


@dataclass(frozen=True, slots=True)
class LocalizeOptions:
    """Per-request options (API: ``options``).

    Attributes
    ----------
    max_detections : int
        Most detections returned (1..100).
    min_score : float or None
        Minimum score in [0, 1]; None uses the model's default.
    refine : bool
        Refine poses against image edges when the model has a mesh.
    """

    max_detections: int = 1
    min_score: float | None = None
    refine: bool = True

    def __post_init__(self) -> None:
        if not 1 <= self.max_detections <= 100:
            raise InvalidInputError("must be in 1..100", "options.max_detections")
        if self.min_score is not None and not 0.0 <= self.min_score <= 1.0:
            raise InvalidInputError("must be in [0, 1]", "options.min_score")


@dataclass(frozen=True, slots=True)
class LocalizationResult:
    """Detections, best first, and where the time went (ms)."""

    detections: list[Detection]
    timing_ms: dict[str, float] = field(default_factory=dict)


_INDEX_CACHE: weakref.WeakKeyDictionary[ObjectModel, ModelIndex] = weakref.WeakKeyDictionary()


def model_index(model: ObjectModel) -> ModelIndex:
    """The alignment index of a model, built once and cached while the model lives."""
    index = _INDEX_CACHE.get(model)
    if index is None:
        index = build_index(model)
        _INDEX_CACHE[model] = index
    return index


_CONTOUR_CACHE: weakref.WeakKeyDictionary[ObjectModel, ContourModel] = (
    weakref.WeakKeyDictionary()
)


def _contour_model(model: ObjectModel) -> ContourModel | None:
    """The model's contour model for refinement (None without a mesh), cached."""
    if model.contour is None:
        return None
    contour = _CONTOUR_CACHE.get(model)
    if contour is None:
        contour = ContourModel.from_arrays(model.contour)
        _CONTOUR_CACHE[model] = contour
    return contour


def _member_view(
    model: ObjectModel, match: Match2D, feats: ImageFeatures
) -> tuple[int, NDArray[np.float64]]:
    """Member training view of the matched model view that fits the image best
    (by coverage): its index and the similarity training-view frame -> image."""
    tr = model.training
    members = np.flatnonzero(tr.model_view == match.model_view)
    best = (-1.0, int(members[0]), match.sim)
    for t in members:
        sim_t = sim2.compose(match.sim, tr.sim_to_model[t])
        pts = tr.edge_xy[t].astype(np.float64)
        cov = coverage(feats, sim_t, pts, orientation_bin(tr.edge_theta[t]))
        if cov > best[0]:
            best = (cov, int(t), sim_t)
    return best[1], best[2]


def _refit_at_model_scale(
    model: ObjectModel, t_view: int, sim: NDArray[np.float64], image: NDArray[np.generic],
    radius_px: float,
) -> tuple[NDArray[np.float64], float]:
    """Final 2D fit of a training view on a crop resampled to training scale.

    Returns the re-fitted similarity training-view frame -> image and its coverage.
    """
    tr = model.training
    pts = tr.edge_xy[t_view].astype(np.float64)
    theta = tr.edge_theta[t_view].astype(np.float64)
    refit, crop_feats, crop_from_image = refine_at_model_scale(image, sim, pts, theta, radius_px)
    cov = coverage(crop_feats, sim2.compose(crop_from_image, refit), pts, orientation_bin(theta))
    return refit, cov


def _to_full_resolution(sim_level: NDArray[np.float64], factor: float) -> Similarity2D:
    """A similarity found on a pyramid level scaled by ``factor``, in full-resolution pixels."""
    sim_full = sim_level.copy()
    if factor < 1.0:
        sim_full[:2] = (sim_level[:2] + 0.5) / factor - 0.5
        sim_full[3] = sim_level[3] / factor
    return sim2.to_similarity2d(sim_full)


def _pose_centred(
    model: ObjectModel, t_view: int, similarity: Similarity2D, camera: Camera
) -> Pose:
    """6D pose of the model's centred frame from a training view's similarity (§4.2)."""
    return pose_from_similarity(
        similarity, model.training.R_m2c[t_view], model.d0_mm, model.f_train_px, camera
    )


@dataclass(frozen=True, slots=True, eq=False)
class _Located:
    """The chosen view at one image location, before the final fit."""

    match: Match2D
    t_view: int
    sim_level: NDArray[np.float64]
    quick: RefinementResult | None


def _quick_rank(result: RefinementResult | None) -> float:
    """Ranking key of a quick 6D check: share of the contour that found its edge."""
    return -1.0 if result is None else float(result.inlier_fraction)


_DIRECTIONS_CACHE: weakref.WeakKeyDictionary[ObjectModel, NDArray[np.float64]] = (
    weakref.WeakKeyDictionary()
)


def _neighbour_views(model: ObjectModel, t_view: int) -> NDArray[np.int64]:
    """Training views within ``NEIGHBOUR_VIEW_DEG`` of ``t_view`` (itself excluded)."""
    dirs = _DIRECTIONS_CACHE.get(model)
    if dirs is None:
        # Row 2 of R_m2c is the camera's viewing axis in object coordinates.
        dirs = np.asarray(model.training.R_m2c[:, 2, :], dtype=np.float64)
        _DIRECTIONS_CACHE[model] = dirs
    cos = dirs @ dirs[t_view]
    near = np.flatnonzero(cos > np.cos(np.radians(NEIGHBOUR_VIEW_DEG)))
    return near[near != t_view]


def _final_detection(
    model: ObjectModel, loc: _Located, level: NDArray[np.generic], factor: float,
    camera: Camera, edges: EdgePyramid | None, contour: ContourModel | None,
    view_radius_px: float,
) -> Detection:
    """2D fit at training scale, 6D pose and, with a contour model, its refinement."""
    sim_level, cov = _refit_at_model_scale(model, loc.t_view, loc.sim_level, level,
                                           view_radius_px)
    similarity = _to_full_resolution(sim_level, factor)
    pose_centred = _pose_centred(model, loc.t_view, similarity, camera)
    refined = False
    pose_std = None
    score = float(cov)
    if contour is not None and edges is not None:
        # The training views around the chosen one, under the same
        # similarity (all training views share one camera geometry), widen
        # the refinement's capture range where appearance changes fast with
        # the view (a barbell seen nearly end-on).
        starts = [loc.quick] if loc.quick is not None else []
        if _quick_rank(loc.quick) < GOOD_FIT_FRACTION:
            starts += [
                refine_pose(edges, camera, _pose_centred(model, t, similarity, camera), contour,
                            QUICK_REFINE)
                for t in _neighbour_views(model, loc.t_view)
            ]
        best_start = max(starts, key=_quick_rank) if starts else None
        start = best_start.pose if best_start is not None else pose_centred
        result = refine_pose(edges, camera, start, contour, FINAL_REFINE)
        if best_start is not None and _quick_rank(best_start) > _quick_rank(result):
            result = best_start
        moved = np.linalg.norm(result.pose.t_m2c - pose_centred.t_m2c)
        # Accept only a fit that matched most of the contour and did not
        # wander off (a wrong 2D match cannot be rescued here).
        fits = result.converged or result.mean_residual_px < 1.0
        if (fits and result.inlier_fraction >= 0.6
                and moved < 0.25 * model.diameter_mm + 0.05 * pose_centred.t_m2c[2]):
            pose_centred = result.pose
            refined = True
            pose_std = result.pose_std
            # The reference point is where the refined pose puts the origin.
            ref_xy = camera.project(pose_centred.t_m2c[None])[0]
            similarity = Similarity2D(float(ref_xy[0]), float(ref_xy[1]),
                                      similarity.angle_deg, similarity.scale)
        score = float(result.inlier_fraction)
    # The model was learned with the bounding-box centre as origin.
    pose = Pose(pose_centred.R_m2c,
                pose_centred.t_m2c - pose_centred.R_m2c @ model.origin_offset_mm)
    if len(model.symmetries) > 1 or model.symmetry_axis is not None:
        # Symmetric equivalents look the same: report the one whose axes are
        # closest to the camera's, so the answer does not jump between them.
        pose = canonical_pose(pose, model.symmetry_group())
    return Detection(
        score=score,
        log_probability=float(loc.match.log_probability),
        model_view=int(model.training.model_view[loc.t_view]),
        azimuth_deg=float(model.training.azimuth_deg[loc.t_view]),
        polar_deg=float(model.training.polar_deg[loc.t_view]),
        similarity=similarity,
        pose=pose,
        refined=refined,
        pose_std=pose_std,
    )


def localize(
    model: ObjectModel,
    image: NDArray[np.generic],
    camera: Camera,
    options: LocalizeOptions = LocalizeOptions(),
) -> LocalizationResult:
    """Find an object in an image and return its 6D poses.

    Parameters
    ----------
    model : ObjectModel
        A learned model.
    image : (H, W) or (H, W, 3) array, uint8 or uint16
        The scene (RGB when colour).
    camera : Camera
        Intrinsics of the scene camera; its width and height must match the image.
    options : LocalizeOptions

    Returns
    -------
    LocalizationResult
        Detections best first; empty when nothing scores above ``min_score``.
    """
    t0 = time.perf_counter()
    arr = np.asarray(image)
    if arr.ndim not in (2, 3) or arr.shape[0] != camera.height or arr.shape[1] != camera.width:
        raise InvalidInputError(
            f"image is {arr.shape[1] if arr.ndim >= 2 else '?'}x{arr.shape[0]}, camera says "
            f"{camera.width}x{camera.height}", "camera",
        )
    to_grey_float(arr[:16, :16])  # dtype and channel checks, cheap
    index = model_index(model)
    timing: dict[str, float] = {}

    factor = min(1.0, MAX_SEARCH_SIDE_PX / max(arr.shape[0], arr.shape[1]))
    level = arr
    if factor < 1.0:
        level = cv2.resize(arr, (round(arr.shape[1] * factor), round(arr.shape[0] * factor)),
                           interpolation=cv2.INTER_AREA)
    t1 = time.perf_counter()
    feats = extract_features(level)
    t2 = time.perf_counter()
    timing["features"] = (t2 - t1) * 1e3
    config = AlignConfig()
    matches = align(model, index, feats, config, max_matches=2 * options.max_detections + 1)
    t3 = time.perf_counter()
    timing["align"] = (t3 - t2) * 1e3

    min_score = model.default_min_score if options.min_score is None else options.min_score
    contour = _contour_model(model) if options.refine else None
    edges = prepare_edges(arr) if contour is not None and matches else None
    # Pass 1: per image location, the view that explains the image best.
    located: list[_Located] = []
    for match in matches:
        candidates = [_member_view(model, m, feats) for m in (match, *match.alternatives)]
        if contour is None or edges is None:
            located.append(_Located(match, *candidates[0], None))
            continue
        # A short 6D refinement of each alternative view tells which one
        # explains the image edges; the 2D similarity cannot.
        checked = [
            (t, sl, refine_pose(
                edges, camera, _pose_centred(model, t, _to_full_resolution(sl, factor), camera),
                contour, QUICK_REFINE))
            for t, sl in candidates
        ]
        # The 2D ranking (g and coverage) chose the first; another view
        # replaces it only when its contour is clearly better confirmed (an
        # outline and its mirror image can both fit about as well).
        best = checked[0]
        for c in checked[1:]:
            if _quick_rank(c[2]) > _quick_rank(best[2]) + ALTERNATIVE_MARGIN:
                best = c
        located.append(_Located(match, *best))
    if edges is not None:
        located.sort(key=lambda c: -_quick_rank(c.quick))
    # Pass 2: final fit of the best locations only.
    detections: list[Detection] = []
    for loc in located[: options.max_detections + SPARE_LOCATIONS]:
        det = _final_detection(model, loc, level, factor, camera, edges, contour,
                               index.view_radius_px)
        if det.score >= min_score:
            detections.append(det)
    detections.sort(key=lambda d: -d.score)
    detections = detections[: options.max_detections]
    timing["pose"] = (time.perf_counter() - t3) * 1e3
    timing["total"] = (time.perf_counter() - t0) * 1e3
    return LocalizationResult(detections, timing)
