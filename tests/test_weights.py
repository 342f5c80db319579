"""The weights file: round trips, and every way a file can be wrong gives a named ValueError."""
import numpy as np
import pytest

from minretarget.weights import (FORMAT_VERSION, flatten_weights, load_weights, save_weights,
                                 weights_from_arrays)


@pytest.fixture()
def arrays(tiny_weights):
    return flatten_weights(tiny_weights)


def write(path, arrays):
    np.savez(path, **arrays)
    return path


def test_save_and_load_round_trip(tiny_weights, tmp_path):
    save_weights(tmp_path / "w.npz", tiny_weights)
    loaded = load_weights(tmp_path / "w.npz")
    assert loaded.config == tiny_weights.config and loaded.metadata == tiny_weights.metadata
    for key, value in flatten_weights(loaded).items():
        np.testing.assert_array_equal(value, flatten_weights(tiny_weights)[key])
    assert not list(tmp_path.glob("*.tmp"))   # the temporary file was renamed away


def test_float16_storage_loads_as_float32(tiny_weights, tmp_path):
    save_weights(tmp_path / "w16.npz", tiny_weights, dtype=np.float16)
    loaded = load_weights(tmp_path / "w16.npz")
    assert loaded.skr.regressor.head.output.weight.dtype == np.float32
    np.testing.assert_allclose(loaded.skin.output.weight, tiny_weights.skin.output.weight,
                               atol=2e-3)


@pytest.mark.parametrize("change, message", [
    (lambda a: a.pop("skin.output.bias"), "missing.*skin.output.bias"),
    (lambda a: a.update(extra=np.zeros(3, np.float32)), "unexpected.*extra"),
    (lambda a: a.update({"skin.output.bias": np.zeros(5, np.float32)}),
     "'skin.output.bias' has shape"),
    (lambda a: a.update({"smrm.root_head.weight": a["smrm.root_head.weight"].astype(np.float64)}),
     "'smrm.root_head.weight' has dtype float64"),
    (lambda a: a.update({"skr.regressor.point.0.bias": np.full(16, np.nan, np.float32)}),
     "'skr.regressor.point.0.bias' holds NaN"),
    (lambda a: a.update(format_version=np.array(FORMAT_VERSION + 1)), "format_version is 2"),
    (lambda a: a.pop("config"), "missing key 'config'"),
    (lambda a: a.update(config=np.array('{"smrm_hidden": 32, "colour": 1}')), "colour"),
])
def test_bad_weights_name_the_problem(arrays, tmp_path, change, message):
    change(arrays)
    path = write(tmp_path / "bad.npz", arrays)
    with pytest.raises(ValueError, match=message) as error:
        load_weights(path)
    assert "bad.npz" in str(error.value)


def test_pickled_content_is_refused_not_loaded(arrays, tmp_path):
    arrays["metadata"] = np.array([{"evil": "object"}], dtype=object)
    path = write(tmp_path / "pickled.npz", arrays)
    with pytest.raises(ValueError, match="pickled.npz"):
        load_weights(path)


def test_not_an_npz_and_missing_files(tmp_path):
    (tmp_path / "junk.npz").write_bytes(b"not a zip file")
    with pytest.raises(ValueError, match="junk.npz"):
        load_weights(tmp_path / "junk.npz")
    with pytest.raises(FileNotFoundError, match="absent.npz"):
        load_weights(tmp_path / "absent.npz")


def test_header_keys_must_be_scalars(arrays):
    arrays["format_version"] = np.array([FORMAT_VERSION])
    with pytest.raises(ValueError, match="'format_version' must be a scalar"):
        weights_from_arrays(arrays)


def test_files_from_before_the_refiner_load_without_one(tiny_weights):
    """A config JSON without the refine_* keys (files written before the refiner) loads with
    ``refine`` None; a refiner's arrays without its config are refused."""
    import json
    arrays = flatten_weights(tiny_weights)
    old = {k: v for k, v in arrays.items() if not k.startswith("refine.")}
    config = json.loads(str(old["config"]))
    for key in ("refine_point_widths", "refine_head_widths", "refine_neighbours"):
        del config[key]
    old["config"] = np.array(json.dumps(config))
    weights = weights_from_arrays(old)
    assert weights.refine is None and not weights.config.refines
    with pytest.raises(ValueError, match="unexpected.*refine"):
        weights_from_arrays({**old, "refine.point.0.weight": arrays["refine.point.0.weight"]})
