"""Rotational symmetries of a rigid part and a canonical pose among equivalents.

A symmetry is a rigid transform ``S`` of the object frame that maps the
surface onto itself, so the poses ``T`` and ``T ∘ S`` look identical
(``x_cam = R (S_R x + S_t) + t``). Representation as in the BOP toolkit's
``models_info.json``: a finite set of discrete transforms, plus at most one
continuous axis (with a point on it) about which every angle is a symmetry.
Discrete transforms here always include the identity first; for an object with
a continuous axis they are the identity and, when present, one 180° flip about
an axis perpendicular to it (every other discrete symmetry is then a product of
these with a rotation about the axis).

Detection (:func:`detect_symmetries`) tests candidate rotations about
candidate axes through the surface centroid (which every symmetry fixes):
principal axes of the surface's second moment, the coordinate axes and the
normals of the largest planar facets. A candidate is accepted when the rotated
surface samples lie on the original surface: the symmetric mean nearest-
neighbour distance (and its 99th percentile, so a small asymmetric feature such
as an off-centre hole breaks symmetry) exceeds the sampling noise floor by less
than ``tol_frac`` of the diameter, and the farthest hundredth of the samples
lies within half of that (so that a few holes in a thin plate, or a bolt
head's corners, break it too). An axis that passes the continuous test at every test angle while
its farthest hundredth shows the turn is n-fold, n the order whose step brings
that hundredth back. Accepted generators are closed into a group.
A sphere has no BOP representation: it is reported as one continuous axis
plus a flip.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import trimesh
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from viewloc_core.errors import InvalidInputError, InvalidMeshError
from viewloc_core.pose import (
    Pose,
    orthonormalize,
    reorthonormalized,
    rotation_about_axis,
    rotation_angle_deg,
)

Array = NDArray[np.float64]

#: Angles (deg) that must all pass for an axis to count as continuous; none of
#: them is a multiple of 360/n for n <= 8, so a discrete n-fold axis fails.
_CONTINUOUS_TEST_DEG = (23.0, 67.0, 131.0)
_DISCRETE_ORDERS = (8, 6, 5, 4, 3, 2)
_MAX_GROUP = 120
#: No finite rotation group of a rigid part (orders <= 8) has a smaller angle.
_MIN_GROUP_ANGLE_DEG = 30.0
#: A transform whose worst-fitting hundredth of the surface
#: (:meth:`_SurfaceTest.top_gap_mm`) lies at least this share of the
#: tolerance off it shows itself: a small feature (a hole, a corner) does not
#: map onto itself, though the mean and 99th-percentile tests pass. True
#: symmetries of the bench's parts and of boxes and prisms lie within 0.07
#: (sampling noise); a thin plate's three asymmetric holes put its half turns
#: at 1.5-1.8, a hex bolt's head its eighth turn at 0.6, LM-O's egg box and
#: glue bottle (which BOP declares twofold, by eye) their half turns at
#: 2.4 and 2.9. An axis that passes the continuous test is n-fold instead
#: when its test angles lie this far off ...
_VISIBLE_TURN_GAP = 0.5
#: ... while turned by 360°/n it lies at most this share of that off (the
#: feature comes back), and turned by half that step at least this share
#: (it does not come back sooner: a twelvefold part is not sixfold).
_ORDER_FIT_SHARE = 0.25
_HALF_STEP_GAP_SHARE = 0.5
#: The share of the probes that :meth:`_SurfaceTest.top_gap_mm` averages.
_TOP_SHARE = 0.01


@dataclass(frozen=True, slots=True)
class Symmetries:
    """Symmetry group of an object (object frame, mm).

    Attributes
    ----------
    discrete : (K, 4, 4) float64
        Discrete symmetry transforms; ``discrete[0]`` is the identity.
    continuous_axis : (3,) float64 or None
        Unit axis of a continuous rotational symmetry, object frame.
    continuous_offset : (3,) float64 or None
        A point on that axis, mm.
    """

    discrete: Array
    continuous_axis: Array | None = None
    continuous_offset: Array | None = None

    def __post_init__(self) -> None:
        d = np.asarray(self.discrete, dtype=np.float64)
        if d.ndim != 3 or d.shape[1:] != (4, 4) or len(d) == 0:
            raise InvalidInputError("discrete must be (K, 4, 4) with K >= 1", "symmetries")
        if not np.allclose(d[0], np.eye(4), atol=1e-9):
            raise InvalidInputError("discrete[0] must be the identity", "symmetries")
        object.__setattr__(self, "discrete", d)
        if (self.continuous_axis is None) != (self.continuous_offset is None):
            raise InvalidInputError("continuous axis and offset go together", "symmetries")
        if self.continuous_axis is not None and self.continuous_offset is not None:
            a = np.asarray(self.continuous_axis, dtype=np.float64).reshape(3)
            n = float(np.linalg.norm(a))
            if not math.isfinite(n) or n < 1e-9:
                raise InvalidInputError("continuous axis must be a non-zero vector", "symmetries")
            object.__setattr__(self, "continuous_axis", a / n)
            o = np.asarray(self.continuous_offset, dtype=np.float64).reshape(3)
            object.__setattr__(self, "continuous_offset", o)

    @classmethod
    def none(cls) -> Symmetries:
        """No symmetry: only the identity."""
        return cls(np.eye(4)[None])

    @property
    def is_continuous(self) -> bool:
        """True when there is a continuous axis."""
        return self.continuous_axis is not None


def _rotation_about(axis: Array, angle_rad: float, point: Array) -> Array:
    """(4, 4) rotation by ``angle_rad`` about the line through ``point`` along ``axis``."""
    R = rotation_about_axis(axis / np.linalg.norm(axis), angle_rad)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = point - R @ point
    return T


#: Two rotations closer than this are the same symmetry.
_SAME_ROTATION_DEG = 0.5
#: The same bound on the Frobenius distance of two rotation matrices, which
#: is 2·sqrt(2)·sin(angle / 2) for an angle between them.
_SAME_ROTATION_FROBENIUS = 2.0 * math.sqrt(2.0) * math.sin(math.radians(_SAME_ROTATION_DEG) / 2)


def _same_transform(A: Array, B: Array, diameter: float) -> bool:
    return (
        rotation_angle_deg(A[:3, :3], B[:3, :3]) < _SAME_ROTATION_DEG
        and float(np.linalg.norm(A[:3, 3] - B[:3, 3])) < 1e-3 * diameter
    )


def _close_group(generators: list[Array], diameter: float,
                 limit: int = _MAX_GROUP) -> list[Array]:
    """All products of the generators (finite group), identity first.

    Stops as soon as the group reaches ``limit`` elements (then it is no
    finite group of a rigid part, or a larger one than wanted). Each product
    is compared with the whole group at once (the rotations' Frobenius
    distance, equivalent to :func:`_same_transform`'s angle): a declared
    list of 240 transforms a little off a group took over ten minutes of
    one-by-one comparisons.
    """
    rotations = np.empty((limit, 3, 3))
    translations = np.empty((limit, 3))
    rotations[0], translations[0] = np.eye(3), 0.0
    size = 1
    tol_mm = 1e-3 * diameter

    def known(T: Array) -> bool:
        rot_gap = np.linalg.norm((rotations[:size] - T[:3, :3]).reshape(size, 9), axis=1)
        gap_mm = np.linalg.norm(translations[:size] - T[:3, 3], axis=1)
        return bool(np.any((rot_gap < _SAME_ROTATION_FROBENIUS) & (gap_mm < tol_mm)))

    # Generators that are the same symmetry as one before them add nothing.
    distinct: list[Array] = []
    for h in generators:
        if not any(_same_transform(h, k, diameter) for k in distinct):
            distinct.append(h)
    generators = distinct
    group = [np.eye(4)]
    frontier = [np.eye(4)]
    while frontier:
        new = []
        for g in frontier:
            for h in generators:
                prod = h @ g
                prod[:3, :3] = orthonormalize(prod[:3, :3])
                if known(prod):
                    continue
                rotations[size], translations[size] = prod[:3, :3], prod[:3, 3]
                size += 1
                group.append(prod)
                new.append(prod)
                if size >= limit:
                    return group
        frontier = new
    return group


class _SurfaceTest:
    """Checks whether a rigid transform maps sampled surface points onto the surface."""

    def __init__(self, mesh: trimesh.Trimesh, n_points: int, tol_mm: float, seed: int) -> None:
        probe, _ = trimesh.sample.sample_surface(mesh, n_points, seed=seed)
        ref, _ = trimesh.sample.sample_surface(mesh, 5 * n_points, seed=seed + 1)
        self.probe = np.asarray(probe, dtype=np.float64)
        self.tree = cKDTree(np.asarray(ref, dtype=np.float64))
        base, _ = self.tree.query(self.probe)
        # Sampling alone leaves probe points this far from the reference set.
        self.base_mean = float(base.mean())
        self.base_p99 = float(np.percentile(base, 99))
        # The probes' own farthest share, as top_gap_mm measures the moved ones.
        self.base_top = _top_mean(base)
        self.tol = tol_mm

    def _distances(self, pts: Array) -> Array:
        # Far-off points (a wrong rotation) would make the tree search every
        # branch; capping the search keeps a rejection as cheap as an acceptance.
        cap = self.base_p99 + 10.0 * self.tol
        d, _ = self.tree.query(pts, eps=0.1, distance_upper_bound=cap)
        return np.minimum(d, cap)

    def _both_ways(self, T: Array) -> Array:
        """Distances of the probes moved by ``T`` and by its inverse from the surface."""
        T_inv = np.linalg.inv(T)
        return np.concatenate([
            self._distances(self.probe @ T[:3, :3].T + T[:3, 3]),
            self._distances(self.probe @ T_inv[:3, :3].T + T_inv[:3, 3]),
        ])

    def mean_gap_mm(self, T: Array) -> float:
        """Mean distance of the moved probes from the surface beyond what
        sampling alone leaves, mm."""
        return float(self._both_ways(T).mean()) - self.base_mean

    def top_gap_mm(self, T: Array) -> float:
        """Mean distance of the farthest hundredth (``_TOP_SHARE``) of the
        probes moved by ``T`` (and its inverse) from the surface, beyond the
        same of the unmoved probes, mm: how far a small feature the transform
        does not map onto itself (a bolt head's corners) lies off."""
        return _top_mean(self._both_ways(T)) - self.base_top

    def maps(self, T: Array) -> bool:
        """Whether ``T`` is a symmetry: it passes :meth:`accepts` and no
        small feature shows it (see ``_VISIBLE_TURN_GAP``)."""
        d = self._close_distances(T)
        return d is not None and _top_mean(d) - self.base_top < _VISIBLE_TURN_GAP * self.tol

    def accepts(self, T: Array) -> bool:
        return self._close_distances(T) is not None

    def _close_distances(self, T: Array) -> Array | None:
        """The distances of :meth:`_both_ways` when their mean and 99th
        percentile are within tolerance, else None."""
        quick = self.probe[: max(50, len(self.probe) // 10)]
        d_quick = self._distances(quick @ T[:3, :3].T + T[:3, 3])
        if d_quick.mean() - self.base_mean > 3.0 * self.tol:
            return None
        d = self._both_ways(T)
        if (d.mean() - self.base_mean < self.tol
                and np.percentile(d, 99) - self.base_p99 < 3.0 * self.tol):
            return d
        return None


def _top_mean(distances: Array) -> float:
    """Mean of the largest hundredth (``_TOP_SHARE``, at least one) of ``distances``."""
    k = max(1, int(len(distances) * _TOP_SHARE))
    return float(np.partition(distances, len(distances) - k)[-k:].mean())


def surface_centroid(mesh: trimesh.Trimesh) -> Array:
    """The area-weighted centroid of the surface, (3,) mm: fixed by every
    symmetry of the surface (and every near one this module finds)."""
    return np.asarray(mesh.triangles_center.T @ mesh.area_faces / mesh.area, dtype=np.float64)


def surface_second_moment(mesh: trimesh.Trimesh, centre: Array) -> Array:
    """The surface's area-weighted second moment about ``centre``, (3, 3) mm².

    Exact per triangle (A/12 (Σ v vᵀ + s sᵀ), s the vertex sum, vertices
    relative to ``centre``), so that the principal axes of a symmetric part
    are its symmetry axes to rounding.
    """
    tri = np.asarray(mesh.triangles, dtype=np.float64) - centre
    vsum = tri.sum(axis=1)
    moment = np.einsum("f,fij->ij", np.asarray(mesh.area_faces) / 12.0,
                       np.einsum("fvi,fvj->fij", tri, tri) + np.einsum("fi,fj->fij", vsum, vsum))
    return np.asarray(moment / float(mesh.area), dtype=np.float64)


def _centroid_and_diagonal(mesh: trimesh.Trimesh) -> tuple[Array, float]:
    """The surface centroid ((3,) mm) and the bounding-box diagonal (mm), the
    size tolerances are relative to."""
    return surface_centroid(mesh), float(np.linalg.norm(mesh.bounds[1] - mesh.bounds[0]))


def _candidate_axes(mesh: trimesh.Trimesh, centre: Array) -> tuple[list[Array], Array, Array]:
    """Candidate axes (unit, deduplicated), principal axes and their eigenvalues."""
    evals, evecs = np.linalg.eigh(surface_second_moment(mesh, centre))
    axes: list[Array] = []

    def add(vec: NDArray[np.floating]) -> None:
        v: Array = np.asarray(vec, dtype=np.float64)
        n = float(np.linalg.norm(v))
        if n < 1e-9:
            return
        v = v / n
        if all(abs(float(np.dot(v, a))) < math.cos(math.radians(5.0)) for a in axes):
            axes.append(v)

    # A principal axis is a symmetry candidate only when its eigenvalue is
    # simple; inside a degenerate eigenspace the eigenvectors are arbitrary.
    rel = evals / max(float(evals.max()), 1e-12)
    for i in range(3):
        others = [j for j in range(3) if j != i]
        if all(abs(rel[i] - rel[j]) > 0.02 for j in others):
            add(evecs[:, i])
    for e in np.eye(3):
        add(e)
    if len(mesh.facets) > 0:
        order = np.argsort(-np.asarray(mesh.facets_area))[:8]
        for k in order:
            add(mesh.facets_normal[k])
    # Large single faces count as facets too (a box's sides may be one
    # triangle pair merged into a facet, or left as triangles).
    order = np.argsort(-np.asarray(mesh.area_faces))[:8]
    for k in order:
        add(mesh.face_normals[k])
    return axes, evals, evecs


def detect_symmetries(
    mesh: trimesh.Trimesh,
    *,
    tol_frac: float = 0.01,
    n_points: int = 3000,
    rng: np.random.Generator | int | None = 0,
) -> Symmetries:
    """Find the rotational symmetries of a mesh (object frame).

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The part, mm, at least one face of non-zero area.
    tol_frac : float
        Tolerance as a fraction of the diameter: how far (mean nearest-
        neighbour distance above the sampling floor) the rotated surface may
        lie from the original.
    n_points : int
        Surface samples used as probes (the reference set is 5x denser).
    rng : numpy Generator, int or None
        Seed of the surface sampling; the default makes detection repeatable.

    Returns
    -------
    Symmetries
        Discrete group (identity first) and the continuous axis if any.
        Typical run time 0.2-1 s for meshes up to 100k faces.
    """
    if len(mesh.faces) == 0 or float(mesh.area) <= 0:
        raise InvalidMeshError("mesh has no surface", "mesh")
    if not (0 < tol_frac < 0.2):
        raise InvalidInputError("tol_frac must be in (0, 0.2)", "tol_frac")
    gen = np.random.default_rng(rng)
    seed = int(gen.integers(0, 2**31 - 1))
    centre, diameter = _centroid_and_diagonal(mesh)
    test = _SurfaceTest(mesh, n_points, tol_frac * diameter, seed)
    axes, evals, evecs = _candidate_axes(mesh, centre)

    # Axes that pass the continuous test but whose surface shows a turn
    # only their order undoes: the orders the discrete search may try there.
    orders: dict[int, tuple[int, ...]] = {}
    for i, axis in enumerate(axes):
        if all(test.accepts(_rotation_about(axis, math.radians(a), centre))
               for a in _CONTINUOUS_TEST_DEG):
            order = _visible_order(test, axis, centre)
            if order is None:
                return _with_flip(axis, centre, axes, evecs, test)
            orders[i] = (order,)

    generators: list[Array] = []
    group = [np.eye(4)]
    for i, axis in enumerate(axes):
        for n in orders.get(i, _DISCRETE_ORDERS):
            T = _rotation_about(axis, 2 * math.pi / n, centre)
            if any(_same_transform(T, g, diameter) for g in group) or not test.maps(T):
                continue
            trial = _close_group([*generators, T], diameter)
            # A candidate axis a little off a true one passes the tolerance
            # but, combined with the true axis, generates small rotations and
            # an ever-growing "group": such a generator is rejected.
            smallest = min(rotation_angle_deg(np.eye(3), g[:3, :3]) for g in trial[1:])
            if len(trial) < _MAX_GROUP and smallest > _MIN_GROUP_ANGLE_DEG:
                generators.append(T)
                group = trial
                break
    return Symmetries(np.stack(group))


def _visible_order(test: _SurfaceTest, axis: Array, centre: Array) -> int | None:
    """The order n of an axis that passed the continuous test, when a small
    feature of the surface shows every turn about it but those by multiples
    of 360°/n; None when none does (the axis is continuous).

    The continuous test bounds the mean gap and its 99th percentile, which
    a small feature hardly moves: a hex bolt's head (a hexagon on a longer
    round shank, 30 mm across its flats) passed it, though its corners,
    2.3 mm out, show its turn in an image. So do an octagonal prism's. The
    worst-fitting hundredth of the surface tells: turned by a test angle,
    it lies 1.1 tolerances off (the bolt; an octagon 0.9), turned by the
    order's step within 0.05 (sampling noise about 0.1); a 12-, 16-, 24- or
    48-gon's lies within 0.1 at every angle and stays continuous, as
    tessellated cylinders must.
    """
    def gap(angle_deg: float) -> float:
        return test.top_gap_mm(_rotation_about(axis, math.radians(angle_deg), centre))

    worst = max(gap(a) for a in _CONTINUOUS_TEST_DEG)
    if worst < _VISIBLE_TURN_GAP * test.tol:
        return None
    for n in _DISCRETE_ORDERS:
        if (gap(360.0 / n) <= _ORDER_FIT_SHARE * worst
                and gap(180.0 / n) >= _HALF_STEP_GAP_SHARE * worst):
            return n
    return None


def near_half_turns(
    mesh: trimesh.Trimesh, exact: Symmetries, *, max_gap_frac: float = 0.03,
    exact_tol_deg: float = 10.0, n_points: int = 1000, rng: int = 0,
) -> tuple[Array, Array]:
    """Half turns about the principal axes that map a mesh almost onto itself.

    The near-symmetries of :mod:`viewloc_core.near_symmetry`: unlike
    :func:`detect_symmetries` only the mean distance counts (a bump or a
    dent may move far), against a looser tolerance, and the part's exact
    symmetries are left out.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The part, mm, in the frame the transforms are wanted in.
    exact : Symmetries
        Its exact symmetry group (rotation parts compared).
    max_gap_frac : float
        Largest mean distance of the turned surface from the surface beyond
        the sampling floor, as a fraction of the diameter.
    exact_tol_deg : float
        A half turn within this angle of an exact symmetry is that symmetry.
    n_points : int
        Surface probes (the reference set is 5x denser).
    rng : int
        Seed of the surface sampling.

    Returns
    -------
    transforms : (K, 4, 4) float64
        Rigid transforms (rotations about lines through the surface centroid).
    mean_gap_mm : (K,) float64
    """
    centre, diameter = _centroid_and_diagonal(mesh)
    test = _SurfaceTest(mesh, n_points, max_gap_frac * diameter, rng)
    _, _, evecs = _candidate_axes(mesh, centre)
    turns, gaps = [], []
    for axis in evecs.T:
        T = _rotation_about(axis, math.pi, centre)
        if within_angle_deg(np.eye(3), T[:3, :3], exact, exact_tol_deg):
            continue
        gap = test.mean_gap_mm(T)
        if gap < test.tol:
            turns.append(T)
            gaps.append(gap)
    return (np.asarray(turns, np.float64).reshape(-1, 4, 4), np.asarray(gaps, np.float64))


def near_mirrors(
    mesh: trimesh.Trimesh, exact: Symmetries, *, max_gap_frac: float = 0.03,
    same_tol_deg: float = 30.0, n_points: int = 1000, rng: int = 0,
) -> tuple[Array, Array]:
    """Reflections through the surface centroid that map a mesh almost onto itself.

    Candidates are the reflections in the planes through the centroid normal
    to the principal axes and to the other candidate axes (coordinate axes,
    large facets' normals: inside a degenerate eigenspace the principal axes
    are arbitrary), and the point reflection in the centroid. The test is
    :func:`near_half_turns`'s. Two reflections whose product is (within
    ``same_tol_deg``) one of the part's exact symmetries give equivalent
    poses (``R Q1 = R Q2 G``), or poses a fit does not tell apart (planes a
    few degrees apart), so only the one with the smaller gap is kept.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The part, mm, in the frame the transforms are wanted in.
    exact : Symmetries
        Its exact symmetry group (rotation parts compared).
    max_gap_frac : float
        Largest mean distance of the reflected surface from the surface beyond
        the sampling floor, as a fraction of the diameter.
    same_tol_deg : float
        Two reflections whose product is within this angle of an exact
        symmetry (the identity included) count as one: planes up to half
        this angle apart.
    n_points : int
        Surface probes (the reference set is 5x denser).
    rng : int
        Seed of the surface sampling.

    Returns
    -------
    transforms : (K, 4, 4) float64
        Affine maps ``X -> Q X + m`` with ``det Q = -1``, each fixing the
        surface centroid; smallest gap first.
    mean_gap_mm : (K,) float64
    """
    centre, diameter = _centroid_and_diagonal(mesh)
    test = _SurfaceTest(mesh, n_points, max_gap_frac * diameter, rng)
    axes, _, evecs = _candidate_axes(mesh, centre)
    normals: list[Array] = []
    for n in [*evecs.T, *axes]:
        if all(abs(float(np.dot(n, m))) < math.cos(math.radians(5.0)) for m in normals):
            normals.append(np.asarray(n, np.float64))
    found: list[tuple[float, Array]] = []
    for Q in [np.eye(3) - 2.0 * np.outer(n, n) for n in normals] + [-np.eye(3)]:
        T = np.eye(4)
        T[:3, :3] = Q
        T[:3, 3] = centre - Q @ centre
        gap = test.mean_gap_mm(T)
        if gap < test.tol:
            found.append((gap, T))
    kept: list[tuple[float, Array]] = []
    for gap, T in sorted(found, key=lambda f: f[0]):
        if not any(within_angle_deg(np.eye(3), K[:3, :3] @ T[:3, :3], exact, same_tol_deg)
                   for _, K in kept):
            kept.append((gap, T))
    return (np.asarray([T for _, T in kept], np.float64).reshape(-1, 4, 4),
            np.asarray([g for g, _ in kept], np.float64))


def _with_flip(
    axis: Array, centre: Array, axes: list[Array], evecs: Array, test: _SurfaceTest
) -> Symmetries:
    """Continuous symmetry about ``axis``, plus a perpendicular 180° flip if one exists."""
    # With a continuous axis every perpendicular flip is equivalent to every
    # other one up to a rotation about the axis, so testing a few suffices.
    perps = [a - np.dot(a, axis) * axis for a in [*axes, *evecs.T]]
    perps = [p / np.linalg.norm(p) for p in perps if np.linalg.norm(p) > 0.1]
    for p in perps[:6]:
        F = _rotation_about(p, math.pi, centre)
        if test.maps(F):
            return Symmetries(np.stack([np.eye(4), F]), axis, centre)
    return Symmetries(np.eye(4)[None], axis, centre)


def symmetries_from_bop(info: Mapping[str, Any]) -> Symmetries:
    """Symmetries declared in BOP ``models_info.json`` format.

    Parameters
    ----------
    info : mapping
        May hold ``symmetries_discrete`` (list of 16 numbers each, a row-major
        4x4 transform with translation in mm) and ``symmetries_continuous``
        (list of ``{"axis": [3], "offset": [3]}``; only one axis is
        supported, as no rigid part has two independent continuous axes but
        a sphere).

    Returns
    -------
    Symmetries
    """
    discrete = [np.eye(4)]
    for k, flat in enumerate(info.get("symmetries_discrete", []) or []):
        T = np.asarray(flat, dtype=np.float64)
        if T.size != 16 or not np.all(np.isfinite(T)):
            raise InvalidInputError(
                f"symmetries_discrete[{k}] must be 16 finite numbers", "symmetries_discrete"
            )
        T = T.reshape(4, 4)
        R = T[:3, :3]
        if abs(np.linalg.det(R) - 1.0) > 1e-3 or np.abs(R @ R.T - np.eye(3)).max() > 1e-3:
            raise InvalidInputError(
                f"symmetries_discrete[{k}] is not a rotation", "symmetries_discrete"
            )
        if not np.allclose(T, np.eye(4), atol=1e-9):
            discrete.append(T)
    cont: Sequence[Mapping[str, Any]] = info.get("symmetries_continuous", []) or []
    if len(cont) > 1:
        raise InvalidInputError("at most one continuous symmetry axis", "symmetries_continuous")
    if cont:
        try:
            axis = np.asarray(cont[0]["axis"], dtype=np.float64).reshape(3)
            offset = np.asarray(cont[0].get("offset", [0.0, 0.0, 0.0]), dtype=np.float64)
            offset = offset.reshape(3)
        except (KeyError, TypeError, ValueError) as exc:
            raise InvalidInputError(
                "symmetries_continuous needs axis [3] and offset [3]", "symmetries_continuous"
            ) from exc
        return Symmetries(np.stack(discrete), axis, offset)
    return Symmetries(np.stack(discrete))


def symmetries_to_bop(sym: Symmetries) -> dict[str, Any]:
    """The BOP ``models_info`` fields for ``sym`` (identity left out, as BOP does)."""
    out: dict[str, Any] = {
        "symmetries_discrete": [T.reshape(16).tolist() for T in sym.discrete[1:]]
    }
    if sym.continuous_axis is not None and sym.continuous_offset is not None:
        out["symmetries_continuous"] = [
            {"axis": sym.continuous_axis.tolist(), "offset": sym.continuous_offset.tolist()}
        ]
    return out


def symmetry_transforms(sym: Symmetries, continuous_step_deg: float = 2.0) -> Array:
    """All symmetry transforms, the continuous axis discretised (as BOP does).

    Parameters
    ----------
    sym : Symmetries
    continuous_step_deg : float
        Angular step about the continuous axis.

    Returns
    -------
    (K, 4, 4) float64
        Identity first; ``K = len(discrete) * ceil(360 / step)`` with a
        continuous axis, ``len(discrete)`` without.
    """
    if sym.continuous_axis is None or sym.continuous_offset is None:
        return sym.discrete.copy()
    if not (0 < continuous_step_deg <= 180):
        raise InvalidInputError("continuous_step_deg must be in (0, 180]", "continuous_step_deg")
    n = math.ceil(360.0 / continuous_step_deg)
    conts = [
        _rotation_about(sym.continuous_axis, 2 * math.pi * i / n, sym.continuous_offset)
        for i in range(n)
    ]
    return np.stack([C @ D for D in sym.discrete for C in conts])


def _trace_about(M: Array, axis: Array) -> tuple[float, float, float]:
    """(A, B, C) with trace(M · R_axis(θ)) = A cos θ + B sin θ + C (Rodrigues' formula)."""
    # In scalars: trace(M K), K the cross-product matrix of the axis, is
    # the axis dotted with M's antisymmetric part; numpy's small-array
    # calls cost several times the arithmetic (every pose comparison of a
    # symmetric part comes here).
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = M.tolist()
    a0, a1, a2 = (float(v) for v in axis)
    along = (a0 * (m00 * a0 + m01 * a1 + m02 * a2) + a1 * (m10 * a0 + m11 * a1 + m12 * a2)
             + a2 * (m20 * a0 + m21 * a1 + m22 * a2))
    twist = a0 * (m12 - m21) + a1 * (m20 - m02) + a2 * (m01 - m10)
    return m00 + m11 + m22 - along, twist, along


def _best_angle_about(M: Array, axis: Array) -> float:
    """θ maximising trace(M · R_axis(θ)) (closed form)."""
    A, B, _ = _trace_about(M, axis)
    return math.atan2(B, A)


def canonical_pose(
    pose: Pose, sym: Symmetries, R_ref: NDArray[np.floating] | None = None
) -> Pose:
    """The symmetric equivalent of ``pose`` whose rotation is closest to ``R_ref``.

    Rule: among all ``pose ∘ S`` (S in the symmetry group, continuous axis
    included exactly, not discretised), take the one minimising the angle of
    ``R_ref^T R_m2c S_R``; ``R_ref`` defaults to the identity, i.e. the
    object's frame as nearly aligned with the camera's as its symmetry
    allows. Deterministic; ties (measure zero) go to the first discrete
    element. The same function with ``R_ref = R_estimate`` gives the
    symmetric equivalent of a ground truth that is closest to an estimate.

    Parameters
    ----------
    pose : Pose
        Object -> camera.
    sym : Symmetries
    R_ref : (3, 3) array or None
        Reference rotation (object -> camera).

    Returns
    -------
    Pose
        Same appearance as ``pose``.
    """
    R_r = np.eye(3) if R_ref is None else np.asarray(R_ref, dtype=np.float64)
    best: tuple[float, Array] | None = None
    best_key: tuple[float, ...] = ()
    for D in sym.discrete:
        S = D
        if sym.continuous_axis is not None and sym.continuous_offset is not None:
            M = D[:3, :3] @ R_r.T @ pose.R_m2c
            theta = _best_angle_about(M, sym.continuous_axis)
            S = _rotation_about(sym.continuous_axis, theta, sym.continuous_offset) @ D
        R_cand = pose.R_m2c @ S[:3, :3]
        # Ties in angle (measure zero, but real for poses built by hand) go to
        # the lexicographically smallest rotation, which does not depend on
        # which equivalent we started from.
        key = (round(rotation_angle_deg(R_r, R_cand), 6), *np.round(R_cand, 6).ravel().tolist())
        if best is None or key < best_key:
            best, best_key = (key[0], S), key
    if best is None:
        raise InvalidInputError("symmetries have no discrete element", "symmetries")
    S = best[1]
    return Pose(reorthonormalized(pose.R_m2c @ S[:3, :3]), pose.R_m2c @ S[:3, 3] + pose.t_m2c)


def min_rotation_error_deg(
    R_est: NDArray[np.floating], R_gt: NDArray[np.floating], sym: Symmetries
) -> float:
    """Rotation error (deg) minimised over the object's symmetries (exact for continuous).

    The smallest angle of ``R_estᵀ R_gt S_R`` over the group, the continuous
    angle in closed form per discrete element (:func:`canonical_pose`'s
    rule, without its tie-breaking: the minimum is the same).
    """
    R_e = np.asarray(R_est, dtype=np.float64)
    R_g = np.asarray(R_gt, dtype=np.float64)
    best = math.inf
    for D in sym.discrete:
        S_R = D[:3, :3]
        if sym.continuous_axis is not None:
            theta = _best_angle_about(S_R @ R_e.T @ R_g, sym.continuous_axis)
            S_R = _rotation_about(sym.continuous_axis, theta, np.zeros(3))[:3, :3] @ S_R
        best = min(best, rotation_angle_deg(R_e, R_g @ S_R))
    return best


def within_angle_deg(R_a: NDArray[np.floating], R_b: NDArray[np.floating], sym: Symmetries,
                     max_deg: float) -> bool:
    """Whether a symmetric equivalent of ``R_b`` is within ``max_deg`` of ``R_a``.

    :func:`min_rotation_error_deg` ``< max_deg``, by the trace of the
    relative rotation (cos of the angle = (trace - 1) / 2) maximised in
    closed form over the continuous axis: about 20 times faster, for
    comparisons away from 0° (the trace loses half the digits there).
    """
    R_rel = np.asarray(R_a, dtype=np.float64).T @ np.asarray(R_b, dtype=np.float64)
    best_trace = -math.inf
    for D in sym.discrete:
        M = D[:3, :3] @ R_rel  # trace(R_rel D) = trace(D R_rel)
        if sym.continuous_axis is None:
            best_trace = max(best_trace, float(np.trace(M)))
            continue
        A, B, C = _trace_about(M, sym.continuous_axis)
        best_trace = max(best_trace, math.hypot(A, B) + C)  # max over θ of A cos + B sin
    return (best_trace - 1.0) / 2.0 > math.cos(math.radians(max_deg))


def any_within_angle_deg(R_a: NDArray[np.floating], R_bs: Sequence[NDArray[np.floating]],
                         sym: Symmetries, max_deg: float) -> bool:
    """Whether :func:`within_angle_deg` holds for ``R_a`` and any of ``R_bs``.

    One batch over the (K,) rotations ``R_bs`` instead of K calls: a
    localization asks it of every rival start against every rotation
    already tried (LM-O: about 900 comparisons an image, 15 ms as single
    calls).
    """
    if not len(R_bs):
        return False
    R_rel = np.asarray(R_a, dtype=np.float64).T @ np.asarray(R_bs, dtype=np.float64)
    best_trace = np.full(len(R_rel), -np.inf)
    axis = sym.continuous_axis
    for D in sym.discrete:
        M = D[:3, :3] @ R_rel
        trace = M[:, 0, 0] + M[:, 1, 1] + M[:, 2, 2]
        if axis is None:
            best_trace = np.maximum(best_trace, trace)
            continue
        # _trace_about for each: A cos θ + B sin θ + C, maximised over θ.
        along = np.einsum("i,kij,j->k", axis, M, axis)
        twist = (axis[0] * (M[:, 1, 2] - M[:, 2, 1]) + axis[1] * (M[:, 2, 0] - M[:, 0, 2])
                 + axis[2] * (M[:, 0, 1] - M[:, 1, 0]))
        best_trace = np.maximum(best_trace, np.hypot(trace - along, twist) + along)
    return bool(np.any((best_trace - 1.0) / 2.0 > math.cos(math.radians(max_deg))))


#: Largest declared group accepted (a 60-tooth gear with a flip has 120 elements).
_MAX_DECLARED_GROUP = 240
#: Tolerances of a declared rotation, as BOP's annotations are written to a few digits.
_DECLARED_ORTHO_TOL = 1e-3
_DECLARED_AXIS_TOL_DEG = 0.5


def _declared_numbers(value: Any, size: int, field: str) -> Array:
    """``value`` as ``size`` finite float64 numbers, else InvalidInputError naming ``field``."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{field} must be {size} numbers", field) from exc
    if arr.size != size or arr.ndim > 2:
        raise InvalidInputError(f"{field} must be {size} numbers, got {arr.size}", field)
    if not np.all(np.isfinite(arr)):
        raise InvalidInputError(f"{field} must be finite numbers", field)
    return arr.reshape(size)


def _declared_transform(flat: Any, to_mm: float, field: str) -> Array:
    T = _declared_numbers(flat, 16, field).reshape(4, 4)
    if np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-6:
        raise InvalidInputError(f"{field}: the last row of the 4x4 transform must be 0 0 0 1",
                                field)
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > _DECLARED_ORTHO_TOL:
        raise InvalidInputError(f"{field}: the 3x3 part is not orthonormal (within "
                                f"{_DECLARED_ORTHO_TOL})", field)
    if abs(float(np.linalg.det(R)) - 1.0) > _DECLARED_ORTHO_TOL:
        raise InvalidInputError(f"{field}: the 3x3 part has determinant "
                                f"{float(np.linalg.det(R)):.3f}, not +1 (a reflection is no "
                                "rigid motion)", field)
    out = np.eye(4)
    out[:3, :3] = orthonormalize(R)
    out[:3, 3] = T[:3, 3] * to_mm
    return out


def _check_within_reach(transforms: Sequence[Array], axis: Array | None,
                        offset: Array | None, reach_mm: float) -> None:
    """Refuse declared transforms that move the origin more than twice the
    part's reach, or an axis farther than the reach from the origin (see
    :func:`declared_symmetries`); a micrometre of slack for rounding."""
    slack = 1e-3
    for k, T in enumerate(transforms):
        moved = float(np.linalg.norm(T[:3, 3]))
        if not moved <= 2.0 * reach_mm + slack:
            raise InvalidInputError(
                f"symmetries_discrete[{k}] moves the part's origin by {moved:.4g} mm, more "
                f"than twice as far as the part reaches from it ({reach_mm:.4g} mm): a "
                "symmetry maps the part onto itself", f"symmetries_discrete[{k}]")
    if axis is not None and offset is not None:
        off_axis = float(np.linalg.norm(offset - (offset @ axis) * axis))
        if not off_axis <= reach_mm + slack:
            raise InvalidInputError(
                f"the continuous symmetry axis passes {off_axis:.4g} mm from the part's "
                f"origin, farther than the part reaches from it ({reach_mm:.4g} mm): the "
                "axis of a symmetry runs through the part",
                "symmetries_continuous[0].offset")


def declared_symmetries(
    info: Mapping[str, Any], *, to_mm: float = 1.0, diameter_mm: float | None = None,
    reach_mm: float | None = None,
) -> Symmetries:
    """A symmetry group declared by a user in BOP ``models_info`` form, checked strictly.

    Unlike :func:`symmetries_from_bop` (which reads trusted annotation files),
    every problem is reported with the offending entry named, the group is
    completed and normalised:

    * without a continuous axis, the declared transforms are closed into a
      group (a declared 90° turn brings 180° and 270°), duplicates dropped;
    * with one, every discrete transform must map the axis (as a line) onto
      itself; turns about the axis are implied by it and dropped, and of the
      flips (axis reversed) one is kept, as they differ only by such a turn.

    Parameters
    ----------
    info : mapping
        ``symmetries_discrete``: list of 16 numbers each (row-major 4x4,
        last row 0 0 0 1, rotation part orthonormal within 1e-3 with
        determinant +1, translation in the declaration's units);
        ``symmetries_continuous``: at most one ``{"axis": [3], "offset": [3]}``
        (non-zero axis; ``offset`` a point on it, default the origin).
        Other keys (BOP's ``diameter``, ``min_x`` ...) are ignored.
    to_mm : float
        Millimetres per unit of the declaration (e.g. 10 for cm).
    diameter_mm : float or None
        Object diameter, sets the translation tolerance (1e-3 of it); without
        it the tolerance is 1e-3 of the largest translation or offset (>= 1 µm).
    reach_mm : float or None
        How far the part reaches from its origin (its farthest point's
        distance), mm. A symmetry maps the part onto itself, so it moves
        the origin by at most twice that, and its axis passes at most that
        far from the origin (through the part's centroid): a declaration
        beyond is refused (an axis declared a metre off a 50 mm part turned
        every pose it was given a metre away). None checks nothing of it.

    Returns
    -------
    Symmetries
        Identity first; translations and offset in mm.

    Raises
    ------
    InvalidInputError
        ``field`` names the entry, e.g. ``"symmetries_discrete[1]"``,
        ``"symmetries_continuous[0].axis"``.
    """
    if not isinstance(info, Mapping):
        raise InvalidInputError("symmetries must be an object", "symmetries")
    if not (math.isfinite(to_mm) and to_mm > 0):
        raise InvalidInputError("to_mm must be a positive number", "to_mm")
    flats = info.get("symmetries_discrete") or []
    conts = info.get("symmetries_continuous") or []
    if not isinstance(flats, Sequence) or isinstance(flats, str):
        raise InvalidInputError("symmetries_discrete must be a list", "symmetries_discrete")
    if not isinstance(conts, Sequence) or isinstance(conts, str):
        raise InvalidInputError("symmetries_continuous must be a list", "symmetries_continuous")
    if len(flats) > _MAX_DECLARED_GROUP:
        raise InvalidInputError(f"at most {_MAX_DECLARED_GROUP} discrete symmetries",
                                "symmetries_discrete")
    transforms = [_declared_transform(f, to_mm, f"symmetries_discrete[{k}]")
                  for k, f in enumerate(flats)]
    if len(conts) > 1:
        raise InvalidInputError("at most one continuous symmetry axis (a rigid part other than "
                                "a sphere has no two)", "symmetries_continuous")
    axis: Array | None = None
    offset: Array | None = None
    if conts:
        entry = conts[0]
        if not isinstance(entry, Mapping) or "axis" not in entry:
            raise InvalidInputError("symmetries_continuous[0] needs an axis [3]",
                                    "symmetries_continuous[0].axis")
        axis = _declared_numbers(entry["axis"], 3, "symmetries_continuous[0].axis")
        norm = float(np.linalg.norm(axis))
        if norm < 1e-9:
            raise InvalidInputError("symmetries_continuous[0].axis must not be zero",
                                    "symmetries_continuous[0].axis")
        axis = axis / norm
        offset = to_mm * _declared_numbers(entry.get("offset", [0.0, 0.0, 0.0]), 3,
                                           "symmetries_continuous[0].offset")
    if reach_mm is not None:
        _check_within_reach(transforms, axis, offset, reach_mm)
    scale = diameter_mm if diameter_mm is not None and diameter_mm > 0 else max(
        [1e-3, *(float(np.linalg.norm(T[:3, 3])) for T in transforms),
         0.0 if offset is None else float(np.linalg.norm(offset))])
    tol_mm = 1e-3 * scale
    if axis is None or offset is None:
        group = _close_group([T for T in transforms if not _same_transform(T, np.eye(4), scale)],
                             scale, limit=_MAX_DECLARED_GROUP + 1)
        if len(group) > _MAX_DECLARED_GROUP:
            raise InvalidInputError(
                f"the discrete symmetries generate more than {_MAX_DECLARED_GROUP} transforms "
                "(an angle that is no whole fraction of 360°?)", "symmetries_discrete")
        return Symmetries(np.stack(group))
    flip: Array | None = None
    for k, T in enumerate(transforms):
        field = f"symmetries_discrete[{k}]"
        turned = T[:3, :3] @ axis
        cos = float(turned @ axis)
        if abs(cos) < math.cos(math.radians(_DECLARED_AXIS_TOL_DEG)):
            raise InvalidInputError(f"{field} moves the continuous symmetry axis off itself",
                                    field)
        moved = T[:3, :3] @ offset + T[:3, 3] - offset
        if float(np.linalg.norm(moved - (moved @ axis) * axis)) > max(tol_mm, 1e-6):
            raise InvalidInputError(f"{field} moves the continuous symmetry axis off its line",
                                    field)
        if cos > 0 and float(np.linalg.norm(moved)) > max(tol_mm, 1e-6):
            raise InvalidInputError(f"{field} shifts along the continuous symmetry axis "
                                    "(a screw motion is no symmetry of a finite part)", field)
        if cos < 0 and flip is None:
            flip = T
    discrete = np.eye(4)[None] if flip is None else np.stack([np.eye(4), flip])
    return Symmetries(discrete, axis, offset)
