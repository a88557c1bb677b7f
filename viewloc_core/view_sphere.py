"""Uniform view directions by iterative subdivision of an icosahedron (paper §4.1).

A *view direction* ``v`` is the unit vector from the object origin towards the
camera, in object coordinates. Its azimuth ``ϑ = atan2(v_y, v_x)`` and polar
angle ``ϕ = arccos(v_z)`` (from the object's +z axis) are what the paper's
§4.2 calls the viewing angles of a training view.

Camera-up rule (fixed, so a view direction defines one training camera): the
camera looks at the object origin; the object's +z axis appears "up" in the
image (towards smaller pixel y). Within ``UP_SWITCH_POLAR_DEG`` of the poles,
where +z is nearly parallel to the line of sight, object +y is used instead.
The in-plane rotation between views either side of the switch is absorbed by
the 2D similarity of the alignment, so the rule only has to be fixed, not smooth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from viewloc_core.errors import InvalidInputError

Array = NDArray[np.float64]

#: Polar angle (deg) from either pole within which the up rule uses object +y.
UP_SWITCH_POLAR_DEG = 1.0


@dataclass(frozen=True, slots=True)
class ViewDirection:
    """One training viewpoint on the view sphere.

    Attributes
    ----------
    direction : (3,) float64
        Unit vector from the object origin to the camera, object frame.
    azimuth_deg : float
        ϑ in degrees, in (-180, 180].
    polar_deg : float
        ϕ in degrees, in [0, 180], measured from object +z.
    level : int
        Subdivision level at which this direction first appeared (0 = icosahedron).
    """

    direction: Array
    azimuth_deg: float
    polar_deg: float
    level: int

    @property
    def R_m2c(self) -> Array:
        """(3, 3) rotation object -> training camera for this view (see module doc)."""
        return view_rotation(self.direction)


def view_rotation(direction: NDArray[np.floating]) -> Array:
    """Rotation object -> camera of a camera looking at the origin from ``direction``.

    Parameters
    ----------
    direction : (3,) array
        Vector from the object origin to the camera (object frame), any length.

    Returns
    -------
    (3, 3) float64
        Rows are the camera's x (right), y (down) and z (forward) axes written
        in object coordinates, so ``x_cam = R @ x_obj + [0, 0, d0]`` for a
        camera at distance ``d0``.
    """
    v = np.asarray(direction, dtype=np.float64)
    v = v / np.linalg.norm(v)
    z_cam = -v
    polar = np.degrees(np.arccos(np.clip(v[2], -1.0, 1.0)))
    near_pole = polar < UP_SWITCH_POLAR_DEG or polar > 180.0 - UP_SWITCH_POLAR_DEG
    up_obj = np.array([0.0, 1.0, 0.0]) if near_pole else np.array([0.0, 0.0, 1.0])
    # Image "up" is -y in OpenCV, so the camera's y axis is minus the up
    # vector with its line-of-sight component removed.
    y_cam = -(up_obj - np.dot(up_obj, z_cam) * z_cam)
    y_cam /= np.linalg.norm(y_cam)
    x_cam = np.cross(y_cam, z_cam)
    return np.stack([x_cam, y_cam, z_cam])


def direction_from_angles(azimuth_deg: float, polar_deg: float) -> Array:
    """Unit view direction (object frame) from azimuth ϑ and polar angle ϕ in degrees."""
    az, po = np.radians(azimuth_deg), np.radians(polar_deg)
    return np.array([np.sin(po) * np.cos(az), np.sin(po) * np.sin(az), np.cos(po)])


def angles_from_direction(direction: NDArray[np.floating]) -> tuple[float, float]:
    """(azimuth_deg, polar_deg) of a view direction."""
    v = np.asarray(direction, dtype=np.float64)
    v = v / np.linalg.norm(v)
    return float(np.degrees(np.arctan2(v[1], v[0]))), float(
        np.degrees(np.arccos(np.clip(v[2], -1.0, 1.0)))
    )


def _icosahedron() -> tuple[Array, NDArray[np.int64]]:
    phi = (1.0 + np.sqrt(5.0)) / 2.0
    verts = np.array(
        [
            [-1, phi, 0], [1, phi, 0], [-1, -phi, 0], [1, -phi, 0],
            [0, -1, phi], [0, 1, phi], [0, -1, -phi], [0, 1, -phi],
            [phi, 0, -1], [phi, 0, 1], [-phi, 0, -1], [-phi, 0, 1],
        ],
        dtype=np.float64,
    )
    faces = np.array(
        [
            [0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
            [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
            [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
            [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1],
        ],
        dtype=np.int64,
    )
    return verts / np.linalg.norm(verts, axis=1, keepdims=True), faces


def _midpoint(
    vert_list: list[Array],
    level_of: list[int],
    cache: dict[tuple[int, int], int],
    a: int,
    b: int,
    level: int,
) -> int:
    """Index of the unit midpoint of edge (a, b), added once per edge."""
    key = (a, b) if a < b else (b, a)
    if key not in cache:
        m = vert_list[a] + vert_list[b]
        vert_list.append(m / np.linalg.norm(m))
        level_of.append(level)
        cache[key] = len(vert_list) - 1
    return cache[key]


def subdivided_sphere(levels: int) -> tuple[Array, NDArray[np.int64], NDArray[np.int64]]:
    """Icosahedron subdivided ``levels`` times, vertices projected to the sphere.

    Each subdivision splits every triangle into four at its edge midpoints.

    Returns
    -------
    vertices : (N, 3) float64
        Unit vectors; ``N = 10 * 4**levels + 2``. Vertices of coarser levels
        come first, so any prefix of the coarse-to-fine order is itself a
        uniform sampling.
    faces : (F, 3) int64
        Triangles of the finest level.
    vertex_level : (N,) int64
        Level at which each vertex appeared.
    """
    if levels < 0 or levels > 7:
        raise InvalidInputError(f"levels must be in 0..7, got {levels}", "levels")
    verts, faces = _icosahedron()
    vert_list = list(verts)
    level_of = [0] * len(vert_list)
    for level in range(1, levels + 1):
        midpoint: dict[tuple[int, int], int] = {}
        new_faces = []
        for a, b, c in faces:
            ab, bc, ca = (
                _midpoint(vert_list, level_of, midpoint, i, j, level)
                for i, j in ((a, b), (b, c), (c, a))
            )
            new_faces += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        faces = np.array(new_faces, dtype=np.int64)
    return np.array(vert_list), faces, np.array(level_of, dtype=np.int64)


def spiral_directions(count: int) -> Array:
    """Unit directions spread evenly over the sphere, for any count.

    Parameters
    ----------
    count : int
        Number of directions, at least 1.

    Returns
    -------
    (count, 3) float64
        Points of the golden-angle spiral: equal areas per point, every
        direction within about ``0.75 * sqrt(4 pi / count)`` radians of one.
    """
    if count < 1:
        raise ValueError(f"count must be at least 1, got {count}")
    i = np.arange(count, dtype=np.float64)
    z = 1.0 - (2.0 * i + 1.0) / count
    azimuth_rad = i * np.pi * (3.0 - np.sqrt(5.0))
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, 1.0))
    return np.stack([r * np.cos(azimuth_rad), r * np.sin(azimuth_rad), z], axis=1)


def view_directions(
    levels: int, max_polar_deg: float = 180.0
) -> list[ViewDirection]:
    """Training view directions, coarse to fine (paper §4.1).

    Parameters
    ----------
    levels : int
        Subdivision depth: 0 gives 12 views, 1 gives 42, 2 gives 162, 3 gives 642.
    max_polar_deg : float
        Keep only directions with polar angle <= this (e.g. 90 for the upper
        hemisphere when the part always lies on a table).

    Returns
    -------
    list of ViewDirection
        Ordered by level, so that the views seen so far always cover the
        sphere about uniformly (needed by the stopping criterion).
    """
    verts, _, level_of = subdivided_sphere(levels)
    views = []
    for v, lvl in zip(verts, level_of, strict=True):
        az, po = angles_from_direction(v)
        if po <= max_polar_deg + 1e-9:
            views.append(ViewDirection(v, az, po, int(lvl)))
    return views


def nearest_neighbour_angles_deg(directions: NDArray[np.floating]) -> Array:
    """Angle (deg) from each direction to its nearest other direction.

    Parameters
    ----------
    directions : (N, 3) array
        Unit vectors, N >= 2.

    Returns
    -------
    (N,) float64
    """
    d = np.asarray(directions, dtype=np.float64)
    cos = np.clip(d @ d.T, -1.0, 1.0)
    np.fill_diagonal(cos, -1.0)
    return np.degrees(np.arccos(cos.max(axis=1)))
