"""The bookkeeping of benchmarks/fit_settings.py: candidates parsed and checked, figures
weighted by frames, counts summed, toes pooled."""
import argparse
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import fit_settings  # noqa: E402


def test_candidates_are_checked_settings():
    assert fit_settings.candidate('{"race_iterations": 4}').race_iterations == 4
    with pytest.raises(argparse.ArgumentTypeError, match="iterations must be"):
        fit_settings.candidate('{"iterations": 0}')
    with pytest.raises(argparse.ArgumentTypeError, match="unexpected keyword"):
        fit_settings.candidate('{"no_such_field": 1}')


def test_summary_weights_sums_and_pools():
    runs = [{"frames": 3, "figures": {"source all": 1.0, "crossed": 2, "reading won": 1,
                                       "toes": [0.6, 3]}},
            {"frames": 1, "figures": {"source all": 5.0, "crossed": 1, "reading won": 0,
                                       "toes": [0.4, 1]}}]
    summary = fit_settings.summarize(runs)
    assert summary["source all"] == pytest.approx((3 * 1.0 + 5.0) / 4)
    assert summary["crossed"] == 3 and summary["reading won"] == 1
    assert summary["toes"] == pytest.approx(1.0 / 4)


def test_every_set_names_a_selection_set_maker():
    from training.data import datasets
    for split, maker in fit_settings.SELECTION_SETS.values():
        assert callable(getattr(datasets, maker))
    assert "test" not in fit_settings.SELECTION_SETS
