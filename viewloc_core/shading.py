"""Shading agreement: does the part's surface explain the intensities inside its outline?

A smooth part's outline says little about which side of it faces the camera:
an egg-shaped part seen from the front and from the back has the same
outline, mirrored, and an outline that is nearly mirror-symmetric fits both
ways (hard bench set, free-form part: the contour refinement confirmed whole
outlines of poses 90-180° wrong). The intensities inside the outline tell
them apart. Under distant lighting, the irradiance of a convex Lambertian
surface is a smooth function of its normal that the first nine spherical
harmonics of the normal capture to within a few % whatever the lights
(Basri and Jacobs, "Lambertian reflectance and linear subspaces", PAMI
2003; Ramamoorthi and Hanrahan 2001). So for a pose hypothesis: place
surface samples of the mesh, keep those the camera sees, read the image
under them, and fit intensity = SH(normal) · c by robust least squares. The
share of the intensity variance the fit explains (R²) is high where the
hypothesis's normals are the part's and low where they are not; it needs no
model of the lights, and an affine change of brightness leaves it unchanged.

Flat-faced parts shade as a few constant patches, which wrong poses explain
about as well; the agreement is then uninformative, not misleading. Texture
and specular highlights lower it for every hypothesis alike (the fit is
robust, so a highlight costs little).

A part whose mesh has colours of its own (vertex colours, a texture) is not
one colour: each sample also carries the brightness of the part's own
colour there (its albedo), and the fit is albedo x SH(normal) plus an
offset. The pattern then tells the sides apart where the outline cannot:
LM-O ape, photos where the localizer had the right place but a wrong turn
(13 of 24, mostly front for back): the fit refined from the truth explained
more than the chosen one in 12 of the 13 with the albedo, in 6 without.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np
import trimesh
from numpy.typing import NDArray

from viewloc_core import shading_kernels
from viewloc_core.camera import Camera
from viewloc_core.pose import Pose

F64 = NDArray[np.float64]

#: Mesh normals across edges sharper than this are not averaged (a crease
#: shades as two faces, a tessellated curve as one smooth surface).
CREASE_DEG = 30.0

#: Samples seen at a grazing angle (cosine between normal and viewing ray
#: below this) are dropped: at the outline the image blurs part and
#: background together, and a pose error of a pixel moves them off the part.
MIN_FACING_COS = 0.3

#: Fewest visible samples for a fit of the 9 coefficients.
MIN_VISIBLE = 40

#: Reweighting passes of the robust fit.
_IRLS_PASSES = 4

#: Rec. 601 luminance weights of R, G, B.
_LUMINANCE = np.array([0.299, 0.587, 0.114])

#: A part whose own colours span less brightness than this (albedo 0..1)
#: is of one colour: its samples carry no albedo.
MIN_ALBEDO_SPREAD = 0.05

#: What the fit's kernel is given for a part of one colour: no albedo.
_NO_ALBEDO = np.empty(0)


@dataclass(frozen=True, slots=True, eq=False)
class SurfaceSamples:
    """Points spread evenly over a part's surface, with their normals.

    Attributes
    ----------
    points_mm : (N, 3) float64
        Object frame, mm.
    normals : (N, 3) float64
        Unit outward normals, object frame (smooth across edges flatter than
        :data:`CREASE_DEG`).
    spacing_mm : float
        Typical distance between neighbouring samples, mm.
    extent_mm : float
        Longest side of the samples' bounding box, mm.
    albedo : (N,) float64 or None
        Brightness (Rec. 601 luminance, 0..1, sRGB) of the part's own colour
        at each sample; None for a part of one colour (a mesh without
        colours).
    """

    points_mm: F64
    normals: F64
    spacing_mm: float
    extent_mm: float
    albedo: F64 | None = None


class VisibleSamples(NamedTuple):
    """The surface samples the camera sees at a pose (:func:`visible_samples`).

    Attributes
    ----------
    uv : (M, 2) float64
        Pixel positions, inside the image.
    normals_cam : (M, 3) float64
        Unit normals, camera frame.
    sample_index : (M,) int64
        Their indices among the :class:`SurfaceSamples`, increasing.
    """

    uv: F64
    normals_cam: F64
    sample_index: NDArray[np.int64]


def surface_samples(vertices_mm: NDArray[np.floating], faces: NDArray[np.integer],
                    count: int = 2000, seed: int = 0,
                    vertex_colours: NDArray[np.integer] | None = None) -> SurfaceSamples:
    """Spread ``count`` samples over a triangle mesh's surface, area-weighted.

    Parameters
    ----------
    vertices_mm : (V, 3) array
        Mesh vertices in the frame poses refer to, mm.
    faces : (F, 3) int array
    count : int
        Number of samples.
    seed : int
        Sampling is deterministic for a given seed.
    vertex_colours : (V, 3) uint8 array, optional
        sRGB colour of each vertex; the samples' albedo is their luminance,
        interpolated across each face (none when it spans less than
        :data:`MIN_ALBEDO_SPREAD`).

    Returns
    -------
    SurfaceSamples
    """
    mesh = trimesh.Trimesh(np.asarray(vertices_mm, np.float64), np.asarray(faces, np.int64),
                           process=False)
    smooth = trimesh.graph.smooth_shade(mesh, angle=math.radians(CREASE_DEG))
    points, face_index = trimesh.sample.sample_surface(smooth, count, seed=seed)
    corners = smooth.triangles[face_index]
    bary = trimesh.triangles.points_to_barycentric(corners, points)
    normals = np.einsum("nk,nkj->nj", bary, smooth.vertex_normals[smooth.faces[face_index]])
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    # Interpolated normals of a sliver can cancel; fall back to the face's own.
    flat = length[:, 0] < 1e-6
    normals = np.where(flat[:, None], smooth.face_normals[face_index], normals
                       / np.maximum(length, 1e-12))
    albedo = None
    if vertex_colours is not None:
        # smooth_shade keeps the faces in their order (it splits vertices
        # only), so face_index names the same face of the input.
        luminance = np.asarray(vertex_colours, np.float64)[:, :3] @ _LUMINANCE / 255.0
        albedo = np.einsum("nk,nk->n", bary, luminance[np.asarray(faces)[face_index]])
        if float(np.ptp(albedo)) < MIN_ALBEDO_SPREAD:
            # One colour: the plain fit (its offset column would repeat the
            # albedo-scaled constant one).
            albedo = None
    area = float(mesh.area)
    return SurfaceSamples(
        points_mm=np.asarray(points, np.float64),
        normals=np.asarray(normals, np.float64),
        spacing_mm=math.sqrt(area / max(count, 1)),
        extent_mm=float(np.ptp(points, axis=0).max()) if count else 0.0,
        albedo=albedo,
    )


def points_mask(uv: NDArray[np.floating], x0: int, y0: int,
                shape: tuple[int, int]) -> NDArray[np.uint8]:
    """A (h, w) uint8 box at pixel ``(x0, y0)`` with 1 at the pixel of each of
    the (N, 2) image points ``uv`` that falls inside it, 0 elsewhere."""
    return shading_kernels.points_mask(np.ascontiguousarray(uv, np.float64).reshape(-1, 2),
                                       int(x0), int(y0), int(shape[0]), int(shape[1]))


def silhouette_mask(uv: NDArray[np.floating], x0: int, y0: int, shape: tuple[int, int],
                    dot_px: int) -> NDArray[np.uint8]:
    """The silhouette the projected surface samples ``uv`` (N, 2) make in the
    box of :func:`points_mask`: each a disc of radius ``dot_px``, their
    spacing in the image, so that neighbours join (uint8, 1 inside)."""
    return np.asarray(cv2.dilate(points_mask(uv, x0, y0, shape), cv2.getStructuringElement(
        cv2.MORPH_ELLIPSE, (2 * dot_px + 1, 2 * dot_px + 1))), np.uint8)


def intensity_at(image: NDArray[np.generic], uv: NDArray[np.floating]) -> F64:
    """Brightness of the image at sub-pixel positions (bilinear), (M,) float64.

    Parameters
    ----------
    image : (H, W) or (H, W, 3|4) array, uint8, uint16 or float (RGB when colour)
        Read where the samples fall only: converting a whole 640x480 image
        to grey takes longer than all the fits of one location.
    uv : (M, 2) array
        Pixel positions inside the image.

    Returns
    -------
    (M,) float64
        Luminance (Rec. 601 weights) of colour images, the value of grey ones,
        in the input's own unit (the agreement is invariant to its scale and
        offset); an alpha channel is ignored.
    """
    arr = np.asarray(image)
    if arr.dtype not in (np.uint8, np.uint16, np.float32):
        arr = arr.astype(np.float32)
    uv32 = np.asarray(uv, np.float32)
    values = cv2.remap(arr, uv32[:, 0][None], uv32[:, 1][None], cv2.INTER_LINEAR)[0]
    values = np.asarray(values, np.float64)
    if values.ndim == 2:
        values = values[:, :3] @ _LUMINANCE
    return np.nan_to_num(values)


def visible_samples(samples: SurfaceSamples, camera: Camera, pose: Pose) -> VisibleSamples:
    """The samples the camera sees at ``pose``: in front of it, facing it
    (cosine with the ray above :data:`MIN_FACING_COS`), inside the image
    and, on a concave part, not behind a nearer surface
    (:func:`viewloc_core.shading_kernels.visible_samples`)."""
    return VisibleSamples(*shading_kernels.visible_samples(
        samples.points_mm, samples.normals, np.ascontiguousarray(pose.R_m2c, np.float64),
        np.ascontiguousarray(pose.t_m2c, np.float64),
        np.array([camera.fx, camera.fy, camera.cx, camera.cy]), camera.dist8,
        camera.has_distortion, camera.width, camera.height, samples.spacing_mm, MIN_FACING_COS))


def shading_agreement(image: NDArray[np.generic], camera: Camera, pose: Pose,
                      samples: SurfaceSamples,
                      visible: VisibleSamples | None = None) -> float | None:
    """How well the surface at ``pose`` explains the image's intensities.

    Parameters
    ----------
    image : (H, W) or (H, W, 3|4) array
        The scene, as :func:`intensity_at` reads it.
    camera : Camera
        Scene camera (its size matches the image).
    pose : Pose
        Object -> camera, the frame of ``samples``.
    samples : SurfaceSamples
    visible : VisibleSamples or None
        :func:`visible_samples` of ``samples`` at ``pose`` when the caller
        has them already (a rival fit is ranked by its shading and by its
        colours under the same samples); computed here when None.

    Returns
    -------
    float in [0, 1] or None
        Share of the intensity variance of the visible samples that a
        robust fit on their normals' spherical harmonics (times their
        albedo, when the samples have one) explains; None when
        fewer than :data:`MIN_VISIBLE` samples are seen or the part looks
        uniform (nothing to explain).
    """
    uv, normals, index = visible_samples(samples, camera, pose) if visible is None else visible
    if len(uv) < MIN_VISIBLE:
        return None
    albedo = _NO_ALBEDO if samples.albedo is None else samples.albedo[index]
    explained = shading_kernels.explained_variance(intensity_at(image, uv), normals, albedo,
                                                   _IRLS_PASSES)
    return None if math.isnan(explained) else explained
