"""Figure-ground contrast: a part stands out from its surroundings, its cast shadow does not."""

import numpy as np
import pytest

from tests.viewloc_core.conftest import blob
from viewloc_core.camera import Camera
from viewloc_core.figure_ground import figure_ground_contrast
from viewloc_core.pose import Pose
from viewloc_core.render import Light, Renderer, prepare
from viewloc_core.shading import surface_samples, visible_samples

CAM = Camera(600.0, 600.0, 319.5, 239.5, 640, 480)
LIGHTS = (Light("directional", direction_cam=(0.4, 0.5, 1.0), intensity=3.0),
          Light("ambient", intensity=0.3))


@pytest.fixture(scope="module")
def scene():
    """(samples, pose, part mask, textured green-brown ground, render of the grey part)."""
    mesh = blob()
    samples = surface_samples(mesh.vertices, mesh.faces)
    pose = Pose(np.eye(3), np.array([20.0, -10.0, 450.0]))
    with Renderer() as renderer:
        out = renderer.render(prepare(mesh), CAM, pose, lights=LIGHTS)
    rng = np.random.default_rng(3)
    # A mottled ground whose hue and brightness vary (a texture, not a flat colour).
    shade = rng.uniform(0.5, 1.0, (CAM.height // 8, CAM.width // 8, 1))
    shade = np.kron(shade, np.ones((8, 8, 1)))
    hue = np.array([110.0, 150.0, 70.0]) + rng.normal(0.0, 12.0, (CAM.height, CAM.width, 3))
    ground = np.clip(shade * hue, 0, 255).astype(np.uint8)
    return samples, pose, out.mask, ground, out.color


def _with_part(ground, mask, part):
    image = ground.copy()
    image[mask] = part[mask]
    return image


def test_the_part_stands_out_and_its_shadow_does_not(scene):
    samples, pose, mask, ground, part = scene
    with_part = _with_part(ground, mask, part)
    # A cast shadow has the part's outline exactly but darkens the ground
    # under it, hue kept.
    shadow = ground.copy()
    shadow[mask] = (0.4 * ground[mask]).astype(np.uint8)
    assert figure_ground_contrast(with_part, CAM, pose, samples) > 0.3
    assert figure_ground_contrast(shadow, CAM, pose, samples) < 0.05
    # A pose where there is only ground encloses the ground's own colours.
    elsewhere = Pose(pose.R_m2c, pose.t_m2c + np.array([-120.0, 60.0, 0.0]))
    assert figure_ground_contrast(with_part, CAM, elsewhere, samples) < 0.05


def test_visible_samples_given_by_the_caller_give_the_same_contrast(scene):
    samples, pose, mask, ground, part = scene
    with_part = _with_part(ground, mask, part)
    uv = visible_samples(samples, CAM, pose)[0]
    assert figure_ground_contrast(with_part, CAM, pose, samples, uv) == figure_ground_contrast(
        with_part, CAM, pose, samples)


def test_contrast_is_the_same_in_16_bit_and_brighter_light(scene):
    samples, pose, mask, ground, part = scene
    image = _with_part(ground, mask, part)
    contrast = figure_ground_contrast(image, CAM, pose, samples)
    assert contrast is not None
    wide = image.astype(np.uint16) * 257
    assert figure_ground_contrast(wide, CAM, pose, samples) == pytest.approx(contrast, abs=1e-3)
    brighter = np.clip(image.astype(np.float64) * 1.3, 0, 255).astype(np.uint8)
    assert figure_ground_contrast(brighter, CAM, pose, samples) == pytest.approx(contrast,
                                                                                 abs=0.05)
    # Float images are read in 0..1.
    unit = image.astype(np.float32) / 255.0
    assert figure_ground_contrast(unit, CAM, pose, samples) == pytest.approx(contrast, abs=1e-3)


def test_grey_images_and_unseen_parts_give_no_contrast(scene):
    samples, pose, mask, ground, part = scene
    image = _with_part(ground, mask, part)
    assert figure_ground_contrast(image.mean(axis=2).astype(np.uint8), CAM, pose,
                                  samples) is None
    beside = Pose(pose.R_m2c, pose.t_m2c + np.array([2000.0, 0.0, 0.0]))
    assert figure_ground_contrast(image, CAM, beside, samples) is None
    behind = Pose(pose.R_m2c, np.array([0.0, 0.0, -450.0]))
    assert figure_ground_contrast(image, CAM, behind, samples) is None


def test_a_part_almost_at_the_lens_gives_no_contrast_or_a_bounded_one(scene):
    # A diverged fit may put the part almost at the camera: the ring is then
    # sized from the image, not from the projection, so it costs no more.
    samples, pose, mask, ground, part = scene
    image = _with_part(ground, mask, part)
    for depth_mm in (60.0, 90.0, 200.0):
        near = Pose(pose.R_m2c, np.array([0.0, 0.0, depth_mm]))
        contrast = figure_ground_contrast(image, CAM, near, samples)
        assert contrast is None or 0.0 <= contrast <= 1.0


@pytest.mark.parametrize("step", [2, 3, 5])
def test_a_large_part_is_ringed_on_a_coarser_grid_with_the_same_contrast(scene, monkeypatch,
                                                                         step):
    # As if the part were `step` times over the largest diameter ringed on
    # every pixel (a large camera image): its ring is read on every
    # step-th pixel, and part and shadow still compare as on every pixel.
    from viewloc_core import figure_ground

    samples, pose, mask, ground, part = scene
    with_part = _with_part(ground, mask, part)
    shadow = ground.copy()
    shadow[mask] = (0.4 * ground[mask]).astype(np.uint8)
    full = figure_ground_contrast(with_part, CAM, pose, samples)
    diameter_px = CAM.fx * samples.extent_mm / pose.t_m2c[2]
    monkeypatch.setattr(figure_ground, "MAX_RING_DIAMETER_PX", diameter_px / (step - 0.5))
    seen = []
    original = figure_ground.ring_values

    def counted_ring_values(*args):
        pixels = original(*args)
        seen.append(len(pixels))
        return pixels

    monkeypatch.setattr(figure_ground, "ring_values", counted_ring_values)
    coarse = figure_ground_contrast(with_part, CAM, pose, samples)
    assert coarse == pytest.approx(full, abs=0.05) and coarse > 0.3
    assert figure_ground_contrast(shadow, CAM, pose, samples) < 0.05
    # The ring was read on the coarser grid: about step² fewer pixels.
    monkeypatch.setattr(figure_ground, "MAX_RING_DIAMETER_PX", 10 * diameter_px)
    figure_ground_contrast(with_part, CAM, pose, samples)
    assert seen[-1] / seen[0] == pytest.approx(step**2, rel=0.35)
