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
    runs = [{"frames": 3, "figures": {"source all": 1.0, "crossed": 2, "result crossed": 4,
                                       "reading won": 1, "toes": [0.6, 3]}},
            {"frames": 1, "figures": {"source all": 5.0, "crossed": 1, "result crossed": 0,
                                       "reading won": 0, "toes": [0.4, 1]}}]
    summary = fit_settings.summarize(runs)
    assert summary["source all"] == pytest.approx((3 * 1.0 + 5.0) / 4)
    assert summary["crossed"] == 3 and summary["reading won"] == 1
    assert summary["result crossed"] == 4
    assert summary["toes"] == pytest.approx(1.0 / 4)


def test_every_set_names_a_selection_set_maker():
    from training.data import datasets
    for split, maker in fit_settings.SELECTION_SETS.values():
        assert callable(getattr(datasets, maker))
    assert "test" not in fit_settings.SELECTION_SETS


def test_draws_are_averaged_and_paired_draw_by_draw():
    """Two candidates on three draws: means over draws, and the second's differences from
    the first draw by draw, with Student's t interval (hand-computed: differences 1, 3, 5 ->
    mean 3, sd 2, t(0.975, 2) = 4.303)."""
    first = [{"crossed": 10, "toes": 0.1}, {"crossed": 20, "toes": 0.2},
             {"crossed": 30, "toes": 0.3}]
    second = [{"crossed": 11, "toes": 0.1}, {"crossed": 23, "toes": 0.2},
              {"crossed": 35, "toes": 0.3}]
    alone = fit_settings.over_draws(first)
    assert alone == {"mean": {"crossed": 20.0, "toes": pytest.approx(0.2)}}
    paired = fit_settings.over_draws(second, first)["minus_first"]
    assert paired["crossed"]["difference"] == pytest.approx(3.0)
    half = 4.302653 * 2.0 / 3 ** 0.5
    assert paired["crossed"]["interval"] == pytest.approx([3 - half, 3 + half], rel=1e-6)
    assert paired["toes"]["interval"] == pytest.approx([0.0, 0.0], abs=1e-12)


def test_draws_refuse_a_candidate_with_its_own_draw(tmp_path, capsys):
    with pytest.raises(SystemExit):
        fit_settings.main(["--draws", "2", "--fit", '{"draw": 3}', "--cmu", str(tmp_path)])
    assert "leave out their draw" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        fit_settings.main(["--draws", "0", "--cmu", str(tmp_path)])
    assert "--draws must be at least 1" in capsys.readouterr().err
