"""Benchmark objects, defined once as primitives that become both a mesh and POV-Ray SDL.

Every shape is a tuple of primitives in its object frame (mm): axis-aligned
boxes, cylinders and triangle meshes. :func:`to_trimesh` tessellates them for
training, metrics and masks; :func:`to_pov` writes the same numbers as POV-Ray
CSG (``box``, ``cylinder``) or ``mesh2``, so the ray-traced test images show
exactly the object the localizer learned (cylinders are exact in POV-Ray and
64-gons in the mesh, a 0.1 % radius difference).
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from numpy.typing import NDArray
from scipy.interpolate import CubicSpline

from viewloc_core.metrics import symmetry_transforms
from viewloc_core.pose import rotation_about_axis

Array = NDArray[np.float64]

ASSETS_DIR = Path(__file__).resolve().parent / "assets"
CYLINDER_SECTIONS = 64


@dataclass(frozen=True, slots=True)
class Box:
    """Axis-aligned box: centre (3,) and full size (3,), mm."""

    center: tuple[float, float, float]
    size: tuple[float, float, float]


@dataclass(frozen=True, slots=True)
class Cylinder:
    """Solid cylinder between two end points with a radius, mm."""

    p0: tuple[float, float, float]
    p1: tuple[float, float, float]
    radius: float


@dataclass(frozen=True, slots=True)
class TriMesh:
    """Triangle mesh: vertices (N, 3) mm, faces (M, 3) counter-clockwise outward.

    ``smooth`` selects interpolated vertex normals in POV-Ray (curved
    surfaces); otherwise faces are shaded flat.
    """

    vertices: Array
    faces: NDArray[np.int64]
    smooth: bool = False


Primitive = Box | Cylinder | TriMesh


@dataclass(frozen=True, slots=True)
class Shape:
    """A named object made of primitives, with its symmetries (BOP style).

    Attributes
    ----------
    name : str
    primitives : tuple of Primitive
    sym_discrete : tuple of (4, 4) arrays
        Discrete symmetries other than the identity.
    sym_continuous : tuple of (axis (3,), offset (3,))
        At most one continuous rotational symmetry.
    """

    name: str
    primitives: tuple[Primitive, ...]
    sym_discrete: tuple[Array, ...] = ()
    sym_continuous: tuple[tuple[Array, Array], ...] = ()

    def symmetries(self, step_deg: float = 1.0) -> Array:
        """(K, 4, 4) symmetry transforms incl. identity, continuous ones every ``step_deg``."""
        return symmetry_transforms(self.sym_discrete, self.sym_continuous, step_deg)


# --- The paper's barbell (§5.1, Fig. 2-4): the dimensions, once. ---------------------------
BARBELL_LENGTH_MM = 180.0  # bar end to bar end, along object x
BAR_RADIUS_MM = 7.5
PLATE_RADIUS_MM = 32.0
PLATE_THICKNESS_MM = 14.0
PLATE_INNER_X_MM = 58.0  # distance of each plate's inner face from the centre


def barbell() -> Shape:
    """The barbell: a bar along object x with a disc plate near each end, origin at the centre.

    Symmetric under every rotation about x and under the half turn about z
    that swaps the ends.
    """
    half = BARBELL_LENGTH_MM / 2
    inner, outer = PLATE_INNER_X_MM, PLATE_INNER_X_MM + PLATE_THICKNESS_MM
    prims: list[Primitive] = [
        Cylinder((-inner, 0.0, 0.0), (inner, 0.0, 0.0), BAR_RADIUS_MM),
        Cylinder((inner, 0.0, 0.0), (outer, 0.0, 0.0), PLATE_RADIUS_MM),
        Cylinder((-outer, 0.0, 0.0), (-inner, 0.0, 0.0), PLATE_RADIUS_MM),
        Cylinder((outer, 0.0, 0.0), (half, 0.0, 0.0), BAR_RADIUS_MM),
        Cylinder((-half, 0.0, 0.0), (-outer, 0.0, 0.0), BAR_RADIUS_MM),
    ]
    flip = np.eye(4)
    flip[:3, :3] = np.diag([-1.0, -1.0, 1.0])
    return Shape(
        "barbell",
        tuple(prims),
        sym_discrete=(flip,),
        sym_continuous=((np.array([1.0, 0.0, 0.0]), np.zeros(3)),),
    )


# --- The hard set's asymmetric industrial part: an L-bracket with holes and a rib. ---------
BRACKET_BASE_MM = (100.0, 60.0, 8.0)  # length (x), width (y), thickness (z)
BRACKET_FLANGE_HEIGHT_MM = 62.0  # above the base, the flange stands at x in [0, thickness]
BRACKET_BASE_HOLES_MM = ((38.0, 17.0, 5.0), (78.0, 41.0, 6.5))  # (x, y, radius)
BRACKET_FLANGE_HOLES_MM = ((40.0, 42.0, 6.0),)  # (y, height above base top, radius)
BRACKET_RIB_MM = (52.0, 4.0, 40.0, 44.0)  # y start, y thickness, length along x, height


def _plate_with_holes(
    length: float, width: float, thickness: float, holes: tuple[tuple[float, float, float], ...]
) -> tuple[Array, NDArray[np.int64]]:
    """Watertight plate [0, length] × [0, width] × [0, thickness] with round through holes.

    Each hole sits in a square cell (side 2r + 6 mm) filled by a ring of
    triangles; the rest of the plate is tiled by the grid of the cells' edges.
    The cells' x and y ranges must be pairwise disjoint so no grid line ends
    on a cell edge (no T-junctions, the mesh closes).
    """
    k = 32  # multiple of 8: the circle points at 45° line up with the square's corners
    cells = [(cu, cv, r + 3.0, r) for cu, cv, r in holes]
    for i, (cu, cv, c, _) in enumerate(cells):
        if not (c < cu < length - c and c < cv < width - c):
            raise ValueError("hole cell must lie inside the plate")
        for cu2, cv2, c2, _ in cells[i + 1 :]:
            if abs(cu - cu2) < c + c2 or abs(cv - cv2) < c + c2:
                raise ValueError("hole cells must not share x or y ranges")
    xs = sorted({0.0, length, *(cu + s * c for cu, _, c, _ in cells for s in (-1, 1))})
    ys = sorted({0.0, width, *(cv + s * c for _, cv, c, _ in cells for s in (-1, 1))})
    pts2: list[tuple[float, float]] = []
    index: dict[tuple[float, float], int] = {}

    def vid(p: tuple[float, float]) -> int:
        key = (round(p[0], 9), round(p[1], 9))
        if key not in index:
            index[key] = len(pts2)
            pts2.append(key)
        return index[key]

    tris: list[tuple[int, int, int]] = []  # counter-clockwise seen from +z
    rings: list[list[int]] = []
    for i in range(len(xs) - 1):
        for j in range(len(ys) - 1):
            x0, x1, y0, y1 = xs[i], xs[i + 1], ys[j], ys[j + 1]
            hole = next(
                (h for h in cells if abs(h[0] - h[2] - x0) < 1e-9 and abs(h[1] - h[2] - y0) < 1e-9),
                None,
            )
            if hole is None:
                a, b, c_, d = vid((x0, y0)), vid((x1, y0)), vid((x1, y1)), vid((x0, y1))
                tris += [(a, b, c_), (a, c_, d)]
                continue
            cu, cv, c, r = hole
            ang = 2 * np.pi * np.arange(k) / k
            ring = [vid((cu + r * np.cos(t), cv + r * np.sin(t))) for t in ang]
            rings.append(ring)
            corners = [
                vid((cu + c * sx, cv + c * sy)) for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1))
            ]
            # Circle point i at angle 360 i / k; corner q sits at 45 + 90 q degrees.
            for i_pt in range(k):
                mid_deg = 360.0 * (i_pt + 0.5) / k
                q = int(round((mid_deg - 45.0) / 90.0)) % 4
                tris.append((ring[i_pt], corners[q], ring[(i_pt + 1) % k]))
            for q in range(4):
                mid = ring[(k // 8 + q * k // 4 + k // 8) % k]  # circle point facing side q
                tris.append((corners[q], corners[(q + 1) % 4], mid))
    n2 = len(pts2)
    p2 = np.array(pts2)
    verts = np.vstack([np.c_[p2, np.zeros(n2)], np.c_[p2, np.full(n2, thickness)]])
    faces = [(a + n2, b + n2, c + n2) for a, b, c in tris] + [(a, c, b) for a, b, c in tris]
    # Outer walls, counter-clockwise boundary walk so quads face outwards.
    boundary = (
        [(x, 0.0) for x in xs[:-1]]
        + [(length, y) for y in ys[:-1]]
        + [(x, width) for x in xs[:0:-1]]
        + [(0.0, y) for y in ys[:0:-1]]
    )
    loop = [index[(round(p[0], 9), round(p[1], 9))] for p in boundary]
    for a, b in zip(loop, loop[1:] + loop[:1], strict=True):
        faces += [(a, b, b + n2), (a, b + n2, a + n2)]
    for ring in rings:
        # Hole walls face the hole's axis: the ring is walked clockwise.
        for a, b in zip(ring, ring[1:] + ring[:1], strict=True):
            faces += [(b, a, a + n2), (b, a + n2, b + n2)]
    return verts, np.array(faces, dtype=np.int64)


def _prism(profile_xz: Array, y0: float, y1: float) -> tuple[Array, NDArray[np.int64]]:
    """Closed prism of a convex (x, z) polygon (counter-clockwise seen from -y) over [y0, y1]."""
    n = len(profile_xz)
    front = np.c_[profile_xz[:, 0], np.full(n, y0), profile_xz[:, 1]]
    back = np.c_[profile_xz[:, 0], np.full(n, y1), profile_xz[:, 1]]
    verts = np.vstack([front, back])
    faces = [(0, i, i + 1) for i in range(1, n - 1)]  # faces -y
    faces += [(n, n + i + 1, n + i) for i in range(1, n - 1)]
    for i in range(n):
        j = (i + 1) % n
        faces += [(i, n + i, n + j), (i, n + j, j)]
    return verts, np.array(faces, dtype=np.int64)


def bracket() -> Shape:
    """An L-bracket: base plate with two holes, upright flange with one hole, one side rib.

    No symmetry (holes and rib are off-centre). Origin at the bounding-box centre.
    """
    L, W, T = BRACKET_BASE_MM
    H = BRACKET_FLANGE_HEIGHT_MM
    base_v, base_f = _plate_with_holes(L, W, T, BRACKET_BASE_HOLES_MM)
    # The flange is a plate in its own (u, v, w) frame; the map to
    # (x, y, z) = (w, u, T + v) has det +1, which keeps its faces outward.
    fl_v, fl_f = _plate_with_holes(W, H, T, BRACKET_FLANGE_HOLES_MM)
    fl_xyz = np.c_[fl_v[:, 2], fl_v[:, 0], T + fl_v[:, 1]]
    ry, rt, rl, rh = BRACKET_RIB_MM
    rib_v, rib_f = _prism(np.array([[T, T], [T + rl, T], [T, T + rh]]), ry, ry + rt)
    centre = np.array([L / 2, W / 2, (T + H) / 2])
    prims: list[Primitive] = [
        TriMesh(base_v - centre, base_f),
        TriMesh(fl_xyz - centre, fl_f),
        TriMesh(rib_v - centre, rib_f),
    ]
    return Shape("bracket", tuple(prims))


# --- The hard set's free-form object: a smooth, asymmetric blob. ---------------------------
FREEFORM_RADIUS_MM = 40.0
FREEFORM_STRETCH = (1.35, 1.0, 0.8)
# (direction, amplitude, width) of smooth radial bumps and dents.
FREEFORM_BUMPS = (
    ((1.0, 0.2, 0.3), 0.45, 0.35),
    ((-0.3, 1.0, 0.5), 0.30, 0.25),
    ((0.2, -0.6, 1.0), -0.25, 0.30),
    ((-1.0, -0.4, -0.2), 0.20, 0.20),
)


def freeform() -> Shape:
    """A smooth organic blob: a stretched sphere with radial Gaussian bumps, no symmetry."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    d = np.asarray(sphere.vertices, dtype=np.float64)
    r = np.ones(len(d))
    for direction, amp, width in FREEFORM_BUMPS:
        a = np.asarray(direction) / np.linalg.norm(direction)
        r += amp * np.exp(-np.sum((d - a) ** 2, axis=1) / width)
    verts = d * r[:, None] * FREEFORM_RADIUS_MM * np.asarray(FREEFORM_STRETCH)
    faces = np.asarray(sphere.faces, dtype=np.int64)
    return Shape("freeform", (TriMesh(verts, faces, smooth=True),))


# --- The novel set's objects: parts the localizer was never tuned on. ----------------------
TEE_RUN_LENGTH_MM = 120.0  # end face to end face of the main run, along object x
TEE_BRANCH_LENGTH_MM = 55.0  # from the run's axis to the branch's end face, along +y
TEE_PIPE_RADIUS_MM = 15.0  # run and branch
TEE_FLANGE_RADIUS_MM = 21.0
TEE_FLANGE_THICKNESS_MM = 8.0  # each flange ends flush with its pipe end


def tee() -> Shape:
    """A pipe tee: a run along object x, a branch along +y, a flange at each of the three ends.

    Origin at the centre of the run (on both pipes' axes). The half turn about
    y swaps the run's ends and keeps the branch: the one symmetry besides the
    identity (any rotation must keep the branch direction +y, so it turns
    about y, and must keep the run's axis, so by 0 or 180°). The 64-gon
    tessellation of the cylinders has a vertex on -z, so the mesh has this
    symmetry exactly too.
    """
    half, r = TEE_RUN_LENGTH_MM / 2, TEE_PIPE_RADIUS_MM
    rf, inner = TEE_FLANGE_RADIUS_MM, TEE_RUN_LENGTH_MM / 2 - TEE_FLANGE_THICKNESS_MM
    branch_end = TEE_BRANCH_LENGTH_MM
    branch_inner = branch_end - TEE_FLANGE_THICKNESS_MM
    prims: list[Primitive] = [
        Cylinder((-inner, 0.0, 0.0), (inner, 0.0, 0.0), r),
        Cylinder((inner, 0.0, 0.0), (half, 0.0, 0.0), rf),
        Cylinder((-half, 0.0, 0.0), (-inner, 0.0, 0.0), rf),
        # The branch starts on the run's axis, inside the run, so the two
        # solids overlap instead of meeting along a curve the primitives
        # cannot express.
        Cylinder((0.0, 0.0, 0.0), (0.0, branch_inner, 0.0), r),
        Cylinder((0.0, branch_inner, 0.0), (0.0, branch_end, 0.0), rf),
    ]
    half_turn_y = np.eye(4)
    half_turn_y[:3, :3] = np.diag([-1.0, 1.0, -1.0])
    return Shape("tee", tuple(prims), sym_discrete=(half_turn_y,))


# A C-profile in the xz plane, built from the corner (0, 0, 0) of its bounding box:
# the web stands at x in [0, web x], the arms run from the web towards +x.
CLAMP_WEB_MM = (15.0, 40.0, 70.0)  # thickness (x), width (y), height (z)
CLAMP_LOWER_ARM_MM = (95.0, 40.0, 12.0)  # length beyond the web (x), width (y), thickness (z)
CLAMP_UPPER_ARM_MM = (60.0, 28.0, 10.0)  # the same; flush with the web's top and its y = 0 side
CLAMP_BOSS_MM = (95.0, 26.0, 10.0, 15.0)  # axis (x, y), radius, height above the lower arm


def clamp() -> Shape:
    """A C-shaped clamp body: a web, a long lower arm and a short, narrow upper arm, with a boss.

    The arms differ in length, width and thickness, the upper arm is flush
    with one side only and the round boss stands off-centre on the lower
    arm's inner face: no rotation maps the part onto itself. Origin at the
    bounding-box centre (about 110 × 40 × 70 mm).
    """
    wx, wy, wz = CLAMP_WEB_MM
    lx, ly, lz = CLAMP_LOWER_ARM_MM
    ux, uy, uz = CLAMP_UPPER_ARM_MM
    bx, by, br, bh = CLAMP_BOSS_MM
    centre = np.array([wx + lx, wy, wz]) / 2

    def corner_box(lo: tuple[float, float, float], size: tuple[float, float, float]) -> Box:
        c = np.asarray(lo) + np.asarray(size) / 2 - centre
        return Box((float(c[0]), float(c[1]), float(c[2])), size)

    boss_lo = np.array([bx, by, lz]) - centre
    boss_hi = np.array([bx, by, lz + bh]) - centre
    prims: list[Primitive] = [
        corner_box((0.0, 0.0, 0.0), (wx, wy, wz)),
        corner_box((wx, 0.0, 0.0), (lx, ly, lz)),
        corner_box((wx, 0.0, wz - uz), (ux, uy, uz)),
        Cylinder(
            (float(boss_lo[0]), float(boss_lo[1]), float(boss_lo[2])),
            (float(boss_hi[0]), float(boss_hi[1]), float(boss_hi[2])),
            br,
        ),
    ]
    return Shape("clamp", tuple(prims))


# The knob's lathe profile (radius, height) in mm from the bottom pole to the top
# pole: a flat foot with a rounded edge, a waisted neck and a domed mushroom cap.
KNOB_PROFILE_MM = (
    (0.0, 0.0), (9.0, 0.0), (16.0, 0.6), (19.5, 3.0), (20.0, 6.5), (17.5, 10.5),
    (13.5, 15.0), (13.0, 19.0), (16.0, 23.0), (24.0, 26.5), (30.0, 30.0), (31.5, 34.5),
    (29.0, 40.0), (21.0, 44.0), (11.0, 46.5), (0.0, 47.2),
)
KNOB_PROFILE_POINTS = 48  # samples of the smooth profile, poles included
KNOB_SECTIONS = 64  # around the axis
# The lever: a box along +x from inside the foot, centred on y = 0.
KNOB_LEVER_MM = (55.0, 12.0, 10.0)  # length (x), width (y), height (z)
KNOB_LEVER_START_MM = (8.0, 6.0)  # inner end's x (inside the foot), centre height above the base


def _revolve(profile_rz: Array, sections: int) -> tuple[Array, NDArray[np.int64]]:
    """Closed mesh of a lathe profile turned about z, one vertex at each pole.

    Parameters
    ----------
    profile_rz : (P, 2) float64
        (radius, height) in mm from the bottom pole (radius 0) to the top pole
        (radius 0), radii positive in between.
    sections : int
        Vertices per ring.

    Returns
    -------
    vertices : (2 + (P - 2) sections, 3) float64
        mm; the bottom pole first, then ring after ring, the top pole last.
    faces : (2 sections (P - 2), 3) int64
        Counter-clockwise seen from outside.
    """
    rings = profile_rz[1:-1]
    n_rings = len(rings)
    ang = 2 * np.pi * np.arange(sections) / sections
    ring_xyz = np.stack(
        [
            np.outer(rings[:, 0], np.cos(ang)),
            np.outer(rings[:, 0], np.sin(ang)),
            np.repeat(rings[:, 1:2], sections, axis=1),
        ],
        axis=2,
    ).reshape(-1, 3)
    verts = np.vstack([[0.0, 0.0, profile_rz[0, 1]], ring_xyz, [0.0, 0.0, profile_rz[-1, 1]]])
    top = len(verts) - 1

    def v(i: int, j: int) -> int:
        return 1 + i * sections + j % sections

    # Around the axis (counter-clockwise about z) crossed with up the profile points
    # outwards, so each triangle takes its ring neighbour before its profile neighbour.
    faces = [(0, v(0, j + 1), v(0, j)) for j in range(sections)]
    for i in range(n_rings - 1):
        for j in range(sections):
            a, b, c, d = v(i, j), v(i, j + 1), v(i + 1, j + 1), v(i + 1, j)
            faces += [(a, b, c), (a, c, d)]
    faces += [(v(n_rings - 1, j), v(n_rings - 1, j + 1), top) for j in range(sections)]
    return verts, np.array(faces, dtype=np.int64)


def _smooth_profile(points_rz: Array, n: int) -> Array:
    """(n, 2) samples of a cubic spline through the profile's points, mm.

    Chord-length parameter, with tangents across the axis at both poles so
    the turned surface has no point at a pole.
    """
    t = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(points_rz, axis=0), axis=1))]
    spline = CubicSpline(t, points_rz, bc_type=((1, [1.0, 0.0]), (1, [-1.0, 0.0])))
    out = np.asarray(spline(np.linspace(0.0, t[-1], n)), dtype=np.float64)
    out[[0, -1], 0] = 0.0
    return out


def knob() -> Shape:
    """A mushroom control knob turned about z, with a box lever sticking out sideways at its foot.

    The turned body alone would be symmetric under every rotation about z;
    the lever breaks that and no rotation maps the part onto itself. Origin at
    the bounding-box centre (the body's axis is 16 mm from it, towards -x).
    """
    profile = _smooth_profile(np.asarray(KNOB_PROFILE_MM, dtype=np.float64), KNOB_PROFILE_POINTS)
    body_v, body_f = _revolve(profile, KNOB_SECTIONS)
    lx, ly, lz = KNOB_LEVER_MM
    x0, zc = KNOB_LEVER_START_MM
    lever_lo = np.array([x0, -ly / 2, zc - lz / 2])
    lever_hi = lever_lo + np.array([lx, ly, lz])
    lo = np.minimum(body_v.min(axis=0), lever_lo)
    hi = np.maximum(body_v.max(axis=0), lever_hi)
    centre = (lo + hi) / 2
    lever_c = (lever_lo + lever_hi) / 2 - centre
    prims: list[Primitive] = [
        TriMesh(body_v - centre, body_f, smooth=True),
        Box((float(lever_c[0]), float(lever_c[1]), float(lever_c[2])), (lx, ly, lz)),
    ]
    return Shape("knob", tuple(prims))


# --- The shop set's parts: a hex bolt, a stepped shaft, a sheet-metal plate. ---------------
# Shapes common on a shop floor that no localizer setting was tuned on: a
# part whose only cue to its turn about its axis is a hexagon, a part with
# no such cue at all, and a thin flat part that seen edge-on is a line.
HEXBOLT_HEAD_ACROSS_FLATS_MM = 30.0
HEXBOLT_HEAD_HEIGHT_MM = 13.0
HEXBOLT_SHANK_MM = (10.0, 90.0)  # radius, length
#: (x start, x end, radius) of each section along the shaft's axis (x).
SHAFT_SECTIONS_MM = ((0.0, 32.0, 8.0), (32.0, 44.0, 16.0), (44.0, 100.0, 11.0),
                     (100.0, 122.0, 7.0))
PLATE_MM = (100.0, 60.0, 3.0)  # length (x), width (y), thickness (z)
#: (x, y, radius) of its holes: no turn or mirror of the plate's rectangle
#: maps them near each other (a pattern symmetric about the plate's centre
#: would leave the half turn about its normal to radii alone to tell).
PLATE_HOLES_MM = ((15.0, 45.0, 6.0), (50.0, 14.0, 5.0), (82.0, 29.0, 3.5))


def _turn_about_y(angle_deg: float) -> Array:
    """(4, 4) rotation by ``angle_deg`` about the object's y axis."""
    out = np.eye(4)
    out[:3, :3] = rotation_about_axis(np.array([0.0, 1.0, 0.0]), np.radians(angle_deg))
    return out


def hexbolt() -> Shape:
    """A hex bolt along object y: hexagonal head, plain round shank.

    Symmetric under the five turns of 60° multiples about y (the head's
    hexagon); the shank's end tells its ends apart. Origin at the
    bounding-box centre, on the axis.
    """
    r_head = HEXBOLT_HEAD_ACROSS_FLATS_MM / np.sqrt(3.0)  # circumradius
    angles = np.radians(60.0 * np.arange(6))
    # Counter-clockwise seen from -y in the prism's (x, z) profile.
    hexagon = np.c_[r_head * np.cos(angles), r_head * np.sin(angles)]
    radius, length = HEXBOLT_SHANK_MM
    total = HEXBOLT_HEAD_HEIGHT_MM + length
    head_v, head_f = _prism(hexagon, -total / 2, -total / 2 + HEXBOLT_HEAD_HEIGHT_MM)
    prims: list[Primitive] = [
        TriMesh(head_v, head_f),
        Cylinder((0.0, -total / 2 + HEXBOLT_HEAD_HEIGHT_MM, 0.0), (0.0, total / 2, 0.0), radius),
    ]
    return Shape("hexbolt", tuple(prims),
                 sym_discrete=tuple(_turn_about_y(60.0 * k) for k in range(1, 6)))


def shaft() -> Shape:
    """A stepped shaft along object x: a collar, a long journal and two ends of
    other radii.

    Symmetric under every turn about x, and under nothing else: the steps
    tell its ends apart. Origin at the bounding-box centre, on the axis.
    """
    centre = (SHAFT_SECTIONS_MM[0][0] + SHAFT_SECTIONS_MM[-1][1]) / 2
    prims: list[Primitive] = [Cylinder((x0 - centre, 0.0, 0.0), (x1 - centre, 0.0, 0.0), r)
                              for x0, x1, r in SHAFT_SECTIONS_MM]
    return Shape("shaft", tuple(prims),
                 sym_continuous=((np.array([1.0, 0.0, 0.0]), np.zeros(3)),))


def plate() -> Shape:
    """A thin sheet-metal plate with three round holes of different sizes.

    No symmetry (the holes are off-centre and of three sizes). Origin at
    the bounding-box centre.
    """
    L, W, T = PLATE_MM
    verts, faces = _plate_with_holes(L, W, T, PLATE_HOLES_MM)
    return Shape("plate", (TriMesh(verts - np.array([L / 2, W / 2, T / 2]), faces),))


# --- Clutter (paper §5.1: "rectangular clutter structures"). -------------------------------
def bar(length: float, width: float, height: float) -> Shape:
    """A rectangular bar along x."""
    return Shape("bar", (Box((0.0, 0.0, 0.0), (length, width, height)),))


def box(sx: float, sy: float, sz: float) -> Shape:
    """A box."""
    return Shape("box", (Box((0.0, 0.0, 0.0), (sx, sy, sz)),))


def frame(outer_x: float, outer_y: float, bar_width: float, thickness: float) -> Shape:
    """A rectangular frame of four bars in the xy plane."""
    hx, hy, w = outer_x / 2, outer_y / 2, bar_width
    return Shape(
        "frame",
        (
            Box((0.0, hy - w / 2, 0.0), (outer_x, w, thickness)),
            Box((0.0, -hy + w / 2, 0.0), (outer_x, w, thickness)),
            Box((hx - w / 2, 0.0, 0.0), (w, outer_y - 2 * w, thickness)),
            Box((-hx + w / 2, 0.0, 0.0), (w, outer_y - 2 * w, thickness)),
        ),
    )


def rod(length: float, radius: float) -> Shape:
    """A round rod along x."""
    return Shape("rod", (Cylinder((-length / 2, 0.0, 0.0), (length / 2, 0.0, 0.0), radius),))


# --- Conversions. --------------------------------------------------------------------------
def to_trimesh(shape: Shape) -> trimesh.Trimesh:
    """Tessellate a shape into one mesh (object frame, mm)."""
    parts = []
    for p in shape.primitives:
        if isinstance(p, Box):
            parts.append(
                trimesh.creation.box(
                    extents=p.size, transform=trimesh.transformations.translation_matrix(p.center)
                )
            )
        elif isinstance(p, Cylinder):
            parts.append(
                trimesh.creation.cylinder(
                    radius=p.radius, segment=np.array([p.p0, p.p1]), sections=CYLINDER_SECTIONS
                )
            )
        else:
            parts.append(trimesh.Trimesh(p.vertices, p.faces, process=False))
    mesh = trimesh.Trimesh(*_stack(parts), process=False)
    mesh.merge_vertices()
    return mesh


def _stack(parts: list[trimesh.Trimesh]) -> tuple[Array, NDArray[np.int64]]:
    verts, faces, offset = [], [], 0
    for m in parts:
        verts.append(np.asarray(m.vertices, dtype=np.float64))
        faces.append(np.asarray(m.faces, dtype=np.int64) + offset)
        offset += len(m.vertices)
    return np.vstack(verts), np.vstack(faces)


def diameter_mm(mesh: trimesh.Trimesh) -> float:
    """Largest distance between two vertices of the mesh (BOP's object diameter), mm."""
    hull = np.asarray(mesh.convex_hull.vertices, dtype=np.float64)
    d2 = np.sum((hull[:, None, :] - hull[None, :, :]) ** 2, axis=2)
    return float(np.sqrt(d2.max()))


def _vec(v: NDArray[np.floating] | tuple[float, ...]) -> str:
    return "<" + ", ".join(f"{float(c):.6f}" for c in v) + ">"


def _pov_primitive(p: Primitive) -> str:
    if isinstance(p, Box):
        c, s = np.asarray(p.center), np.asarray(p.size) / 2
        return f"box {{ {_vec(c - s)}, {_vec(c + s)} }}"
    if isinstance(p, Cylinder):
        return f"cylinder {{ {_vec(p.p0)}, {_vec(p.p1)}, {p.radius:.6f} }}"
    out = io.StringIO()
    out.write(f"mesh2 {{\n vertex_vectors {{ {len(p.vertices)},\n")
    out.write(",\n".join(_vec(v) for v in p.vertices))
    out.write("\n }\n")
    if p.smooth:
        normals = trimesh.Trimesh(p.vertices, p.faces, process=False).vertex_normals
        out.write(f" normal_vectors {{ {len(normals)},\n")
        out.write(",\n".join(_vec(n) for n in normals))
        out.write("\n }\n")
    out.write(f" face_indices {{ {len(p.faces)},\n")
    out.write(",\n".join(f"<{a}, {b}, {c}>" for a, b, c in p.faces))
    out.write("\n }\n}")
    return out.getvalue()


def to_pov(shape: Shape, texture: str, transform: str) -> str:
    """POV-Ray SDL of a shape as a ``union`` with a texture block and a transform.

    Parameters
    ----------
    shape : Shape
    texture : str
        SDL placed inside the object, e.g. ``"texture { pigment { rgb 1 } }"``.
    transform : str
        SDL transform applied after the texture (e.g. a ``matrix <...>``).
    """
    body = "\n".join(_pov_primitive(p) for p in shape.primitives)
    if len(shape.primitives) == 1:
        # A union of one primitive makes POV-Ray warn; wrap it as a merge-free object.
        return f"object {{ {body}\n {texture}\n {transform}\n}}"
    return f"union {{\n{body}\n {texture}\n {transform}\n}}"


ASSET_FILES = {
    "barbell": "barbell.stl",
    "bracket": "bracket.stl",
    "freeform": "freeform.ply",
    "tee": "tee.stl",
    "clamp": "clamp.stl",
    "knob": "knob.ply",
    "hexbolt": "hexbolt.stl",
    "shaft": "shaft.stl",
    "plate": "plate.stl",
}
SHAPES = {
    "barbell": barbell,
    "bracket": bracket,
    "freeform": freeform,
    "tee": tee,
    "clamp": clamp,
    "knob": knob,
    "hexbolt": hexbolt,
    "shaft": shaft,
    "plate": plate,
}


def asset_path(name: str) -> Path:
    """Path of the committed mesh file of a benchmark object."""
    return ASSETS_DIR / ASSET_FILES[name]


def write_assets(directory: Path = ASSETS_DIR) -> list[Path]:
    """(Re)write the mesh files of the benchmark objects from their definitions."""
    directory.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, make in SHAPES.items():
        path = directory / ASSET_FILES[name]
        to_trimesh(make()).export(path)
        paths.append(path)
    return paths
