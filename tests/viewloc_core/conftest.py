"""Shared fixtures for the engine tests: small meshes and one learned model."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from viewloc_core.camera import Camera
from viewloc_core.contour_model import build_contour_model
from viewloc_core.learn import LearningConfig, learn_from_mesh
from viewloc_core.model import ObjectModel
from viewloc_core.pose import Pose
from viewloc_core.render import Light, Renderer, prepare
from viewloc_core.view_sphere import subdivided_sphere


def l_bracket() -> trimesh.Trimesh:
    """An asymmetric part (a plate, an upright and a rib), mm, origin off-centre."""
    plate = trimesh.creation.box((100.0, 60.0, 8.0))
    plate.apply_translation([0.0, 0.0, 4.0])
    upright = trimesh.creation.box((8.0, 60.0, 70.0))
    upright.apply_translation([-46.0, 0.0, 35.0])
    rib = trimesh.creation.box((40.0, 6.0, 40.0))
    rib.apply_translation([-30.0, 10.0, 20.0])
    return trimesh.util.concatenate([plate, upright, rib])


#: The colour of :func:`coloured_bracket`'s orange copy (:func:`orange_model`).
ORANGE = (230, 110, 20)


def coloured_bracket(rgb: tuple[int, int, int]) -> trimesh.Trimesh:
    """:func:`l_bracket` with every face of colour ``rgb``."""
    mesh = l_bracket()
    mesh.visual.face_colors = [*rgb, 255]
    return mesh


def ribbed_bracket() -> trimesh.Trimesh:
    """A smaller asymmetric bracket (plate, wall at one end, thin rib), mm."""
    base = trimesh.creation.box((100.0, 40.0, 8.0))
    base.apply_translation([0.0, 0.0, 4.0])
    wall = trimesh.creation.box((8.0, 40.0, 60.0))
    wall.apply_translation([46.0, 0.0, 38.0])
    rib = trimesh.creation.box((30.0, 5.0, 20.0))
    rib.apply_translation([27.0, 12.0, 18.0])
    return trimesh.util.concatenate([base, wall, rib])


def blob() -> trimesh.Trimesh:
    """A smooth egg-like part with bumps and a dent: no symmetry, outline
    nearly mirror-symmetric (its two sides look alike in outline), mm."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    d = np.asarray(sphere.vertices)
    r = np.ones(len(d))
    for direction, amp, width in (((1.0, 0.2, 0.3), 0.45, 0.35), ((-0.3, 1.0, 0.5), 0.3, 0.25),
                                  ((0.2, -0.6, 1.0), -0.25, 0.3)):
        a = np.asarray(direction) / np.linalg.norm(direction)
        r += amp * np.exp(-np.sum((d - a) ** 2, axis=1) / width)
    return trimesh.Trimesh(d * r[:, None] * 40.0 * np.array([1.35, 1.0, 0.8]), sphere.faces)


@pytest.fixture(scope="session")
def bracket_mesh() -> trimesh.Trimesh:
    return l_bracket()


@pytest.fixture(scope="session")
def bracket_model(bracket_mesh: trimesh.Trimesh) -> ObjectModel:
    # Level 1 (42 views) keeps the suite fast; the bench uses the defaults.
    return learn_from_mesh(bracket_mesh, LearningConfig(max_level=1, min_level=1))


@pytest.fixture(scope="session")
def orange_model() -> ObjectModel:
    """The orange bracket learned with its colours (level-1 view sphere)."""
    return learn_from_mesh(coloured_bracket(ORANGE),
                           LearningConfig(max_level=1, min_level=1, contour_level=1))


@pytest.fixture(scope="session")
def renderer():
    with Renderer() as r:
        yield r


@pytest.fixture(scope="module")
def bracket_contour_scene(renderer):
    """The renderer, the ribbed bracket prepared for it and its contour
    model on a level-2 view sphere (the refinement tests' scene)."""
    mesh = ribbed_bracket()
    dirs, _, _ = subdivided_sphere(2)
    model = build_contour_model(mesh, dirs, renderer, 600.0, 600.0, (320, 320), 200)
    return renderer, prepare(mesh), model


#: Two lights from different sides so faces differ in brightness, as on a
#: lit inspection table.
TABLE_LIGHTS = [
    Light("directional", direction_cam=(0.6, 0.5, 1.0), intensity=3.0),
    Light("directional", direction_cam=(-0.7, -0.2, 0.6), intensity=1.2),
    Light("ambient", intensity=0.2),
]


def render_scene(
    renderer: Renderer,
    mesh: trimesh.Trimesh,
    camera: Camera,
    pose: Pose,
    clutter: int = 0,
    rng: np.random.Generator | int | None = 0,
) -> np.ndarray:
    """Colour image of ``mesh`` at ``pose`` with ``clutter`` random boxes behind/around it."""
    gen = np.random.default_rng(rng)
    items = [(prepare(mesh), pose)]
    for _ in range(clutter):
        box = trimesh.creation.box(gen.uniform([15, 10, 10], [120, 30, 30]))
        R = trimesh.transformations.random_rotation_matrix(gen.random(3))[:3, :3]
        uv = gen.uniform([0, 0], [camera.width, camera.height])
        z = gen.uniform(pose.t_m2c[2] + 50, pose.t_m2c[2] + 500)
        t = z * np.array([(uv[0] - camera.cx) / camera.fx, (uv[1] - camera.cy) / camera.fy, 1])
        items.append((prepare(box), Pose(R, t)))
    return renderer.render_scene(items, camera, lights=TABLE_LIGHTS,
                                 background_rgb=(40, 40, 40)).color


def render_copies(renderer: Renderer, mesh: trimesh.Trimesh, camera: Camera,
                  poses: list[Pose]) -> np.ndarray:
    """Colour image of copies of ``mesh``, one at each of ``poses``, lit as
    by :func:`render_scene`."""
    prepared = prepare(mesh)
    return renderer.render_scene([(prepared, p) for p in poses], camera, lights=TABLE_LIGHTS,
                                 background_rgb=(40, 40, 40)).color


def faint_noise(shape: tuple[int, int], seed: int, blur_px: float, mean: float,
                contrast: float) -> np.ndarray:
    """A grey noise texture (uint8, ``shape``): Gaussian noise blurred by
    ``blur_px`` and scaled to standard deviation ``contrast`` grey levels
    about ``mean``; the faint backgrounds of the strong-edge tests."""
    import cv2

    noise = cv2.GaussianBlur(np.random.default_rng(seed).normal(0.0, 1.0, shape), (0, 0),
                             blur_px)
    return np.clip(mean + contrast * noise / noise.std(), 0, 255).astype(np.uint8)
