"""Mesh loading: every format round trips, units convert, bad files are refused."""

import math

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from trimesh.exchange.gltf import export_gltf

from viewloc_core import mesh as mesh_module
from viewloc_core.errors import InvalidInputError, InvalidMeshError
from viewloc_core.mesh import (
    load_mesh,
    mesh_diameter_mm,
    mesh_has_colour,
    mesh_vertex_colours,
    outward_wound,
)

EXTENTS = (10.0, 20.0, 30.0)


def _box(colour: tuple[int, int, int] | None = None) -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=EXTENTS)
    box.apply_translation([1.0, 2.0, 3.0])
    if colour is not None:
        box.visual.vertex_colors = np.tile([*colour, 255], (len(box.vertices), 1))
    return box


def _export(mesh: trimesh.Trimesh | trimesh.Scene, file_type: str) -> bytes:
    if file_type == "gltf":
        scene = mesh if isinstance(mesh, trimesh.Scene) else trimesh.Scene(mesh)
        # Buffers embedded as data URIs: bytes carry no sibling files.
        return export_gltf(scene, embed_buffers=True)["model.gltf"]
    data = mesh.export(file_type=file_type)
    return data.encode() if isinstance(data, str) else data


@pytest.mark.parametrize("file_type", ["stl", "obj", "ply", "off", "glb", "gltf"])
def test_round_trip_keeps_extents(file_type):
    loaded = load_mesh(_export(_box(), file_type), file_type=file_type)
    np.testing.assert_allclose(np.sort(loaded.extents), EXTENTS, atol=1e-4)
    np.testing.assert_allclose(loaded.bounds.mean(axis=0), [1.0, 2.0, 3.0], atol=1e-4)
    assert len(loaded.faces) == 12
    # STL stores each triangle's corners separately; they must be merged.
    assert len(loaded.vertices) == 8


@pytest.mark.parametrize(("units", "factor"), [("mm", 1.0), ("cm", 10.0), ("m", 1000.0),
                                               ("in", 25.4)])
def test_units_convert_to_mm(units, factor):
    loaded = load_mesh(_export(_box(), "ply"), file_type="PLY", units=units)
    np.testing.assert_allclose(np.sort(loaded.extents), np.array(EXTENTS) * factor, rtol=1e-9)


def test_type_is_inferred_from_path_suffix(tmp_path):
    path = tmp_path / "part.stl"
    path.write_bytes(_export(_box(), "stl"))
    loaded = load_mesh(path, units="cm")
    np.testing.assert_allclose(np.sort(loaded.extents), np.array(EXTENTS) * 10.0, atol=1e-3)
    assert load_mesh(str(path)).faces.shape == (12, 3)


@pytest.mark.parametrize("file_type", ["ply", "glb"])
def test_vertex_colours_survive(file_type):
    loaded = load_mesh(_export(_box(colour=(200, 30, 10)), file_type), file_type=file_type)
    assert mesh_has_colour(loaded)
    colours = mesh_vertex_colours(loaded)
    assert colours is not None
    assert colours.dtype == np.uint8 and colours.shape == (len(loaded.vertices), 3)
    np.testing.assert_array_equal(np.unique(colours, axis=0), [[200, 30, 10]])


def test_scene_is_flattened_with_transforms_and_colours():
    red = _box(colour=(255, 0, 0))
    green = trimesh.creation.icosphere(subdivisions=1, radius=5.0)
    green.visual.face_colors = np.tile([0, 255, 0, 255], (len(green.faces), 1))
    scene = trimesh.Scene()
    scene.add_geometry(red)
    shift = np.eye(4)
    shift[:3, 3] = [100.0, 0.0, 0.0]
    scene.add_geometry(green, transform=shift)
    loaded = load_mesh(_export(scene, "glb"), file_type="glb")
    assert len(loaded.faces) == 12 + len(green.faces)
    assert loaded.bounds[1, 0] == pytest.approx(105.0, abs=1e-3)
    colours = mesh_vertex_colours(loaded)
    assert colours is not None
    present = {tuple(c) for c in np.unique(colours, axis=0)}
    assert {(255, 0, 0), (0, 255, 0)} <= present


def test_plain_mesh_has_no_colour():
    loaded = load_mesh(_export(_box(), "stl"), file_type="stl")
    assert not mesh_has_colour(loaded)
    assert mesh_vertex_colours(loaded) is None


def test_diameter_is_the_space_diagonal():
    box = trimesh.creation.box(extents=EXTENTS)
    assert mesh_diameter_mm(box) == pytest.approx(math.sqrt(10**2 + 20**2 + 30**2))
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=50.0)
    assert mesh_diameter_mm(sphere) == pytest.approx(100.0, rel=1e-6)


def test_finely_tessellated_round_parts_get_their_diameter():
    # Every vertex of a ball lies on its hull and equally far out; a
    # cylinder's caps put all their points on two circles (Qhull took
    # minutes over 20,000 sections, comparing all pairs of the ball's
    # 40,962 vertices as long).
    ball = trimesh.creation.icosphere(subdivisions=6, radius=20.0)
    assert len(ball.vertices) > 40_000
    assert mesh_diameter_mm(ball) == pytest.approx(40.0, rel=2e-3)
    assert mesh_diameter_mm(ball) <= 40.0 + 1e-9
    cylinder = trimesh.creation.cylinder(radius=10.0, height=50.0, sections=20_000)
    assert mesh_diameter_mm(cylinder) == pytest.approx(math.hypot(20.0, 50.0), rel=2e-3)


def test_the_diameter_directions_lie_within_their_stated_angle():
    from viewloc_core.view_sphere import spiral_directions

    directions = spiral_directions(mesh_module.DIAMETER_DIRECTIONS)
    probes = np.random.default_rng(3).normal(size=(50_000, 3))
    probes /= np.linalg.norm(probes, axis=1, keepdims=True)
    nearest_deg = np.degrees(np.arccos(np.clip((probes @ directions.T).max(axis=1), -1, 1)))
    assert nearest_deg.max() <= mesh_module.DIAMETER_DIRECTIONS_MAX_ANGLE_DEG


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(2, 400),
    scale=st.tuples(*[st.floats(0.01, 100.0)] * 3),
    seed=st.integers(0, 2**31 - 1),
    limit=st.sampled_from([1, 8, 64, 4000]),
)
def test_max_pairwise_distance_is_the_largest_or_nearly(n, scale, seed, limit):
    # With a low limit of points compared pair by pair, the extreme points
    # and the pruning do the work (as for a mesh of more than 4000 points).
    pts = np.random.default_rng(seed).normal(size=(n, 3)) * np.asarray(scale)
    brute = max(float(np.linalg.norm(pts[i] - pts, axis=1).max()) for i in range(n))
    found = mesh_module._max_pairwise_distance(pts, limit)
    assert found <= brute * (1 + 1e-9)
    cos_bound = math.cos(math.radians(mesh_module.DIAMETER_DIRECTIONS_MAX_ANGLE_DEG))
    assert found >= brute * cos_bound * (1 - 1e-6)
    if limit >= n:
        assert found == pytest.approx(brute, rel=1e-12)


def _expect_mesh_error(data, file_type, fragment):
    with pytest.raises(InvalidMeshError) as info:
        load_mesh(data, file_type=file_type)
    assert info.value.field == "mesh"
    assert fragment in info.value.message.lower()


@pytest.mark.parametrize("file_type", ["stl", "obj", "ply", "off", "glb", "gltf"])
def test_garbage_bytes_are_refused(file_type):
    with pytest.raises(InvalidMeshError) as info:
        load_mesh(b"\x00\x17 this is not a mesh \xff" * 7, file_type=file_type)
    assert info.value.field == "mesh"


def test_empty_and_faceless_meshes_are_refused():
    _expect_mesh_error(b"", "ply", "empty")
    faceless = trimesh.Trimesh(vertices=np.eye(3), faces=np.zeros((0, 3), dtype=np.int64))
    _expect_mesh_error(_export(faceless, "ply"), "ply", "no faces")


def test_nan_vertices_are_refused():
    box = _box()
    vertices = box.vertices.copy()
    vertices[3] = np.nan
    bad = trimesh.Trimesh(vertices=vertices, faces=box.faces, process=False)
    _expect_mesh_error(_export(bad, "ply"), "ply", "nan")


def test_degenerate_and_absurd_meshes_are_refused(monkeypatch):
    point = trimesh.Trimesh(vertices=np.ones((3, 3)), faces=[[0, 1, 2]], process=False)
    _expect_mesh_error(_export(point, "ply"), "ply", "zero extent")
    huge = trimesh.creation.box(extents=(200.0, 1.0, 1.0))
    with pytest.raises(InvalidMeshError, match="limit"):
        load_mesh(_export(huge, "ply"), file_type="ply", units="m")
    # A 50 mm part drawn in metres and uploaded as millimetres.
    in_metres = trimesh.creation.box(extents=(0.05, 0.02, 0.01))
    _expect_mesh_error(_export(in_metres, "ply"), "ply", "check the units")
    assert load_mesh(_export(in_metres, "ply"), file_type="ply", units="m").extents[0] == (
        pytest.approx(50.0))
    monkeypatch.setattr(mesh_module, "MAX_FACES", 11)
    _expect_mesh_error(_export(_box(), "ply"), "ply", "faces, more than")


def test_a_part_drawn_far_from_its_origin_is_refused_and_one_near_it_kept():
    # A triangle at 1e39 mm overflowed the model's float32 vertices (every
    # localization of it answered 500); a box 1e30 mm out lost its size to
    # rounding. Both are refused, naming the mesh.
    with pytest.raises(InvalidMeshError, match="from its origin") as err:
        load_mesh(b"v 1e39 0 0\nv 1e39 10 0\nv 1e39 0 10\nf 1 2 3\n", file_type="obj")
    assert err.value.field == "mesh"
    moved = _box()
    moved.apply_translation((1e30, 0.0, 0.0))
    _expect_mesh_error(_export(moved, "ply"), "ply", "from its origin")
    # Scaled beyond what merging the vertices rounds to integers without
    # overflow, a box was called degenerate: it is too large, and says so.
    for scale in (1e10, 1e20, 1e30):
        grown = _box()
        grown.apply_scale(scale)
        _expect_mesh_error(_export(grown, "ply"), "ply", "check the units")
    # 9,000 diameters out: kept, at its size.
    near = _box()
    diameter = float(np.linalg.norm(EXTENTS))
    near.apply_translation((9_000.0 * diameter, 0.0, 0.0))
    kept = load_mesh(_export(near, "ply"), file_type="ply")
    np.testing.assert_allclose(kept.extents, EXTENTS, rtol=1e-6)


def test_unknown_type_and_units_name_their_field():
    _expect_mesh_error(b"solid x", "dae", "unknown mesh type")
    _expect_mesh_error(b"solid x", None, "file_type is required")
    with pytest.raises(InvalidInputError) as info:
        load_mesh(_export(_box(), "ply"), file_type="ply", units="furlong")
    assert info.value.field == "units"


def _flipped(mesh: trimesh.Trimesh, faces: np.ndarray) -> trimesh.Trimesh:
    """``mesh`` with the corners of ``faces`` reversed."""
    out = mesh.copy()
    rows = np.array(out.faces)
    rows[faces] = rows[faces][:, ::-1]
    out.faces = rows
    return out


def _same_triangle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per row, whether two (F, 3) face arrays list the same corners in the
    same cyclic order (the same triangle, wound the same way)."""
    return np.any([np.all(np.roll(b, k, axis=1) == a, axis=1) for k in range(3)], axis=0)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 3), st.data())
def test_a_closed_mesh_with_faces_wound_inward_is_wound_outward_again(shape, data):
    mesh = [trimesh.creation.box(extents=EXTENTS), trimesh.creation.icosphere(2, 15.0),
            trimesh.creation.cylinder(8.0, 30.0, sections=24),
            trimesh.creation.annulus(5.0, 12.0, 10.0, sections=20)][shape]
    mesh.visual.vertex_colors = np.column_stack([
        np.arange(len(mesh.vertices)) % 256, np.zeros((len(mesh.vertices), 2)),
        np.full(len(mesh.vertices), 255)]).astype(np.uint8)
    faces = data.draw(st.lists(st.integers(0, len(mesh.faces) - 1), min_size=1,
                               max_size=len(mesh.faces), unique=True))
    wrong = _flipped(mesh, np.array(faces))
    assert not wrong.is_winding_consistent or wrong.volume < 0

    fixed = outward_wound(wrong)

    assert fixed.is_winding_consistent and fixed.volume > 0
    # Every face is the original triangle, wound as it was: the surface's own
    # outward winding, whichever faces were turned (all of them included).
    assert np.all(_same_triangle(np.asarray(fixed.faces), np.asarray(mesh.faces)))
    np.testing.assert_array_equal(fixed.vertices, mesh.vertices)
    np.testing.assert_array_equal(fixed.visual.vertex_colors, mesh.visual.vertex_colors)
    # The input is left as it was.
    assert not np.all(_same_triangle(np.asarray(wrong.faces), np.asarray(mesh.faces)))


def test_sound_and_open_meshes_are_returned_as_they_are():
    box = _box((10, 20, 30))
    assert outward_wound(box) is box
    # An open surface has no outside: its faces stay as they are.
    open_box = _flipped(trimesh.Trimesh(box.vertices, box.faces[2:], process=False),
                        np.array([0, 3]))
    assert not open_box.is_watertight
    assert outward_wound(open_box) is open_box


def test_repeated_faces_are_dropped_and_a_double_sided_surface_kept():
    box = _box()
    repeated = trimesh.Trimesh(box.vertices, np.concatenate([box.faces] * 50), process=False)
    loaded = load_mesh(_export(repeated, "ply"), file_type="ply")
    assert len(loaded.faces) == len(box.faces)
    np.testing.assert_allclose(loaded.extents, EXTENTS)
    # The same faces turned to start at another corner repeat them too; the
    # reversed ones (the other side of the surface) do not.
    turned = np.roll(box.faces, 1, axis=1)
    both_sides = trimesh.Trimesh(box.vertices, np.concatenate(
        [box.faces, turned, box.faces[:, ::-1]]), process=False)
    loaded = load_mesh(_export(both_sides, "ply"), file_type="ply")
    assert len(loaded.faces) == 2 * len(box.faces)
