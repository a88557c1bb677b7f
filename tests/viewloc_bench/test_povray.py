"""POV-Ray camera geometry: projection to 0.5 px and no mirroring (IoU with pyrender)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from viewloc_bench import povray as pv
from viewloc_bench import shapes
from viewloc_core.camera import Camera
from viewloc_core.pose import Pose

pytestmark = pytest.mark.skipif(pv.povray_executable() is None, reason="povray not installed")

# fx != fy and a principal point off the centre exercise every term of camera_sdl.
CAM = Camera(260.0, 250.0, 83.3, 57.9, 160, 120)


def _flat(rgb: tuple[float, float, float]) -> str:
    return f"texture {{ pigment {{ rgb {pv.vec(rgb)} }} finish {{ emission 1 diffuse 0 }} }}"


def test_sphere_centroids_match_the_projection() -> None:
    centres = [
        np.array([0.0, 0.0, 600.0]),
        np.array([-150.0, 70.0, 700.0]),
        np.array([120.0, -90.0, 520.0]),
    ]
    colours = [(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)]
    sdl = pv.scene_header(CAM)
    for c, rgb in zip(centres, colours, strict=True):
        sdl += f"sphere {{ {pv.cam_point(c)}, 7 {_flat(rgb)} }}\n"
    img = pv.render(sdl, CAM.width, CAM.height, antialias=None, threads=1)
    for ch, c in enumerate(centres):
        ys, xs = np.nonzero(img[..., ch] > 127)
        assert len(xs) > 10
        # A sphere's outline is an ellipse whose centre is off the projected
        # centre by ~f r^2 x / z^3; below 0.05 px here, far under the tolerance.
        uv = CAM.project(c[None])[0]
        assert abs(xs.mean() - uv[0]) < 0.5
        assert abs(ys.mean() - uv[1]) < 0.5


def _pyrender_mask(mesh_vertices: np.ndarray, faces: np.ndarray, pose: Pose) -> np.ndarray:
    import trimesh

    from viewloc_core.render import Renderer

    # The project's renderer (pyrender underneath): a raw OffscreenRenderer's
    # delete() terminates the EGL display and with it every other context.
    tm = trimesh.Trimesh(mesh_vertices, faces, process=False)
    with Renderer() as r:
        return r.render_depth(tm, CAM, pose).mask


def test_asymmetric_object_matches_pyrender_and_is_not_mirrored() -> None:
    shape = shapes.bracket()
    mesh = shapes.to_trimesh(shape)
    pose = Pose(Rotation.from_euler("xyz", [30, -40, 20], degrees=True).as_matrix(),
                np.array([10.0, -5.0, 450.0]))
    sdl = pv.scene_header(CAM) + shapes.to_pov(
        shape, _flat((1.0, 0.0, 0.0)), pv.pose_matrix_sdl(pose)
    )
    pov = pv.render(sdl, CAM.width, CAM.height, antialias=None, threads=1)[..., 0] > 127
    gl = _pyrender_mask(np.asarray(mesh.vertices), np.asarray(mesh.faces), pose)
    iou = (pov & gl).sum() / (pov | gl).sum()
    assert pov.sum() > 500
    assert iou > 0.95
    # The mirror image of the object (reflected in the object's yz plane) differs clearly.
    mirrored = np.asarray(mesh.vertices) * np.array([-1.0, 1.0, 1.0])
    gl_mirror = _pyrender_mask(mirrored, np.asarray(mesh.faces)[:, ::-1], pose)
    iou_mirror = (pov & gl_mirror).sum() / (pov | gl_mirror).sum()
    assert iou_mirror < iou - 0.1
