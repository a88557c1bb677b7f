"""Headless offscreen rendering of meshes in OpenCV conventions (pyrender).

Colour, depth and mask of one or several meshes at given poses, seen by a
pinhole :class:`~viewloc_core.camera.Camera`, lit by given lights. This is the
only module that knows OpenGL's frames; everything it returns uses the
project's conventions (DESIGN.md §3):

- poses are object -> camera, ``x_cam = R x_obj + t``, OpenCV camera frame
  (x right, y down, z forward), millimetres;
- images are row-major with row 0 at the top; the centre of the top-left pixel
  is (0, 0), so a point projects to ``camera.project(x_cam)`` exactly;
- ``depth_mm`` is the z coordinate in the camera frame (not the ray length),
  0 where nothing was hit, as in BOP's depth images.

Frames: the pyrender camera sits at the world origin with identity pose, so
the world *is* OpenGL's camera frame (x right, y up, z backward). An object
pose is moved there by ``F = diag(1, -1, -1)``, a rotation by 180° about x, so
nothing is mirrored. pyrender's ``IntrinsicsCamera`` puts pixel *edges* at
integer window coordinates, hence it gets ``cx + 0.5`` and ``cy + 0.5``; it
already flips the read-back rows so that row 0 is the top.

Platform: ``PYOPENGL_PLATFORM`` must be fixed before OpenGL is first imported.
An explicit value is respected. When it is unset, the first use of this module
(``prepare`` or ``Renderer``) probes EGL in a child process (about 0.3 s, once
per process) and sets ``egl`` if a context can be created there, ``osmesa``
(Mesa's software rasteriser, package ``libosmesa6``) otherwise. To force the
fallback, start the process with ``PYOPENGL_PLATFORM=osmesa``.

Shading: flat normals make a tessellated cylinder look faceted, which creates
edges that the real part does not have; smooth normals round off the sharp
creases of CAD parts, which are exactly the edges the features need. Normals
are therefore smoothed across edges whose dihedral angle is below
:data:`CREASE_ANGLE_DEG` and kept sharp across steeper ones. Back faces are
always culled; open meshes get a reversed copy of every triangle instead (see
:class:`PreparedMesh`), so their inside is drawn and lit in colour and depth.

Cost (Mesa llvmpipe, no GPU): a few ms fixed per render plus shading, which
grows with covered pixels and with triangle count; depth-only renders skip
the shading and are several times cheaper. Lighting is pyrender's
metallic-roughness model with 4x multisampling.
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
import subprocess
import sys
import threading
import weakref
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import trimesh
from numpy.typing import NDArray

from viewloc_core.camera import Camera
from viewloc_core.errors import InvalidInputError
from viewloc_core.mesh import is_closed_outward
from viewloc_core.pose import Pose

if TYPE_CHECKING:
    import pyrender

#: Dihedral angle (deg) above which an edge is drawn as a sharp crease.
CREASE_ANGLE_DEG = 30.0

#: Largest image side rendered (llvmpipe's framebuffer limit is 16384).
MAX_IMAGE_SIDE = 8192

#: Point-light intensities are given at this distance (mm); see :class:`Light`.
POINT_LIGHT_REFERENCE_MM = 1000.0

_GL_FROM_CV = np.diag([1.0, -1.0, -1.0])
_GAMMA = 2.2

_platform_lock = threading.Lock()


class RenderBackendError(RuntimeError):
    """No OpenGL context could be created (EGL nor OSMesa usable).

    An environment problem, not bad input, so it is not a ``ViewlocError``.
    """


def _finite_triple(values: Sequence[float], field: str) -> tuple[float, float, float]:
    try:
        a, b, c = (float(v) for v in values)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{field} must be three numbers", field) from exc
    if not all(math.isfinite(v) for v in (a, b, c)):
        raise InvalidInputError(f"{field} must be finite", field)
    return a, b, c


# ---------------------------------------------------------------------------
# Values
# ---------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Light:
    """A light source, given in the OpenCV camera frame.

    Attributes
    ----------
    kind : {"directional", "point", "ambient"}
        ``directional``: parallel light travelling along ``direction_cam``.
        ``point``: light from ``position_cam_mm``, falling off with 1/d².
        ``ambient``: uniform light from everywhere, no direction.
    direction_cam : (3,) tuple of float
        Direction of travel of a directional light (from the light towards
        the scene), camera frame, normalised here. ``(0, 0, 1)`` is a
        headlight. Ignored for other kinds.
    position_cam_mm : (3,) tuple of float
        Position of a point light, camera frame, mm. Ignored for other kinds.
    colour_rgb : (3,) tuple of float
        Light colour, linear RGB, each 0..1.
    intensity : float
        Irradiance scale, >= 0. For a directional light pyrender's intensity
        (about 3 lights a grey face well); for a point light the same
        irradiance is reached at :data:`POINT_LIGHT_REFERENCE_MM`; for an
        ambient light the added radiance (about 0.2-0.4).
    """

    kind: Literal["directional", "point", "ambient"]
    direction_cam: tuple[float, float, float] = (0.0, 0.0, 1.0)
    position_cam_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    colour_rgb: tuple[float, float, float] = (1.0, 1.0, 1.0)
    intensity: float = 3.0

    def __post_init__(self) -> None:
        if self.kind not in ("directional", "point", "ambient"):
            raise InvalidInputError(
                f"light kind must be directional, point or ambient, got {self.kind!r}",
                "light.kind",
            )
        direction = _finite_triple(self.direction_cam, "light.direction_cam")
        norm = math.sqrt(sum(c * c for c in direction))
        if self.kind == "directional" and norm < 1e-12:
            raise InvalidInputError("a directional light needs a non-zero direction",
                                    "light.direction_cam")
        if norm >= 1e-12:
            direction = (direction[0] / norm, direction[1] / norm, direction[2] / norm)
        colour = _finite_triple(self.colour_rgb, "light.colour_rgb")
        if min(colour) < 0.0 or max(colour) > 1.0:
            raise InvalidInputError("light colour channels must be in 0..1", "light.colour_rgb")
        if not (math.isfinite(self.intensity) and self.intensity >= 0.0):
            raise InvalidInputError("light intensity must be finite and >= 0", "light.intensity")
        object.__setattr__(self, "direction_cam", direction)
        object.__setattr__(self, "position_cam_mm",
                           _finite_triple(self.position_cam_mm, "light.position_cam_mm"))
        object.__setattr__(self, "colour_rgb", colour)
        object.__setattr__(self, "intensity", float(self.intensity))


@dataclass(frozen=True, slots=True)
class Material:
    """A uniform physically based material (glTF metallic-roughness model).

    Attributes
    ----------
    base_rgb : (3,) tuple of float
        Display (sRGB) colour, each 0..1; converted to linear reflectance here.
    metallic : float
        0 (dielectric) .. 1 (metal).
    roughness : float
        0 (mirror) .. 1 (matte).
    """

    base_rgb: tuple[float, float, float] = (0.6, 0.6, 0.6)
    metallic: float = 0.0
    roughness: float = 0.6

    def __post_init__(self) -> None:
        base = _finite_triple(self.base_rgb, "material.base_rgb")
        if min(base) < 0.0 or max(base) > 1.0:
            raise InvalidInputError("material colour channels must be in 0..1",
                                    "material.base_rgb")
        for name in ("metallic", "roughness"):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and 0.0 <= value <= 1.0):
                raise InvalidInputError(f"material {name} must be in 0..1", f"material.{name}")
            object.__setattr__(self, name, value)
        object.__setattr__(self, "base_rgb", base)


#: What a mesh without colours of its own looks like.
DEFAULT_MATERIAL = Material()


@dataclass(frozen=True, slots=True, eq=False)
class RenderResult:
    """One rendered image.

    Attributes
    ----------
    color : (H, W, 3) uint8
        RGB image, anti-aliased.
    depth_mm : (H, W) float32
        Camera-frame z in mm of the nearest surface, 0 for background.
    mask : (H, W) bool
        ``depth_mm > 0``.
    """

    color: NDArray[np.uint8]
    depth_mm: NDArray[np.float32]
    mask: NDArray[np.bool_]


@dataclass(frozen=True, slots=True, eq=False)
class DepthResult:
    """A depth-only render (no shading): see :class:`RenderResult`."""

    depth_mm: NDArray[np.float32]
    mask: NDArray[np.bool_]


@dataclass(frozen=True, slots=True, eq=False)
class SceneRenderResult:
    """A render of several objects with a per-pixel object label.

    Attributes
    ----------
    color : (H, W, 3) uint8 or None
        RGB image; ``None`` for a depth-only scene render.
    depth_mm : (H, W) float32
        Camera-frame z in mm of the nearest surface, 0 for background.
    mask : (H, W) bool
        ``depth_mm > 0``.
    labels : (H, W) int16
        Index into the rendered items of the visible surface, -1 background.
    item_pixels : (N,) int64
        Pixels each item would cover alone (unoccluded silhouette area).
    """

    color: NDArray[np.uint8] | None
    depth_mm: NDArray[np.float32]
    mask: NDArray[np.bool_]
    labels: NDArray[np.int16]
    item_pixels: NDArray[np.int64]

    def visible_fraction(self, index: int) -> float:
        """Visible share (0..1) of item ``index``'s unoccluded silhouette."""
        total = int(self.item_pixels[index])
        if total == 0:
            return 0.0
        return float(np.count_nonzero(self.labels == index)) / total


@dataclass(frozen=True, slots=True, eq=False, weakref_slot=True)
class PreparedMesh:
    """A mesh turned into renderable vertex arrays once, for many renders.

    Built by :func:`prepare`. Faces are unrolled to three corners each so that
    normals can be sharp at creases and smooth elsewhere.

    Attributes
    ----------
    mesh : trimesh.Trimesh
        The source mesh (mm, object frame).
    material : Material or None
        The material baked in; ``None`` means the mesh's own colours.
    positions : (3F, 3) or (6F, 3) float32
        Corner positions, object frame, mm (see ``double_sided``).
    normals : same shape, float32
        Unit corner normals, object frame.
    colours_linear : (3F or 6F, 4) float32 or None
        Linear RGBA vertex colours (multiply the lit colour), if any.
    texcoords : (3F or 6F, 2) float32 or None
        UVs for ``texture``, if any.
    texture : (h, w, 3 or 4) uint8 or None
        Base colour texture (sRGB), if any.
    base_colour_linear : (4,) float64
        glTF ``baseColorFactor``.
    metallic, roughness : float
        glTF metallic-roughness factors.
    centre_obj : (3,) float64
        Centre of a sphere bounding the mesh, object frame, mm.
    radius_mm : float
        Radius of that sphere.
    double_sided : bool
        True when the arrays hold every triangle twice, the second copy with
        reversed winding and normals, so its back side is drawn and lit too.
        Closed, consistently and outward wound meshes never show a back face
        and get one copy; back faces are always culled, which halves the
        shading work (the dominant cost with Mesa's llvmpipe) and keeps
        depth-only renders (where pyrender always culls) equal to colour ones.
    """

    mesh: trimesh.Trimesh
    material: Material | None
    positions: NDArray[np.float32]
    normals: NDArray[np.float32]
    colours_linear: NDArray[np.float32] | None
    texcoords: NDArray[np.float32] | None
    texture: NDArray[np.uint8] | None
    base_colour_linear: NDArray[np.float64]
    metallic: float
    roughness: float
    centre_obj: NDArray[np.float64]
    radius_mm: float
    double_sided: bool


# ---------------------------------------------------------------------------
# Preparing meshes
# ---------------------------------------------------------------------------


def prepare(
    mesh: trimesh.Trimesh,
    material: Material | None = None,
    crease_angle_deg: float = CREASE_ANGLE_DEG,
) -> PreparedMesh:
    """Turn a mesh into vertex arrays ready for any number of renders.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Object-frame mesh in mm (e.g. from :func:`viewloc_core.mesh.load_mesh`).
    material : Material or None
        Uniform material overriding the mesh's colours; ``None`` uses the
        mesh's vertex/face colours or texture, or :data:`DEFAULT_MATERIAL`.
    crease_angle_deg : float
        Edges with a larger dihedral angle stay sharp (see module doc).

    Returns
    -------
    PreparedMesh
    """
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InvalidInputError("prepare needs a trimesh.Trimesh with faces", "mesh")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if not np.all(np.isfinite(vertices)):
        raise InvalidInputError("mesh vertices must be finite", "mesh")
    positions = vertices[faces].reshape(-1, 3).astype(np.float32)
    normals = _corner_normals(vertices, faces, math.radians(crease_angle_deg))

    colours: NDArray[np.float32] | None = None
    texcoords: NDArray[np.float32] | None = None
    texture: NDArray[np.uint8] | None = None
    chosen = material
    if material is None:
        colours, texcoords, texture, own = _mesh_visuals(mesh, faces)
        if colours is not None or texture is not None:
            chosen = own
    if chosen is None:
        chosen = DEFAULT_MATERIAL
    base = np.ones(4)
    base[:3] = _srgb_to_linear(np.asarray(chosen.base_rgb, dtype=np.float64))

    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    centre = (lo + hi) / 2.0
    radius = float(np.sqrt(np.max(np.sum((vertices - centre) ** 2, axis=1))))
    closed = is_closed_outward(mesh)
    if not closed:
        positions = np.concatenate([positions, _reverse_corners(positions)])
        normals = np.concatenate([normals, -_reverse_corners(normals)])
        if colours is not None:
            colours = np.concatenate([colours, _reverse_corners(colours)])
        if texcoords is not None:
            texcoords = np.concatenate([texcoords, _reverse_corners(texcoords)])
    return PreparedMesh(
        mesh=mesh, material=material, positions=positions, normals=normals,
        colours_linear=colours, texcoords=texcoords, texture=texture,
        base_colour_linear=base, metallic=chosen.metallic, roughness=chosen.roughness,
        centre_obj=centre, radius_mm=radius, double_sided=not closed,
    )


def _reverse_corners(corners: NDArray[np.float32]) -> NDArray[np.float32]:
    """Per-corner arrays (3F, k) with each triangle's corner order reversed."""
    k = corners.shape[1]
    return np.ascontiguousarray(corners.reshape(-1, 3, k)[:, ::-1, :].reshape(-1, k))


def _corner_normals(
    vertices: NDArray[np.float64], faces: NDArray[np.int64], crease_rad: float
) -> NDArray[np.float32]:
    """(3F, 3) normals: area-weighted over faces at a vertex within the crease angle."""
    tri = vertices[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    double_area = np.linalg.norm(cross, axis=1)
    face_n = np.zeros_like(cross)
    ok = double_area > 0
    face_n[ok] = cross[ok] / double_area[ok, None]
    weighted = cross  # |cross| = 2 * area, so this is the area-weighted normal

    n_faces = len(faces)
    corner_v = faces.reshape(-1)
    corner_f = np.repeat(np.arange(n_faces), 3)
    order = np.argsort(corner_v, kind="stable")
    sorted_f = corner_f[order]
    counts = np.bincount(corner_v, minlength=len(vertices))
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    cos_limit = math.cos(crease_rad)

    out = np.empty((3 * n_faces, 3), dtype=np.float64)
    # Chunks bound the (corner, neighbour face) pair arrays to a few million.
    chunk = max(1, 4_000_000 // max(int(counts.max()), 1))
    for c0 in range(0, 3 * n_faces, chunk):
        cs = np.arange(c0, min(c0 + chunk, 3 * n_faces))
        deg = counts[corner_v[cs]]
        pair_c = np.repeat(cs, deg)
        offsets = np.arange(len(pair_c)) - np.repeat(np.cumsum(deg) - deg, deg)
        pair_g = sorted_f[starts[corner_v[pair_c]] + offsets]
        keep = np.einsum("ij,ij->i", face_n[corner_f[pair_c]], face_n[pair_g]) >= cos_limit
        local = pair_c[keep] - c0
        acc = np.stack(
            [np.bincount(local, weights=weighted[pair_g[keep], k], minlength=len(cs))
             for k in range(3)],
            axis=1,
        )
        out[cs] = acc
    norm = np.linalg.norm(out, axis=1)
    fallback = norm < 1e-12
    out[fallback] = face_n[corner_f[fallback]]
    norm[fallback] = 1.0
    return (out / norm[:, None]).astype(np.float32)


def _mesh_visuals(
    mesh: trimesh.Trimesh, faces: NDArray[np.int64]
) -> tuple[
    NDArray[np.float32] | None, NDArray[np.float32] | None, NDArray[np.uint8] | None, Material
]:
    """Corner colours or UVs + texture from the mesh's own visual, and its material."""
    visual: Any = mesh.visual
    own = Material(base_rgb=(1.0, 1.0, 1.0), metallic=0.0, roughness=0.7)
    if visual is None or not visual.defined:
        return None, None, None, own
    if visual.kind == "texture":
        uv = getattr(visual, "uv", None)
        image = _texture_image(visual.material)
        if uv is not None and image is not None and len(uv) == len(mesh.vertices):
            uv_corner = np.asarray(uv, dtype=np.float32)[faces].reshape(-1, 2)
            return None, uv_corner, image, own
        visual = visual.to_color()
    if visual.kind == "face":
        face_rgba = np.asarray(visual.face_colors, dtype=np.float64) / 255.0
        rgba = np.repeat(face_rgba, 3, axis=0)
    elif visual.kind == "vertex":
        vertex_rgba = np.asarray(visual.vertex_colors, dtype=np.float64) / 255.0
        rgba = vertex_rgba[faces].reshape(-1, 4)
    else:
        return None, None, None, own
    linear = np.empty((len(rgba), 4), dtype=np.float32)
    linear[:, :3] = _srgb_to_linear(rgba[:, :3])
    # Alpha 1: parts are opaque, and blending would need depth-sorted draws.
    linear[:, 3] = 1.0
    return linear, None, None, own


def _texture_image(material: Any) -> NDArray[np.uint8] | None:
    image = getattr(material, "image", None)
    if image is None:
        image = getattr(material, "baseColorTexture", None)
    if image is None:
        return None
    arr = np.asarray(image.convert("RGB") if hasattr(image, "convert") else image)
    if arr.ndim != 3 or arr.shape[2] not in (3, 4) or arr.size == 0:
        return None
    return np.ascontiguousarray(arr[:, :, :3], dtype=np.uint8)


# ---------------------------------------------------------------------------
# Lights
# ---------------------------------------------------------------------------


def default_lights() -> list[Light]:
    """A key light from the upper left behind the camera plus ambient light."""
    return [
        Light("directional", direction_cam=(0.35, 0.45, 1.0), intensity=3.0),
        Light("ambient", intensity=0.3),
    ]


def random_lights(
    rng: np.random.Generator | int | None = None, n: tuple[int, int] = (1, 3)
) -> list[Light]:
    """Varied lighting for training views (paper §4.1).

    Draws ``n[0]..n[1]`` (inclusive) directional or point lights, all coming
    from the camera's side of the object (within 75° of the optical axis, so
    the visible surfaces are lit), with random intensity and a slight colour
    tint, plus one ambient light. Features that only exist under one light
    then get a low presence probability.

    Parameters
    ----------
    rng : numpy Generator, int seed or None
        Source of randomness; a fixed seed gives the same lights.
    n : (int, int)
        Inclusive range of the number of non-ambient lights, ``1 <= n[0] <= n[1]``.

    Returns
    -------
    list of Light
        The non-ambient lights followed by one ambient light.
    """
    lo, hi = int(n[0]), int(n[1])
    if lo < 1 or hi < lo:
        raise InvalidInputError(f"n must satisfy 1 <= n[0] <= n[1], got {n}", "n")
    gen = np.random.default_rng(rng)
    count = int(gen.integers(lo, hi + 1))
    lights: list[Light] = []
    for _ in range(count):
        # Direction towards the light: uniform on the spherical cap around -z
        # (the camera side) with half-angle 75°.
        cos_theta = gen.uniform(math.cos(math.radians(75.0)), 1.0)
        sin_theta = math.sqrt(1.0 - cos_theta * cos_theta)
        phi = gen.uniform(0.0, 2.0 * math.pi)
        to_light = (sin_theta * math.cos(phi), sin_theta * math.sin(phi), -cos_theta)
        tint = 1.0 - gen.uniform(0.0, 0.15, size=3)
        colour = (float(tint[0]), float(tint[1]), float(tint[2]))
        intensity = float(gen.uniform(1.5, 4.5) / math.sqrt(count))
        if gen.uniform() < 0.3:
            distance = gen.uniform(800.0, 2500.0)
            position = (to_light[0] * distance, to_light[1] * distance,
                        to_light[2] * distance + 700.0)
            lights.append(Light("point", position_cam_mm=position, colour_rgb=colour,
                                intensity=intensity))
        else:
            lights.append(Light("directional",
                                direction_cam=(-to_light[0], -to_light[1], -to_light[2]),
                                colour_rgb=colour, intensity=intensity))
    lights.append(Light("ambient", intensity=float(gen.uniform(0.1, 0.4))))
    return lights


# ---------------------------------------------------------------------------
# Renderer
# ---------------------------------------------------------------------------


class Renderer:
    """Offscreen renderer giving colour, depth and mask in OpenCV conventions.

    Holds one GL context (a ``pyrender.OffscreenRenderer``, about 0.5-1 s to
    create) for its whole life and the GL copies of the meshes it has drawn.
    Under EGL a change of image size only reallocates the framebuffer (well
    under a millisecond), so one context serves every size and every pyramid
    level shares the uploaded meshes. Several contexts per size would not be
    better: pyrender's ``delete`` calls ``eglTerminate``, which destroys every
    other context on the display, so this class releases its context without
    terminating the display. Under OSMesa pyrender recreates the context on a
    size change, so keep one image size per Renderer there.

    Not thread-safe: an OpenGL context is current in one thread only, so a
    Renderer may be used only by the thread that created it (others get a
    ``RuntimeError``). Create one Renderer per worker thread or process.

    Examples
    --------
    >>> with Renderer() as renderer:                        # doctest: +SKIP
    ...     out = renderer.render(prepare(mesh), camera, pose)
    """

    def __init__(self) -> None:
        self._offscreen: Any = None
        self._thread = threading.get_ident()
        self._closed = False
        # GL buffers belong to the context; weak keys let a dropped
        # PreparedMesh (and its material variants) free them on the next draw.
        self._gl_meshes: weakref.WeakKeyDictionary[PreparedMesh, Any] = (
            weakref.WeakKeyDictionary()
        )
        self._overrides: weakref.WeakKeyDictionary[
            PreparedMesh, dict[Material, PreparedMesh]
        ] = weakref.WeakKeyDictionary()

    def __del__(self) -> None:
        # At interpreter shutdown OpenGL may be half torn down already.
        with contextlib.suppress(Exception):
            self.close()

    def __enter__(self) -> Renderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Release the GL context and the meshes in it. Idempotent."""
        if self._offscreen is not None:
            if threading.get_ident() == self._thread:
                _release(self._offscreen)
            else:
                # Another thread (e.g. the garbage collector's) cannot make
                # the context current; leaking it beats pyrender's own
                # clean-up, whose eglTerminate would break other Renderers.
                _disarm(self._offscreen)
        self._offscreen = None
        self._gl_meshes.clear()
        self._overrides.clear()
        self._closed = True

    def render(
        self,
        mesh: PreparedMesh | trimesh.Trimesh,
        camera: Camera,
        pose: Pose,
        lights: Sequence[Light] | None = None,
        material: Material | None = None,
        background_rgb: tuple[int, int, int] = (0, 0, 0),
    ) -> RenderResult:
        """Render one object.

        Parameters
        ----------
        mesh : PreparedMesh or trimesh.Trimesh
            A raw Trimesh is prepared on every call; prepare it once for
            repeated renders.
        camera : Camera
            Intrinsics and image size; distortion is ignored (ideal pinhole).
        pose : Pose
            Object -> camera, mm.
        lights : sequence of Light or None
            ``None`` uses :func:`default_lights`. pyrender lights a part with
            at most four lights of each kind: of more, the first four
            directional ones given and the four point lights nearest the
            part's origin.
        material : Material or None
            Overrides the prepared mesh's material for this render (a second
            GL copy of the mesh is kept per material used).
        background_rgb : (3,) int
            Background colour, 0..255.

        Returns
        -------
        RenderResult
        """
        prepared = self._prepared(mesh, material)
        out = self._draw([(prepared, pose)], camera, lights, background_rgb, depth_only=False)
        color, depth = out
        assert color is not None
        return RenderResult(color=color, depth_mm=depth, mask=depth > 0)

    def render_depth(
        self, mesh: PreparedMesh | trimesh.Trimesh, camera: Camera, pose: Pose
    ) -> DepthResult:
        """Depth and mask only (no shading, no colour read-back), e.g. for contours.

        See :meth:`render` for the parameters.
        """
        prepared = self._prepared(mesh, None)
        _, depth = self._draw([(prepared, pose)], camera, None, (0, 0, 0), depth_only=True)
        return DepthResult(depth_mm=depth, mask=depth > 0)

    def render_scene(
        self,
        items: Sequence[tuple[PreparedMesh, Pose]],
        camera: Camera,
        lights: Sequence[Light] | None = None,
        background_rgb: tuple[int, int, int] = (0, 0, 0),
        depth_only: bool = False,
    ) -> SceneRenderResult:
        """Render several objects together, with a per-pixel object label.

        Labels come from one depth-only render per item: the label of a pixel
        is the item nearest to the camera there, so they agree exactly with
        ``depth_mm`` and give each item's unoccluded area for free. Cost:
        ``len(items)`` depth renders plus one colour render.

        Parameters
        ----------
        items : sequence of (PreparedMesh, Pose)
            Objects and their object -> camera poses; the same prepared mesh
            may appear several times.
        camera, lights, background_rgb
            As for :meth:`render`.
        depth_only : bool
            Skip the colour render (``color`` is then ``None``).

        Returns
        -------
        SceneRenderResult
        """
        if len(items) == 0:
            raise InvalidInputError("render_scene needs at least one item", "items")
        if len(items) > 32767:
            raise InvalidInputError("render_scene takes at most 32767 items", "items")
        prepared_items = [(self._prepared(m, None), p) for m, p in items]
        depth = np.zeros((camera.height, camera.width), dtype=np.float32)
        labels = np.full((camera.height, camera.width), -1, dtype=np.int16)
        item_pixels = np.zeros(len(items), dtype=np.int64)
        for index, item in enumerate(prepared_items):
            _, item_depth = self._draw([item], camera, None, (0, 0, 0), depth_only=True)
            hit = item_depth > 0
            item_pixels[index] = int(np.count_nonzero(hit))
            nearer = hit & ((depth == 0) | (item_depth < depth))
            depth[nearer] = item_depth[nearer]
            labels[nearer] = index
        color = None
        if not depth_only:
            color, _ = self._draw(prepared_items, camera, lights, background_rgb, depth_only=False)
        return SceneRenderResult(color=color, depth_mm=depth, mask=depth > 0, labels=labels,
                                 item_pixels=item_pixels)

    # -- internals ----------------------------------------------------------

    def _prepared(
        self, mesh: PreparedMesh | trimesh.Trimesh, material: Material | None
    ) -> PreparedMesh:
        if isinstance(mesh, PreparedMesh):
            if material is None or material == mesh.material:
                return mesh
            variants = self._overrides.setdefault(mesh, {})
            if material not in variants:
                variants[material] = _with_material(mesh, material)
            return variants[material]
        if isinstance(mesh, trimesh.Trimesh):
            return prepare(mesh, material)
        raise InvalidInputError(
            f"expected a PreparedMesh or trimesh.Trimesh, got {type(mesh).__name__}", "mesh"
        )

    def _context(self, width: int, height: int) -> Any:
        if threading.get_ident() != self._thread:
            raise RuntimeError("a Renderer may only be used by the thread that created it")
        if self._closed:
            raise RuntimeError("this Renderer is closed")
        if self._offscreen is None:
            pyrender = _pyrender()
            try:
                self._offscreen = pyrender.OffscreenRenderer(width, height)
            except Exception as exc:
                raise RenderBackendError(
                    f"cannot create an OpenGL context with PYOPENGL_PLATFORM="
                    f"{os.environ.get('PYOPENGL_PLATFORM')!r}: {exc}. Install libegl1 "
                    "libegl-mesa0 libgl1-mesa-dri, or start with PYOPENGL_PLATFORM=osmesa "
                    "(needs libosmesa6)."
                ) from exc
        else:
            self._offscreen.viewport_width = width
            self._offscreen.viewport_height = height
        return self._offscreen

    def _gl_mesh(self, prepared: PreparedMesh) -> Any:
        mesh = self._gl_meshes.get(prepared)
        if mesh is None:
            mesh = _to_pyrender(prepared)
            self._gl_meshes[prepared] = mesh
        return mesh

    def _draw(
        self,
        items: Sequence[tuple[PreparedMesh, Pose]],
        camera: Camera,
        lights: Sequence[Light] | None,
        background_rgb: tuple[int, int, int],
        depth_only: bool,
    ) -> tuple[NDArray[np.uint8] | None, NDArray[np.float32]]:
        pyrender = _pyrender()
        bg = np.asarray(background_rgb, dtype=np.float64)
        if bg.shape != (3,) or not np.all((bg >= 0) & (bg <= 255)):
            raise InvalidInputError("background_rgb must be three values in 0..255",
                                    "background_rgb")
        H, W = camera.height, camera.width
        if max(H, W) > MAX_IMAGE_SIDE:
            raise InvalidInputError(
                f"cannot render {W}x{H}: the largest side is {MAX_IMAGE_SIDE} pixels",
                "camera.width",
            )
        clip = _clip_range(items)
        if clip is None:  # everything is behind the camera
            empty_color = None if depth_only else np.empty((H, W, 3), dtype=np.uint8)
            if empty_color is not None:
                empty_color[:] = np.round(bg).astype(np.uint8)
            return empty_color, np.zeros((H, W), dtype=np.float32)
        znear, zfar = clip

        offscreen = self._context(W, H)
        lights = default_lights() if lights is None else list(lights)
        ambient = np.zeros(3)
        for light in lights:
            if light.kind == "ambient":
                ambient += np.asarray(light.colour_rgb) * light.intensity
        scene = _ordered_scene_type()(bg_color=np.append(bg / 255.0, 1.0),
                                      ambient_light=ambient)
        scene.add(pyrender.IntrinsicsCamera(
            fx=camera.fx, fy=camera.fy, cx=camera.cx + 0.5, cy=camera.cy + 0.5,
            znear=znear, zfar=zfar,
        ), pose=np.eye(4))
        for prepared, pose in items:
            T_gl = np.eye(4)
            T_gl[:3, :3] = _GL_FROM_CV @ pose.R_m2c
            T_gl[:3, 3] = _GL_FROM_CV @ pose.t_m2c
            scene.add(self._gl_mesh(prepared), pose=T_gl)
        if not depth_only:
            for light in lights:
                _add_light(pyrender, scene, light)

        if depth_only:
            depth = offscreen.render(scene, flags=pyrender.RenderFlags.DEPTH_ONLY)
            return None, np.ascontiguousarray(depth, dtype=np.float32)
        color, depth = offscreen.render(scene)
        return (np.ascontiguousarray(color[:, :, :3], dtype=np.uint8),
                np.ascontiguousarray(depth, dtype=np.float32))


@functools.cache
def _ordered_scene_type() -> type:
    """A ``pyrender.Scene`` that hands its lights and meshes to the renderer
    in the order they were added.

    pyrender keeps a scene's nodes in sets, and its renderer binds the lights
    to the shader (and draws meshes the same distance away) in the sets'
    order, which follows the nodes' memory addresses. The shader then sums
    the lights in another order from one render to the next, and a pixel can
    come out one grey level apart: learning the paper set's barbell, one of
    its 162 training views differed in one pixel in 6 to 19 of 40 renders,
    which moved three edge orientations of that view by 0.1° and made the
    models learned from one mesh differ from run to run (the two barbell
    models gave the same answers on the 220 images of two paper sets, but
    nothing bounds what a flip elsewhere would do).
    """
    class OrderedScene(_pyrender().Scene):  # type: ignore[misc]  # pyrender is untyped
        """See :func:`_ordered_scene_type`."""

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            # Before pyrender's __init__, which adds its nodes through add_node.
            self._added: dict[Any, int] = {}
            super().__init__(*args, **kwargs)

        def add_node(self, node: Any, parent_node: Any = None) -> None:
            super().add_node(node, parent_node)
            self._added.setdefault(node, len(self._added))

        def _in_added_order(self, nodes: Any) -> list[Any]:
            return sorted(nodes, key=self._added.__getitem__)

        @property
        def light_nodes(self) -> list[Any]:
            return self._in_added_order(super().light_nodes)

        @property
        def mesh_nodes(self) -> list[Any]:
            return self._in_added_order(super().mesh_nodes)

    return OrderedScene


def _clip_range(items: Sequence[tuple[PreparedMesh, Pose]]) -> tuple[float, float] | None:
    """znear, zfar (mm) enclosing every item's bounding sphere, or None if all are behind."""
    z_lo, z_hi = math.inf, -math.inf
    for prepared, pose in items:
        z_centre = float(pose.transform(prepared.centre_obj)[0, 2])
        z_lo = min(z_lo, z_centre - prepared.radius_mm)
        z_hi = max(z_hi, z_centre + prepared.radius_mm)
    if z_hi <= 0:
        return None
    zfar = 1.01 * z_hi + 1.0
    # 24-bit depth keeps ~0.1 mm at 1 m as long as znear >= zfar / 1e4; parts
    # closer than that to the camera plane are clipped as a real lens would.
    znear = max(0.9 * z_lo, zfar * 1e-4)
    return znear, zfar


def _add_light(pyrender: Any, scene: Any, light: Light) -> None:
    colour = np.asarray(light.colour_rgb)
    if light.kind == "directional":
        direction_gl = _GL_FROM_CV @ np.asarray(light.direction_cam)
        pose = np.eye(4)
        # pyrender's directional light shines along its node's -z axis.
        pose[:3, :3] = _frame_with_z(-direction_gl)
        scene.add(pyrender.DirectionalLight(color=colour, intensity=light.intensity), pose=pose)
    elif light.kind == "point":
        pose = np.eye(4)
        pose[:3, 3] = _GL_FROM_CV @ np.asarray(light.position_cam_mm)
        # The shader divides by the squared distance in scene units (mm).
        intensity = light.intensity * POINT_LIGHT_REFERENCE_MM**2
        scene.add(pyrender.PointLight(color=colour, intensity=intensity), pose=pose)


def _frame_with_z(z_axis: NDArray[np.float64]) -> NDArray[np.float64]:
    """A rotation matrix whose third column is the unit vector ``z_axis``."""
    z = z_axis / np.linalg.norm(z_axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def _with_material(prepared: PreparedMesh, material: Material) -> PreparedMesh:
    base = np.ones(4)
    base[:3] = _srgb_to_linear(np.asarray(material.base_rgb, dtype=np.float64))
    return PreparedMesh(
        mesh=prepared.mesh, material=material, positions=prepared.positions,
        normals=prepared.normals, colours_linear=None, texcoords=None, texture=None,
        base_colour_linear=base, metallic=material.metallic, roughness=material.roughness,
        centre_obj=prepared.centre_obj, radius_mm=prepared.radius_mm,
        double_sided=prepared.double_sided,
    )


def _to_pyrender(prepared: PreparedMesh) -> pyrender.Mesh:
    pyrender = _pyrender()
    material = pyrender.MetallicRoughnessMaterial(
        baseColorFactor=prepared.base_colour_linear,
        metallicFactor=prepared.metallic,
        roughnessFactor=prepared.roughness,
        baseColorTexture=prepared.texture,
        alphaMode="OPAQUE",
        # Back faces are culled; open meshes carry reversed copies instead.
        doubleSided=False,
    )
    primitive = pyrender.Primitive(
        positions=prepared.positions,
        normals=prepared.normals,
        color_0=prepared.colours_linear,
        texcoord_0=prepared.texcoords,
        material=material,
        mode=pyrender.constants.GLTF.TRIANGLES,
    )
    return pyrender.Mesh(primitives=[primitive])


def _release(offscreen: Any) -> None:
    """Free a pyrender.OffscreenRenderer's GL objects and context.

    Unlike ``OffscreenRenderer.delete`` this leaves an EGL display initialised:
    ``eglTerminate`` would also destroy the contexts of every other Renderer in
    the process (they share the device's display).
    """
    platform: Any = getattr(offscreen, "_platform", None)
    display = getattr(platform, "_egl_display", None)
    context = getattr(platform, "_egl_context", None)
    if display is None or context is None:
        offscreen.delete()
        return
    from OpenGL.EGL import EGL_NO_CONTEXT, EGL_NO_SURFACE, eglDestroyContext, eglMakeCurrent

    platform.make_current()
    offscreen._renderer.delete()
    eglMakeCurrent(display, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT)
    eglDestroyContext(display, context)
    _disarm(offscreen)


def _disarm(offscreen: Any) -> None:
    """Stop pyrender's finalisers from calling ``eglTerminate`` (see _release)."""
    platform: Any = getattr(offscreen, "_platform", None)
    if platform is not None and hasattr(platform, "_egl_display"):
        platform._egl_context = None
        platform._egl_display = None
    offscreen._renderer = None
    offscreen._platform = None


# ---------------------------------------------------------------------------
# Platform selection and small helpers
# ---------------------------------------------------------------------------

# Creates an OpenGL 4.1 core context on the first EGL device the way pyrender
# does (device platform display, pbuffer config), with ctypes only: importing
# pyrender in the child would cost seconds. Run in a child process so that a
# broken driver cannot crash or pollute this one.
_EGL_PROBE = """
import ctypes, ctypes.util
P, U, I = ctypes.c_void_p, ctypes.c_uint, ctypes.c_int
egl = ctypes.CDLL(ctypes.util.find_library("EGL") or "libEGL.so.1")
egl.eglGetProcAddress.restype, egl.eglGetProcAddress.argtypes = P, [ctypes.c_char_p]
def ext(name, res, *args):
    addr = egl.eglGetProcAddress(name)
    assert addr, name
    return ctypes.CFUNCTYPE(res, *args)(addr)
query = ext(b"eglQueryDevicesEXT", U, I, P, ctypes.POINTER(I))
platform_display = ext(b"eglGetPlatformDisplayEXT", P, U, P, P)
for name, res, args in [("eglInitialize", U, [P, P, P]), ("eglChooseConfig", U, [P, P, P, I, P]),
                        ("eglBindAPI", U, [U]), ("eglCreateContext", P, [P, P, P, P]),
                        ("eglMakeCurrent", U, [P, P, P, P])]:
    getattr(egl, name).restype, getattr(egl, name).argtypes = res, args
n = I()
assert query(0, None, ctypes.byref(n)) and n.value > 0
devices = (P * n.value)()
assert query(n.value, devices, ctypes.byref(n))
display = platform_display(0x313F, devices[0], None)
assert display and egl.eglInitialize(display, None, None)
config, count = P(), I()
wanted = (I * 5)(0x3033, 0x0001, 0x3040, 0x0008, 0x3038)
assert egl.eglChooseConfig(display, wanted, ctypes.byref(config), 1, ctypes.byref(count))
assert count.value > 0 and egl.eglBindAPI(0x30A2)
gl41_core = (I * 7)(0x3098, 4, 0x30FB, 1, 0x30FD, 1, 0x3038)
context = egl.eglCreateContext(display, config, None, gl41_core)
assert context and egl.eglMakeCurrent(display, None, None, context)
"""


def _select_platform() -> str:
    """Fix PYOPENGL_PLATFORM before OpenGL is imported (see module doc)."""
    with _platform_lock:
        if "PYOPENGL_PLATFORM" in os.environ or "OpenGL" in sys.modules:
            return os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
        try:
            probe = subprocess.run([sys.executable, "-c", _EGL_PROBE], capture_output=True,
                                   timeout=60, check=False)
            egl_ok = probe.returncode == 0
        except (OSError, subprocess.TimeoutExpired):
            egl_ok = False
        return os.environ.setdefault("PYOPENGL_PLATFORM", "egl" if egl_ok else "osmesa")


def _pyrender() -> Any:
    """The pyrender module, imported after the platform is chosen."""
    module = sys.modules.get("pyrender")
    if module is not None:
        return module
    _select_platform()
    import pyrender

    return pyrender


def _srgb_to_linear(rgb: NDArray[np.float64]) -> NDArray[np.float64]:
    # pyrender's shader ends with pow(c, 1/2.2), so 2.2 is the exact inverse.
    return np.power(np.clip(rgb, 0.0, 1.0), _GAMMA)
