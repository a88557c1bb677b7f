"""Offscreen rendering: OpenCV geometry (no half-pixel shift, no mirror), depth, labels."""

import os
import subprocess
import sys
import threading

import numpy as np
import pytest
import trimesh
from PIL import Image
from scipy import ndimage
from scipy.spatial.transform import Rotation

from viewloc_core.camera import Camera
from viewloc_core.errors import InvalidInputError
from viewloc_core.mesh import load_mesh, outward_wound
from viewloc_core.pose import Pose
from viewloc_core.render import (
    Light,
    Material,
    PreparedMesh,
    Renderer,
    prepare,
    random_lights,
)

CAMERA = Camera(fx=600.0, fy=610.0, cx=300.3, cy=251.7, width=640, height=480)
WHITE = Material(base_rgb=(1.0, 1.0, 1.0))
# Ambient light only: every covered sample is white, so a pixel's grey value is
# its anti-aliased coverage and the weighted centroid has sub-pixel accuracy.
FLAT = [Light("ambient", intensity=1.0)]


@pytest.fixture(scope="module")
def renderer():
    with Renderer() as shared:
        yield shared


def _weighted_centroid(weights: np.ndarray) -> np.ndarray:
    w = weights.astype(np.float64)
    rows, cols = np.mgrid[: w.shape[0], : w.shape[1]]
    return np.array([(w * cols).sum(), (w * rows).sum()]) / w.sum()


def _colour_sphere(radius: float, rgb: tuple[int, int, int], centre) -> trimesh.Trimesh:
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    sphere.apply_translation(centre)
    sphere.visual.face_colors = np.tile([*rgb, 255], (len(sphere.faces), 1))
    return sphere


@pytest.mark.parametrize(
    ("centre", "camera"),
    [
        ((0.0, 0.0, 500.0), CAMERA),
        ((150.0, -110.0, 600.0), CAMERA),
        ((-290.0, 220.0, 800.0), CAMERA),  # far off-centre, near the left/bottom edge
        ((180.0, 130.0, 400.0), CAMERA),
        ((10.0, -20.0, 700.0), Camera(520.0, 520.0, 127.5, 127.5, 256, 256)),
    ],
)
def test_sphere_centroid_matches_projection(renderer, centre, camera):
    sphere = prepare(trimesh.creation.icosphere(subdivisions=3, radius=3.0), WHITE)
    pose = Pose(np.eye(3), np.array(centre))
    out = renderer.render(sphere, camera, pose, lights=FLAT)
    expected = camera.project(np.array([centre]))[0]
    error = np.linalg.norm(_weighted_centroid(out.color[:, :, 0]) - expected)
    assert error < 0.5, f"centroid off by {error:.3f} px"
    assert out.color.shape == (camera.height, camera.width, 3)
    assert out.color.dtype == np.uint8


def test_asymmetric_object_is_not_mirrored(renderer):
    axes_obj = np.array([[40.0, 0.0, 0.0], [0.0, 40.0, 0.0], [0.0, 0.0, 40.0]])
    colours = [(255, 0, 0), (0, 255, 0), (0, 0, 255)]
    marker = trimesh.util.concatenate(
        [_colour_sphere(6.0, c, p) for c, p in zip(colours, axes_obj, strict=True)]
    )
    R = Rotation.from_euler("xyz", [25.0, -35.0, 60.0], degrees=True).as_matrix()
    pose = Pose(R, np.array([15.0, -10.0, 600.0]))
    out = renderer.render(prepare(marker), CAMERA, pose, lights=FLAT)
    expected = CAMERA.project(pose.transform(axes_obj))
    # The three markers land >= 20 px apart, so a mirror or flip moves at least
    # one by far more than the tolerance.
    assert min(np.linalg.norm(expected[i] - expected[j]) for i, j in [(0, 1), (0, 2), (1, 2)]) > 20
    for channel in range(3):
        others = [c for c in range(3) if c != channel]
        rgb = out.color.astype(np.int32)
        only = np.where(rgb[:, :, others].max(axis=2) < 8, rgb[:, :, channel], 0)
        found = _weighted_centroid(only)
        assert np.linalg.norm(found - expected[channel]) < 1.0, (channel, found, expected)


def test_box_face_depth_and_mask(renderer):
    box = prepare(trimesh.creation.box(extents=(40.0, 60.0, 80.0)))
    R = Rotation.from_euler("xyz", [10.0, 25.0, -15.0], degrees=True).as_matrix()
    pose = Pose(R, np.array([20.0, -15.0, 520.0]))
    out = renderer.render(box, CAMERA, pose)
    # The face at object z = -40 faces the camera; intersect the ray through
    # the pixel nearest its projected centre with the face's plane.
    centre_cam = pose.transform([[0.0, 0.0, -40.0]])[0]
    normal_cam = R @ np.array([0.0, 0.0, -1.0])
    u, v = np.round(CAMERA.project(centre_cam[None])[0]).astype(int)
    ray = CAMERA.ray(np.array([[u, v]], dtype=float))[0]
    z_true = ray[2] * (normal_cam @ centre_cam) / (normal_cam @ ray)
    assert out.depth_mm.dtype == np.float32
    assert out.depth_mm[v, u] == pytest.approx(z_true, abs=0.5)
    np.testing.assert_array_equal(out.mask, out.depth_mm > 0)
    assert out.mask.any() and not out.mask.all()
    # Anti-aliased colour may spill one pixel past the (single-sample) mask.
    grown = ndimage.binary_dilation(out.mask, iterations=1)
    assert np.all(out.color[~grown] == 0)
    assert np.all(out.color[out.mask].max(axis=1) > 0)
    depth_only = renderer.render_depth(box, CAMERA, pose)
    np.testing.assert_allclose(depth_only.depth_mm, out.depth_mm, atol=1e-3)
    np.testing.assert_array_equal(depth_only.mask, out.mask)


def test_near_object_is_not_clipped(renderer):
    box = prepare(trimesh.creation.box(extents=(20.0, 20.0, 20.0)))
    out = renderer.render_depth(box, CAMERA, Pose(np.eye(3), np.array([0.0, 0.0, 40.0])))
    v, u = 252, 300
    assert out.depth_mm[v, u] == pytest.approx(30.0, abs=0.05)


def test_scene_labels_follow_depth_order(renderer):
    front = prepare(trimesh.creation.box(extents=(40.0, 40.0, 40.0)))
    back = prepare(trimesh.creation.box(extents=(80.0, 80.0, 20.0)))
    items = [(back, Pose(np.eye(3), np.array([0.0, 0.0, 700.0]))),
             (front, Pose(np.eye(3), np.array([30.0, 0.0, 600.0])))]
    out = renderer.render_scene(items, CAMERA)
    assert out.labels.dtype == np.int16
    np.testing.assert_array_equal(out.labels == -1, ~out.mask)
    assert out.visible_fraction(1) == pytest.approx(1.0)
    assert 0.3 < out.visible_fraction(0) < 0.95
    alone = renderer.render_depth(back, CAMERA, items[0][1])
    assert out.item_pixels[0] == np.count_nonzero(alone.mask)
    v, u = np.round(CAMERA.project(np.array([[30.0, 0.0, 580.0]]))[0, ::-1]).astype(int)
    assert out.labels[v, u] == 1 and out.depth_mm[v, u] == pytest.approx(580.0, abs=0.5)
    assert out.color is not None and out.color[v, u].max() > 0
    assert renderer.render_scene(items, CAMERA, depth_only=True).color is None


def test_colours_materials_and_lights_change_the_image(renderer):
    red = trimesh.creation.box(extents=(50.0, 50.0, 50.0))
    red.visual.vertex_colors = np.tile([220, 20, 20, 255], (len(red.vertices), 1))
    prepared = prepare(red)
    pose = Pose(Rotation.from_euler("xy", [30.0, 40.0], degrees=True).as_matrix(),
                np.array([0.0, 0.0, 500.0]))
    own = renderer.render(prepared, CAMERA, pose)
    r, g, b = (own.color[own.mask][:, k].astype(float).mean() for k in range(3))
    assert r > 3 * g and r > 3 * b
    blue = renderer.render(prepared, CAMERA, pose, material=Material(base_rgb=(0.1, 0.2, 0.9)))
    assert blue.color[blue.mask][:, 2].mean() > 3 * blue.color[blue.mask][:, 0].mean()
    dark = renderer.render(prepared, CAMERA, pose, lights=[Light("ambient", intensity=0.05)])
    lit = renderer.render(prepared, CAMERA, pose,
                          lights=[Light("point", position_cam_mm=(0.0, 0.0, 0.0), intensity=3.0)])
    assert lit.color[lit.mask].mean() > dark.color[dark.mask].mean() + 20


def test_texture_from_glb_is_drawn_unmirrored(renderer):
    box = trimesh.creation.box(extents=(40.0, 40.0, 40.0))
    box.unmerge_vertices()
    image = np.zeros((8, 8, 3), dtype=np.uint8)
    image[:, :4] = (255, 0, 0)  # u < 0.5: red
    image[:, 4:] = (0, 0, 255)  # u > 0.5: blue
    uv = np.stack([np.where(box.vertices[:, 0] > 0, 0.95, 0.05), np.full(len(box.vertices), 0.5)],
                  axis=1)
    box.visual = trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(image))
    loaded = load_mesh(box.export(file_type="glb"), file_type="glb")
    prepared = prepare(loaded)
    assert prepared.texture is not None and not prepared.double_sided
    out = renderer.render(prepared, CAMERA, Pose(np.eye(3), np.array([0.0, 0.0, 400.0])),
                          lights=FLAT)
    # Object -x (red) appears left of the principal point, +x (blue) right.
    left, right = out.color[252, 300 - 25].astype(int), out.color[252, 300 + 25].astype(int)
    assert left[0] > left[2] + 100 and right[2] > right[0] + 100


def test_prepared_normals_are_sharp_at_creases_and_smooth_on_curves():
    box = prepare(trimesh.creation.box(extents=(10.0, 10.0, 10.0)))
    face_normals = np.repeat(trimesh.creation.box(extents=(10.0, 10.0, 10.0)).face_normals, 3, 0)
    np.testing.assert_allclose(box.normals, face_normals, atol=1e-6)
    sphere = prepare(trimesh.creation.icosphere(subdivisions=4, radius=10.0))
    radial = sphere.positions / np.linalg.norm(sphere.positions, axis=1, keepdims=True)
    assert np.min(np.einsum("ij,ij->i", sphere.normals, radial)) > 0.999


def test_open_meshes_are_drawn_from_both_sides(renderer):
    closed = trimesh.creation.box(extents=(40.0, 40.0, 40.0))
    assert not prepare(closed).double_sided
    facing_camera = np.flatnonzero(closed.face_normals[:, 2] < -0.5)
    keep = np.setdiff1d(np.arange(len(closed.faces)), facing_camera)
    open_box = trimesh.Trimesh(closed.vertices, closed.faces[keep], process=False)
    prepared = prepare(open_box)
    assert prepared.double_sided
    out = renderer.render_depth(prepared, CAMERA, Pose(np.eye(3), np.array([0.0, 0.0, 500.0])))
    # Looking into the opening: the inside of the far wall, whose outward
    # normal points away from the camera.
    assert out.depth_mm[252, 300] == pytest.approx(520.0, abs=0.5)
    shaded = renderer.render(prepared, CAMERA, Pose(np.eye(3), np.array([0.0, 0.0, 500.0])))
    np.testing.assert_array_equal(shaded.mask, out.mask)
    assert shaded.color[252, 300].max() > 0


def test_object_behind_the_camera_renders_empty(renderer):
    box = prepare(trimesh.creation.box(extents=(10.0, 10.0, 10.0)))
    out = renderer.render(box, CAMERA, Pose(np.eye(3), np.array([0.0, 0.0, -100.0])),
                          background_rgb=(10, 20, 30))
    assert not out.mask.any()
    assert np.all(out.color == np.array([10, 20, 30], dtype=np.uint8))


def test_renders_repeat_bit_for_bit_under_many_lights(renderer):
    # pyrender keeps lights in sets, whose order follows the nodes' memory
    # addresses. It binds at most four of each kind, so with eight it lit the
    # part with a different four from one render to the next (a third of the
    # pixels changed); with fewer it summed them in another order, and now
    # and then a pixel came out one level apart (learning's training views).
    sphere = prepare(trimesh.creation.icosphere(subdivisions=4, radius=60.0))
    camera = Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
    pose = Pose(np.eye(3), np.array([0.0, 0.0, 200.0]))
    rng = np.random.default_rng(3)
    lights = [Light("directional", intensity=0.4 + 0.05 * i,
                    direction_cam=tuple(d / np.linalg.norm(d)))
              for i, d in enumerate(rng.normal(size=(8, 3)) * [1.0, 1.0, 0.2] + [0.0, 0.0, 1.0])]
    first = renderer.render(sphere, camera, pose, lights=lights).color
    for _ in range(4):
        np.testing.assert_array_equal(renderer.render(sphere, camera, pose, lights=lights).color,
                                      first)


def test_random_lights_are_deterministic_and_varied():
    a, b = random_lights(7), random_lights(np.random.default_rng(7))
    assert a == b
    draws = [random_lights(seed, n=(1, 3)) for seed in range(40)]
    assert {len(d) - 1 for d in draws} == {1, 2, 3}
    assert len({d[0] for d in draws}) == 40
    for lights in draws:
        assert lights[-1].kind == "ambient"
        for light in lights[:-1]:
            if light.kind == "directional":
                assert light.direction_cam[2] > 0.2  # shines into the scene
            else:
                assert light.kind == "point" and light.position_cam_mm[2] < 700.0
    with pytest.raises(InvalidInputError):
        random_lights(0, n=(0, 2))


def test_values_validate_their_fields(renderer):
    with pytest.raises(InvalidInputError) as info:
        Material(base_rgb=(1.5, 0.0, 0.0))
    assert info.value.field == "material.base_rgb"
    with pytest.raises(InvalidInputError) as info:
        Light("directional", direction_cam=(0.0, 0.0, 0.0))
    assert info.value.field == "light.direction_cam"
    with pytest.raises(InvalidInputError):
        renderer.render("not a mesh", CAMERA, Pose.identity())  # type: ignore[arg-type]
    box = prepare(trimesh.creation.box(extents=(10.0, 10.0, 10.0)))
    with pytest.raises(InvalidInputError) as info:
        renderer.render_depth(box, Camera(500.0, 500.0, 5000.0, 10.0, 10000, 20),
                              Pose(np.eye(3), np.array([0.0, 0.0, 300.0])))
    assert info.value.field == "camera.width"


def test_renderer_refuses_other_threads(renderer):
    box = prepare(trimesh.creation.box(extents=(10.0, 10.0, 10.0)))
    errors: list[BaseException] = []

    def use() -> None:
        try:
            renderer.render_depth(box, CAMERA, Pose(np.eye(3), np.array([0.0, 0.0, 300.0])))
        except BaseException as exc:  # noqa: BLE001 - the test inspects it
            errors.append(exc)

    worker = threading.Thread(target=use)
    worker.start()
    worker.join()
    assert len(errors) == 1 and isinstance(errors[0], RuntimeError)
    assert isinstance(box, PreparedMesh)


def test_closing_one_renderer_leaves_others_working(renderer):
    box = prepare(trimesh.creation.box(extents=(30.0, 30.0, 30.0)))
    pose = Pose(np.eye(3), np.array([0.0, 0.0, 400.0]))
    before = renderer.render_depth(box, CAMERA, pose)
    with Renderer() as other:
        other.render_depth(box, CAMERA.scaled(0.5), pose)
    dropped = Renderer()
    dropped.render_depth(box, CAMERA, pose)
    del dropped  # garbage collection must not terminate the shared EGL display
    after = renderer.render_depth(box, CAMERA, pose)
    np.testing.assert_array_equal(after.depth_mm, before.depth_mm)


_CHILD = """
import numpy as np, os, trimesh
from viewloc_core.camera import Camera
from viewloc_core.pose import Pose
from viewloc_core.render import Light, Material, Renderer, prepare
camera = Camera(600.0, 610.0, 300.3, 251.7, 640, 480)
sphere = prepare(trimesh.creation.icosphere(subdivisions=3, radius=3.0), Material((1.0, 1.0, 1.0)))
with Renderer() as r:
    out = r.render(sphere, camera, Pose(np.eye(3), np.array([-120.0, 90.0, 600.0])),
                   lights=[Light("ambient", intensity=1.0)])
w = out.color[:, :, 0].astype(float)
rows, cols = np.mgrid[: w.shape[0], : w.shape[1]]
found = np.array([(w * cols).sum(), (w * rows).sum()]) / w.sum()
error = np.linalg.norm(found - camera.project(np.array([[-120.0, 90.0, 600.0]]))[0])
print(os.environ["PYOPENGL_PLATFORM"], error)
"""


@pytest.mark.slow
@pytest.mark.parametrize("platform", [None, "osmesa"])
def test_platform_choice_in_a_fresh_process(platform):
    """Unset: EGL is probed and chosen here; osmesa: the fallback draws the same."""
    env = {k: v for k, v in os.environ.items() if k != "PYOPENGL_PLATFORM"}
    if platform is not None:
        env["PYOPENGL_PLATFORM"] = platform
    done = subprocess.run([sys.executable, "-c", _CHILD], env=env, capture_output=True,
                          text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    chosen, error = done.stdout.split()
    assert chosen == (platform or "egl")
    assert float(error) < 0.5


def test_a_closed_mesh_wound_outward_again_renders_as_drawn_on_both_sides(renderer):
    """A few faces of a closed surface wound the wrong way make the renderer
    draw every triangle twice (both windings); wound outward again
    (:func:`viewloc_core.mesh.outward_wound`) it is drawn once, and shows
    the same depth and outline."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=40.0)
    faces = np.array(sphere.faces)
    wrong = np.arange(0, len(faces), 37)
    faces[wrong] = faces[wrong][:, ::-1]
    mis_wound = trimesh.Trimesh(sphere.vertices, faces, process=False)
    fixed = outward_wound(mis_wound)
    assert prepare(mis_wound).double_sided and not prepare(fixed).double_sided
    pose = Pose(np.eye(3), np.array([10.0, -5.0, 500.0]))
    both_sides = renderer.render_depth(prepare(mis_wound), CAMERA, pose)
    once = renderer.render_depth(prepare(fixed), CAMERA, pose)
    np.testing.assert_array_equal(once.mask, both_sides.mask)
    np.testing.assert_allclose(once.depth_mm, both_sides.depth_mm, atol=0.05)
