"""The training loop end to end on tiny synthetic datasets: every stage, export, resume."""
import json
import os
import signal
import types

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from conftest import with_rest_pose  # noqa: E402
from minretarget import Retargeter, metrics  # noqa: E402
from minretarget.conventions import JOINT_INDEX, NUM_JOINTS, PARENTS  # noqa: E402
from minretarget.weights import flatten_weights, load_weights, save_weights  # noqa: E402
from minretarget.pipeline import PipelineConfig
from training import kinematics  # noqa: E402
from training.losses import foot_velocity_error, rotation_distance, skin_loss  # noqa: E402
from training.recipe import load_recipe  # noqa: E402
from training.analytic import analytic_rotations  # noqa: E402
from training.train import (fit_steps, initial_models, main, retarget_ground_truth,  # noqa: E402
                            resume_differences, run_command, smoothed_skeletons,
                            source_noise)

TINY_RECIPE = {
    "name": "tiny", "seed": 0,
    "model": {"skr_point_widths": [8, 16, 32], "skr_head_widths": [16, 16], "smrm_hidden": 16,
              "smrm_layers": 1, "skin_widths": [16], "refine_point_widths": [8, 16],
              "refine_head_widths": [16], "refine_neighbours": 20, "denoise_hidden": 8},
    "skr": {"steps": 6, "batch_size": 4, "points": 80, "eval_every": 3},
    "refine": {"steps": 4, "batch_size": 4, "min_points": 60, "eval_every": 2},
    "denoise": {"steps": 4, "batch_size": 3, "window": 8, "eval_every": 2},
    "skin": {"steps": 4, "batch_size": 2, "points": 50, "eval_every": 2},
    "smrm": {"steps": 4, "batch_size": 3, "eval_every": 2, "discriminator_width": 8},
}


def skeleton(rng, height):
    """A random tree of bones below/above a pelvis at ``height``, feet near y = 0."""
    joints = np.zeros((NUM_JOINTS, 3), np.float32)
    joints[0] = [0, height, 0]
    for j in range(1, NUM_JOINTS):
        joints[j] = joints[PARENTS[j]] + rng.normal(0, 0.1, 3)
    return joints


def random_quaternions(rng, shape):
    q = rng.normal(size=shape + (4,)) * [1, 0.2, 0.2, 0.2] + [3, 0, 0, 0]
    return (q / np.linalg.norm(q, axis=-1, keepdims=True)).astype(np.float32)


def write_datasets(directory, rng):
    """Small files shaped like training/data's, with consistent kinematics."""
    def posed(rotations, root, tpose):
        joints, _ = kinematics.forward_kinematics(*map(torch.from_numpy, (rotations, root, tpose)))
        return joints.numpy()

    bodies = np.stack([skeleton(rng, h) for h in (0.8, 0.9, 1.0)])
    for split, n in (("train", 12), ("val", 5)):
        body = rng.integers(3, size=n)
        rotations, root = random_quaternions(rng, (n, NUM_JOINTS)), rng.normal(size=(n, 3))
        joints = posed(rotations, root.astype(np.float32), bodies[body])
        for name in ("skr", "skr_tpose"):
            np.savez(directory / f"{name}_{split}.npz", body=body.astype(np.int32), joints=joints,
                     points=(joints[:, rng.integers(NUM_JOINTS, size=100)]
                             + rng.normal(0, 0.05, (n, 100, 3))).astype(np.float32))
        tpose_points = (bodies[body][:, rng.integers(NUM_JOINTS, size=60)]
                        + rng.normal(0, 0.03, (n, 60, 3))).astype(np.float32)
        np.savez(directory / f"skin_{split}.npz", tpose_points=tpose_points,
                 posed_points=tpose_points + 0.01, rotations=rotations,
                 root=root.astype(np.float32), tpose_joints=bodies[body], joints=joints,
                 weights=np.full((n, 60, NUM_JOINTS), 1 / NUM_JOINTS, np.float16),
                 body=body.astype(np.int32))
        clip_rotations = random_quaternions(rng, (n, 30, NUM_JOINTS))
        clip_root = np.cumsum(rng.normal(0, 0.02, (n, 30, 3)), axis=1).astype(np.float32)
        np.savez(directory / f"smrm_{split}.npz", rotations=clip_rotations, root=clip_root,
                 joints=posed(clip_rotations, clip_root, bodies[body][:, None]),
                 tpose_joints=bodies[body], body=body.astype(np.int32),
                 bodies_tpose_joints=bodies)
        # Whole trials of 9 to 14 frames, one after another.
        starts = np.cumsum([0] + list(rng.integers(9, 15, size=3)))
        trials = rng.integers(3, size=3)
        frames = random_quaternions(rng, (starts[-1], NUM_JOINTS))
        root = np.cumsum(rng.normal(0, 0.02, (starts[-1], 3)), axis=0).astype(np.float32)
        joints = posed(frames, root, np.repeat(bodies[trials], np.diff(starts), axis=0))
        np.savez(directory / f"sequences_{split}.npz", joints=joints, starts=starts,
                 body=trials.astype(np.int32),
                 points=(joints[:, rng.integers(NUM_JOINTS, size=100)]
                         + rng.normal(0, 0.05, (starts[-1], 100, 3))).astype(np.float32))


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    directory = tmp_path_factory.mktemp("training")
    write_datasets(directory, np.random.default_rng(0))
    (directory / "tiny.json").write_text(json.dumps(TINY_RECIPE))
    main(["all", "--recipe", str(directory / "tiny.json"), "--data", str(directory),
          "--out", str(directory / "run"), "--threads", "1"])
    return directory


def test_all_stages_train_log_and_export_loadable_weights(run):
    out = run / "run"
    for stage in ("skr", "refine", "denoise", "skin", "smrm"):
        rows = (out / f"{stage}.csv").read_text().splitlines()
        assert len(rows) == 3                     # header + two evaluations
        assert (out / f"{stage}.png").stat().st_size > 0
    retargeter = Retargeter.from_weights(out / "weights.npz")
    assert retargeter.weights.metadata["recipe"]["name"] == "tiny"
    # the splits that may choose them, never the test split
    assert retargeter.weights.metadata["selected_on"] == ["validation", "training dances"]
    assert retargeter.weights.config.smrm_layers == 1
    assert retargeter.weights.refine is not None and retargeter.weights.denoise is not None
    retargeter.set_target(np.random.default_rng(1).normal(size=(100, 3)))
    frame = retargeter.step(np.random.default_rng(2).normal(size=(100, 3)))
    assert np.isfinite(frame.vertices).all()


def test_resume_continues_to_the_same_result(run, tmp_path):
    """Stop SKR half way, resume: the same weights and log as one uninterrupted run."""
    common = ["--recipe", str(run / "tiny.json"), "--data", str(run),
              "--out", str(tmp_path / "resumed"), "--threads", "1"]
    main(["skr", "--stop-at", "4"] + common)
    stopped = torch.load(tmp_path / "resumed" / "skr.pt", weights_only=True)
    assert stopped["step"] == 4
    stopped["seconds"] = 1000.0                    # as if the first part had taken long
    torch.save(stopped, tmp_path / "resumed" / "skr.pt")
    main(["skr", "--resume"] + common)
    whole = torch.load(run / "run" / "skr.pt", weights_only=True)
    resumed = torch.load(tmp_path / "resumed" / "skr.pt", weights_only=True)
    assert resumed["step"] == whole["step"] == 6
    for key, value in whole["modules"]["skr"].items():
        torch.testing.assert_close(resumed["modules"]["skr"][key], value, msg=key)
    assert resumed["rows"] == [dict(row, seconds=r["seconds"])
                               for row, r in zip(whole["rows"], resumed["rows"])]
    assert resumed["rows"][-1]["seconds"] >= 1000.0    # the log's clock goes on across it


def test_init_trains_listed_stages_and_keeps_the_others(run, tmp_path):
    """--init: SMRM fine-tuned from an exported file, SKR and SKIN carried over exactly."""
    start = run / "run" / "weights.npz"
    main(["smrm", "--init", str(start), "--recipe", str(run / "tiny.json"), "--data", str(run),
          "--out", str(tmp_path / "tuned"), "--threads", "1"])
    before = np.load(start)
    after = np.load(tmp_path / "tuned" / "weights.npz")
    assert sorted(before.files) == sorted(after.files)
    for key in before.files:
        if key.startswith(("skr.", "skin.", "refine.", "denoise.")):
            np.testing.assert_allclose(after[key], before[key], rtol=1e-6, atol=1e-7,
                                       err_msg=key)
    assert any(not np.array_equal(after[k], before[k]) for k in before.files
               if k.startswith("smrm."))
    metadata = json.loads(str(after["metadata"]))
    assert metadata["init"]["recipe"]["name"] == "tiny"


def test_analytic_prior_fine_tunes_from_weights_without_it(run, tmp_path):
    """--init from a file without the analytic prior: SMRM starts as exactly the analytic
    retargeting (its rotation head reset), trains, and exports weights that say so."""
    start = load_weights(run / "run" / "weights.npz")
    assert not start.config.smrm_analytic_prior
    recipe = load_recipe(run / "tiny.json", ["model.smrm_analytic_prior=true"])
    smrm = initial_models(recipe, start)["smrm"]
    joints = torch.from_numpy(np.load(run / "smrm_val.npz")["joints"][:2])      # (2, 30, J, 3)
    target = torch.from_numpy(np.load(run / "smrm_val.npz")["bodies_tpose_joints"][:2])
    with torch.no_grad():
        rotations, _, _, _ = smrm(joints, target)
    want = analytic_rotations(joints, target[:, None])
    assert (rotation_distance(rotations, want) < 1e-6).all()
    main(["smrm", "--init", str(run / "run" / "weights.npz"), "--recipe", str(run / "tiny.json"),
          "--set", "model.smrm_analytic_prior=true", "--data", str(run),
          "--out", str(tmp_path / "prior"), "--threads", "1"])
    assert load_weights(tmp_path / "prior" / "weights.npz").config.smrm_analytic_prior


def test_the_rest_pose_model_is_carried_through_training(run, tmp_path):
    """smrm --init <file with a rest-pose model>, with a recipe whose model has none: SMRM
    trains with that model in its prior and the export keeps it, array for array."""
    with_rest = with_rest_pose(load_weights(run / "run" / "weights.npz"))
    directions = with_rest.rest_pose.directions
    save_weights(tmp_path / "rest.npz", with_rest)
    recipe = load_recipe(run / "tiny.json", ["model.smrm_analytic_prior=true"])
    assert not recipe.model.rest_pose
    main(["smrm", "--init", str(tmp_path / "rest.npz"), "--recipe", str(run / "tiny.json"),
          "--set", "model.smrm_analytic_prior=true", "--data", str(run),
          "--out", str(tmp_path / "tuned"), "--threads", "1"])
    tuned = load_weights(tmp_path / "tuned" / "weights.npz")
    assert tuned.config.rest_pose
    np.testing.assert_array_equal(tuned.rest_pose.directions, directions)
    assert json.loads((tmp_path / "tuned" / "recipe.json").read_text())["model"]["rest_pose"]
    # SMRM from scratch keeps it too; a recipe without the analytic prior leaves it out.
    main(["smrm", "--init", str(tmp_path / "rest.npz"), "--recipe", str(run / "tiny.json"),
          "--set", "model.smrm_analytic_prior=true", "--scratch", "smrm", "--data", str(run),
          "--out", str(tmp_path / "scratch"), "--threads", "1"])
    scratch = load_weights(tmp_path / "scratch" / "weights.npz")
    np.testing.assert_array_equal(scratch.rest_pose.directions, directions)
    main(["smrm", "--init", str(tmp_path / "rest.npz"), "--recipe", str(run / "tiny.json"),
          "--scratch", "smrm", "--data", str(run), "--out", str(tmp_path / "plain"),
          "--threads", "1"])
    plain = load_weights(tmp_path / "plain" / "weights.npz")
    assert not plain.config.rest_pose and plain.rest_pose is None


def test_a_one_view_skr_is_carried_through_training(run, tmp_path):
    """smrm --init <file with a one-view SKR> (trained apart, training.skr_view): the export
    keeps it, array for array."""
    weights = load_weights(run / "run" / "weights.npz")
    head = weights.skr.regressor.head        # a network unlike the SKR, so a mix-up shows
    view = weights.skr._replace(regressor=weights.skr.regressor._replace(head=head._replace(
        output=head.output._replace(weight=head.output.weight * np.float32(0.5)))))
    with_view = weights._replace(config=weights.config.with_view_skr(), skr_view=view)
    save_weights(tmp_path / "view.npz", with_view)
    main(["smrm", "--init", str(tmp_path / "view.npz"), "--recipe", str(run / "tiny.json"),
          "--data", str(run), "--out", str(tmp_path / "tuned"), "--threads", "1"])
    tuned = load_weights(tmp_path / "tuned" / "weights.npz")
    assert tuned.config.skr_view
    kept, given = flatten_weights(tuned), flatten_weights(with_view)
    view_keys = [key for key in given if key.startswith("skr_view.")]
    assert view_keys and set(view_keys) == {key for key in kept if key.startswith("skr_view.")}
    for key in view_keys:
        np.testing.assert_array_equal(kept[key], given[key])


def weights_without(run, tmp_path, part):
    """The ``all`` run's weights (as loaded) and the same saved to tmp_path/old.npz without
    ``part`` ("refine" or "denoise"), as files from before it were."""
    whole = load_weights(run / "run" / "weights.npz")
    config = {"refine": whole.config.without_refiner,
              "denoise": whole.config.without_denoiser}[part]()
    old = whole._replace(config=config, **{part: None})
    save_weights(tmp_path / "old.npz", old)
    return whole, old


def test_refiner_trains_on_weights_from_before_it(run, tmp_path):
    """--init with a file that has no refiner (as the shipped weights before it): ``refine``
    trains a fresh one on that file's SKR and the export holds both."""
    whole, old = weights_without(run, tmp_path, "refine")
    main(["refine", "--init", str(tmp_path / "old.npz"), "--recipe", str(run / "tiny.json"),
          "--data", str(run), "--out", str(tmp_path / "refined"), "--threads", "1"])
    new = load_weights(tmp_path / "refined" / "weights.npz")
    assert new.config == whole.config and new.refine is not None
    before, after = flatten_weights(old), flatten_weights(new)
    assert set(after) - set(before) == {k for k in after if k.startswith("refine.")} != set()
    for key, value in before.items():
        if key.startswith(("skr.", "smrm.", "skin.", "denoise.")):
            np.testing.assert_allclose(after[key], value, rtol=1e-6, atol=1e-7, err_msg=key)
    rows = (tmp_path / "refined" / "refine.csv").read_text().splitlines()
    assert rows[0].split(",")[2:] == ["loss", "val_mpjpe", "val_mpjpe_skr", "val_tpose_mpjpe",
                                      "val_tpose_mpjpe_skr"]


def test_denoiser_trains_on_weights_from_before_it(run, tmp_path):
    """denoise --init <file without a denoiser> adds one and keeps every other array; its log
    has the smoothed skeleton's errors it must beat."""
    whole, _ = weights_without(run, tmp_path, "denoise")
    main(["denoise", "--init", str(tmp_path / "old.npz"), "--recipe", str(run / "tiny.json"),
          "--data", str(run), "--out", str(tmp_path / "denoised"), "--threads", "1"])
    new = load_weights(tmp_path / "denoised" / "weights.npz")
    assert new.config == whole.config and new.denoise is not None
    before, after = np.load(tmp_path / "old.npz"), np.load(tmp_path / "denoised" / "weights.npz")
    assert set(after.files) - set(before.files) == {k for k in after.files
                                                    if k.startswith("denoise.")} != set()
    for key in set(before.files) - {"metadata", "config"}:
        np.testing.assert_array_equal(after[key], before[key], err_msg=key)
    header = (tmp_path / "denoised" / "denoise.csv").read_text().splitlines()[0].split(",")
    assert {"val_mpjpe", "val_acc", "val_foot_velocity", "val_mpjpe_smoothed",
            "val_acc_smoothed", "val_foot_velocity_smoothed", "foot_velocity"} <= set(header)


def test_denoiser_learns_from_the_skeletons_the_runtime_smooths(run):
    """The stage's inputs are what a Retargeter hands the denoiser: SKR, refiner, smoothing
    from each trial's first frame."""
    weights = load_weights(run / "run" / "weights.npz")
    data = np.load(run / "sequences_val.npz")
    got = smoothed_skeletons(weights.skr, weights.refine, weights.config.refine_neighbours,
                             torch.from_numpy(data["points"]), torch.from_numpy(data["starts"]))
    retargeter = Retargeter(weights, PipelineConfig(foot_lock=None, denoise=False), warn=False)
    retargeter.set_target(np.random.default_rng(1).normal(size=(100, 3)))
    for a, b in zip(data["starts"][:-1], data["starts"][1:]):
        want = np.stack([f.source_joints for f in retargeter.run(data["points"][a:b])])
        np.testing.assert_allclose(got[a:b].numpy(), want, atol=1e-5)


def test_the_denoiser_never_learns_from_an_untrained_refiner(run, tmp_path):
    """denoise --init <file without a refiner>, with a recipe that has one: the denoiser
    learns SKR's smoothed skeletons (its validation baseline says so), and no refiner is
    exported."""
    _, old = weights_without(run, tmp_path, "refine")
    main(["denoise", "--init", str(tmp_path / "old.npz"), "--recipe", str(run / "tiny.json"),
          "--data", str(run), "--out", str(tmp_path / "denoised"), "--threads", "1"])
    new = load_weights(tmp_path / "denoised" / "weights.npz")
    assert new.refine is None and new.denoise is not None
    data = np.load(run / "sequences_val.npz")
    skeletons = smoothed_skeletons(old.skr, None, 0, torch.from_numpy(data["points"]),
                                   torch.from_numpy(data["starts"]))
    error = float((skeletons - torch.from_numpy(data["joints"])).norm(dim=-1).mean())
    last = (tmp_path / "denoised" / "denoise.csv").read_text().splitlines()
    row = dict(zip(last[0].split(","), last[-1].split(",")))
    assert abs(float(row["val_mpjpe_smoothed"]) - error) < 1e-6


def test_an_untrained_refiner_is_never_exported_nor_trained_on_a_random_skr(run, tmp_path):
    """smrm --init <file without a refiner> exports no refiner (it would be random); refine
    alone without a trained SKR is refused."""
    weights_without(run, tmp_path, "refine")
    main(["smrm", "--init", str(tmp_path / "old.npz"), "--recipe", str(run / "tiny.json"),
          "--data", str(run), "--out", str(tmp_path / "tuned"), "--threads", "1"])
    tuned = load_weights(tmp_path / "tuned" / "weights.npz")
    assert tuned.refine is None and not tuned.config.refines
    with pytest.raises(SystemExit):
        main(["refine", "--recipe", str(run / "tiny.json"), "--data", str(run),
              "--out", str(tmp_path / "alone"), "--threads", "1"])
    assert not (tmp_path / "alone" / "refine.pt").exists()


def test_scratch_retrains_a_stage_as_from_random_initialisation(run, tmp_path):
    """--init W --scratch smrm: SKR and SKIN are W's, SMRM is what training from scratch
    gives (the ``all`` run's SMRM, same recipe and seeds)."""
    main(["smrm", "--init", str(run / "run" / "weights.npz"), "--scratch", "smrm",
          "--recipe", str(run / "tiny.json"), "--data", str(run),
          "--out", str(tmp_path / "scratch"), "--threads", "1"])
    whole = np.load(run / "run" / "weights.npz")
    again = np.load(tmp_path / "scratch" / "weights.npz")
    for key in whole.files:
        if whole[key].dtype.kind == "f":
            np.testing.assert_allclose(again[key], whole[key], rtol=1e-5, atol=1e-6,
                                       err_msg=key)


def test_set_overrides_the_recipe_and_clips_are_cut_to_length(run, tmp_path):
    """--set smrm.clip_frames=5 trains on 5-frame windows; the run records the recipe."""
    main(["smrm", "--init", str(run / "run" / "weights.npz"), "--scratch", "smrm",
          "--set", "smrm.clip_frames=5", "--set", "smrm.rotation_cycle=0",
          "--recipe", str(run / "tiny.json"), "--data", str(run),
          "--out", str(tmp_path / "short"), "--threads", "1"])
    recorded = json.loads((tmp_path / "short" / "recipe.json").read_text())
    assert recorded["smrm"]["clip_frames"] == 5 and recorded["smrm"]["rotation_cycle"] == 0
    metadata = json.loads(str(np.load(tmp_path / "short" / "weights.npz")["metadata"]))
    assert metadata["recipe"]["smrm"]["clip_frames"] == 5
    # Other windows, other losses: the SMRM differs from the 30-frame one.
    assert not np.array_equal(np.load(tmp_path / "short" / "weights.npz")["smrm.root_head.bias"],
                              np.load(run / "run" / "weights.npz")["smrm.root_head.bias"])
    with pytest.raises(ValueError, match="clip_frames 31"):
        main(["smrm", "--set", "smrm.clip_frames=31", "--recipe", str(run / "tiny.json"),
              "--data", str(run), "--out", str(tmp_path / "long"), "--threads", "1"])
    with pytest.raises(ValueError, match="unknown keys"):
        load_recipe(run / "tiny.json", ["smrm.clip_length=10"])
    with pytest.raises(ValueError, match="JSON value"):
        load_recipe(run / "tiny.json", ["smrm.clip_frames=ten"])
    assert load_recipe("cpu", ["skr.points=1024"]).skr.points == 1024


@pytest.mark.parametrize("override, message", [
    ('skr.steps="5"', r"skr.steps: expected int, got '5'"),
    ("skr.steps=5.5", "skr.steps: expected int, got 5.5"),
    ("skr.steps=true", "skr.steps: expected int, got True"),
    ("skr.steps=0", "skr.steps: 0 is out of range"),
    ("skr.eval_every=0", "skr.eval_every: 0 is out of range"),
    ("skr.learning_rate=0", "skr.learning_rate: 0 is out of range"),
    ('skr.learning_rate="x"', "skr.learning_rate: expected float"),
    ("skr.tpose_fraction=2", "skr.tpose_fraction: 2 is out of range"),
    ("smrm.input_noise=-0.1", "smrm.input_noise: -0.1 is out of range"),
    ("smrm.input_noise_autocorrelation=-1.5", "input_noise_autocorrelation: -1.5 is out of"),
    ('smrm.input_noise_bias=[0.1, "a"]', "smrm.input_noise_bias: .* is out of range"),
    ("seed=-1", "seed: must be 0 or more, got -1"),
    ("name=3", "name: expected str, got 3")])
def test_recipe_values_are_checked(override, message):
    with pytest.raises(ValueError, match=message):
        load_recipe("cpu", [override])
    assert load_recipe("cpu", ["skr.tpose_fraction=1", "smrm.cycle=0",
                               "smrm.input_noise_bias=[0.01, 0]",
                               "smrm.input_noise_autocorrelation=-0.0079"]).smrm.cycle == 0


def test_a_run_folder_is_continued_or_replaced_never_mixed(run, tmp_path, capsys):
    """--out holding a run: refused without --resume or --overwrite; --resume refuses other
    settings (more steps are fine) and a checkpoint past the recipe's steps; --overwrite
    starts again; the command line says so in one line."""
    out = tmp_path / "out"
    common = ["--recipe", str(run / "tiny.json"), "--data", str(run), "--out", str(out),
              "--threads", "1"]
    main(["skr", "--stop-at", "3"] + common)
    with pytest.raises(ValueError, match="holds an earlier run .*skr.pt.*--resume.*--overwrite"):
        main(["skr"] + common)
    for override, named in (("skr.learning_rate=0.5", "recipe.skr.learning_rate: 0.0001 then, 0.5 now"),
                            ("seed=7", "recipe.seed: 0 then, 7 now")):
        with pytest.raises(ValueError, match=named):
            main(["skr", "--resume", "--set", override] + common)
    with pytest.raises(ValueError, match="init_sha256: None then, [0-9a-f]{64} now"):
        main(["skr", "--resume", "--init", str(run / "run" / "weights.npz")] + common)
    main(["skr", "--resume", "--set", "skr.steps=8"] + common)          # extended
    assert torch.load(out / "skr.pt", weights_only=True)["step"] == 8
    with pytest.raises(SystemExit):
        main(["skr", "--resume", "--set", "skr.steps=4"] + common)
    assert "is at step 8, past this recipe's 4: resume with skr.steps of at least 8" \
        in capsys.readouterr().err
    main(["skr", "--overwrite", "--stop-at", "2"] + common)
    assert torch.load(out / "skr.pt", weights_only=True)["step"] == 2
    (out / "skr.pt").write_bytes(b"not a checkpoint")
    capsys.readouterr()
    assert run_command(["skr", "--resume"] + common) == 1
    err = capsys.readouterr().err
    assert err.startswith("python -m training.train: error: ") and err.count("\n") == 1
    assert "skr.pt: not a readable checkpoint" in err and "weights_only" not in err
    assert run_command(["skr", "--recipe", str(tmp_path / "absent.json")] + common[2:]) == 1
    assert "absent.json: cannot read the recipe" in capsys.readouterr().err


@pytest.mark.parametrize("extra, message", [
    (["--threads", "0"], "argument --threads: must be at least 1, got 0"),
    (["--stop-at", "0"], "argument --stop-at: must be at least 1, got 0"),
    (["--scratch", "smrm"], "--scratch: the stages not retrained come from --init"),
    (["--device", "tpu"], "--device tpu:")])
def test_options_are_checked_by_name(run, tmp_path, capsys, extra, message):
    with pytest.raises(SystemExit):
        main(["skr", "--recipe", str(run / "tiny.json"), "--data", str(run), "--out",
              str(tmp_path / "x")] + extra)
    assert message in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_missing_data_is_found_before_any_stage_trains(run, tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    for path in run.glob("*.npz"):
        if not path.name.startswith("sequences_"):
            (data / path.name).symlink_to(path)
    with pytest.raises(ValueError, match="lacks sequences_train.npz, sequences_val.npz"):
        main(["all", "--recipe", str(run / "tiny.json"), "--data", str(data), "--out",
              str(tmp_path / "x")])
    assert not (tmp_path / "x").exists()


def test_resume_differences_of_a_run_from_before_init_json(tmp_path):
    """A run folder without init.json (started before it was written) is resumed whatever
    --init says; with it, another --init is named. More steps are never a difference."""
    (tmp_path / "recipe.json").write_text(json.dumps({"seed": 0, "skr": {"steps": 5}}))
    now = {"recipe": {"seed": 0, "skr": {"steps": 9}}, "init_sha256": "ab"}
    assert resume_differences(tmp_path, now) == []
    (tmp_path / "init.json").write_text("null")
    assert resume_differences(tmp_path, now) == ["init_sha256: None then, ab now"]
    now["recipe"]["seed"] = 1
    assert "recipe.seed: 0 then, 1 now" in resume_differences(tmp_path, now)
    now["recipe"].update(seed=0, smrm={"learning_rate": 0.5}, skr={"learning_rate": 0.5})
    assert resume_differences(tmp_path, now) == ["init_sha256: None then, ab now"]  # unrecorded
    (tmp_path / "recipe.json").write_text(json.dumps({"seed": 0, "skr": {"learning_rate": 1},
                                                      "smrm": {"learning_rate": 1}}))
    (tmp_path / "skr.pt").write_bytes(b"")       # skr started: its section counts, smrm's not
    assert resume_differences(tmp_path, now) == ["init_sha256: None then, ab now",
                                                 "recipe.skr.learning_rate: 1 then, 0.5 now"]


def test_ctrl_c_in_a_stages_last_step_stops_the_run(run, tmp_path, monkeypatch):
    from training import train
    calls, loss = [], train.skr_loss

    def interrupted_in_the_last_step(*args):
        calls.append(1)
        if len(calls) == TINY_RECIPE["skr"]["steps"]:
            os.kill(os.getpid(), signal.SIGINT)
        return loss(*args)
    monkeypatch.setattr(train, "skr_loss", interrupted_in_the_last_step)
    out = tmp_path / "stopped"
    assert run_command(["all", "--recipe", str(run / "tiny.json"), "--data", str(run),
                        "--out", str(out), "--threads", "1"]) == 130
    assert sorted(p.name for p in out.glob("*.pt")) == ["skr.pt"] and not (
        out / "weights.npz").exists()


def test_more_steps_for_a_stage_others_learned_from_is_refused(run, tmp_path):
    common = ["--recipe", str(run / "tiny.json"), "--data", str(run), "--out",
              str(tmp_path / "run"), "--threads", "1"]
    main(["skr,refine", "--stop-at", "6"] + common)          # skr done, refine stopped
    with pytest.raises(ValueError, match=r"skr goes on from step 6 to 9, but refine learned "
                                         r"its output so far: delete refine\.\*"):
        main(["skr,refine", "--resume", "--set", "skr.steps=9"] + common)
    for path in (tmp_path / "run").glob("refine.*"):
        path.unlink()
    main(["skr,refine", "--resume", "--set", "skr.steps=9"] + common)
    assert torch.load(tmp_path / "run" / "skr.pt", weights_only=True)["step"] == 9


def test_all_waits_for_an_unfinished_stage(run, tmp_path):
    """all --stop-at stops after the first unfinished stage (refine and denoise learn SKR's
    errors); --resume then gives the uninterrupted run's weights."""
    common = ["--recipe", str(run / "tiny.json"), "--data", str(run), "--out",
              str(tmp_path / "split"), "--threads", "1"]
    main(["all", "--stop-at", "4"] + common)
    assert sorted(p.name for p in (tmp_path / "split").glob("*.pt")) == ["skr.pt"]
    main(["all", "--resume"] + common)
    whole, split = (np.load(path / "weights.npz") for path in (run / "run", tmp_path / "split"))
    for key in whole.files:
        if key != "metadata":
            np.testing.assert_array_equal(split[key], whole[key], err_msg=key)


def test_a_stage_stops_on_a_non_finite_loss_and_on_ctrl_c(run, tmp_path, monkeypatch,
                                                            capsys):
    """A NaN loss stops the stage with the last evaluated checkpoint kept; Ctrl-C stops it
    after the step in progress, checkpointed, and --resume ends where one run would."""
    common = ["--recipe", str(run / "tiny.json"), "--data", str(run), "--threads", "1"]
    nan = tmp_path / "nan"
    with pytest.raises(ValueError, match=r"skr: validation \{'val_mpjpe': nan, .* at step 1 "
                                         r"\(too high a learning rate\?\)"):
        main(["skr", "--out", str(nan), "--init", str(run / "run" / "weights.npz"),
              "--set", "skr.learning_rate=1e30", "--set", "skr.eval_every=1"] + common)
    assert not (nan / "skr.pt").exists()                 # nothing saved from a NaN
    # The way on: the stage's files deleted (none here), --resume with another rate.
    main(["skr", "--resume", "--out", str(nan), "--init", str(run / "run" / "weights.npz"),
          "--set", "skr.eval_every=1"] + common)
    kept = torch.load(nan / "skr.pt", weights_only=True)
    assert kept["step"] == 6 and all(torch.isfinite(v).all()
                                     for v in kept["modules"]["skr"].values())

    from training import train
    calls, loss = [], train.skr_loss

    def interrupted_at_the_second_step(*args):
        calls.append(1)
        if len(calls) == 2:
            os.kill(os.getpid(), signal.SIGINT)           # a Ctrl-C inside the step
        return loss(*args)
    monkeypatch.setattr(train, "skr_loss", interrupted_at_the_second_step)
    out = ["--out", str(tmp_path / "stopped")]
    assert run_command(["skr"] + out + common) == 130
    assert "interrupted; each stage's checkpoint is kept" in capsys.readouterr().err
    stopped = torch.load(tmp_path / "stopped" / "skr.pt", weights_only=True)
    assert (stopped["step"], stopped["running_steps"]) == (2, 2)     # between evaluations
    monkeypatch.undo()
    main(["skr", "--resume"] + out + common)
    whole = torch.load(run / "run" / "skr.pt", weights_only=True)["modules"]["skr"]
    resumed = torch.load(tmp_path / "stopped" / "skr.pt", weights_only=True)["modules"]["skr"]
    for key, value in whole.items():
        torch.testing.assert_close(resumed[key], value, msg=key)


def test_source_noise_has_the_profile_it_is_given():
    """Per joint: the clip-constant and frame parts' stds, and the frame part's lag-1
    autocorrelation, measured on many clips, are the recipe's."""
    bias, frame = np.linspace(0.01, 0.05, NUM_JOINTS), np.linspace(0.02, 0.04, NUM_JOINTS)
    stage = load_recipe("cpu").smrm.__class__(input_noise_bias=tuple(bias),
                                               input_noise_frame=tuple(frame),
                                               input_noise_autocorrelation=0.8)
    noise = source_noise((4000, 30, NUM_JOINTS, 3), stage, torch.Generator().manual_seed(0))
    noise = noise.numpy().astype(np.float64)
    clip_mean = noise.mean(axis=1)                                       # (B, J, 3)
    rest = noise - clip_mean[:, None]
    np.testing.assert_allclose(noise.std(axis=(0, 1, 3)), np.hypot(bias, frame), rtol=0.03)
    lag1 = (rest[:, 1:] * rest[:, :-1]).mean() / (rest[:, :-1] ** 2).mean()
    assert 0.7 < lag1 < 0.8   # below 0.8: the clip mean removes part of the slow component
    white = source_noise((100, 30, NUM_JOINTS, 3), load_recipe("cpu").smrm,
                         torch.Generator().manual_seed(0))
    assert abs(float(white.std()) - 0.01) < 0.0005


def test_recipes_load_and_reject_unknown_keys(tmp_path):
    assert load_recipe("paper").model.skr_point_widths == (64, 128, 1024)
    assert load_recipe("cpu").name == "cpu"
    (tmp_path / "typo.json").write_text(json.dumps({"skr": {"stepz": 1}}))
    with pytest.raises(ValueError, match="stepz"):
        load_recipe(tmp_path / "typo.json")


def test_skin_loss_is_zero_for_the_true_weights():
    rng = np.random.default_rng(3)
    tpose = torch.from_numpy(skeleton(rng, 0.9))[None]
    points = tpose[:, rng.integers(NUM_JOINTS, size=50)] + 0.05
    weights = torch.from_numpy(rng.dirichlet(np.ones(NUM_JOINTS), size=(1, 50))).float()
    rotations = torch.from_numpy(random_quaternions(rng, (1, NUM_JOINTS)))
    root = torch.tensor([[0.1, 0.9, 0.2]])
    joints, rotation_matrices = kinematics.forward_kinematics(rotations, root, tpose)
    posed = kinematics.linear_blend_skinning(
        points, weights, kinematics.skinning_transforms(joints, rotation_matrices, tpose))
    assert float(skin_loss(weights, points, posed, rotations, root, tpose)) < 1e-6
    uniform = torch.full_like(weights, 1 / NUM_JOINTS)
    assert float(skin_loss(uniform, points, posed, rotations, root, tpose)) > 1e-3


def test_foot_velocity_error_counts_only_the_true_feet_ground_steps():
    """Hand-computed, two clips on floors 1 m apart (contact is judged per clip): the left foot
    stays down, the right lifts 10 cm in the last frame; the denoised left foot steps 1 cm (3 cm
    in the second clip) sideways and back while lifted 5 cm (contact is the truth's, not the
    denoised), the right slides 2 cm in the air and 1 cm up while down (the height is not a
    horizontal step)."""
    left, right = JOINT_INDEX["left_foot"], JOINT_INDEX["right_foot"]
    truth = torch.zeros(2, 3, NUM_JOINTS, 3)
    truth[1, :, :, 1] += 1.0
    truth[:, 2, right, 1] += 0.1
    denoised = truth.clone()
    denoised[:, 1, left, 0] += torch.tensor([0.01, 0.03])
    denoised[:, 1, left, 1] += 0.05
    denoised[:, 1, right, 1] += 0.01
    denoised[:, 2, right, 2] += 0.02
    # contacts per clip: left 0->1 and 1->2 (error 1 cm each in the first clip, 3 cm in the
    # second), right 0->1 only (no error)
    for clip in truth:
        assert metrics.foot_contacts(clip.numpy()).sum() == 3
    assert float(foot_velocity_error(denoised, truth)) == pytest.approx(0.08 / 6)
    assert float(foot_velocity_error(truth, truth)) == 0.0


def test_rotation_distance_treats_q_and_minus_q_alike():
    q = torch.from_numpy(random_quaternions(np.random.default_rng(4), (5,)))
    assert float(rotation_distance(q, -q).abs().max()) < 1e-6
    assert float(rotation_distance(q, q.flip(0)).max()) > 1e-3


def test_ground_truth_on_the_same_body_is_the_source_motion():
    rng = np.random.default_rng(5)
    tpose = torch.from_numpy(skeleton(rng, 0.9))[None]
    rotations = torch.from_numpy(random_quaternions(rng, (1, 4, NUM_JOINTS)))
    root = torch.from_numpy(rng.normal(size=(1, 4, 3)).astype(np.float32))
    source, _ = kinematics.forward_kinematics(rotations, root, tpose[:, None])
    torch.testing.assert_close(retarget_ground_truth(rotations, root, tpose, tpose), source)
    taller = tpose * 2   # twice the size: twice the root, twice every bone
    torch.testing.assert_close(retarget_ground_truth(rotations, root, tpose, taller),
                               source * 2, atol=1e-5, rtol=1e-5)


def test_fit_steps_fills_the_time_left_at_the_pace_so_far():
    assert fit_steps(20, 0.5, 50.0, cap=1000) == 120     # 50 s left at 0.5 s a step
    assert fit_steps(20, 0.5, 50.0, cap=50) == 50        # never past the recipe
    assert fit_steps(20, 0.5, -1.0, cap=1000) == 21      # past the deadline: one more
    assert fit_steps(20, 0.5, 0.1, cap=1000) == 21


class FakeClock:
    """time.perf_counter for training.train, advanced by hand."""
    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


@pytest.mark.parametrize("seconds_per_step, seconds_per_evaluation", [(0.5, 1.0), (0.01, 0.0)])
def test_a_time_budget_cuts_the_schedule_to_fit_and_resumes_it(tmp_path, monkeypatch,
                                                                seconds_per_step,
                                                                seconds_per_evaluation):
    """Steps of 0.5 s and an evaluation of 1 s first and every 10 steps under a 20 s budget:
    30 of the recipe's 1,000 steps (1 s, then 0.6 s a step, and 1 s for the last
    evaluation), ending within the budget, the learning rate decayed to its floor by the last
    step; a resumed stage keeps the cut schedule. At 0.01 s a step the whole recipe fits and
    nothing is cut."""
    import training.train as train
    clock = FakeClock()
    monkeypatch.setattr(train, "time", types.SimpleNamespace(perf_counter=clock))
    monkeypatch.setattr(train.Stage, "write_log", lambda self: None)

    def stage():
        layer = torch.nn.Linear(2, 1)
        optimizer = torch.optim.SGD(layer.parameters(), lr=1.0)
        return train.Stage("toy", tmp_path, {"toy": layer}, {"toy": optimizer}, steps=1000,
                           eval_every=10, seed=0)
    rates = []

    def train_step(stage):
        clock.now += seconds_per_step
        rates.append(stage.optimizers["toy"].param_groups[0]["lr"])
        return {"loss": 0.0}

    def evaluate():
        clock.now += seconds_per_evaluation
        return {}

    toy = stage()
    assert toy.run(train_step, evaluate, resume=False, limit=train.Limit(seconds=20.0))
    if seconds_per_evaluation == 0.0:
        assert toy.steps == 1000 and not toy.planned
        return
    assert toy.planned and toy.steps == toy.step == 30
    assert clock.now <= 20.0
    assert [row["step"] for row in toy.rows] == [0, 10, 20, 30]
    assert rates[-1] == pytest.approx(0.1, abs=0.01)    # the cosine's floor: 10 % of base
    resumed = stage()
    resumed.load()
    assert (resumed.step, resumed.steps, resumed.planned) == (toy.steps, toy.steps, True)


def test_stage_seconds_from_the_command_line(run, tmp_path, capsys):
    """A budget the tiny recipe fits in leaves its schedule whole; a non-positive one is
    refused by name."""
    common = ["--recipe", str(run / "tiny.json"), "--data", str(run), "--threads", "1"]
    main(["skr", "--stage-seconds", "600", "--out", str(tmp_path / "timed")] + common)
    state = torch.load(tmp_path / "timed" / "skr.pt", weights_only=True)
    assert (state["step"], state["steps"], state["planned"]) == (6, 6, False)
    for bad in ("0", "-5", "nan"):
        with pytest.raises(SystemExit):
            main(["skr", "--stage-seconds", bad, "--out", str(tmp_path / "bad")] + common)
        assert "must be positive and finite" in capsys.readouterr().err
