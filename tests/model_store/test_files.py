"""The model files' checksum: what the store keeps and the API reports."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from model_store import load_model_dir, save_model_dir
from model_store.files import model_sha256
from viewloc_core.learn import LearningConfig, learn_from_mesh
from viewloc_core.model import ObjectModel, model_from_arrays, model_to_arrays


@pytest.fixture(scope="module")
def box_model() -> ObjectModel:
    config = LearningConfig(max_level=0, min_level=0, contour_level=1, object_px=64)
    return learn_from_mesh(trimesh.creation.box((40.0, 20.0, 10.0)), config, rng=0)


def test_a_models_checksum_is_the_stored_one_and_follows_its_arrays(
    box_model: ObjectModel, tmp_path: Path
) -> None:
    digest = model_sha256(box_model)
    assert len(digest) == 64
    assert save_model_dir(tmp_path / "a", box_model) == digest
    assert model_sha256(load_model_dir(tmp_path / "a", digest)) == digest
    arrays, meta = model_to_arrays(box_model)
    nudged = dict(arrays, tv_edge_theta=arrays["tv_edge_theta"].copy())
    nudged["tv_edge_theta"][7] = np.nextafter(nudged["tv_edge_theta"][7], np.float32(10.0))
    assert model_sha256(model_from_arrays(nudged, meta)) != digest
