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
