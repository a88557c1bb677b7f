"""The shading agreement's compiled steps against their array formulation."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from tests.viewloc_core.conftest import blob, l_bracket
from viewloc_core.camera import Camera
from viewloc_core.pose import Pose
from viewloc_core.robust import tukey_weights
from viewloc_core.shading import (
    MIN_FACING_COS,
    SurfaceSamples,
    intensity_at,
    shading_agreement,
    surface_samples,
    visible_samples,
)

CAMERAS = (Camera(600.0, 600.0, 319.5, 239.5, 640, 480),
           Camera(600.0, 590.0, 322.0, 236.0, 640, 480, (-0.2, 0.08, 0.001, -0.002, 0.0)))
SAMPLES = (surface_samples(blob().vertices, blob().faces),
           surface_samples(l_bracket().vertices, l_bracket().faces))


def _array_visible(samples: SurfaceSamples, camera: Camera, pose: Pose):
    """The array formulation shading.visible_samples had before it was compiled."""
    pts_cam = samples.points_mm @ pose.R_m2c.T + pose.t_m2c
    normals_cam = samples.normals @ pose.R_m2c.T
    in_front = pts_cam[:, 2] > 1e-6
    ray = pts_cam / np.maximum(np.linalg.norm(pts_cam, axis=1, keepdims=True), 1e-12)
    facing = -np.sum(normals_cam * ray, axis=1) > MIN_FACING_COS
    idx = np.flatnonzero(in_front & facing)
    uv = camera.project(pts_cam[idx])
    inside = ((uv[:, 0] >= 0) & (uv[:, 0] <= camera.width - 1)
              & (uv[:, 1] >= 0) & (uv[:, 1] <= camera.height - 1))
    idx, uv = idx[inside], uv[inside]
    if len(idx) == 0:
        return uv, np.zeros((0, 3)), idx
    z = pts_cam[idx, 2]
    cell_px = max(1.0, 3.0 * samples.spacing_mm * camera.fx / float(np.median(z)))
    cells = (np.floor(uv[:, 1] / cell_px) * (camera.width / cell_px + 1)
             + np.floor(uv[:, 0] / cell_px))
    order = np.lexsort((z, cells))
    sorted_cells = cells[order]
    starts = np.flatnonzero(np.r_[True, sorted_cells[1:] != sorted_cells[:-1]])
    nearest = np.repeat(z[order][starts], np.diff(np.r_[starts, len(order)]))
    seen = order[z[order] <= nearest + 2.0 * samples.spacing_mm]
    return uv[seen], normals_cam[idx[seen]], idx[seen]


def _array_agreement(image, uv, normals, albedo=None):
    """The array formulation of shading_agreement's robust fit (with
    ``albedo``, (M,): of albedo x SH(normal) plus an offset)."""
    intensity = intensity_at(image, uv)
    x, y, z = normals[:, 0], normals[:, 1], normals[:, 2]
    basis = np.stack([np.ones_like(x), x, y, z, x * y, x * z, y * z, x * x - y * y,
                      3.0 * z * z - 1.0], axis=1)
    if albedo is not None:
        basis = np.concatenate([basis * albedo[:, None], np.ones((len(x), 1))], axis=1)
    weights = np.ones(len(intensity))
    residual = intensity - intensity.mean()
    min_scale = 1e-9 * (1.0 + float(np.abs(intensity).max()))
    for _ in range(4):
        weighted = basis.T * weights
        coef, *_ = np.linalg.lstsq(weighted @ basis, weighted @ intensity, rcond=None)
        residual = intensity - basis @ coef
        weights, _ = tukey_weights(residual, min_scale)
    total_weight = float(weights.sum())
    mean = float(weights @ intensity) / total_weight
    spread = float(weights @ (intensity - mean) ** 2)
    if spread <= 1e-9 * total_weight * max(1.0, mean * mean):
        return None
    return float(np.clip(1.0 - float(weights @ residual**2) / spread, 0.0, 1.0))


def _rows(uv, normals):
    """The rows sorted by position (the compiled form keeps the samples' order)."""
    order = np.lexsort((uv[:, 1], uv[:, 0]))
    return uv[order], normals[order]


#: The compiled fit and the array form sum in different orders, and four
#: reweighted least-squares rounds carry the rounding on: a draw of
#: Hypothesis's put them 3e-9 apart (an agreement of 0.385). A change of
#: the arithmetic itself moves the agreement by far more than this.
AGREEMENT_TOLERANCE = 1e-6


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(0, 1), st.integers(0, 1),
       st.floats(-250.0, 250.0), st.floats(-200.0, 200.0), st.floats(250.0, 1500.0))
def test_visible_samples_and_agreement_are_the_array_forms(seed, part, lens, x, y, z):
    # Off-centre poses put parts across the image border; near ones make
    # the depth-buffer cells a pixel wide.
    samples, camera = SAMPLES[part], CAMERAS[lens]
    pose = Pose(Rotation.random(random_state=seed).as_matrix(), np.array([x, y, z]))
    uv, normals, index = visible_samples(samples, camera, pose)
    visible_a = _array_visible(samples, camera, pose)
    uv_a, normals_a, index_a = visible_a
    assert len(uv) == len(uv_a)
    assert np.all(np.diff(index) > 0) and np.array_equal(index, np.sort(index_a))
    if len(uv) == 0:
        return
    uv, normals = _rows(uv, normals)
    uv_a, normals_a = _rows(uv_a, normals_a)
    assert np.allclose(uv, uv_a, atol=1e-9) and np.allclose(normals, normals_a, atol=1e-12)
    rng = np.random.default_rng(seed)
    image = cv2.GaussianBlur((rng.random((480, 640, 3)) * 255).astype(np.uint8), (0, 0), 4.0)
    expected = _array_agreement(image, uv_a, normals_a) if len(uv) >= 40 else None
    got = shading_agreement(image, camera, pose, samples)
    assert (got is None) == (expected is None)
    if got is not None:
        assert got == pytest.approx(expected, abs=AGREEMENT_TOLERANCE)
    # A patterned part: each sample's albedo scales its harmonics.
    albedo = rng.uniform(0.1, 0.9, len(samples.points_mm))
    patterned = replace(samples, albedo=albedo)
    expected = (_array_agreement(image, visible_a[0], visible_a[1], albedo[index_a])
                if len(uv) >= 40 else None)
    got = shading_agreement(image, camera, pose, patterned)
    assert (got is None) == (expected is None)
    if got is not None:
        assert got == pytest.approx(expected, abs=AGREEMENT_TOLERANCE)


def test_nothing_is_seen_behind_the_camera_or_outside_the_image():
    samples, camera = SAMPLES[0], CAMERAS[0]
    assert len(visible_samples(samples, camera, Pose(np.eye(3), np.array([0, 0, -500.0])))[0]) == 0
    assert len(visible_samples(samples, camera,
                               Pose(np.eye(3), np.array([5000.0, 0, 500.0])))[0]) == 0


def test_a_uniform_part_has_nothing_to_explain():
    samples, camera = SAMPLES[0], CAMERAS[0]
    grey = np.full((480, 640), 128, np.uint8)
    assert shading_agreement(grey, camera, Pose(np.eye(3), np.array([0, 0, 500.0])),
                             samples) is None
