"""The bookkeeping of benchmarks/accuracy.py: the paired comparison with the analytic baseline
and the tables of a saved run, on hand-made per-sequence results."""
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import with_rest_pose
from minretarget.contacts import FootLock
from minretarget.conventions import JOINT_INDEX, NUM_JOINTS
from minretarget.kinematics import leg_length
from minretarget.metrics import METRIC_NAMES
from minretarget.nn import Dense
from minretarget.pipeline import DEFAULT_PRESET, PRESETS
from minretarget.retargeter import Retargeter, Target
from minretarget.weights import checksum_path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import accuracy  # noqa: E402


def results(gaps, frames, base=1.0):
    """Per-sequence results whose model scores ``base + gap`` and analytic ``base`` on every
    metric; toe speeds are placeholders the tables need."""
    return [{"sequence": f"s{k}", "category": "walk", "target_body": "b", "frames": n,
             "metrics": {"model": dict.fromkeys(METRIC_NAMES, base + gap),
                         "analytic": dict.fromkeys(METRIC_NAMES, base)},
             "feet": {"model": [1.0, 2], "analytic": [2.0, 2], "ground truth": [0.5, 2]}}
            for k, (gap, n) in enumerate(zip(gaps, frames))]


def test_paired_difference_by_hand():
    """Gaps -1 (1 frame) and +1 (3 frames): frame-weighted +0.5; every resample lies between
    the two gaps; one sequence of two is better."""
    out = accuracy.paired_difference(results([-1.0, 1.0], [1, 3]), "model", "analytic",
                                     samples=2000)
    for metric in METRIC_NAMES:
        assert out[metric]["difference"] == pytest.approx(0.5)
        low, high = out[metric]["ci95"]
        assert -1.0 <= low < 0.5 < high <= 1.0
        assert (out[metric]["sequences_better"], out[metric]["sequences"]) == (1, 2)


def test_a_constant_gap_has_no_spread_and_the_draws_are_seeded():
    saved = results([-0.25] * 5, [10, 20, 30, 40, 50])
    out = accuracy.paired_difference(saved, "model", "analytic")
    assert out["MPJPE"]["ci95"] == pytest.approx([-0.25, -0.25])
    assert out["MPJPE"]["sequences_better"] == 5
    varied = results([-0.3, 0.1, 0.2, -0.5, 0.05], [10, 20, 30, 40, 50])
    assert (accuracy.paired_difference(varied, "model", "analytic")
            == accuracy.paired_difference(varied, "model", "analytic"))


def test_from_json_prints_a_saved_run_and_adds_its_tables(tmp_path, capsys):
    """--from-json recomputes nothing: the rows are the saved per-sequence metrics weighted
    by frames, and --json writes the run back with the comparison added."""
    saved = {"per_sequence": results([-0.1, 0.3], [3, 1], base=2.0), "split": "test",
             "weights": "w"}
    path = tmp_path / "run.json"
    path.write_text(json.dumps(saved))
    accuracy.main(["--from-json", str(path), "--json", str(path)])
    printed = capsys.readouterr().out
    assert "Model minus analytic" in printed
    written = json.loads(path.read_text())
    assert written["weights"] == "w" and written["per_sequence"] == saved["per_sequence"]
    assert written["rows"]["model"]["MPJPE"] == pytest.approx(2.0 + (-0.1 * 3 + 0.3) / 4)
    comparison = written["paired_differences"]["model minus analytic"]
    assert comparison["PA-MPJPE"]["difference"] == pytest.approx(0.0)
    assert written["feet_on_truth_contacts"]["all"]["model"] == pytest.approx(0.5)


@pytest.mark.parametrize("pair", [["--validation", "--dances"], ["--quick", "--dances"],
                                  ["--quick", "--validation"], ["--motions", "--dances"],
                                  ["--validation", "--motions"]])
def test_one_set_of_sequences_a_run(pair, capsys):
    with pytest.raises(SystemExit) as stop:
        accuracy.main(pair)
    assert stop.value.code == 2 and "not allowed with argument" in capsys.readouterr().err


def test_compare_pairs_the_model_with_a_saved_runs_model(tmp_path, capsys):
    """--compare: this run's model minus the saved run's, frame-weighted over the same
    sequences; runs over other sequences are refused, naming the first that differs, and a
    run of another split (or quick against full) before any work."""
    this, other = tmp_path / "this.json", tmp_path / "other.json"
    this.write_text(json.dumps({"per_sequence": results([0.0, 0.0], [3, 1], base=2.0),
                                "split": "validation"}))
    other.write_text(json.dumps({"per_sequence": results([0.4, -0.4], [3, 1], base=2.0),
                                 "split": "validation", "weights": "old.npz",
                                 "weights_sha256": "ab" * 32}))
    accuracy.main(["--from-json", str(this), "--compare", str(other), "--json", str(this)])
    assert f"Model minus the model of {other}" in capsys.readouterr().out
    compared = json.loads(this.read_text())["compared_with"]
    assert compared["run"] == str(other)
    # which weights that was, kept for when the other file is gone
    assert (compared["weights"], compared["weights_sha256"]) == ("old.npz", "ab" * 32)
    difference = compared["model minus its model"]["MPJPE"]
    assert difference["difference"] == pytest.approx(-(0.4 * 3 - 0.4) / 4)
    assert (difference["sequences_better"], difference["sequences"]) == (1, 2)
    shorter = results([0.0], [3])
    shorter[0]["sequence"] = "s9"
    other.write_text(json.dumps({"per_sequence": shorter, "split": "validation"}))
    with pytest.raises(ValueError, match=r"sequence 0 is s0 \(3 frames\) here but s9"):
        accuracy.main(["--from-json", str(this), "--compare", str(other)])
    other.write_text(json.dumps({"per_sequence": results([0.0], [3]), "split": "validation"}))
    with pytest.raises(ValueError, match="2 sequences here, 1 in the saved run"):
        accuracy.main(["--from-json", str(this), "--compare", str(other)])
    other.write_text(json.dumps({"per_sequence": results([0.0, 0.0], [3, 1]), "split": "test",
                                 "quick": True}))
    with pytest.raises(SystemExit) as stop:     # another split: refused before any work
        accuracy.main(["--from-json", str(this), "--compare", str(other)])
    assert stop.value.code == 2
    assert "scored test sequences (quick), this run validation" in capsys.readouterr().err


def test_compare_refuses_a_run_of_other_sequences_before_loading_any(tmp_path, capsys):
    (tmp_path / "test").mkdir()
    for name in ("a", "b"):                    # never loaded: the check comes first
        (tmp_path / "test" / f"{name}.npz").write_bytes(b"not an npz")
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"per_sequence": results([0.0, 0.0], [3, 1]), "split": "test"}))
    with pytest.raises(SystemExit) as stop:
        accuracy.main(["--data", str(tmp_path), "--compare", str(other), "--rows", "model",
                       "--report"])
    assert stop.value.code == 2
    assert "--compare: sequence 0 is a (? frames) here but s0 (3 frames)" in \
        capsys.readouterr().err


def test_weights_record_names_the_bytes_measured(tmp_path):
    """A saved run records the weights' SHA-256: the shipped file's matches the one recorded
    beside it, and a copy under another name records the same digest, its path as given."""
    weights = accuracy.load_weights()
    shipped = accuracy.weights_record(None, weights)
    recorded = checksum_path(accuracy.DEFAULT_WEIGHTS).read_text().split()[0]
    assert shipped["weights"] == "shipped default" and shipped["weights_sha256"] == recorded
    copy = tmp_path / "candidate.npz"
    copy.write_bytes(accuracy.DEFAULT_WEIGHTS.read_bytes())
    record = accuracy.weights_record(str(copy), weights)
    assert record["weights"] == str(copy) and record["weights_sha256"] == recorded
    assert record["weights_metadata"] == weights.metadata
    changed = bytearray(copy.read_bytes())
    changed[-1] ^= 1                                       # one bit flipped: another digest
    copy.write_bytes(bytes(changed))
    assert accuracy.weights_record(str(copy), weights)["weights_sha256"] != recorded


def test_bad_runs_are_refused_at_once(tmp_path, capsys):
    """No data: refused with the build command, not built (unless --build); a saved run that
    is not one, and --from-json with options that would not apply: refused by name."""
    with pytest.raises(SystemExit):
        accuracy.main(["--data", str(tmp_path / "nodata"), "--quick", "--report"])
    err = capsys.readouterr().err
    assert "nodata/test is absent: build it (-m training.data build" in err and "--build" in err
    assert not (tmp_path / "nodata").exists()
    (tmp_path / "empty.json").write_text("{}")
    with pytest.raises(ValueError, match="empty.json: not a saved accuracy run"):
        accuracy.main(["--from-json", str(tmp_path / "empty.json")])
    (tmp_path / "text.json").write_text("not json")
    with pytest.raises(ValueError, match="text.json: cannot read a saved run"):
        accuracy.main(["--from-json", str(tmp_path / "text.json")])
    saved = tmp_path / "saved.json"
    saved.write_text(json.dumps({"per_sequence": results([0.0], [3]), "split": "test"}))
    with pytest.raises(SystemExit):
        accuracy.main(["--from-json", str(saved), "--weights", "other.npz", "--rows", "model"])
    assert "--weights, --rows would not apply" in capsys.readouterr().err


def test_command_line_errors_are_one_line(tmp_path):
    import subprocess
    script = Path(accuracy.__file__)
    done = subprocess.run([sys.executable, str(script), "--from-json", str(tmp_path / "no.json")],
                          capture_output=True, text=True)
    assert done.returncode == 1 and "Traceback" not in done.stderr
    assert done.stderr == (f"accuracy.py: error: {tmp_path / 'no.json'}: cannot read a saved "
                           f"run ([Errno 2] No such file or directory: '{tmp_path / 'no.json'}')\n")


def test_skeleton_figures_are_summed_and_pooled(tmp_path):
    """source_error frame-weighted, crossed_legs summed, skating pooled over steps, the
    truth's own skating ratio and toe speed in a 'ground truth' row of the JSON."""
    runs = results([0.0, 0.0], [3, 1])
    figures = ({"model": {"crossed_legs": 2, "skating": [1, 4], "source_error":
                          {"all": 0.01, "legs": 0.02}},
                "analytic": {"crossed_legs": 0, "skating": [0, 4], "source_error":
                             {"all": 0.01, "legs": 0.02}},
                "ground truth": {"skating": [0, 4]}},
               {"model": {"crossed_legs": 1, "skating": [3, 4], "source_error":
                          {"all": 0.05, "legs": 0.06}},
                "analytic": {"crossed_legs": 0, "skating": [0, 4], "source_error":
                             {"all": 0.05, "legs": 0.06}},
                "ground truth": {"skating": [2, 4]}})
    for run, figure in zip(runs, figures):
        run["skeleton"] = figure
    path = tmp_path / "run.json"
    path.write_text(json.dumps({"per_sequence": runs, "split": "test"}))
    accuracy.main(["--from-json", str(path), "--json", str(path)])
    rows = json.loads(path.read_text())["rows"]
    assert rows["model"]["source_error"] == pytest.approx((0.01 * 3 + 0.05) / 4)
    assert rows["model"]["source_error_legs"] == pytest.approx((0.02 * 3 + 0.06) / 4)
    assert rows["model"]["crossed_legs"] == 3
    assert rows["model"]["skating_ratio"] == pytest.approx(4 / 8)
    assert rows["ground truth"]["skating_ratio"] == pytest.approx(2 / 8)
    assert rows["ground truth"]["toe_speed"] == pytest.approx(0.25)
    assert rows["model"]["toe_speed"] == pytest.approx(0.5)


@pytest.mark.parametrize("argv", [[], ["--quick"], ["--rows", "model", "analytic"],
                                  ["--build"]])
def test_the_test_split_is_refused_without_report(tmp_path, capsys, argv):
    """A run of the test split without --report stops at once (nothing built or read) and
    says why: the test split is run once per release, for the report, never to choose."""
    with pytest.raises(SystemExit) as stop:
        accuracy.main(["--data", str(tmp_path / "nodata"), *argv])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and "--report" in err
    assert "run once per release, for the report, and never selects anything" in err
    assert not (tmp_path / "nodata").exists()


def test_report_applies_to_the_test_split_only(tmp_path, capsys):
    for split in ("--validation", "--dances", "--motions"):
        with pytest.raises(SystemExit) as stop:
            accuracy.main([split, "--report", "--cmu", str(tmp_path)])
        assert stop.value.code == 2 and "--report is for the test split" in \
            capsys.readouterr().err
    saved = tmp_path / "saved.json"           # a saved test run prints without --report
    saved.write_text(json.dumps({"per_sequence": results([0.0], [3]), "split": "test"}))
    accuracy.main(["--from-json", str(saved)])
    with pytest.raises(SystemExit):
        accuracy.main(["--from-json", str(saved), "--report"])
    assert "--report would not apply" in capsys.readouterr().err


@pytest.mark.parametrize("name", ["robustness", "ablations", "heading_flips", "renders"])
def test_every_benchmark_of_the_test_split_wants_report(name, tmp_path, capsys):
    """The other benchmarks that read DIR/test refuse without --report, before any work."""
    import importlib
    module = importlib.import_module(name)
    with pytest.raises(SystemExit) as stop:
        module.main(["--data", str(tmp_path / "nodata")])
    assert stop.value.code == 2
    assert accuracy.TEST_SPLIT_RULE in capsys.readouterr().err


def test_the_weights_note_names_the_splits_that_chose_them(tmp_path, capsys):
    record = {"weights": "w.npz", "weights_metadata": {"selected_on": ["validation",
                                                                       "training dances"]}}
    assert accuracy.weights_note(record) == \
        "Weights: w.npz; chosen on: validation, training dances"
    assert accuracy.weights_note({"weights": "old.npz", "weights_metadata": {}}) == \
        "Weights: old.npz; chosen on: not recorded in their metadata"
    saved = tmp_path / "saved.json"
    saved.write_text(json.dumps({"per_sequence": results([0.0], [3]), "split": "validation",
                                 **record}))
    accuracy.main(["--from-json", str(saved)])
    assert "Weights: w.npz; chosen on: validation, training dances" in capsys.readouterr().out


# ----------------------------------------------------------------------------- analytic rows

def standing_stream(frames=40, seed=0):
    """(T, J, 3) a person standing still, every joint jittering by a few millimetres a frame
    (the way SKR's skeletons do): toes that the foot lock plants."""
    from test_contacts import human_tpose
    rng = np.random.default_rng(seed)
    return (human_tpose()[None] + rng.normal(0, 0.004, (frames, NUM_JOINTS, 3))
            ).astype(np.float32)


def simple_target(scale=1.1, seed=1):
    """A target rig: a scaled adult T-pose, points about it, each bound to its nearest joint."""
    from test_contacts import human_tpose
    tpose = human_tpose() * np.float32(scale)
    points = (tpose[np.random.default_rng(seed).integers(NUM_JOINTS, size=300)]
              + np.random.default_rng(seed + 1).normal(0, 0.03, (300, 3))).astype(np.float32)
    nearest = np.linalg.norm(points[:, None] - tpose[None], axis=-1).argmin(axis=1)
    return Target(points, None, tpose, np.eye(NUM_JOINTS, dtype=np.float32)[nearest],
                  float(leg_length(tpose)))


def test_the_analytic_row_without_rest_pose_or_foot_lock_is_the_plain_row():
    joints, target = standing_stream(), simple_target()
    full = accuracy.analytic_full(joints, target, rest_pose=None, foot_lock=None)
    plain = accuracy.analytic_plain(joints, target)
    for a, b in zip(full, plain):
        np.testing.assert_array_equal(a, b)


def test_the_analytic_rows_scale_the_root_by_the_target_s_leg_length():
    """As SMRM does: the target's ``leg_length`` (a mesh's read from its surface), not its
    skeleton's, over the source legs' running mean; twice the length, twice the root."""
    joints, target = standing_stream(), simple_target()
    longer = target._replace(leg_length=2 * target.leg_length)
    for analytic in (accuracy.analytic_plain, accuracy.analytic_full):
        root, twice = (analytic(joints, rig)[0][:, 0] for rig in (target, longer))
        legs = np.cumsum(leg_length(joints)) / np.arange(1, len(joints) + 1)
        np.testing.assert_allclose(root, (target.leg_length / legs)[:, None] * joints[:, 0],
                                   atol=1e-5)
        np.testing.assert_allclose(twice, 2 * root, atol=1e-5)


def test_the_foot_lock_holds_the_analytic_rows_feet_and_moves_only_the_legs():
    joints, target = standing_stream(), simple_target()
    locked, _ = accuracy.analytic_full(joints, target, foot_lock=FootLock())
    free, _ = accuracy.analytic_full(joints, target, foot_lock=None)
    toes = [JOINT_INDEX["left_foot"], JOINT_INDEX["right_foot"]]
    moved = [JOINT_INDEX[f"{side}_{name}"] for side in ("left", "right")
             for name in ("knee", "ankle", "foot")]
    others = [j for j in range(NUM_JOINTS) if j not in moved]
    np.testing.assert_array_equal(locked[:, others], free[:, others])
    assert np.abs(locked[:, moved] - free[:, moved]).max() > 1e-3

    def ground_speed(joints):          # horizontal toe travel per frame, metres
        return np.linalg.norm(np.diff(joints[:, toes][..., [0, 2]], axis=0), axis=-1).mean()
    assert ground_speed(locked) < 0.5 * ground_speed(free)


def test_the_analytic_row_is_the_model_with_smrms_networks_turned_to_identity(tiny_weights,
                                                                              tiny_stream):
    """SMRM whose heads answer no correction (identity quaternions, no root offset) on top of
    its analytic prior with the rest-pose model, then the foot lock: the model's frames are
    the analytic row's, computed independently from the source skeletons SMRM saw."""
    weights = with_rest_pose(tiny_weights)
    heads = weights.smrm
    identity = np.tile(np.float32([1, 0, 0, 0]), NUM_JOINTS)
    weights = weights._replace(smrm=heads._replace(
        rotation_head=Dense(np.zeros_like(heads.rotation_head.weight), identity),
        root_head=Dense(np.zeros_like(heads.root_head.weight),
                        np.zeros_like(heads.root_head.bias))))
    retargeter = Retargeter(weights, warn=False)
    foot_lock = retargeter.config.foot_lock
    assert accuracy.rest_pose_of(retargeter) is not None and foot_lock is not None
    target_points, _, _ = tiny_stream
    retargeter.set_target(target_points)
    skeletons = standing_stream(30) * np.float32(0.9)
    frames = [retargeter.step_skeleton(joints) for joints in skeletons]
    seen = np.stack([f.source_joints for f in frames])
    joints, vertices = accuracy.analytic_full(seen, retargeter.target,
                                              accuracy.rest_pose_of(retargeter), foot_lock)
    np.testing.assert_allclose(joints, np.stack([f.joints for f in frames]), atol=1e-4)
    np.testing.assert_allclose(vertices, np.stack([f.vertices for f in frames]), atol=1e-4)
    plain, _ = accuracy.analytic_plain(seen, retargeter.target)
    assert np.abs(plain - joints).max() > 1e-3        # the rest pose and the lock did move it


def test_the_analytic_rows_are_listed_and_paired():
    assert {"analytic", "analytic, plain"} <= set(accuracy.ROWS)
    assert {("model", "analytic"), ("model", "analytic, plain")} <= set(accuracy.PAIRS)


# ----------------------------------------------------------------------------- --draws

GOLDEN_WEIGHTS = Path(__file__).resolve().parent / "golden" / "tiny_weights.npz"
DRAWN_ROWS = ["model", "analytic", "regressed preset"]


def fake_test_split(folder, tiny_stream, frames=3, points=1300):
    """DIR/test with two short sequences: a jittering T-pose as the source (clouds of more
    points than the source fit reads, so that its draws differ) and the golden target."""
    from test_contacts import human_tpose
    target, _, _ = tiny_stream
    (folder / "test").mkdir()
    for k in range(2):
        rng = np.random.default_rng(k)
        joints = standing_stream(frames, seed=k)
        clouds = (joints[:, rng.integers(NUM_JOINTS, size=points)]
                  + rng.normal(0, 0.05, (frames, points, 3))).astype(np.float32)
        tpose = human_tpose()
        nearest = np.linalg.norm(target[:, None] - tpose[None], axis=-1).argmin(axis=1)
        np.savez(folder / "test" / f"s{k}.npz", name=f"s{k}", category="walk",
                 target_body="b", source_points=clouds, source_joints=joints,
                 target_points=np.repeat(target[None], frames, axis=0),
                 target_joints=np.repeat(tpose[None], frames, axis=0),
                 target_tpose_points=target, target_tpose_joints=tpose,
                 target_weights=np.eye(NUM_JOINTS, dtype=np.float32)[nearest])
    return folder


def run_draws(folder, out, draws, *extra):
    accuracy.main(["--data", str(folder), "--report", "--weights", str(GOLDEN_WEIGHTS),
                   "--rows", *DRAWN_ROWS, "--draws", str(draws), "--json", str(out), *extra])
    return json.loads(out.read_text())


@pytest.fixture(scope="module")
def drawn_runs(tmp_path_factory, tiny_stream):
    """The fake test split run over one draw and over two."""
    folder = fake_test_split(tmp_path_factory.mktemp("split"), tiny_stream)
    return (folder, run_draws(folder, folder / "one.json", 1),
            run_draws(folder, folder / "two.json", 2))


def test_one_draw_is_the_run_of_before(drawn_runs):
    """--draws 1 adds nothing, and a run over two draws keeps draw 0's figures where one
    draw's are."""
    _, one, two = drawn_runs
    assert "draws" not in one and "over_draws" not in one
    assert set(two) - set(one) == {"draws", "over_draws"}
    assert two["per_sequence"] == one["per_sequence"] and two["rows"] == one["rows"]


def test_the_rows_with_the_fit_are_run_on_every_draw(drawn_runs):
    """The model (the fitted preset) and the analytic row on its skeletons move with the
    draw; the regressed preset has no fit and runs once; the mean over draws is the mean of
    the draws' pooled figures, draw 0's those of the run."""
    assert PRESETS[DEFAULT_PRESET].fit_source is not None
    _, one, two = drawn_runs
    over = two["over_draws"]
    assert two["draws"] == 2 and list(over) == ["model", "analytic"]
    for row in ("model", "analytic"):
        first, second = over[row]["per_draw"]
        assert first == one["rows"][row]
        assert first["MPJPE"] != second["MPJPE"]
        for key, mean in over[row]["mean"].items():
            assert mean == pytest.approx((first[key] + second[key]) / 2)
    # draw 1's model row, pooled by hand from run_sequence on draw 1
    weights = accuracy.load_weights(GOLDEN_WEIGHTS)
    folder = drawn_runs[0]
    frames, mpjpe = 0, 0.0
    for path in sorted((folder / "test").glob("*.npz")):
        sequence = accuracy.load_sequence(path)
        rows, _, _ = accuracy.run_sequence(weights, sequence, DRAWN_ROWS, draw=1)
        assert list(rows) == ["model", "analytic"]
        joints = rows["model"][0]
        mpjpe += np.linalg.norm(joints - sequence["target_joints"], axis=-1).mean() * len(joints)
        frames += len(joints)
    assert over["model"]["per_draw"][1]["MPJPE"] == pytest.approx(mpjpe / frames, rel=1e-5)


def test_compare_over_draws_pairs_them_and_refuses_other_draws(drawn_runs, tmp_path, capsys):
    """--compare over two draws: the model minus the saved model draw by draw; a saved run
    over another number of draws is refused before any work."""
    folder, one, two = drawn_runs
    other = dict(two, over_draws=json.loads(json.dumps(two["over_draws"])))
    for d, figures in enumerate(other["over_draws"]["model"]["per_draw"]):
        figures["MPJPE"] += 0.01 * (d + 1)          # the saved model worse by 1 and 2 cm
    saved, path = tmp_path / "other.json", tmp_path / "this.json"
    saved.write_text(json.dumps(other))
    path.write_text(json.dumps(two))
    accuracy.main(["--from-json", str(path), "--compare", str(saved), "--json", str(path)])
    assert "draw by draw over 2 draws" in capsys.readouterr().out
    paired = json.loads(path.read_text())["compared_with"]["model minus its model, over draws"]
    assert paired["MPJPE"]["per_draw"] == pytest.approx([-0.01, -0.02])
    assert paired["MPJPE"]["difference"] == pytest.approx(-0.015)
    low, high = paired["MPJPE"]["interval"]       # t(0.975, 1) * 0.005 / sqrt(2) * sqrt(2)
    assert (low, high) == pytest.approx([-0.015 - 12.7062 * 0.005, -0.015 + 12.7062 * 0.005],
                                        rel=1e-4)
    assert paired["PA-MPJPE"]["per_draw"] == [0.0, 0.0]
    (tmp_path / "one.json").write_text(json.dumps(one))
    for argv in (["--from-json", str(path), "--compare", str(tmp_path / "one.json")],
                 ["--data", str(folder), "--report", "--rows", "model", "--draws", "2",
                  "--compare", str(tmp_path / "one.json"), "--weights", "absent.npz"]):
        with pytest.raises(SystemExit) as stop:
            accuracy.main(argv)
        assert stop.value.code == 2
        assert "ran the source fit on 1 draws, this run on 2" in capsys.readouterr().err
