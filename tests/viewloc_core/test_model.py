"""Model serialisation: arrays + JSON round trip, schema checks."""

import json

import numpy as np
import pytest

from viewloc_core.errors import ModelFormatError
from viewloc_core.model import model_from_arrays, model_to_arrays


def test_round_trip_is_identical(bracket_model, tmp_path):
    arrays, meta = model_to_arrays(bracket_model)
    np.savez(tmp_path / "model.npz", **arrays)
    (tmp_path / "model.json").write_text(json.dumps(meta))
    with np.load(tmp_path / "model.npz") as loaded:
        back = model_from_arrays(dict(loaded), json.loads((tmp_path / "model.json").read_text()))
    arrays2, meta2 = model_to_arrays(back)
    assert meta2 == meta
    assert arrays.keys() == arrays2.keys()
    for key in arrays:
        np.testing.assert_array_equal(arrays[key], arrays2[key], err_msg=key)
    assert back.n_model_views == bracket_model.n_model_views
    assert back.training_views == bracket_model.training_views


def test_unknown_schema_version_is_rejected(bracket_model):
    arrays, meta = model_to_arrays(bracket_model)
    with pytest.raises(ModelFormatError):
        model_from_arrays(arrays, meta | {"schema_version": 999})


def test_missing_array_is_rejected(bracket_model):
    arrays, meta = model_to_arrays(bracket_model)
    del arrays["mv_xy"]
    with pytest.raises(ModelFormatError):
        model_from_arrays(arrays, meta)


@pytest.mark.parametrize("name", ["mesh_vertices_mm", "mv_xy", "tv_sim_to_model",
                                  "contour_points_obj", "symmetries"])
@pytest.mark.parametrize("bad", [np.inf, np.nan])
def test_a_non_finite_array_is_rejected_naming_it(bracket_model, name, bad):
    arrays, meta = model_to_arrays(bracket_model)
    values = np.array(arrays[name], copy=True)
    values.reshape(-1)[-1] = bad
    with pytest.raises(ModelFormatError, match=f"'{name}' holds 1 non-finite"):
        model_from_arrays({**arrays, name: values}, meta)


@pytest.mark.parametrize("name", ["d0_mm", "f_train_px", "contour_meta.f_px"])
def test_a_non_finite_metadata_number_is_rejected_naming_it(bracket_model, name):
    arrays, meta = model_to_arrays(bracket_model)
    outer, _, key = name.rpartition(".")
    changed = ({**meta, outer: {**meta[outer], key: float("inf")}} if outer
               else {**meta, key: float("inf")})
    with pytest.raises(ModelFormatError, match=f"'{name}' is inf"):
        model_from_arrays(arrays, changed)


def test_symmetries_round_trip_and_form_a_group(bracket_model):
    from dataclasses import replace

    from viewloc_core.symmetry import Symmetries

    # The learned bracket is asymmetric: only the identity, no axis.
    assert bracket_model.symmetries.shape == (1, 4, 4)
    assert bracket_model.symmetry_axis is None
    assert bracket_model.symmetry_group().is_continuous is False
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    sym = replace(bracket_model, symmetries=np.stack([np.eye(4), flip]),
                  symmetry_axis=np.array([1.0, 0.0, 0.0, 0.0, 0.0, 5.0]))
    arrays, meta = model_to_arrays(sym)
    back = model_from_arrays(arrays, meta)
    group = back.symmetry_group()
    assert isinstance(group, Symmetries) and group.is_continuous
    np.testing.assert_array_equal(group.continuous_offset, [0.0, 0.0, 5.0])
    np.testing.assert_array_equal(back.symmetries, sym.symmetries)


def test_a_models_symmetry_group_is_built_once_and_a_changed_model_gets_its_own(bracket_model):
    from dataclasses import replace

    group = bracket_model.symmetry_group()
    assert bracket_model.symmetry_group() is group
    assert len(group.discrete) == 1 and not group.is_continuous
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    flipped = replace(bracket_model, symmetries=np.stack([np.eye(4), flip]))
    other = flipped.symmetry_group()
    assert other is not group and flipped.symmetry_group() is other
    np.testing.assert_array_equal(other.discrete, flipped.symmetries)
    assert bracket_model.symmetry_group() is group

