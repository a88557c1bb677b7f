"""Operator overlays: detections drawn on the scene image.

The projected model contour is the outline of the union of the mesh's
projected triangles (filled with ``cv2.fillPoly``, traced with
``cv2.findContours``): the exact silhouette of the mesh at the detected pose,
with no rendering context needed in the request thread. Axes: x red, y green,
z blue, each half the object diameter long, from the object origin.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from viewloc_core.camera import Camera
from viewloc_core.detection import Detection
from viewloc_core.errors import InvalidImageError

_CONTOUR_RGB = (255, 220, 0)
_AXES_RGB = ((255, 40, 40), (40, 220, 40), (60, 120, 255))
_MAX_FACES_DRAWN = 200_000


def to_rgb8(image: NDArray[Any]) -> NDArray[np.uint8]:
    """(H, W, 3) uint8 RGB copy of an (H, W) / (H, W, 3) uint8 or uint16 image.

    16-bit images are scaled by their 99.5th percentile so dim scenes stay visible.
    """
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
        raise InvalidImageError(f"expected (H, W) or (H, W, 3), got {img.shape}", "image")
    if img.dtype == np.uint16:
        top = max(1.0, float(np.percentile(img, 99.5)))
        img = np.clip(img.astype(np.float32) * (255.0 / top), 0, 255).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise InvalidImageError(f"expected uint8 or uint16, got {img.dtype}", "image")
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    return np.ascontiguousarray(img.copy())


def silhouette_mask(
    camera: Camera,
    R_m2c: NDArray[np.floating],
    t_m2c: NDArray[np.floating],
    vertices_mm: NDArray[np.floating],
    faces: NDArray[np.integer],
) -> NDArray[np.uint8]:
    """(H, W) uint8 mask (255 = object) of the mesh projected at a pose.

    Triangles with a vertex at or behind the camera plane are skipped.
    """
    mask = np.zeros((camera.height, camera.width), np.uint8)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)[:_MAX_FACES_DRAWN]
    pts_cam = np.asarray(vertices_mm, np.float64) @ np.asarray(R_m2c, np.float64).T + t_m2c
    z_ok = pts_cam[:, 2] > 1e-6
    keep = z_ok[faces].all(axis=1)
    if not keep.any():
        return mask
    uv = np.zeros((len(pts_cam), 2))
    uv[z_ok] = camera.project(pts_cam[z_ok])
    # Sub-pixel precision: shift=4 takes 1/16-pixel coordinates.
    tri = np.round(uv[faces[keep]] * 16).astype(np.int64)
    bound = 16 * 4 * max(camera.width, camera.height)
    tri = np.clip(tri, -bound, bound).astype(np.int32)
    # One triangle at a time: fillPoly given them all at once fills by the
    # even-odd rule, so where a front and a back face overlap (everywhere
    # on a closed mesh) the pixels were left out.
    for triangle in tri:
        cv2.fillConvexPoly(mask, triangle, 255, lineType=cv2.LINE_8, shift=4)
    return mask


def draw_detections(
    image: NDArray[Any],
    detections: Sequence[Detection],
    camera: Camera,
    mesh_vertices_mm: NDArray[np.floating] | None = None,
    mesh_faces: NDArray[np.integer] | None = None,
) -> NDArray[np.uint8]:
    """Draw each detection's projected model contour, axes and score.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8 or uint16
        The scene (RGB when colour).
    detections : sequence of Detection
        Poses are object -> camera, mm.
    camera : Camera
        Intrinsics of the scene image (its size should match the image).
    mesh_vertices_mm : (N, 3) array, optional
        Model mesh in the object frame, mm; without it only axes are drawn.
    mesh_faces : (F, 3) int array, optional

    Returns
    -------
    (H, W, 3) uint8
        A new RGB image.
    """
    canvas = to_rgb8(image)
    h, w = canvas.shape[:2]
    cam = camera if (camera.width, camera.height) == (w, h) else Camera(
        camera.fx, camera.fy, camera.cx, camera.cy, w, h, camera.dist)
    thickness = max(1, round(max(h, w) / 400))
    for det in detections:
        R, t = det.pose.R_m2c, det.pose.t_m2c
        if t[2] <= 1e-6:
            continue
        if mesh_vertices_mm is not None and mesh_faces is not None and len(mesh_faces):
            mask = silhouette_mask(cam, R, t, mesh_vertices_mm, mesh_faces)
            contours, _ = cv2.findContours(mask, cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
            cv2.drawContours(canvas, contours, -1, _CONTOUR_RGB, thickness, cv2.LINE_AA)
            extent = float(np.linalg.norm(np.ptp(np.asarray(mesh_vertices_mm), axis=0)))
        else:
            extent = 0.1 * float(t[2])
        axes_obj = np.vstack([np.zeros(3), 0.5 * extent * np.eye(3)])
        pts = axes_obj @ R.T + t
        if np.all(pts[:, 2] > 1e-6):
            uv = cam.project(pts)
            if np.all(np.isfinite(uv)) and np.all(np.abs(uv) < 1e6):
                o = tuple(int(round(v)) for v in uv[0])
                for k in range(3):
                    p = tuple(int(round(v)) for v in uv[k + 1])
                    cv2.arrowedLine(canvas, o, p, _AXES_RGB[k], thickness + 1, cv2.LINE_AA,
                                    tipLength=0.08)
                cv2.putText(canvas, f"{det.score:.2f}", (o[0] + 6, o[1] - 6),
                            cv2.FONT_HERSHEY_SIMPLEX, 0.4 + 0.4 * thickness, _CONTOUR_RGB,
                            thickness, cv2.LINE_AA)
    return canvas
