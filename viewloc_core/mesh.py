"""Loading and checking object meshes (STL, OBJ, PLY, OFF, GLB, glTF).

Every mesh leaving this module is one ``trimesh.Trimesh`` in millimetres with
finite vertices, at least one face of non-zero area and a sane size. Scenes
(GLB, glTF, multi-object OBJ) are flattened with their node transforms applied
and their colours kept (vertex colours, face colours or a texture with UVs), so
that LM-O's vertex-coloured PLY models render in colour.

Parsing is done from memory (``trimesh.load`` on a ``BytesIO``): nothing is
written, and nothing in the file is executed. A file given by path may pull in
sibling assets it names (an OBJ's MTL and textures, a glTF's buffers) through
trimesh's ``FilePathResolver``, which refuses paths outside the file's folder;
bytes have no resolver, so their external references are simply missing.
"""

from __future__ import annotations

import io
import math
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from numba import njit
from numpy.typing import NDArray
from scipy.spatial import ConvexHull, QhullError

from viewloc_core.errors import InvalidInputError, InvalidMeshError
from viewloc_core.view_sphere import spiral_directions

#: Accepted ``file_type`` values (lower case, no dot).
MESH_TYPES: frozenset[str] = frozenset({"stl", "obj", "ply", "off", "glb", "gltf"})

#: Length of one unit in millimetres.
UNIT_TO_MM: dict[str, float] = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}

#: Largest accepted face count; bigger meshes are not industrial parts but scans
#: that would make every render and contour extraction slow.
MAX_FACES = 2_000_000

#: Largest accepted diameter in mm (after unit conversion).
MAX_DIAMETER_MM = 100_000.0

#: Smallest accepted diameter in mm (after unit conversion). A part this
#: small is nearly always a mesh drawn in metres or inches and uploaded as
#: millimetres (a 50 mm part in metres is 0.05 "mm" across): learned as it
#: is, every pose would come out a thousand times too near the camera. The
#: smallest parts machine vision places (01005 chips) are 0.4 mm long.
MIN_DIAMETER_MM = 0.1

#: Farthest a mesh's vertex may lie from its origin, in diameters of the
#: part. The model keeps its vertices in float32 (7 digits): a part this far
#: out keeps them to about a thousandth of its size. A triangle drawn at
#: 1e39 mm overflowed float32 to infinity, and every localization of it,
#: and every all-object one beside it, answered 500; a box moved 1e30 mm
#: away lost its size to float64 rounding (45.8 mm across came out 22.4).
MAX_ORIGIN_DISTANCE_DIAMETERS = 10_000.0

_FIELD = "mesh"


def load_mesh(
    data: bytes | str | Path,
    file_type: str | None = None,
    units: str = "mm",
) -> trimesh.Trimesh:
    """Parse a mesh file into one checked triangle mesh in millimetres.

    Parameters
    ----------
    data : bytes, str or Path
        The file contents (bytes), or a path to the file (str or Path).
    file_type : str or None
        One of :data:`MESH_TYPES` (case-insensitive, a leading dot is
        ignored). ``None`` infers it from the path suffix; bytes need it.
    units : str
        Unit of the file's coordinates: ``"mm"``, ``"cm"``, ``"m"`` or ``"in"``.

    Returns
    -------
    trimesh.Trimesh
        Vertices (V, 3) float64 in mm, faces (F, 3) int64, duplicate vertices
        merged and repeated faces dropped, colours (``visual``) kept where the
        file has them.

    Raises
    ------
    InvalidInputError
        ``field="units"`` for an unknown unit.
    InvalidMeshError
        ``field="mesh"`` when the type is unknown, the bytes do not parse, or
        the mesh has no faces, non-finite vertices, zero extent, more than
        :data:`MAX_FACES` faces, a diameter above :data:`MAX_DIAMETER_MM`
        or below :data:`MIN_DIAMETER_MM`, or vertices farther from the origin
        than :data:`MAX_ORIGIN_DISTANCE_DIAMETERS` diameters.
    """
    if units not in UNIT_TO_MM:
        raise InvalidInputError(
            f"units must be one of {sorted(UNIT_TO_MM)}, got {units!r}", "units"
        )
    kind = _file_type(data, file_type)
    loaded = _parse(data, kind)
    mesh = _as_single_mesh(loaded, kind)
    _check_raw(mesh, kind)
    _check_not_huge(mesh, UNIT_TO_MM[units])
    mesh.merge_vertices()
    _drop_repeated_faces(mesh)
    scale = UNIT_TO_MM[units]
    if scale != 1.0:
        mesh.apply_scale(scale)
    _check_size(mesh)
    return mesh


def mesh_diameter_mm(mesh: trimesh.Trimesh) -> float:
    """Largest distance between two vertices, in the mesh's units (mm).

    Only the convex hull's vertices can realise the maximum, so the search
    (:func:`_max_pairwise_distance`) runs on those: a few hundred to a few
    thousand for a typical part, nearly all of a finely tessellated round
    one's. Qhull joggles the points (``QJ``): without, it took minutes over a
    cylinder of 20,000 sections (its caps' points all on two circles, 1 s
    with), and trimesh's hull (triangulated, ``Qt``) as long.
    """
    pts = np.asarray(mesh.vertices, dtype=np.float64)
    if len(pts) < 2:
        return 0.0
    try:
        hull_pts = pts[ConvexHull(pts, qhull_options="QJ").vertices]
    except (QhullError, ValueError):
        # Qhull fails on too few points; the plain vertex set is then the
        # fallback (such meshes are small).
        hull_pts = np.unique(pts, axis=0)
    return _max_pairwise_distance(hull_pts)


def mesh_reach_mm(mesh: trimesh.Trimesh) -> float:
    """How far the mesh reaches from its origin: its farthest vertex's
    distance, in the mesh's units (mm)."""
    pts = np.asarray(mesh.vertices, dtype=np.float64)
    return float(np.linalg.norm(pts, axis=1).max()) if len(pts) else 0.0


def is_closed_outward(mesh: trimesh.Trimesh) -> bool:
    """Whether ``mesh`` is a closed surface wound consistently outward.

    Only such a mesh never shows the back of a face, so the renderer draws
    it with one winding (:func:`viewloc_core.render.prepare`). Seams of UVs
    or colours split vertices; closedness is about positions, so the mesh
    is judged welded.
    """
    return _closed_outward(_welded(mesh))


def outward_wound(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """``mesh`` with the faces of a closed surface wound consistently outward.

    Scanned meshes are often watertight with a few faces wound the wrong way
    (LM-O: the watering can 7 of 45,666, the egg box 26 of 36,942). The
    renderer then takes the surface for an open one and draws every
    triangle twice, both windings, and the contour model reads those faces'
    normals pointing inward (front and back swapped along their edges).
    Reversing the few faces, as a closed surface allows, fixes both.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The part (any units); its vertices, visuals and face order are kept.

    Returns
    -------
    trimesh.Trimesh
        A copy with the offending faces' corners reversed, or ``mesh``
        itself when it is not watertight (nothing says which side is out),
        already wound consistently outward, or cannot be made so.
    """
    welded = _welded(mesh)
    if (not welded.is_watertight or len(welded.faces) != len(mesh.faces)
            or _closed_outward(welded)):
        return mesh
    before = np.array(welded.faces)
    trimesh.repair.fix_winding(welded)
    trimesh.repair.fix_inversion(welded)
    if not _closed_outward(welded):
        return mesh
    # Welding keeps the faces' order: a row that is no rotation of its
    # former self was reversed.
    after = np.asarray(welded.faces)
    kept = np.any([np.all(np.roll(before, k, axis=1) == after, axis=1) for k in range(3)],
                  axis=0)
    wound = mesh.copy()
    faces = np.array(wound.faces)
    faces[~kept] = faces[~kept][:, ::-1]
    wound.faces = faces
    return wound


def _welded(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """``mesh``'s faces over its vertices merged by position (no visuals)."""
    return trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), process=True)


def _closed_outward(welded: trimesh.Trimesh) -> bool:
    """Whether a welded mesh is watertight and wound consistently outward."""
    return bool(welded.is_watertight and welded.is_winding_consistent and welded.volume > 0)


def mesh_has_colour(mesh: trimesh.Trimesh) -> bool:
    """True when the mesh carries its own colours (vertex, face or texture)."""
    visual = mesh.visual
    if visual is None or not visual.defined:
        return False
    return visual.kind in ("vertex", "face", "texture")


def mesh_vertex_colours(mesh: trimesh.Trimesh) -> NDArray[np.uint8] | None:
    """Per-vertex RGB colours, or ``None`` when the mesh has none.

    Face colours are averaged onto vertices and textures sampled at the
    vertices' UVs (trimesh's ``to_color``), so the result is coarser than what
    the renderer draws for textured meshes.

    Returns
    -------
    (V, 3) uint8 or None
    """
    if not mesh_has_colour(mesh):
        return None
    visual: Any = mesh.visual
    if visual.kind == "texture":
        visual = visual.to_color()
    colours = np.asarray(visual.vertex_colors)
    if colours.ndim != 2 or len(colours) != len(mesh.vertices):
        return None
    return np.ascontiguousarray(colours[:, :3], dtype=np.uint8)


def _file_type(data: bytes | str | Path, file_type: str | None) -> str:
    if file_type is None:
        if isinstance(data, (str, Path)):
            file_type = Path(data).suffix
        else:
            raise InvalidMeshError("file_type is required when the mesh is given as bytes", _FIELD)
    kind = file_type.lower().lstrip(".")
    if kind not in MESH_TYPES:
        raise InvalidMeshError(
            f"unknown mesh type {file_type!r}; expected one of {sorted(MESH_TYPES)}", _FIELD
        )
    return kind


def _parse(data: bytes | str | Path, kind: str) -> object:
    resolver: trimesh.resolvers.Resolver | None = None
    if isinstance(data, (str, Path)):
        path = Path(data)
        try:
            raw = path.read_bytes()
        except OSError as exc:
            raise InvalidMeshError(f"cannot read mesh file {str(path)!r}: {exc}", _FIELD) from exc
        resolver = trimesh.resolvers.FilePathResolver(str(path.resolve()))
    elif isinstance(data, (bytes, bytearray, memoryview)):
        raw = bytes(data)
    else:
        raise InvalidMeshError(
            f"mesh data must be bytes or a path, got {type(data).__name__}", _FIELD
        )
    if not raw:
        raise InvalidMeshError("mesh file is empty", _FIELD)
    try:
        # process=False: finiteness is checked on the file's own vertices,
        # before trimesh would silently drop NaN vertices and their faces.
        return trimesh.load(io.BytesIO(raw), file_type=kind, resolver=resolver, process=False)
    except Exception as exc:
        # Each trimesh parser fails in its own way on bad input (ValueError,
        # IndexError, KeyError, struct.error, ...): all mean "unparseable".
        raise InvalidMeshError(
            f"cannot parse the data as {kind.upper()}: {type(exc).__name__}: {exc}", _FIELD
        ) from exc


def _as_single_mesh(loaded: object, kind: str) -> trimesh.Trimesh:
    if isinstance(loaded, trimesh.Scene):
        meshes = [g for g in loaded.geometry.values() if isinstance(g, trimesh.Trimesh)]
        if not meshes:
            raise InvalidMeshError(
                f"the {kind.upper()} data has no faces (no triangle mesh in it)", _FIELD
            )
        try:
            # to_mesh applies the scene graph's transforms and concatenates
            # the visuals (textures are packed, mixed kinds become colours).
            return loaded.to_mesh()
        except Exception as exc:
            raise InvalidMeshError(
                f"cannot flatten the {kind.upper()} scene into one mesh: {exc}", _FIELD
            ) from exc
    if isinstance(loaded, trimesh.Trimesh):
        return loaded
    raise InvalidMeshError(
        f"the {kind.upper()} data has no faces (it parsed as a {type(loaded).__name__})", _FIELD
    )


def _check_raw(mesh: trimesh.Trimesh, kind: str) -> None:
    faces = np.asarray(mesh.faces)
    vertices = np.asarray(mesh.vertices)
    if faces.ndim != 2 or len(faces) == 0:
        raise InvalidMeshError(f"the {kind.upper()} mesh has no faces", _FIELD)
    if len(faces) > MAX_FACES:
        raise InvalidMeshError(
            f"the mesh has {len(faces)} faces, more than the limit of {MAX_FACES}", _FIELD
        )
    if not np.all(np.isfinite(vertices)):
        bad = int(np.count_nonzero(~np.all(np.isfinite(vertices), axis=1)))
        raise InvalidMeshError(f"the mesh has {bad} vertices with NaN or infinite coordinates",
                               _FIELD)
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise InvalidMeshError("the mesh has faces referring to missing vertices", _FIELD)


def _check_not_huge(mesh: trimesh.Trimesh, to_mm: float) -> None:
    """Refuse, before its vertices are merged, a mesh larger than
    :func:`_check_size` allows or farther from its origin than it allows
    of any part: merging rounds the coordinates to integers, which
    overflow beyond about 1e10 (a box scaled by 1e10 was called degenerate)."""
    vertices = np.asarray(mesh.vertices, dtype=np.float64) * to_mm
    extent = float(np.max(vertices.max(axis=0) - vertices.min(axis=0)))
    if extent > MAX_DIAMETER_MM:
        raise InvalidMeshError(
            f"the mesh is at least {extent / 1000.0:.3g} m across, more than the limit of "
            f"{MAX_DIAMETER_MM / 1000.0:.0f} m; check the units", _FIELD)
    farthest = float(np.max(np.abs(vertices)))
    if farthest > MAX_ORIGIN_DISTANCE_DIAMETERS * MAX_DIAMETER_MM:
        raise InvalidMeshError(
            f"the mesh lies {farthest:.3g} mm from its origin: its coordinates cannot be "
            "kept precisely; move the part near its origin", _FIELD)


def _drop_repeated_faces(mesh: trimesh.Trimesh) -> None:
    """Drop the faces that repeat an earlier one with the same winding, in
    place (a face and its reverse both stay: a surface drawn double-sided).

    An OBJ of two faces written a million times over was accepted, then its
    learning failed: simplified to the face budget, nothing was left.
    """
    faces = np.asarray(mesh.faces)
    # Each triangle turned to start at its smallest index: the same face
    # with the same winding gives the same row.
    first = np.argmin(faces, axis=1)[:, None]
    canonical = np.take_along_axis(faces, (first + np.arange(3)[None, :]) % 3, axis=1)
    _, kept = np.unique(canonical, axis=0, return_index=True)
    if len(kept) < len(faces):
        keep = np.zeros(len(faces), bool)
        keep[kept] = True
        mesh.update_faces(keep)


def _check_size(mesh: trimesh.Trimesh) -> None:
    extent = float(np.max(mesh.extents))
    if not extent > 0.0 or not float(mesh.area) > 0.0:
        raise InvalidMeshError("the mesh has zero extent (all faces degenerate)", _FIELD)
    diameter = mesh_diameter_mm(mesh)
    if diameter > MAX_DIAMETER_MM:
        raise InvalidMeshError(
            f"the mesh is {diameter / 1000.0:.1f} m across, more than the limit of "
            f"{MAX_DIAMETER_MM / 1000.0:.0f} m; check the units",
            _FIELD,
        )
    if diameter < MIN_DIAMETER_MM:
        raise InvalidMeshError(
            f"the mesh is {diameter:.3g} mm across, less than the limit of "
            f"{MIN_DIAMETER_MM} mm; check the units (a mesh in metres needs units \"m\")",
            _FIELD,
        )
    farthest = mesh_reach_mm(mesh)
    if farthest > MAX_ORIGIN_DISTANCE_DIAMETERS * diameter:
        raise InvalidMeshError(
            f"the mesh lies up to {farthest:.3g} mm from its origin, more than "
            f"{MAX_ORIGIN_DISTANCE_DIAMETERS:g} times its size ({diameter:.3g} mm): its "
            "coordinates cannot be kept precisely; move the part near its origin",
            _FIELD,
        )


#: Most points that can reach farther than the first estimate whose pairs
#: :func:`_max_pairwise_distance` compares all (2e8 pairs, about 0.2 s).
EXACT_PAIRS_MAX_POINTS = 20_000

#: Directions whose extreme points give the diameter's first estimate in
#: :func:`_max_pairwise_distance`: every direction lies within
#: :data:`DIAMETER_DIRECTIONS_MAX_ANGLE_DEG` of one of them.
DIAMETER_DIRECTIONS = 2000
DIAMETER_DIRECTIONS_MAX_ANGLE_DEG = 3.5

#: Points projected onto the directions at a time (a float32 block of
#: DIAMETER_DIRECTIONS x this, 80 MB).
DIAMETER_BLOCK_POINTS = 10_000


def _max_pairwise_distance(pts: NDArray[np.float64],
                           exact_max_points: int = EXACT_PAIRS_MAX_POINTS) -> float:
    """The largest distance between two of ``pts`` ((N, 3), mm).

    Every pair is compared for up to ``exact_max_points`` points. Beyond,
    the extreme points along :data:`DIAMETER_DIRECTIONS` directions give a
    first, shorter or equal, distance, and only the points that can reach
    farther than it are compared pair by pair: a point p is no farther
    from any other than max over the directions u of (the farthest point's
    reach along u minus p's) / cos(the directions' spacing). Exact where
    those are few (the rims of a can, the corners of a machined part), else
    (a finely tessellated ball: every point reaches as far) the extreme
    points' distance, at least cos 3.5° = 0.998 of the diameter (more than
    ``exact_max_points`` of them reach that far). Every pair of a round
    part's 40,000 hull vertices took minutes in numpy.
    """
    if len(pts) <= exact_max_points:
        return _all_pairs_max_distance(pts)
    directions = spiral_directions(DIAMETER_DIRECTIONS).astype(np.float32)
    rows = np.arange(len(directions))
    top = np.full(len(directions), -np.inf, np.float32)
    bottom = np.full(len(directions), np.inf, np.float32)
    top_at = np.zeros(len(directions), np.int64)
    bottom_at = np.zeros(len(directions), np.int64)
    centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
    blocks = range(0, len(pts), DIAMETER_BLOCK_POINTS)

    def along(start: int) -> NDArray[np.float32]:
        block = (pts[start:start + DIAMETER_BLOCK_POINTS] - centre).astype(np.float32)
        return np.asarray(directions @ block.T, np.float32)

    for start in blocks:
        projected = along(start)
        hi, lo = projected.argmax(axis=1), projected.argmin(axis=1)
        higher = projected[rows, hi] > top
        lower = projected[rows, lo] < bottom
        top[higher], top_at[higher] = projected[rows, hi][higher], start + hi[higher]
        bottom[lower], bottom_at[lower] = projected[rows, lo][lower], start + lo[lower]
    first = _all_pairs_max_distance(pts[np.unique(np.concatenate([top_at, bottom_at]))])
    spacing = math.cos(math.radians(DIAMETER_DIRECTIONS_MAX_ANGLE_DEG))
    reach = np.concatenate([
        np.maximum(top[:, None] - projected, projected - bottom[:, None]).max(axis=0)
        for projected in map(along, blocks)]) / spacing
    # float32 projections: a margin of a millionth keeps every point that
    # could reach farther.
    candidates = pts[reach > first * (1.0 - 1e-6)]
    if len(candidates) <= exact_max_points:
        return max(first, _all_pairs_max_distance(candidates))
    return first


def _all_pairs_max_distance(pts: NDArray[np.float64]) -> float:
    """The largest distance between two of ``pts`` ((N, 3)), every pair compared."""
    if len(pts) < 2:
        return 0.0
    i, j = _farthest_pair(np.ascontiguousarray(pts, dtype=np.float64))
    # Measured as numpy's einsum measures it (by which diameters were taken
    # before the compiled search): the sum of squares rounds differently by
    # an ulp now and then, and models learned from the same mesh stay the same.
    diff = (pts[i] - pts[j])[None, None, :]
    return float(np.sqrt(np.einsum("ijk,ijk->ij", diff, diff))[0, 0])


@njit(cache=True, nogil=True)
def _farthest_pair(pts: NDArray[np.float64]) -> tuple[int, int]:  # pragma: no cover - compiled
    """Indices of the two of ``pts`` ((N, 3), N >= 2) farthest apart."""
    best, best_i, best_j = -1.0, 0, 1
    for i in range(len(pts)):
        x, y, z = pts[i, 0], pts[i, 1], pts[i, 2]
        for j in range(i + 1, len(pts)):
            dx, dy, dz = pts[j, 0] - x, pts[j, 1] - y, pts[j, 2] - z
            squared = dx * dx + dy * dy + dz * dz
            if squared > best:
                best, best_i, best_j = squared, i, j
    return best_i, best_j
