from pathlib import Path

import numpy as np
import pytest

from minretarget.weights import load_weights

GOLDEN = Path(__file__).parent / "golden"


@pytest.fixture(scope="session")
def tiny_weights():
    """The tiny random model of tests/golden (made by tests/make_golden.py)."""
    return load_weights(GOLDEN / "tiny_weights.npz")


@pytest.fixture(scope="session")
def tiny_stream():
    """The golden stream: target (V, 3), source frames [(P_t, 3)], torch outputs by name."""
    with np.load(GOLDEN / "tiny_stream.npz") as data:
        arrays = dict(data)
    sources = np.split(arrays.pop("source_points"), np.cumsum(arrays.pop("source_counts"))[:-1])
    return arrays.pop("target"), sources, arrays
