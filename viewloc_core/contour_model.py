"""Precomputed 3D contour points per view, so pose refinement never renders.

The sparse-viewpoint idea of contour trackers such as RBOT, SRT3D and M3T
(Stoiber et al.): for each of V view directions, store up to P points in the
object frame that lie on the part's visible outline as seen from there —
occluding contours (outer and inner silhouette, e.g. a plate in front of a
bar) and sharp crease edges — each with a 3D direction whose projection gives
the contour's 2D normal at any nearby pose. At run time the refinement picks
the view nearest to its current pose and projects that view's points.

Points come from the mesh's own edges, not from rendered pixels, so they are
exact to the tessellation instead of to half a training pixel (half a pixel
at 1 mm/px is 0.5% of the distance of a 100 mm part): for view direction v the
candidate edges are those between a front- and a back-facing triangle
(occluding contour), boundary edges of open meshes, and creases whose dihedral
angle exceeds ``crease_deg`` with at least one front face. They are sampled
every ``sample_step_px`` training pixels, and kept where a depth-only render
from that view shows them unoccluded. Normals of occluding contours come from
the smoothed rendered silhouette (the contour generator of a finely tessellated
curved surface zig-zags across triangle edges, whose own directions would give
noisy normals); crease normals are perpendicular to the projected edge.
Finally points are thinned to about ``points_per_view`` with a uniform grid.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any, Protocol

import cv2
import numpy as np
import trimesh
from numpy.typing import NDArray

from viewloc_core.camera import Camera
from viewloc_core.contour_kernels import nearest_view
from viewloc_core.errors import InvalidInputError, ModelFormatError
from viewloc_core.pose import Pose
from viewloc_core.view_sphere import view_rotation

Array = NDArray[np.float64]

#: Bump when the array layout or the meaning of its values changes. Version 1
#: had no :data:`KIND_INNER` (its inner occluding contours are
#: :data:`KIND_OCCLUDING`); it is still read.
CONTOUR_SCHEMA_VERSION = 2
_READABLE_SCHEMA_VERSIONS = (1, 2)

#: Point kinds: the outline against the surroundings (occluding contours
#: with the background behind them, and the edges of an open surface),
#: sharp creases between two faces, and inner occluding contours (the part
#: in front of itself, e.g. a knob's foot seen against its cap). The first
#: is an edge against almost any background; the other two are edges only
#: where the part's own two sides differ in brightness.
KIND_OCCLUDING = 0
KIND_CREASE = 1
KIND_INNER = 2

#: The kinds of the outline in the wider sense: every occluding contour.
OUTLINE_KINDS = (KIND_OCCLUDING, KIND_INNER)


class _DepthRenderer(Protocol):
    def render_depth(self, mesh: Any, camera: Camera, pose: Pose) -> Any: ...


@dataclass(frozen=True, slots=True, eq=False)
class ContourModel:
    """Contour points of a part seen from V view directions.

    Attributes
    ----------
    directions : (V, 3) float64
        Unit view directions (object origin -> camera), object frame.
    points_obj : (V, P, 3) float32
        Contour points, object frame, mm; rows ``>= counts[v]`` are padding.
    normals_obj : (V, P, 3) float32
        Unit 3D vectors at each point whose projection at a nearby pose gives
        the contour's 2D normal (``project(X + ε n) - project(X)``); in the
        view's own camera they are parallel to the image plane. Sign is
        arbitrary (the edge search is sign-agnostic).
    kinds : (V, P) uint8
        :data:`KIND_OCCLUDING`, :data:`KIND_CREASE` or :data:`KIND_INNER`.
    counts : (V,) int32
        Valid points per view.
    d0_mm, f_px : float
        Distance and focal length of the views the points were taken from.
    image_size : (int, int)
        (width, height) of those views.
    """

    directions: Array
    points_obj: NDArray[np.float32]
    normals_obj: NDArray[np.float32]
    kinds: NDArray[np.uint8]
    counts: NDArray[np.int32]
    d0_mm: float
    f_px: float
    image_size: tuple[int, int]

    def __post_init__(self) -> None:
        V = len(self.directions)
        if (
            self.directions.shape != (V, 3)
            or self.points_obj.ndim != 3
            or self.points_obj.shape[0] != V
            or self.points_obj.shape[2] != 3
            or self.normals_obj.shape != self.points_obj.shape
            or self.kinds.shape != self.points_obj.shape[:2]
            or self.counts.shape != (V,)
        ):
            raise ModelFormatError("contour model arrays have inconsistent shapes", "contour")
        if V == 0 or np.any(self.counts < 0) or np.any(self.counts > self.points_obj.shape[1]):
            raise ModelFormatError("contour model counts out of range", "contour")
        if self.kinds.size and int(self.kinds.max()) > KIND_INNER:
            raise ModelFormatError("contour model has an unknown point kind", "contour")

    @property
    def n_views(self) -> int:
        """Number of view directions V."""
        return len(self.directions)

    @property
    def nbytes(self) -> int:
        """Memory held by the arrays, bytes."""
        return int(sum(a.nbytes for a in (self.directions, self.points_obj, self.normals_obj,
                                           self.kinds, self.counts)))

    def nearest_view(self, pose: Pose) -> int:
        """Index of the view whose direction is closest to where the camera sees from.

        The camera's direction in the object frame is ``-R^T t`` (object
        origin -> camera centre): it depends on the translation too, since an
        object off the optical axis is seen from the side.
        """
        return int(nearest_view(self.directions, np.ascontiguousarray(pose.R_m2c, np.float64),
                                np.ascontiguousarray(pose.t_m2c, np.float64)))

    def view_points(self, view: int, kind: int | tuple[int, ...] | None = None,
                    ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """(points_obj (n, 3), normals_obj (n, 3)) of one view, float32; only
        those of ``kind`` (one of the ``KIND_*`` or a tuple of them) when given."""
        n = int(self.counts[view])
        if kind is None:
            return self.points_obj[view, :n], self.normals_obj[view, :n]
        keep = np.isin(self.kinds[view, :n], kind)
        return self.points_obj[view, :n][keep], self.normals_obj[view, :n][keep]

    def view_kinds(self, view: int, kind: int | tuple[int, ...] | None = None,
                   ) -> NDArray[np.uint8]:
        """(n,) kind of each point :meth:`view_points` gives for the same arguments."""
        kinds = self.kinds[view, :int(self.counts[view])]
        return kinds if kind is None else kinds[np.isin(kinds, kind)]

    def crease_share(self) -> float:
        """Share in [0, 1] of the valid points, over every view, that are
        :data:`KIND_CREASE` (0 for a model without points)."""
        valid = np.arange(self.points_obj.shape[1]) < self.counts[:, None]
        total = int(np.count_nonzero(valid))
        if total == 0:
            return 0.0
        return int(np.count_nonzero(valid & (self.kinds == KIND_CREASE))) / total

    def outline_only(self) -> ContourModel:
        """The same model without its crease points (see
        :mod:`viewloc_core.crease_visibility`); occluding contours keep their kinds."""
        points = np.zeros_like(self.points_obj)
        normals = np.zeros_like(self.normals_obj)
        kinds = np.full_like(self.kinds, KIND_OCCLUDING)
        counts = np.zeros_like(self.counts)
        for v in range(self.n_views):
            pts, nrm = self.view_points(v, OUTLINE_KINDS)
            n = len(pts)
            points[v, :n] = pts
            normals[v, :n] = nrm
            kinds[v, :n] = self.view_kinds(v, OUTLINE_KINDS)
            counts[v] = n
        return ContourModel(self.directions, points, normals, kinds, counts, self.d0_mm,
                            self.f_px, self.image_size)

    def to_arrays(self) -> dict[str, Any]:
        """Plain arrays plus JSON-able metadata (for the model file)."""
        return {
            "directions": self.directions,
            "points_obj": self.points_obj,
            "normals_obj": self.normals_obj,
            "kinds": self.kinds,
            "counts": self.counts,
            "schema_version": CONTOUR_SCHEMA_VERSION,
            "d0_mm": float(self.d0_mm),
            "f_px": float(self.f_px),
            "image_size": [int(self.image_size[0]), int(self.image_size[1])],
        }

    @classmethod
    def from_arrays(cls, data: dict[str, Any]) -> ContourModel:
        """Inverse of :meth:`to_arrays`; raises ModelFormatError on bad content."""
        try:
            version = int(data["schema_version"])
            if version not in _READABLE_SCHEMA_VERSIONS:
                raise ModelFormatError(f"unknown contour schema version {version}", "contour")
            size = data["image_size"]
            return cls(
                directions=np.asarray(data["directions"], dtype=np.float64),
                points_obj=np.asarray(data["points_obj"], dtype=np.float32),
                normals_obj=np.asarray(data["normals_obj"], dtype=np.float32),
                kinds=np.asarray(data["kinds"], dtype=np.uint8),
                counts=np.asarray(data["counts"], dtype=np.int32),
                d0_mm=float(data["d0_mm"]),
                f_px=float(data["f_px"]),
                image_size=(int(size[0]), int(size[1])),
            )
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise ModelFormatError(f"contour model is incomplete: {exc}", "contour") from exc

    def metadata_json(self) -> str:
        """The non-array fields as a JSON string."""
        meta = {k: v for k, v in self.to_arrays().items() if not isinstance(v, np.ndarray)}
        return json.dumps(meta)


@dataclass(frozen=True, slots=True)
class _EdgeSet:
    """Mesh edges with their adjacent faces (one face for boundary edges)."""

    v0: NDArray[np.int64]
    v1: NDArray[np.int64]
    f0: NDArray[np.int64]
    f1: NDArray[np.int64]  # -1 for boundary edges
    sharp: NDArray[np.bool_]


def _edge_set(mesh: trimesh.Trimesh, crease_deg: float) -> _EdgeSet:
    adj = np.asarray(mesh.face_adjacency, dtype=np.int64)
    adj_edges = np.asarray(mesh.face_adjacency_edges, dtype=np.int64)
    angles = np.asarray(mesh.face_adjacency_angles, dtype=np.float64)
    boundary = trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1)
    b_edges = np.asarray(mesh.edges_sorted[boundary], dtype=np.int64).reshape(-1, 2)
    b_faces = np.asarray(mesh.edges_face[boundary], dtype=np.int64).reshape(-1)
    return _EdgeSet(
        v0=np.concatenate([adj_edges[:, 0], b_edges[:, 0]]),
        v1=np.concatenate([adj_edges[:, 1], b_edges[:, 1]]),
        f0=np.concatenate([adj[:, 0], b_faces]),
        f1=np.concatenate([adj[:, 1], -np.ones(len(b_faces), dtype=np.int64)]),
        sharp=np.concatenate([angles > math.radians(crease_deg),
                              np.ones(len(b_faces), dtype=bool)]),
    )


def _bilinear(img: NDArray[np.float32], uv: Array) -> Array:
    """Sample (H, W) or (H, W, C) at float pixel positions (N, 2), border-replicated."""
    mapx = uv[:, 0].astype(np.float32).reshape(1, -1)
    mapy = uv[:, 1].astype(np.float32).reshape(1, -1)
    out = cv2.remap(img, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return np.asarray(out, dtype=np.float64).reshape(len(uv), -1)


def _grid_thin(uv: Array, target: int, rng: np.random.Generator) -> NDArray[np.int64]:
    """Indices of about ``target`` points spread uniformly along the contours."""
    n = len(uv)
    if n <= target:
        return np.arange(n)
    order = rng.permutation(n)
    lo, hi = 0.1, float(np.ptp(uv, axis=0).max() + 1.0)
    keep = order[:target]
    # Bisection on the cell size: one point per occupied cell.
    for _ in range(20):
        cell = 0.5 * (lo + hi)
        keys = np.floor(uv[order] / cell).astype(np.int64)
        _, first = np.unique(keys[:, 0] * 1_000_003 + keys[:, 1], return_index=True)
        if len(first) > target:
            lo = cell
        else:
            hi = cell
            keep = order[np.sort(first)]
            if len(first) > 0.9 * target:
                break
    return np.sort(keep)


def build_contour_model(
    mesh: trimesh.Trimesh,
    directions: NDArray[np.floating],
    renderer: _DepthRenderer,
    d0_mm: float,
    f_px: float,
    image_size: tuple[int, int],
    points_per_view: int = 200,
    *,
    crease_deg: float = 35.0,
    sample_step_px: float = 1.0,
    rng: np.random.Generator | int | None = 0,
    visibility_mesh: trimesh.Trimesh | None = None,
) -> ContourModel:
    """Contour points of ``mesh`` seen from each direction (see module notes).

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The part, object frame, mm.
    directions : (V, 3) array
        View directions (object origin -> camera), any length; e.g. the
        vertices of :func:`viewloc_core.view_sphere.subdivided_sphere`.
    renderer : Renderer
        Anything with ``render_depth(mesh, camera, pose) -> .depth_mm``
        (:class:`viewloc_core.render.Renderer`; pass a prepared mesh's
        source or let it prepare once — the mesh is prepared here).
    d0_mm : float
        Camera distance from the object origin, mm (the whole part in view).
    f_px : float
        Focal length of the views, pixels; about ``d0 / f_px`` mm per pixel
        sets the sampling density along the contours.
    image_size : (int, int)
        (width, height) of the views, pixels; principal point at the centre.
    points_per_view : int
        Upper bound P on points kept per view.
    crease_deg : float
        Dihedral angle above which an edge counts as a sharp crease.
    sample_step_px : float
        Spacing of samples along edges before thinning, training pixels.
    rng : numpy Generator, int or None
        Seed of the thinning order; fixed by default so builds repeat.
    visibility_mesh : trimesh.Trimesh, optional
        The mesh each view renders to tell which contour points are hidden
        and where the silhouette's normal points (``mesh`` when None): a
        simplification of a dense mesh costs a fraction of its renders,
        while the points themselves lie on ``mesh``'s own edges.

    Returns
    -------
    ContourModel
    """
    dirs = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    if len(dirs) == 0 or not np.all(np.isfinite(dirs)):
        raise InvalidInputError("directions must be a non-empty finite (V, 3) array", "directions")
    if len(mesh.faces) == 0:
        raise InvalidInputError("mesh has no faces", "mesh")
    if not (d0_mm > 0 and f_px > 0 and points_per_view >= 6 and sample_step_px > 0):
        raise InvalidInputError("d0_mm, f_px, sample_step_px must be positive and "
                                "points_per_view >= 6", "contour")
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    gen = np.random.default_rng(rng)
    width, height = int(image_size[0]), int(image_size[1])
    cam = Camera(f_px, f_px, (width - 1) / 2.0, (height - 1) / 2.0, width, height)
    rendered = mesh if visibility_mesh is None else visibility_mesh
    try:
        from viewloc_core.render import prepare

        source: Any = prepare(rendered)
    except ImportError:
        source = rendered

    verts = np.asarray(mesh.vertices, dtype=np.float64)
    face_n = np.asarray(mesh.face_normals, dtype=np.float64)
    face_c = np.asarray(mesh.triangles_center, dtype=np.float64)
    edges = _edge_set(mesh, crease_deg)
    V, P = len(dirs), int(points_per_view)
    pts_all = np.zeros((V, P, 3), dtype=np.float32)
    nrm_all = np.zeros((V, P, 3), dtype=np.float32)
    kinds_all = np.zeros((V, P), dtype=np.uint8)
    counts = np.zeros(V, dtype=np.int32)
    for k in range(V):
        R_v = view_rotation(dirs[k])
        t_v = np.array([0.0, 0.0, d0_mm])
        depth = np.asarray(renderer.render_depth(source, cam, Pose(R_v, t_v)).depth_mm,
                           dtype=np.float32)
        pts, nrm2d, kind = _view_contour(verts, face_n, face_c, edges, dirs[k] * d0_mm,
                                         R_v, t_v, cam, depth, sample_step_px)
        if len(pts) == 0:
            continue
        uv = cam.project(pts @ R_v.T + t_v)
        keep = _grid_thin(uv, P, gen)
        n = len(keep)
        # 2D normal in the view's image plane, lifted to a 3D object-frame vector.
        n3 = np.column_stack([nrm2d[keep], np.zeros(n)]) @ R_v
        pts_all[k, :n] = pts[keep]
        nrm_all[k, :n] = n3
        kinds_all[k, :n] = kind[keep]
        counts[k] = n
    return ContourModel(dirs, pts_all, nrm_all, kinds_all, counts, float(d0_mm), float(f_px),
                        (width, height))


def _view_contour(
    verts: Array,
    face_n: Array,
    face_c: Array,
    edges: _EdgeSet,
    cam_centre_obj: Array,
    R_v: Array,
    t_v: Array,
    cam: Camera,
    depth: NDArray[np.float32],
    step_px: float,
) -> tuple[Array, Array, NDArray[np.uint8]]:
    """Visible contour samples of one view: points (N, 3), 2D normals (N, 2), kinds (N,)."""
    front = np.einsum("fi,fi->f", face_n, cam_centre_obj - face_c) > 0
    f0_front = front[edges.f0]
    f1_front = np.where(edges.f1 >= 0, front[np.maximum(edges.f1, 0)], False)
    boundary = edges.f1 < 0
    occluding = (f0_front != f1_front) & ~boundary
    crease = edges.sharp & (f0_front | f1_front) & ~occluding
    crease |= boundary
    sel = np.flatnonzero(occluding | crease)
    if len(sel) == 0:
        return np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0, dtype=np.uint8)
    a = verts[edges.v0[sel]]
    b = verts[edges.v1[sel]]
    ua = cam.project(a @ R_v.T + t_v)
    ub = cam.project(b @ R_v.T + t_v)
    seg = ub - ua
    length = np.linalg.norm(seg, axis=1)
    n_samp = np.maximum(1, np.ceil(length / step_px)).astype(np.int64)
    idx = np.repeat(np.arange(len(sel)), n_samp)
    start = np.repeat(np.cumsum(n_samp) - n_samp, n_samp)
    frac = (np.arange(len(idx)) - start + 0.5) / n_samp[idx]
    pts = a[idx] + frac[:, None] * (b[idx] - a[idx])
    pts_c = pts @ R_v.T + t_v
    uv = cam.project(pts_c)
    z = pts_c[:, 2]
    h, w = depth.shape
    inside = (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
    # Visible when some pixel of the 3x3 neighbourhood is not nearer than the
    # point: background counts as infinitely far, so the outline always is.
    far = np.where(depth > 0, depth, np.float32(1e9)).astype(np.float32)
    far_max = cv2.dilate(far, np.ones((3, 3), np.uint8))
    ui = np.clip(np.rint(uv[:, 0]).astype(np.int64), 0, w - 1)
    vi = np.clip(np.rint(uv[:, 1]).astype(np.int64), 0, h - 1)
    tol = 3.0 * z / cam.fx + 0.5
    visible = inside & (far_max[vi, ui] >= z - tol)
    if not np.any(visible):
        return np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0, dtype=np.uint8)
    is_occ = occluding[sel][idx]
    seg_n = np.column_stack([-seg[idx, 1], seg[idx, 0]]) / np.maximum(length[idx], 1e-9)[:, None]
    normals = seg_n.copy()
    # Occluding contours take their normal from the smoothed silhouette, where
    # it is clear (outer outline); inner ones (a part in front of another)
    # keep the edge's perpendicular.
    mask = (depth > 0).astype(np.float32)
    blurred = cv2.GaussianBlur(mask, (0, 0), 1.5)
    gx = cv2.Sobel(blurred, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(blurred, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    g = _bilinear(np.dstack([gx, gy]), uv)
    gnorm = np.linalg.norm(g, axis=1)
    use_mask = is_occ & (gnorm > 0.05)
    normals[use_mask] = g[use_mask] / gnorm[use_mask, None]
    # The edge of an open surface is part of the outline, not a crease. An
    # occluding contour away from the silhouette's border (no gradient of
    # the blurred mask, more than about 3 px inside) has the part itself
    # behind it.
    kinds = np.where(is_occ | boundary[sel][idx], KIND_OCCLUDING, KIND_CREASE).astype(np.uint8)
    kinds[is_occ & ~use_mask & ~boundary[sel][idx]] = KIND_INNER
    return pts[visible], normals[visible], kinds[visible]
