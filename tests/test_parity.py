"""The runtime against the torch reference: per stage and end to end, tiny and paper sizes."""
import dataclasses

import numpy as np
import pytest

torch = pytest.importorskip("torch")  # the runtime-only suite (test_golden.py) runs without it

from conftest import denoised_stream  # noqa: E402
from make_golden import reference_outputs  # noqa: E402
from reference_models import TINY_CONFIG, random_reference, random_stream  # noqa: E402

from minretarget.config import ModelConfig  # noqa: E402
from minretarget.conventions import NUM_JOINTS  # noqa: E402
from minretarget.refine import refine_joints  # noqa: E402
from minretarget.retargeter import Retargeter  # noqa: E402
from minretarget.skin import linear_blend_skinning, skinning_weights  # noqa: E402
from minretarget.skr import regress_joints  # noqa: E402
from minretarget.weights import load_weights  # noqa: E402
from minretarget.pipeline import UNCOUPLED  # noqa: E402
from training import kinematics as torch_kinematics  # noqa: E402
from training.export import export_weights, runtime_weights  # noqa: E402
from training.models.pipeline import RUNTIME_CONFIG as RAW  # noqa: E402

TOLERANCE = 1e-4   # metres, on joints and vertices


@pytest.fixture(scope="module")
def tiny_model():
    return random_reference(seed=0)


def test_end_to_end_stream_matches_torch_after_export_and_reload(tiny_model, tmp_path):
    export_weights(tmp_path / "w.npz", tiny_model.skr, tiny_model.smrm, tiny_model.skin,
                   {"pipeline": UNCOUPLED}, refine=tiny_model.refine, denoise=tiny_model.denoise)
    retargeter = Retargeter.from_weights(tmp_path / "w.npz", RAW)
    target, sources = random_stream(seed=1, frames=60)
    want = reference_outputs(tiny_model, target, sources)
    retargeter.set_target(target)
    np.testing.assert_allclose(retargeter.target.tpose_joints, want["tpose_joints"],
                               atol=TOLERANCE)
    np.testing.assert_allclose(retargeter.target.skin_weights, want["skin_weights"], atol=1e-5)
    frames = list(retargeter.run(sources))
    for key in ("vertices", "joints", "root", "source_joints"):
        got = np.stack([getattr(frame, key) for frame in frames])
        np.testing.assert_allclose(got, want[key], atol=TOLERANCE, err_msg=key)
    rotations = np.stack([frame.rotations for frame in frames])
    np.testing.assert_allclose(rotations, want["rotations"], atol=1e-5)


def test_a_mesh_target_matches_torch_given_the_runtime_s_leg_length(tiny_model, tmp_path):
    """A mesh target's legs, which scale the root, are read from its surface by the runtime;
    the torch reference, which reads points only, matches it end to end once given that leg
    length (``ReferenceRetargeter.leg_length``, as benchmarks/speed.py gives it), and not
    without it."""
    export_weights(tmp_path / "w.npz", tiny_model.skr, tiny_model.smrm, tiny_model.skin,
                   {"pipeline": UNCOUPLED}, refine=tiny_model.refine, denoise=tiny_model.denoise)
    retargeter = Retargeter.from_weights(tmp_path / "w.npz", RAW)
    target, sources = random_stream(seed=2, frames=20)
    faces = np.random.default_rng(3).integers(len(target), size=(400, 3))
    retargeter.set_target(target, faces)
    got = np.stack([frame.vertices for frame in retargeter.run(sources)])
    plain = reference_outputs(tiny_model, target, sources)["vertices"]
    assert np.abs(got - plain).max() > 10 * TOLERANCE
    tiny_model.set_target(torch.from_numpy(target))
    tiny_model.leg_length = torch.tensor(retargeter.target.leg_length)
    want = np.stack([tiny_model.step(torch.from_numpy(points))["vertices"].numpy()
                     for points in sources])
    np.testing.assert_allclose(got, want, atol=TOLERANCE)


@pytest.mark.parametrize("rest_pose", [False, True])
def test_smrm_with_the_analytic_prior_matches_torch(tmp_path, rest_pose):
    """SMRM's corrections applied after the analytic rotations: the runtime's kernel (and its
    analytic kernel) against training.analytic and the torch model, end to end; with
    ``rest_pose``, the prior's reference skeleton from the rest-pose model (random here) and
    the mean source bone lengths, both sides."""
    config = dataclasses.replace(TINY_CONFIG, smrm_analytic_prior=True, rest_pose=rest_pose)
    model = random_reference(config, 3)
    if rest_pose:
        with torch.no_grad():
            model.smrm.rest_directions.normal_(0.0, 1.0,
                                               generator=torch.Generator().manual_seed(5))
    export_weights(tmp_path / "w.npz", model.skr, model.smrm, model.skin, {"pipeline": UNCOUPLED},
                   refine=model.refine, denoise=model.denoise)
    retargeter = Retargeter.from_weights(tmp_path / "w.npz", RAW)
    assert retargeter.weights.config.smrm_analytic_prior and retargeter.weights.smrm.analytic_prior
    assert (retargeter.weights.rest_pose is not None) == rest_pose
    target, sources = random_stream(seed=4, frames=40)
    want = reference_outputs(model, target, sources)
    retargeter.set_target(target)
    frames = list(retargeter.run(sources))
    rotations = np.stack([frame.rotations for frame in frames])
    np.testing.assert_allclose(np.abs((rotations * want["rotations"]).sum(-1)), 1.0, atol=1e-5)
    for key in ("joints", "vertices"):
        got = np.stack([getattr(frame, key) for frame in frames])
        np.testing.assert_allclose(got, want[key], atol=TOLERANCE, err_msg=key)


def test_the_torch_reference_traces_under_torch_compile():
    """The speed benchmark times the reference under torch.compile: its whole step, the
    rest-pose prior included, must trace (dynamo turns NumPy integer index lists into
    tensors it cannot index with) and give eager's outputs. The eager backend traces as
    inductor does, without its minutes of code generation."""
    config = dataclasses.replace(TINY_CONFIG, smrm_analytic_prior=True, rest_pose=True)
    model = random_reference(config, 3)
    target, sources = random_stream(seed=4, frames=3)
    with torch.no_grad():
        model.smrm.rest_directions.normal_(0.0, 1.0, generator=torch.Generator().manual_seed(5))
        model.set_target(torch.from_numpy(target))
        first, state = model(torch.from_numpy(sources[0]), None)
        want, _ = model(torch.from_numpy(sources[1]), state)
        torch._dynamo.reset()
        got, _ = torch.compile(model, backend="eager")(
            torch.from_numpy(sources[1]), state)
    for key in want:
        torch.testing.assert_close(got[key], want[key], atol=1e-6, rtol=0, msg=key)


def test_golden_files_match_the_current_torch_reference(tiny_model, tiny_weights, tiny_stream):
    """tests/golden was made from this reference; regenerate it (make_golden.py) if this fails."""
    target, sources, golden = tiny_stream
    want = reference_outputs(tiny_model, target, sources)
    # 1e-5 m: torch's float32 kernels round differently on different CPUs (2.3e-6 m on
    # vertices 2 m from the origin, 10 float32 steps, between two machines of this project);
    # a change to the reference itself moves them by far more.
    for key, value in want.items():
        np.testing.assert_allclose(golden[f"torch_{key}"], value, atol=1e-5, err_msg=key)
    exported = runtime_weights(tiny_model.skr, tiny_model.smrm, tiny_model.skin,
                               {"pipeline": UNCOUPLED}, refine=tiny_model.refine,
                               denoise=tiny_model.denoise)
    flat = lambda weights: np.concatenate([np.ravel(a) for a in leaves(weights)])  # noqa: E731
    np.testing.assert_array_equal(flat(exported), flat(tiny_weights))

def leaves(weights):
    def walk(tree):
        if isinstance(tree, tuple):
            for child in tree:
                yield from walk(child)
        else:                          # an array, or a flag such as SMRMWeights.analytic_prior
            yield np.asarray(tree, dtype=np.float32)
    return [a for stage in (weights.skr, weights.smrm, weights.skin, weights.refine,
                            weights.denoise) for a in walk(stage)]


def test_torch_step_by_step_equals_whole_sequence(tiny_model):
    rng = np.random.default_rng(2)
    joints = torch.from_numpy(rng.normal(size=(3, 40, 22, 3)).astype(np.float32))
    tpose = torch.from_numpy(rng.normal(size=(3, 22, 3)).astype(np.float32))
    with torch.no_grad():
        whole = tiny_model.smrm(joints, tpose)
        state, steps = None, []
        for t in range(40):
            *outputs, state = tiny_model.smrm(joints[:, t:t + 1], tpose, state)
            steps.append(outputs)
    for index, atol in ((0, 1e-5), (1, TOLERANCE), (2, TOLERANCE)):   # rotations, root, joints
        stepped = torch.cat([s[index] for s in steps], dim=1)
        torch.testing.assert_close(stepped, whole[index], atol=atol, rtol=0)


def test_torch_fk_and_lbs_match_the_runtime():
    from minretarget.kinematics import forward_kinematics, skinning_transforms
    rng = np.random.default_rng(3)
    q = rng.normal(size=(5, 22, 4)).astype(np.float32)
    root = rng.normal(size=(5, 3)).astype(np.float32)
    tpose = rng.normal(size=(22, 3)).astype(np.float32)
    joints, rotations = forward_kinematics(q, root, tpose)
    torch_joints, torch_rotations = torch_kinematics.forward_kinematics(
        torch.from_numpy(q), torch.from_numpy(root), torch.from_numpy(tpose))
    np.testing.assert_allclose(joints, torch_joints.numpy(), atol=1e-5)
    np.testing.assert_allclose(rotations, torch_rotations.numpy(), atol=1e-5)
    points = rng.normal(size=(300, 3)).astype(np.float32)
    weights = rng.dirichlet(np.ones(22), size=300).astype(np.float32)
    transforms = skinning_transforms(joints[0], rotations[0], tpose)
    torch_points = torch_kinematics.linear_blend_skinning(
        torch.from_numpy(points), torch.from_numpy(weights),
        torch_kinematics.skinning_transforms(torch_joints[0], torch_rotations[0],
                                             torch.from_numpy(tpose)))
    np.testing.assert_allclose(linear_blend_skinning(points, weights, transforms),
                               torch_points.numpy(), atol=1e-5)


def test_paper_size_stages_match_torch(tmp_path):
    """The paper's widths (1024-wide max-pool, 512-wide GRUs) at P = 2048 points."""
    model = random_reference(ModelConfig(), seed=4)
    export_weights(tmp_path / "paper.npz", model.skr, model.smrm, model.skin)
    weights = load_weights(tmp_path / "paper.npz")
    rng = np.random.default_rng(4)
    points = (rng.normal(size=(2048, 3)) * [0.3, 0.8, 0.15]).astype(np.float32)
    with torch.no_grad():
        want_joints = model.skr(torch.from_numpy(points)[None])[0].numpy()
        want_weights = model.skin(torch.from_numpy(points)[None],
                                  torch.from_numpy(want_joints)[None])[0].numpy()
        source = torch.from_numpy(rng.normal(size=(1, 10, 22, 3)).astype(np.float32))
        want_rotations, want_root, want_fk, _ = model.smrm(source, torch.from_numpy(want_joints)[None])
    joints = regress_joints(points, weights.skr)
    np.testing.assert_allclose(joints, want_joints, atol=TOLERANCE)
    np.testing.assert_allclose(skinning_weights(points, joints, weights.skin), want_weights,
                               atol=1e-5)
    retargeter = Retargeter(weights, RAW)
    retargeter.set_target(points)
    for t in range(10):
        frame = retargeter.step_skeleton(source[0, t].numpy())
        np.testing.assert_allclose(frame.rotations, want_rotations[0, t].numpy(), atol=1e-5)
        np.testing.assert_allclose(frame.root, want_root[0, t].numpy(), atol=TOLERANCE)
        np.testing.assert_allclose(frame.joints, want_fk[0, t].numpy(), atol=TOLERANCE)


def test_refiner_at_the_cpu_recipe_sizes_matches_torch():
    """The shipped refiner's widths and neighbour count, on 2,048 points and on 5,000 (which
    both sides thin by the same stride)."""
    from training.recipe import load_recipe
    model = random_reference(load_recipe("cpu").model, seed=6)
    weights = runtime_weights(model.skr, model.smrm, model.skin, refine=model.refine)
    rng = np.random.default_rng(6)
    for count in (2048, 5000):
        points = (rng.normal(size=(2, count, 3)) * [0.3, 0.8, 0.15]).astype(np.float32)
        joints = points[:, :NUM_JOINTS] + rng.normal(0, 0.05, (2, NUM_JOINTS, 3)).astype(
            np.float32)
        with torch.no_grad():
            want = model.refine(torch.from_numpy(points), torch.from_numpy(joints)).numpy()
        got = refine_joints(points, joints, weights.refine, weights.config.refine_neighbours)
        np.testing.assert_allclose(got, want, atol=TOLERANCE, err_msg=f"{count} points")


def test_denoiser_at_the_cpu_recipe_sizes_matches_torch():
    """The shipped denoiser's width: the runtime one frame at a time against torch over the
    whole sequence at once (both views, mirror-averaged), from a stream's start."""
    from training.recipe import load_recipe
    model = random_reference(load_recipe("cpu").model, seed=7)
    weights = runtime_weights(model.skr, model.smrm, model.skin, denoise=model.denoise)
    rng = np.random.default_rng(7)
    joints = (np.cumsum(rng.normal(0, 0.02, (50, 1, 3)), axis=0)
              + rng.normal(0, 0.3, (1, NUM_JOINTS, 3))).astype(np.float32)
    with torch.no_grad():
        want = model.denoise.mirror_averaged(torch.from_numpy(joints)[None])[0][0].numpy()
    np.testing.assert_allclose(denoised_stream(weights.denoise, joints), want, atol=TOLERANCE)


def test_batch_norm_is_folded_with_running_statistics(tiny_model):
    """Export folds eval-mode batch norm: the exported SKR equals torch in eval mode only."""
    weights = runtime_weights(tiny_model.skr, tiny_model.smrm, tiny_model.skin,
                               refine=tiny_model.refine, denoise=tiny_model.denoise)
    points = np.random.default_rng(5).normal(size=(4, 200, 3)).astype(np.float32)
    with torch.no_grad():
        want = tiny_model.skr(torch.from_numpy(points)).numpy()
        tiny_model.skr.train()
        batch_stats = tiny_model.skr(torch.from_numpy(points)).numpy()
        tiny_model.skr.eval()
    got = regress_joints(points, weights.skr)
    np.testing.assert_allclose(got, want, atol=TOLERANCE)
    assert np.abs(got - batch_stats).max() > 10 * TOLERANCE
