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
from viewloc_core.detection import Detection
from viewloc_core.errors import InvalidInputError
from viewloc_core.features import ImageFeatures, extract_features, orientation_bin, to_grey_float
from viewloc_core.model import ObjectModel
from viewloc_core.pose import Pose
from viewloc_core.pose_from_match import pose_from_similarity
from viewloc_core.refine import EdgePyramid, prepare_edges, refine_pose

#: Images larger than this (longest side, px) are searched on a pyramid level.
MAX_SEARCH_SIDE_PX = 700


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


def _best_training_view(
    model: ObjectModel, match: Match2D, feats: ImageFeatures, image: NDArray[np.generic],
    radius_px: float,
) -> tuple[int, NDArray[np.float64], float]:
    """Member training view of the matched model view that fits the image best.

    Returns the training view index, the similarity training-view frame ->
    image (re-fitted on that view's own edge samples, at training scale) and
    its coverage.
    """
    tr = model.training
    members = np.flatnonzero(tr.model_view == match.model_view)
    best = (-1.0, int(members[0]), match.sim)
    for t in members:
        sim_t = sim2.compose(match.sim, tr.sim_to_model[t])
        pts = tr.edge_xy[t].astype(np.float64)
        cov = coverage(feats, sim_t, pts, orientation_bin(tr.edge_theta[t]))
        if cov > best[0]:
            best = (cov, int(t), sim_t)
    _, t_best, sim_best = best
    pts = tr.edge_xy[t_best].astype(np.float64)
    theta = tr.edge_theta[t_best].astype(np.float64)
    refit, crop_feats, crop_from_image = refine_at_model_scale(
        image, sim_best, pts, theta, radius_px
    )
    cov = coverage(crop_feats, sim2.compose(crop_from_image, refit), pts, orientation_bin(theta))
    return t_best, refit, cov


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
    detections: list[Detection] = []
    edges: EdgePyramid | None = None
    for match in matches:
        t_view, sim_level, cov = _best_training_view(
            model, match, feats, level, index.view_radius_px
        )
        sim_full = sim_level.copy()
        if factor < 1.0:
            sim_full[:2] = (sim_level[:2] + 0.5) / factor - 0.5
            sim_full[3] = sim_level[3] / factor
        similarity = sim2.to_similarity2d(sim_full)
        R_view = model.training.R_m2c[t_view]
        pose_centred = pose_from_similarity(
            similarity, R_view, model.d0_mm, model.f_train_px, camera
        )
        refined = False
        pose_std = None
        score = float(cov)
        contour = _contour_model(model) if options.refine else None
        if contour is not None:
            if edges is None:
                edges = prepare_edges(arr)
            result = refine_pose(edges, camera, pose_centred, contour)
            moved = np.linalg.norm(result.pose.t_m2c - pose_centred.t_m2c)
            # Accept only a fit that converged on most of the contour and did
            # not wander off (a wrong 2D match cannot be rescued here).
            fits = result.converged or result.mean_residual_px < 1.0
            if (fits and result.inlier_fraction >= 0.6
                    and moved < 0.25 * model.diameter_mm + 0.05 * pose_centred.t_m2c[2]):
                pose_centred = result.pose
                refined = True
                pose_std = result.pose_std
            score = 0.5 * (float(cov) + float(result.inlier_fraction))
        # The model was learned with the bounding-box centre as origin.
        pose = Pose(
            pose_centred.R_m2c,
            pose_centred.t_m2c - pose_centred.R_m2c @ model.origin_offset_mm,
        )
        if score < min_score:
            continue
        detections.append(
            Detection(
                score=score,
                log_probability=float(match.log_probability),
                model_view=int(match.model_view),
                azimuth_deg=float(model.training.azimuth_deg[t_view]),
                polar_deg=float(model.training.polar_deg[t_view]),
                similarity=similarity,
                pose=pose,
                refined=refined,
                pose_std=pose_std,
            )
        )
    detections.sort(key=lambda d: -d.score)
    detections = detections[: options.max_detections]
    timing["pose"] = (time.perf_counter() - t3) * 1e3
    timing["total"] = (time.perf_counter() - t0) * 1e3
    return LocalizationResult(detections, timing)
