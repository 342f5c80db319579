"""benchmarks/worst_sequence.py: its pick follows WORST_RULE on a hand-made saved run, its strip
shows each preset's crossed legs, and its figure function writes a small PNG."""
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import worst_sequence  # noqa: E402

from minretarget.conventions import JOINT_INDEX  # noqa: E402


def saved_entry(name, regressed_crossed, regressed_pa, fitted_crossed=0):
    return {"sequence": name, "target_body": "body", "frames": 10,
            "metrics": {"regressed preset": {"PA-MPJPE": regressed_pa},
                        "model": {"PA-MPJPE": 0.01}},
            "skeleton": {"regressed preset": {"crossed_legs": regressed_crossed},
                         "model": {"crossed_legs": fitted_crossed}}}


def test_the_pick_is_the_regressed_presets_most_crossed_legs_then_its_pa_mpjpe():
    saved = [saved_entry("a", 3, 0.09, fitted_crossed=90),   # the fitted's worst: not picked
             saved_entry("b", 12, 0.02),
             saved_entry("c", 12, 0.03),                     # tie on crossed legs: higher PA
             saved_entry("d", 11, 0.08),
             saved_entry("e", 12, 0.03)]                     # a full tie: the first in the file
    assert worst_sequence.pick_worst(saved)["sequence"] == "c"
    assert worst_sequence.pick_worst(saved[:2] + saved[3:])["sequence"] == "e"
    assert worst_sequence.pick_worst(saved[:1])["sequence"] == "a"
    with pytest.raises(ValueError):
        worst_sequence.pick_worst([])


def test_the_strip_shows_the_middles_of_each_presets_longest_crossed_runs():
    regressed, fitted = np.zeros(100, bool), np.zeros(100, bool)
    regressed[10:20] = regressed[40:43] = regressed[60:62] = regressed[90] = True
    fitted[70:80] = True
    assert worst_sequence.runs_of(regressed) == [(10, 20), (40, 43), (60, 62), (90, 91)]
    assert worst_sequence.strip_frames([regressed, fitted]) == [0, 14, 20, 41, 60, 74]   # then 0, 20 spread
    assert worst_sequence.strip_frames([np.zeros(3, bool)] * 2) == [0, 1, 2]


def synthetic(frames=8, seed=0):
    """A short sequence dict and both presets' (joints, vertices): the regressed result's
    ankles swapped sides in frames 2 and 3, the fitted one's in frame 5."""
    rng = np.random.default_rng(seed)
    truth = rng.normal(scale=0.2, size=(frames, 22, 3)) + [0.0, 1.0, 0.0]
    truth[:, :, 0] += np.linspace(0.0, 0.5, frames)[:, None]            # walking along x
    for side, x in (("left", 0.1), ("right", -0.1)):
        for joint in ("hip", "ankle", "foot"):
            truth[:, JOINT_INDEX[f"{side}_{joint}"], 0] = x + np.linspace(0.0, 0.5, frames)
            truth[:, JOINT_INDEX[f"{side}_{joint}"], 2] = 0.0
        truth[:, JOINT_INDEX[f"{side}_ankle"], 1] = truth[:, JOINT_INDEX[f"{side}_foot"], 1] = 0
    points = rng.normal(scale=0.3, size=(frames, 50, 3)) + truth[:, :1]
    sequence = {"source_points": rng.normal(scale=0.3, size=(frames, 64, 3)),
                "source_joints": truth, "target_joints": truth, "target_points": points,
                "target_tpose_points": points[0]}
    runs = {}
    for name, crossed in (("regressed", [2, 3]), ("fitted", [5])):
        joints = truth.copy()
        left, right = JOINT_INDEX["left_ankle"], JOINT_INDEX["right_ankle"]
        joints[crossed, left, 0], joints[crossed, right, 0] = (joints[crossed, right, 0],
                                                                joints[crossed, left, 0])
        runs[name] = (joints, points + 0.01)
    return sequence, runs


def test_the_figures_and_the_picture(tmp_path):
    sequence, runs = synthetic()
    numbers, truth_speed = worst_sequence.figures(runs, sequence)
    assert [numbers[name]["crossed_legs"] for name in runs] == [2, 1]
    assert truth_speed == pytest.approx(0.5 / 7 * 30)     # the toes walk 0.5 m in 7 steps
    png = tmp_path / "worst.png"
    shown = worst_sequence.draw_figure(sequence, runs, png, title="synthetic")
    assert shown == [0, 1, 2, 3, 4, 5]      # crossed 2 and 5, then spread 0, 1, 3, 4
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert 1_000 < png.stat().st_size < 300_000


def test_it_refuses_the_test_split_without_report(capsys):
    with pytest.raises(SystemExit):
        worst_sequence.main(["--out", "unused"])
    assert "--report" in capsys.readouterr().err
