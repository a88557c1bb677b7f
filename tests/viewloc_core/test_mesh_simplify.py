"""Simplification of dense meshes before learning: budget, shape, colours."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from viewloc_core.mesh import mesh_vertex_colours
from viewloc_core.mesh_simplify import simplified

#: Radius of the test sphere, mm.
RADIUS_MM = 50.0


def _dense_sphere() -> trimesh.Trimesh:
    """An icosphere of 20,480 faces, 50 mm radius, centred at (10, -20, 30) mm."""
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=RADIUS_MM)
    sphere.apply_translation([10.0, -20.0, 30.0])
    return sphere


DENSE = _dense_sphere()
CENTRE_MM = np.array([10.0, -20.0, 30.0])


def test_a_mesh_within_the_budget_is_returned_as_it_is():
    assert simplified(DENSE, len(DENSE.faces)) is DENSE
    assert simplified(DENSE, 10**6) is DENSE


def test_the_budget_must_leave_a_closed_surface():
    with pytest.raises(ValueError, match="at least 4"):
        simplified(DENSE, 3)


@settings(max_examples=12, deadline=None)
@given(budget=st.integers(min_value=500, max_value=15_000))
def test_a_dense_mesh_keeps_its_shape_within_the_budget(budget):
    out = simplified(DENSE, budget)
    assert out is not DENSE
    assert len(out.faces) <= budget
    # Fewer faces, but most of the budget used: a sphere has no flat area
    # to collapse wholesale.
    assert len(out.faces) >= 0.9 * budget
    # Every kept vertex lies on the sphere to within a small share of its
    # radius (500 faces: chords of about 8 mm), and the frame is unchanged.
    radial_mm = np.linalg.norm(out.vertices - CENTRE_MM, axis=1)
    tolerance_mm = 0.02 * RADIUS_MM if budget < 2_000 else 0.005 * RADIUS_MM
    assert np.max(np.abs(radial_mm - RADIUS_MM)) < tolerance_mm
    np.testing.assert_allclose(np.asarray(out.bounds).mean(axis=0), CENTRE_MM, atol=0.5)
    assert out.volume == pytest.approx(DENSE.volume, rel=0.03)


def test_a_mesh_on_read_only_arrays_is_simplified():
    # Built from another mesh's cached triangles: its vertices are a
    # read-only view, which the decimation library refuses as it is.
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=RADIUS_MM)
    soup = trimesh.Trimesh(sphere.triangles.reshape(-1, 3),
                           np.arange(3 * len(sphere.faces)).reshape(-1, 3), process=False)
    assert not soup.vertices.view(np.ndarray).flags.writeable
    out = simplified(soup, 2_000)
    assert 0 < len(out.faces) <= 2_000


def test_every_body_of_a_mesh_keeps_its_place():
    small = trimesh.creation.icosphere(subdivisions=5, radius=20.0)
    other = small.copy()
    other.apply_translation([100.0, 0.0, 0.0])
    out = simplified(trimesh.util.concatenate([small, other]), 3_000)
    assert len(out.split(only_watertight=False)) == 2
    np.testing.assert_allclose(out.bounds, [[-20.0, -20.0, -20.0], [120.0, 20.0, 20.0]], atol=0.5)


def test_vertex_colours_follow_the_surface():
    mesh = DENSE.copy()
    # Two halves: red where x > centre, blue elsewhere.
    east = mesh.vertices[:, 0] > CENTRE_MM[0]
    rgba = np.where(east[:, None], [200, 30, 30, 255], [30, 30, 200, 255]).astype(np.uint8)
    mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=rgba)
    out = simplified(mesh, 2_000)
    colours = mesh_vertex_colours(out)
    assert colours is not None and len(colours) == len(out.vertices)
    # Away from the seam every vertex has its half's colour.
    x = out.vertices[:, 0] - CENTRE_MM[0]
    assert np.all(colours[x > 3.0] == [200, 30, 30])
    assert np.all(colours[x < -3.0] == [30, 30, 200])


def test_face_colours_become_vertex_colours():
    mesh = DENSE.copy()
    mesh.visual.face_colors = [40, 160, 60, 255]
    out = simplified(mesh, 2_000)
    colours = mesh_vertex_colours(out)
    assert colours is not None
    assert np.all(colours == [40, 160, 60])


def test_a_grey_mesh_stays_without_colours():
    out = simplified(DENSE, 2_000)
    assert mesh_vertex_colours(out) is None
