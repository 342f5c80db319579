"""The Retargeter's public behaviour: streaming, state, and input errors."""
import itertools
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from minretarget import PipelineConfig, Retargeter, stages
from minretarget.kinematics import leg_length


@pytest.fixture()
def retargeter(tiny_weights, tiny_stream):
    retargeter = Retargeter(tiny_weights)
    retargeter.set_target(tiny_stream[0])
    return retargeter


def test_frame_shapes_and_dtypes(retargeter, tiny_stream):
    frame = retargeter.step(tiny_stream[1][0])
    assert frame.vertices.shape == (256, 3) and frame.joints.shape == (22, 3)
    assert frame.rotations.shape == (22, 4) and frame.root.shape == (3,)
    assert all(a.dtype == np.float32 for a in frame)
    np.testing.assert_allclose(np.linalg.norm(frame.rotations, axis=1), 1.0, atol=1e-5)
    np.testing.assert_array_equal(frame.joints[0], frame.root)


def test_run_equals_step_by_step_and_restarts_the_stream(retargeter, tiny_stream):
    sources = tiny_stream[1][:10]
    first = [f.vertices for f in retargeter.run(sources)]
    retargeter.reset()
    stepped = [retargeter.step(points).vertices for points in sources]
    again = [f.vertices for f in retargeter.run(sources)]   # run() resets by itself
    np.testing.assert_array_equal(np.stack(first), np.stack(stepped))
    np.testing.assert_array_equal(np.stack(first), np.stack(again))


def test_retarget_sequence_equals_the_stream_and_can_continue(retargeter, tiny_stream):
    """The batched offline path gives the online result (to float32 rounding) and leaves the
    state after its last frame, so streaming picks up where it ended."""
    sources = np.stack([points[:100] for points in tiny_stream[1][:11]])   # one P for all
    streamed = list(retargeter.run(sources))
    retargeter.reset()
    batched = retargeter.retarget_sequence(sources[:10])
    for field in ("vertices", "joints", "rotations", "root", "source_joints"):
        np.testing.assert_allclose(getattr(batched, field),
                                   np.stack([getattr(f, field) for f in streamed[:10]]),
                                   atol=2e-5, err_msg=field)
    np.testing.assert_allclose(retargeter.step(sources[10]).vertices, streamed[10].vertices,
                               atol=2e-5)
    with pytest.raises(ValueError, match="non-finite"):
        retargeter.retarget_sequence(np.full((2, 100, 3), np.nan))


def test_state_carries_across_frames(retargeter, tiny_stream):
    """The same frame gives a different result after other frames than at a stream's start."""
    sources = tiny_stream[1]
    fresh = retargeter.step(sources[5]).rotations
    retargeter.reset()
    for points in sources[:5]:
        retargeter.step(points)
    assert np.abs(retargeter.step(sources[5]).rotations - fresh).max() > 1e-4


def test_run_is_lazy_over_endless_streams(retargeter, tiny_stream):
    endless = itertools.cycle(tiny_stream[1][:3])
    frames = list(itertools.islice(retargeter.run(endless), 5))
    assert len(frames) == 5


def test_order_of_target_points_is_kept(tiny_weights, tiny_stream):
    target, sources, _ = tiny_stream
    order = np.random.default_rng(0).permutation(len(target))
    a, b = Retargeter(tiny_weights), Retargeter(tiny_weights)
    a.set_target(target)
    b.set_target(target[order])
    np.testing.assert_allclose(b.step(sources[0]).vertices, a.step(sources[0]).vertices[order],
                               atol=1e-5)


def test_faces_are_checked_and_kept(tiny_weights, tiny_stream):
    retargeter = Retargeter(tiny_weights)
    faces = np.array([[0, 1, 2], [2, 3, 4]])
    retargeter.set_target(tiny_stream[0], faces)
    np.testing.assert_array_equal(retargeter.target.faces, faces)
    with pytest.raises(ValueError, match="outside"):
        retargeter.set_target(tiny_stream[0], np.array([[0, 1, 256]]))
    with pytest.raises(ValueError, match="faces must be"):
        retargeter.set_target(tiny_stream[0], np.array([[0.5, 1, 2]]))
    retargeter.set_target(tiny_stream[0], np.zeros((0, 3), int))   # no triangles: a cloud,
    assert retargeter.target.faces is None                        # as the file readers say


def test_a_mesh_s_legs_are_read_from_its_surface(tiny_weights, monkeypatch):
    """A mesh's legs, which scale the root, come from area-uniform samples of its surface:
    vertices that carry no area (a crowd of 3,000 above the head, in triangles of no area)
    move its skeleton, read from its points, but not its legs; points without faces, a mesh
    of no area and a given skeleton keep the skeleton's legs; a length given is kept; SMRM
    is handed the target's."""
    with np.load(Path(__file__).parents[1] / "minretarget" / "data" / "sample.npz") as data:
        points, faces = data["target_points"], data["target_faces"]
    crowd = points[np.argmax(points[:, 1])] + np.random.default_rng(0).normal(
        0.0, 0.02, size=(3000, 3)).astype(np.float32) + [0.0, 0.1, 0.0]
    crowded = np.concatenate([points, crowd])
    flat = np.repeat(np.arange(len(points), len(crowded))[:, None], 3, axis=1)   # no area
    targets = {}
    for name, arguments in (("mesh", (points, faces)),
                            ("crowded mesh", (crowded, np.concatenate([faces, flat]))),
                            ("points", (points,)), ("flat mesh", (crowded, flat))):
        retargeter = Retargeter(tiny_weights)
        retargeter.set_target(*arguments)
        targets[name] = retargeter.target
    assert targets["crowded mesh"].leg_length == targets["mesh"].leg_length
    assert np.abs(targets["crowded mesh"].tpose_joints
                  - targets["mesh"].tpose_joints).max() > 1e-3
    for name in ("points", "flat mesh"):
        assert targets[name].leg_length == float(leg_length(targets[name].tpose_joints))
    assert abs(targets["mesh"].leg_length - targets["points"].leg_length) > 1e-4
    rig = Retargeter(tiny_weights)
    rig.set_target(points, faces, tpose_joints=targets["points"].tpose_joints)
    assert rig.target.leg_length == targets["points"].leg_length
    rig.set_target(points, faces, leg_length=0.8)
    assert rig.target.leg_length == 0.8
    with pytest.raises(ValueError, match="leg_length must be a finite length > 0"):
        rig.set_target(points, leg_length=-0.8)
    handed, step_checked = [], stages.step_checked

    def spied(*arguments):
        handed.append(arguments[-1])
        return step_checked(*arguments)
    monkeypatch.setattr(stages, "step_checked", spied)
    rig.step(points[::7])
    assert handed == [0.8]


def test_bad_input_names_the_problem(tiny_weights, retargeter, tiny_stream):
    with pytest.raises(RuntimeError, match="set_target"):
        Retargeter(tiny_weights).step(tiny_stream[1][0])
    with pytest.raises(ValueError, match="target points has 10 points"):
        Retargeter(tiny_weights).set_target(np.zeros((10, 3)))
    with pytest.raises(ValueError, match=r"source points must have shape \(any, 3\), got \(100, 4\)"):
        retargeter.step(np.zeros((100, 4)))
    bad = tiny_stream[1][0].copy()
    bad[7, 1] = np.inf
    with pytest.raises(ValueError, match=r"non-finite value inf at index \(7, 1\)"):
        retargeter.step(bad)
    with pytest.raises(ValueError, match="frame 2: source points"):
        list(retargeter.run([tiny_stream[1][0], tiny_stream[1][1], np.zeros((3, 3))]))
    with pytest.raises(ValueError, match="dtype"):
        retargeter.step(np.array([["a", "b", "c"]] * 100))


def test_a_given_rig_replaces_skr_and_skin(tiny_weights, tiny_stream):
    target, sources, _ = tiny_stream
    rng = np.random.default_rng(1)
    joints = rng.normal(size=(22, 3)).astype(np.float32)
    weights = rng.dirichlet(np.ones(22), size=len(target)).astype(np.float32)
    retargeter = Retargeter(tiny_weights)
    retargeter.set_target(target, tpose_joints=joints, skin_weights=weights)
    np.testing.assert_array_equal(retargeter.target.tpose_joints, joints)
    np.testing.assert_array_equal(retargeter.target.skin_weights, weights)
    # SKIN runs on the given skeleton when only the skeleton is given.
    retargeter.set_target(target, tpose_joints=joints)
    own = Retargeter(tiny_weights)
    own.set_target(target)
    assert np.abs(retargeter.target.skin_weights - own.target.skin_weights).max() > 1e-4
    with pytest.raises(ValueError, match="sum to 1"):
        retargeter.set_target(target, skin_weights=weights * 2)
    with pytest.raises(ValueError, match="skin_weights must have shape"):
        retargeter.set_target(target, skin_weights=weights[:10])


def test_target_skeleton_is_averaged_with_its_mirror_image(tiny_weights, tiny_stream):
    """mirror_averaged = the mean of a skeleton finder on the cloud and on its mirror image
    mapped back (by hand); on a mirror-symmetric cloud the result is itself mirror-symmetric;
    the Retargeter uses it on SKR + refiner unless mirror_target=False."""
    from minretarget.conventions import JOINT_NAMES, MIRROR
    from minretarget.refine import refine_joints
    from minretarget.skr import mirror_averaged, regress_joints
    assert all(JOINT_NAMES[MIRROR[j]] == name.replace("left", "right") if "left" in name else
               JOINT_NAMES[MIRROR[j]] == name.replace("right", "left") if "right" in name else
               MIRROR[j] == j for j, name in enumerate(JOINT_NAMES))
    k = tiny_weights.config.refine_neighbours

    def skeleton(clouds):
        return refine_joints(clouds, regress_joints(clouds, tiny_weights.skr),
                             tiny_weights.refine, k)
    target = tiny_stream[0]
    flip = np.array([-1, 1, 1], np.float32)
    plain = skeleton(target[None])[0]
    mirrored = skeleton((target * flip)[None])[0]
    swapped = np.array([mirrored[MIRROR[j]] for j in range(len(MIRROR))]) * flip
    np.testing.assert_allclose(mirror_averaged(skeleton, target), (plain + swapped) / 2,
                               atol=1e-6)
    symmetric = np.concatenate([target, target * flip])
    joints = mirror_averaged(skeleton, symmetric)
    np.testing.assert_allclose(joints[list(MIRROR)] * flip, joints, atol=1e-5)
    for mirror_target, want in ((True, mirror_averaged(skeleton, target)), (False, plain)):
        retargeter = Retargeter(tiny_weights, PipelineConfig(mirror_target=mirror_target),
            warn=False)
        retargeter.set_target(target)
        np.testing.assert_allclose(retargeter.target.tpose_joints, want, atol=1e-6)


def test_mirror_source_feeds_smrm_the_mirror_averaged_skeleton(tiny_weights, tiny_stream):
    """step with mirror_source = step_skeleton of mirror_averaged SKR, frame by frame, and
    retarget_sequence agrees with it (refiner off: the previous test covers it)."""
    from minretarget.skr import mirror_averaged, regress_joints
    target, sources, _ = tiny_stream
    mirrored, by_hand = (Retargeter(tiny_weights, PipelineConfig(mirror_source=True, refine=False),
        warn=False),
                         Retargeter(tiny_weights, PipelineConfig(refine=False), warn=False))

    def skr(clouds):
        return regress_joints(clouds, tiny_weights.skr)
    for retargeter in (mirrored, by_hand):
        retargeter.set_target(target)
    for points in sources[:8]:
        want = by_hand.step_skeleton(mirror_averaged(skr, points))
        np.testing.assert_array_equal(mirrored.step(points).vertices, want.vertices)
    offline = mirrored.retarget_sequence(np.stack([s[:200] for s in sources[:8]]))
    by_hand.reset()
    for t, points in enumerate(sources[:8]):
        want = by_hand.step_skeleton(mirror_averaged(skr, points[:200]))
        np.testing.assert_allclose(offline.joints[t], want.joints, atol=1e-5)


def test_skeletons_go_through_the_refiner_unless_refine_is_off(tiny_weights, tiny_stream):
    """Source skeletons = refine_joints of SKR's; step = step_skeleton of ``skeleton``;
    refine=False, or weights without a refiner, leave SKR's joints as they are (the target's
    too)."""
    from minretarget.refine import refine_joints
    from minretarget.skr import mirror_averaged, regress_joints
    target, sources, _ = tiny_stream
    k = tiny_weights.config.refine_neighbours
    refined = Retargeter(tiny_weights, "regressed", warn=False)
    plain = Retargeter(tiny_weights, PipelineConfig(refine=False), warn=False)
    for retargeter in (refined, plain):
        retargeter.set_target(target)
    skr_target = mirror_averaged(lambda c: regress_joints(c, tiny_weights.skr), target)
    np.testing.assert_allclose(plain.target.tpose_joints, skr_target, atol=1e-6)
    assert np.abs(refined.target.tpose_joints - skr_target).max() > 1e-3
    by_hand = Retargeter(tiny_weights, "regressed", warn=False)
    by_hand.set_target(target)
    for points in sources[:5]:
        skeleton = refine_joints(points, regress_joints(points, tiny_weights.skr),
                                 tiny_weights.refine, k)
        np.testing.assert_allclose(refined.skeleton(points), skeleton, atol=1e-6)
        np.testing.assert_array_equal(refined.step(points).vertices,
                                      by_hand.step_skeleton(refined.skeleton(points)).vertices)
        np.testing.assert_allclose(plain.skeleton(points), regress_joints(points,
                                                                          tiny_weights.skr))
    batch = np.stack([s[:150] for s in sources[:3]])
    np.testing.assert_allclose(refined.skeleton(batch),
                               np.stack([refined.skeleton(c) for c in batch]), atol=1e-6)
    without = tiny_weights._replace(config=tiny_weights.config.without_refiner(), refine=None)
    bare = Retargeter(without, warn=False)
    np.testing.assert_allclose(bare.skeleton(sources[0]),
                               regress_joints(sources[0], tiny_weights.skr))
    with pytest.raises(ValueError, match="source points"):
        refined.skeleton(sources[0][:10])


def test_denoise_hands_smrm_the_denoised_skeleton_unless_off(tiny_weights, tiny_stream):
    """denoise=False, and weights without a denoiser, are the same pipeline; with it, SMRM
    sees the denoiser's output of the smoothed skeleton, which the frames report; a state
    from one pipeline is refused by the other."""
    from conftest import denoised_stream
    target, sources, _ = tiny_stream
    without = tiny_weights._replace(config=tiny_weights.config.without_denoiser(), denoise=None)
    on, off, bare = (Retargeter(tiny_weights, "regressed", warn=False),
                     Retargeter(tiny_weights, PipelineConfig(denoise=False), warn=False),
                     Retargeter(without, "regressed", warn=False))
    for retargeter in (on, off, bare):
        retargeter.set_target(target)
    assert "denoiser" in [stage.name for stage in on.stages]
    assert "denoiser" not in [stage.name for stage in off.stages + bare.stages]
    frames, states = [], []
    for points in sources[:6]:
        frames.append((on.step(points), off.step(points), bare.step(points)))
        states.append(on.state.stages["smoothing"].joints)
    smoothed = np.stack([f.source_joints for _, f, _ in frames])
    want = denoised_stream(tiny_weights.denoise, smoothed)
    for (with_it, without_it, plain), joints in zip(frames, want):
        np.testing.assert_array_equal(without_it.vertices, plain.vertices)
        np.testing.assert_allclose(with_it.source_joints, joints, atol=1e-6)
    np.testing.assert_allclose(np.stack(states), smoothed, atol=1e-6)
    assert np.abs(with_it.vertices - without_it.vertices).max() > 1e-4
    with pytest.raises(ValueError, match="no denoiser state"):
        on.state = off.state
    with pytest.raises(ValueError, match="does not run: denoiser"):
        off.state = on.state


WARM_UP_SCRIPT = """
import json, sys
import numba
import numpy as np
from conftest import turned_about_up
from minretarget import PipelineConfig, Retargeter
from minretarget.sources import load_sample

settings, skeleton = json.loads(sys.argv[1]), sys.argv[2] == "skeleton"
retargeter = Retargeter.from_weights(None, PipelineConfig.from_dict(settings), warn=False)
source, target, faces, _ = load_sample()
retargeter.set_target(target, faces)
retargeter.warm_up(skeleton)


def loaded():
    return {(name, str(signature)) for module in list(sys.modules.values())
            if module and module.__name__.startswith("minretarget")
            for name, value in vars(module).items()
            if isinstance(value, numba.core.registry.CPUDispatcher)
            for signature in value.signatures}


before = loaded()
clouds = [cloud for cloud, _ in zip(source.frames, range(4))]
clouds.append(turned_about_up(clouds[-1], np.pi).astype(np.float32))  # the facing check rereads
for cloud in clouds:
    if skeleton:
        retargeter.step_skeleton(retargeter.target.tpose_joints)
    else:
        retargeter.step(cloud)
print(json.dumps(sorted(loaded() - before)))
"""


@pytest.mark.parametrize("settings, skeleton", [
    ({}, False), ({"mirror_source": True}, False), ({"smoothing": None, "foot_lock": None,
                                                     "refine": False, "denoise": False}, False),
    ({"fit_source": {}, "smoothing": None, "denoise": False}, False), ({}, True)])
def test_warm_up_loads_every_kernel_a_stream_uses(settings, skeleton):
    """In a fresh process, a stream after ``warm_up`` loads no kernel signature that the
    warm-up did not (so that nothing compiles once frames, and a progress bar, are going)."""
    tests = Path(__file__).parent
    result = subprocess.run(
        [sys.executable, "-c", WARM_UP_SCRIPT, json.dumps(settings),
         "skeleton" if skeleton else "points"], capture_output=True, text=True, timeout=600,
        env={**os.environ, "PYTHONPATH": f"{tests.parent}{os.pathsep}{tests}"})
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout) == []


def test_a_stream_belongs_to_the_thread_that_started_it(tiny_weights):
    """Frames from a second thread are refused (they would mix two motions into one stream)
    until that thread starts its own stream with reset()."""
    import threading
    retargeter = Retargeter(tiny_weights, warn=False)
    retargeter.set_target(np.random.default_rng(0).normal(size=(200, 3)))
    cloud = np.random.default_rng(1).normal(size=(100, 3))
    retargeter.step(cloud)
    outcome = {}

    def other_thread():
        try:
            retargeter.step(cloud)
        except RuntimeError as error:
            outcome["refused"] = str(error)
        retargeter.reset()
        outcome["frame"] = retargeter.step(cloud)

    worker = threading.Thread(target=other_thread)
    worker.start()
    worker.join()
    assert "belongs to another thread" in outcome["refused"]
    assert outcome["frame"].vertices.shape == (200, 3)
    with pytest.raises(RuntimeError, match="belongs to another thread"):
        retargeter.step(cloud)                   # the stream is the other thread's now
