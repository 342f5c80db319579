"""Accuracy of the runtime on the test benchmark (../shared/DESIGN.md, "Accuracy protocol").

    python benchmarks/accuracy.py (--validation | --dances | --motions | --crossed
                                   | --more-dances | --report [--quick]) [--rows ROW ...]
                                  [--weights FILE] [--data DIR] [--cmu DIR] [--json OUT.json] [--markdown OUT.md]
                                  [--compare OTHER.json] [--draws K]
    python benchmarks/accuracy.py --from-json OUT.json [--markdown OUT.md] [--compare OTHER.json]

Every test sequence (CMU subjects 08, 11, 12, 14 and aclstm/indian, on fixed unseen bodies) is
retargeted online, frame by frame, by minretarget (not torch). Rows, in one run:
    model                the weights given (default: the shipped weights), as ``Retargeter``
                         runs them by default (``pipeline.DEFAULT_PRESET``)
The ``model, no X`` and ``model, mirrored source`` rows are the ``regressed`` preset (SKR's
joints moved by the joint refiner, smoothed over time and denoised before SMRM, whose analytic
prior allows for the two bodies' rest poses, feet held on their contacts after it, a skeleton
facing far from the heading kept so far read again half turned) with one thing changed:
    model, no refiner    without the joint refiner (source and target skeletons)
    model, no denoiser   without the skeleton denoiser
    model, no foot lock  without the foot contacts
    model, no rest pose  with SMRM's plain analytic prior (target bones turned onto the source
                         bones, no rest-pose model)
    model, no facing check  with every SKR reading as it comes
    model, mirrored source  with ``mirror_source=True``: SKR's source joints
                         averaged with those of each cloud's mirror image
    regressed preset     the ``regressed`` preset (SKR's readings, refined, checked for facing,
                         smoothed and denoised): the same as ``model`` while it is the default
    paper preset         the ``paper`` preset: SKR once on the target T-pose (not mirror-averaged;
                         its legs, which scale the root, read from the mesh's surface, as in
                         every row), SKR's source joints as they come (no refiner, no facing
                         check, no smoothing, no denoiser), SMRM's plain prior, its rotations
                         as they come
    analytic             the model without SMRM's networks, every other stage kept: the
                         model's (smoothed, denoised) source skeletons; per frame SMRM's
                         analytic prior as the model computes it (each bone of the target's
                         T-pose, turned by the rest-pose model, rotated onto its source bone:
                         minretarget.analytic, minretarget.rest_pose), the root scaled as
                         SMRM scales it, the model's foot lock (minretarget.contacts), FK,
                         LBS with SKIN weights (``analytic_full``). The rest-pose model is
                         fitted, but it is part of the prior the model gets, so this row has
                         it: ``model - analytic`` is SMRM's own effect
    analytic, plain      the analytic row of earlier runs, kept comparable: the same source
                         skeletons, each target T-pose bone rotated onto its source bone, no
                         rest-pose model, no foot lock (``analytic_plain``)
    analytic, mirrored source  ``analytic`` on the mirrored source row's skeletons
    oracle source        ground-truth source joints instead of SKR (not smoothed or denoised;
                         foot lock on)
    oracle target        ground-truth target T-pose joints and skinning weights instead of
                         SKR + SKIN (otherwise as the model)
    oracle both          both of the above (not smoothed or denoised; foot lock on)
    paper                the paper's Table 4, reported on its own SMPL test set (not this one)
Only when named in --rows:
    model, source fit    the model with the source fit (the ``fitted`` preset,
                         minretarget.fit: a body model tracked in every cloud after SKR, the
                         refiner and the facing check), no smoothing and no denoiser (both
                         learned or tuned on SKR's errors, not the fit's)
    analytic, source fit  ``analytic`` on that row's source skeletons
    model, source fit, no X  ``model, source fit`` with one stage off (``FIT_VARIANTS``): the
                         refiner on the source readings, the facing check, the rest-pose
                         model, the foot lock
    model, source fit, thinned to 1024  ``model, source fit`` with every cloud thinned to
                         1,024 points (seeded by the frame's index) before SKR
    model, foot leash X m  the ``regressed`` preset (like the ``no X`` rows: no source fit)
                         with the foot lock's leash (``FootLock.max_offset``, the command
                         line's --foot-leash) X instead of 1 cm: planted toes held firmer,
                         for X in ``FOOT_LEASHES``
Every row but ``paper`` is averaged over frames. A second table gives foot sliding: the mean
horizontal speed of the toes over the steps where the ground truth's toes touch the ground
(``metrics.foot_contacts``, 3 cm), pooled over those steps, and the ground truth's own.
If DIR/test is absent, the run stops and says how to build it; with --build it builds it
first (python -m training.data build --only test, about 13 minutes).
A third compares the model with the analytic baseline, sequence by sequence (and with the
plain one, and the mirrored source rows likewise, ``PAIRS``): for each metric the frame-weighted difference (model minus
analytic; below zero, the model is better), its 95 % interval from a bootstrap over the
sequences (``paired_difference``), and on how many sequences the model is better.
--from-json OUT.json prints every table again from a saved run, computing nothing.
--compare OTHER.json adds the same paired comparison of the model with the model of a saved
run over the same sequences (other weights, say: ``against_saved``); a saved run of another
split, quick against full, or of other sequences (their names, and their lengths where known
before loading: validation and dances) is refused before the run starts.
--draws K: the source fit reads a seeded random subset of each cloud, and which points it
draws moves the figures about as much as the differences judged (docs/source_fit.md, "How far
the figures move with the points drawn"), a noise the intervals above, paired by sequence, do
not hold. With K > 1 every row whose retargeter runs the fit (``model`` while the default
preset is ``fitted``; ``oracle target``; the source-fit rows) and every analytic row on such a
row's skeletons is run again on the draws 1..K-1 (``FitSettings.draw``); the other rows, which
do not depend on the draw, run once. The tables and the JSON's "rows", "per_sequence" and the
rest stay draw 0's; the JSON adds "draws" and "over_draws": each repeated row's pooled figures
per draw and their mean. With --compare (a run over as many draws; another number is refused
before the run) the model minus its model is also given draw by draw, with its mean and 95 %
interval over the draws (Student's t, ``fit_settings.over_draws``).
--report: score the test split. Without it a run of the test split (the default, or --quick)
is refused: the test split is run once per release, for the report, and never selects
anything; weights, settings and rows are chosen on --validation and --dances.
--quick: a fixed subset of the test split (the first 150 frames of the first two sequences of
each category), about 3 minutes; needs --report too. --validation: the same rows on validation
trials (held-out training subjects and bodies), for choosing between weights or settings.
--dances: on dance and martial-arts trials of the training split played by held-out bodies,
the motion the validation subjects lack (the networks trained on it, on other bodies).
--motions: up to four trials of each other motion category of the training split, likewise.
--crossed: the --dances trials (240 frames at most) with a leg crossed over the other every
second or so (``datasets.crossings_over_time``): legs that cross, which the others barely show.
--more-dances: every other dance, salsa and martial-arts trial of the training split, likewise.
"""
import argparse
import functools
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from minretarget.analytic import analytic_rotations
from minretarget.atomic import atomic_write
from minretarget.contacts import FootLock, plant_feet
from minretarget.kinematics import forward_kinematics, leg_length, skinning_transforms
from minretarget.metrics import (METRIC_NAMES, crossed_feet, evaluate, foot_contacts,
                                 foot_speeds, joint_errors, skating_steps)
from minretarget.rest_pose import bone_lengths, prior_reference
from minretarget.retargeter import Retargeter
from minretarget.skin import linear_blend_skinning
from minretarget.weights import DEFAULT_WEIGHTS, file_sha256, load_weights
from minretarget.pipeline import PRESETS, PipelineConfig, as_config

# `training` runs from the checkout (it is not installed): the repository root on the path
# lets this script, and the benchmarks that import it, load training's datasets.
ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(1, str(ROOT))


# The test split chooses nothing: weights, settings and rows are chosen on validation and the
# training dances (--validation, --dances); the test split is scored once per release, for the
# report, and every benchmark that reads it refuses to unless told --report.
TEST_SPLIT_RULE = ("the test split is run once per release, for the report, and never selects "
                   "anything (weights, settings, rows): choose on --validation or --dances")


def add_report_option(parser):
    """Add ``--report``, the switch without which a benchmark refuses the test split."""
    parser.add_argument("--report", action="store_true",
                        help="score the test split: once per release, for the report only "
                             "(it never selects anything; choose on validation)")


def refuse_test_split(parser, args):
    """Stop (argparse's error, exit code 2) unless ``args.report``: this run would score the
    test split."""
    if not args.report:
        parser.error(f"this run scores the test split: {TEST_SPLIT_RULE}. Add --report only "
                     "for the release's report")


def training_env():
    """The environment for a ``python -m training...`` subprocess: the repository root first
    on PYTHONPATH, so that it runs from any working directory."""
    paths = [str(ROOT)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    return {**os.environ, "PYTHONPATH": os.pathsep.join(paths)}


PAPER = {"MPJPE": 0.178, "PA-MPJPE": 0.056, "Acc": 0.016, "PA-Acc": 0.008, "MPVD": 0.145,
         "PA-MPVD": 0.058, "MEDL": 0.001}
ROWS = ("model", "model, no refiner", "model, no denoiser", "model, no foot lock",
        "model, no rest pose", "model, no facing check", "model, mirrored source",
        "paper preset", "regressed preset", "analytic", "analytic, plain",
        "analytic, mirrored source",
        "oracle source",
        "oracle target", "oracle both")
FOOT_LEASHES = (0.02, 0.05, 0.1)     # metres: the optional rows' FootLock.max_offset
LEASH_ROWS = tuple(f"model, foot leash {leash:g} m" for leash in FOOT_LEASHES)
# The fitted preset with one stage off each (docs/source_fit.md, "Which stages the fit makes
# redundant"; "no refiner": the source readings only, the target's skeleton keeps it), or
# every cloud thinned to the fit's 1,024 points before SKR ("Speed").
FIT_VARIANTS = {"model, source fit, no refiner": {"refine": False},
                "model, source fit, no facing check": {"facing_check": False},
                "model, source fit, no rest pose": {"rest_pose": False},
                "model, source fit, no foot lock": {"foot_lock": None},
                "model, source fit, thinned to 1024": {"cloud_points": 1024}}
FIT_ROWS = ("model, source fit", "analytic, source fit", *FIT_VARIANTS)
CONTACT_HEIGHT = 0.03        # metres above a toe's lowest point that count as touching
QUICK_FRAMES, QUICK_PER_CATEGORY = 150, 2
BOOTSTRAP_SAMPLES = 10_000
# Paired comparisons, sequence by sequence, printed when a run has both rows.
PAIRS = (("model", "analytic"), ("model", "analytic, plain"), ("model", "regressed preset"),
         ("model, mirrored source", "analytic, mirrored source"),
         ("model, source fit", "analytic, source fit"), ("model, source fit", "model"),
         *((row, "model, source fit") for row in FIT_VARIANTS))


def command_line(main):
    """Run a benchmark's ``main`` from the command line: bad input (a missing or damaged
    file, a value out of range) is one line naming it, exit status 1, not a traceback."""
    try:
        main()
    except (ValueError, OSError) as error:
        sys.exit(f"{Path(sys.argv[0]).name}: error: {error}")


def load_measured(path):
    """The weights at ``path`` (None: the shipped ones) and their ``weights_record``, taken
    as they are loaded, so a file replaced during a long run is not the one recorded."""
    weights = load_weights(path)
    return weights, weights_record(path, weights)


def load_results(path):
    """A saved run's JSON (``--json``), checked to be one; ValueError naming the file."""
    try:
        saved = json.loads(Path(path).read_text())
    except (OSError, ValueError) as error:
        raise ValueError(f"{path}: cannot read a saved run ({error})") from None
    if not isinstance(saved, dict) or not {"split", "per_sequence"} <= set(saved):
        raise ValueError(f"{path}: not a saved accuracy run (no split and per_sequence)")
    return saved


def weights_record(path, weights):
    """What a saved result was measured with: the weights file as given ("shipped default"
    when none was), the SHA-256 of its bytes (so a file measured under one name and shipped
    under another is still recognised) and the metadata recorded in it."""
    return {"weights": path or "shipped default",
            "weights_sha256": file_sha256(DEFAULT_WEIGHTS if path is None else path),
            "weights_metadata": weights.metadata}


def weights_note(record):
    """One line naming the weights a run measured and the splits that chose them (their
    metadata's ``selected_on``, written by training.export) from a ``weights_record`` or a
    saved run."""
    chosen = (record.get("weights_metadata") or {}).get("selected_on")
    return (f"Weights: {record.get('weights', 'not recorded')}; chosen on: "
            f"{', '.join(chosen) if chosen else 'not recorded in their metadata'}")


def load_sequence(path, frames=None):
    with np.load(path, allow_pickle=False) as data:
        return {key: data[key][:frames] if data[key].ndim and key in (
            "source_points", "source_joints", "target_points", "target_joints", "rotations",
            "source_root", "target_root") else data[key] for key in data.files}


def pose_with_rig(rotations, root, tpose_joints, points, skin_weights):
    """(T, J, 4), (T, 3) on a rig -> joints (T, J, 3), vertices (T, V, 3)."""
    joints, global_rotations = forward_kinematics(rotations, root, tpose_joints)
    transforms = skinning_transforms(joints, global_rotations, tpose_joints)
    return joints, linear_blend_skinning(points, skin_weights, transforms)


def analytic_root(source_joints, target_leg_length):
    """(T, J, 3) source skeletons, the target's leg length (``Target.leg_length``, metres) ->
    (T, 3) roots: each source root scaled by the target's leg length over the mean source leg
    length so far, as SMRM scales it (``smrm`` step 5, without SMRM's learned offset)."""
    legs = np.cumsum(leg_length(source_joints)) / np.arange(1, len(source_joints) + 1)
    return (target_leg_length / legs)[:, None] * source_joints[:, 0]


def analytic_plain(source_joints, target):
    """The plain analytic baseline (row ``analytic, plain``; the ``analytic`` row of runs
    before it had every non-learned stage): each target T-pose bone turned onto its source
    bone (``minretarget.analytic``), the root scaled (``analytic_root``), FK and LBS on the
    model's target rig; no rest-pose model, no foot lock.
    (T, J, 3) source skeletons, a ``Target`` -> joints (T, J, 3), vertices (T, V, 3)."""
    return pose_with_rig(analytic_rotations(source_joints, target.tpose_joints),
                         analytic_root(source_joints, target.leg_length),
                         target.tpose_joints, target.points, target.skin_weights)


def rest_pose_of(retargeter):
    """The rest-pose model ``retargeter``'s SMRM uses (its config's ``rest_pose`` on and the
    weights have one), or None."""
    return retargeter.weights.rest_pose if retargeter.config.rest_pose else None


def analytic_full(source_joints, target, rest_pose=None, foot_lock=None):
    """The analytic baseline with every stage the model has but SMRM's networks (row
    ``analytic``), so that ``model - analytic`` is SMRM's own effect: per frame, the
    rotations of SMRM's analytic prior, i.e. each bone of the prior's reference skeleton
    turned onto its source bone (``minretarget.analytic``), where the reference is the
    target's T-pose turned by the rest-pose model (``rest_pose.prior_reference``, from the
    mean source bone lengths so far, as SMRM computes it; the target's T-pose itself when
    ``rest_pose`` is None); the root scaled as SMRM scales it (``analytic_root``); then the
    foot lock (``contacts.plant_feet``; ``foot_lock`` None: off), FK and LBS on the target
    rig. The rest-pose model is fitted (``training.rest_pose``), not a part of SMRM's
    networks, but it is a part of the prior the model gets, so this row gets it too.

    Args:
        source_joints: (T, J, 3) float32 the source skeletons SMRM saw (smoothed,
            denoised), metres.
        target: the model's ``Target`` (its points, T-pose joints, skinning weights).
        rest_pose: ``RestPoseWeights`` the model's prior uses, or None (the plain prior).
        foot_lock: ``FootLock`` the model uses, or None.
    Returns:
        joints (T, J, 3), vertices (T, V, 3), float32.
    """
    tpose = target.tpose_joints
    lengths = np.cumsum(bone_lengths(source_joints), axis=0, dtype=np.float64)
    lengths /= np.arange(1, len(source_joints) + 1)[:, None]          # (T, B) means so far
    rotations = (analytic_rotations(source_joints, tpose) if rest_pose is None else
                 np.stack([analytic_rotations(joints, prior_reference(rest_pose, tpose, mean))
                           for joints, mean in zip(source_joints,
                                                   lengths.astype(np.float32))]))
    root = analytic_root(source_joints, target.leg_length).astype(np.float32)
    state = None
    for t in range(len(rotations) if foot_lock is not None else 0):
        rotations[t], state = plant_feet(rotations[t], root[t], tpose, state, foot_lock)
    return pose_with_rig(rotations, root, tpose, target.points, target.skin_weights)


def stream(retargeter, source_joints, clouds=None):
    """Run SMRM, FK and LBS online over known source joints (found in ``clouds``, if given:
    the facing check reads those again) -> joints, vertices (T, ...)."""
    retargeter.reset()
    clouds = [None] * len(source_joints) if clouds is None else clouds
    return stacked([retargeter.step_skeleton(joints, cloud)
                    for joints, cloud in zip(source_joints, clouds)])


def stacked(frames):
    """RetargetedFrames (any iterable) -> their joints (T, J, 3) and vertices (T, V, 3)."""
    frames = list(frames)
    return np.stack([f.joints for f in frames]), np.stack([f.vertices for f in frames])


def run_sequence(weights, sequence, wanted=ROWS, draw=None):
    """The ``wanted`` rows' (joints, vertices) for one test sequence, the seconds the
    default model took (SKR and the joint refiner over the frames, then smoothing, the
    denoiser, SMRM, foot contacts, FK and LBS a frame at a time) and the source skeletons of
    the rows that keep them. With ``draw``, every source fit reads that draw of the clouds'
    points (``FitSettings.draw``) and only the wanted rows that the draw moves are made: those
    whose retargeter runs the fit, and the analytic rows on their skeletons."""

    def on_draw(config="default"):
        """A retargeter of ``config`` (a preset's name or a PipelineConfig), its source fit, if
        it has one, on ``draw``."""
        config = as_config(config)
        if draw is not None and config.fit_source is not None:
            config = config.replace(fit_source=config.fit_source._replace(draw=draw))
        return Retargeter(weights, config)

    points = sequence["target_tpose_points"]
    faces = sequence["target_faces"] if "target_faces" in sequence else None    # None: a cloud
    learned = on_draw()
    learned.set_target(points, faces)            # a mesh: its legs read from its surface
    rig = {"tpose_joints": learned.target.tpose_joints,
           "skin_weights": learned.target.skin_weights, "leg_length": learned.target.leg_length}
    true_rig = {"tpose_joints": sequence["target_tpose_joints"],
                "skin_weights": sequence["target_weights"]}
    paper = on_draw("paper")
    paper.set_target(points, faces)                  # its own rig: SKR once on the T-pose
    unrefined = on_draw(PipelineConfig(refine=False, allow_untrained=True))
    unrefined.set_target(points, faces)              # its own rig: SKR's, not refined
    no_lock = on_draw(PipelineConfig(foot_lock=None))
    no_denoiser = on_draw(PipelineConfig(denoise=False))
    no_rest_pose = on_draw(PipelineConfig(rest_pose=False))
    no_facing_check = on_draw(PipelineConfig(facing_check=False))
    raw = on_draw(PipelineConfig(smoothing=None, denoise=False))
    mirrored = on_draw(PipelineConfig(mirror_source=True))
    regressed = on_draw("regressed")
    fitted = (on_draw("fitted")
              if set(FIT_ROWS) & set(wanted) else None)
    fit_variants = {row: on_draw(PRESETS["fitted"].replace(**changes))
                     for row, changes in FIT_VARIANTS.items() if row in wanted}
    oracle_rig = on_draw()
    oracle_rig_raw = on_draw(PipelineConfig(smoothing=None, denoise=False))
    leashed = {row: on_draw(PipelineConfig(foot_lock=FootLock(max_offset=leash)))
               for row, leash in zip(LEASH_ROWS, FOOT_LEASHES) if row in wanted}
    for retargeter, this_rig in ((no_lock, rig), (no_denoiser, rig), (no_rest_pose, rig),
                                 (regressed, rig),
                                 (no_facing_check, rig), (raw, rig), (mirrored, rig),
                                 *(((fitted, rig),) if fitted else ()),
                                 *((retargeter, rig) for retargeter in fit_variants.values()),
                                 (oracle_rig, true_rig), (oracle_rig_raw, true_rig),
                                 *((retargeter, rig) for retargeter in leashed.values())):
        retargeter.set_target(points, faces, **this_rig)
    clouds = sequence["source_points"]
    kinds = {}

    def readings(retargeter):
        """SKR's (and the refiner's) readings of the clouds as ``retargeter``'s config makes
        them: computed once for each kind (thinning, refiner, mirror averaging)."""
        config = retargeter.config
        kind = (config.cloud_points, config.refine, config.mirror_source)
        if kind not in kinds:
            kinds[kind] = retargeter.skeleton(clouds)
        return kinds[kind]

    def streamed(retargeter):
        """``retargeter`` over its own readings, with the clouds (facing check, source fit)."""
        return [retargeter.step_skeleton(joints, cloud)
                for joints, cloud in zip(readings(retargeter), clouds)]

    start = time.perf_counter()
    frames = streamed(learned)          # the default pipeline, SKR batched over the frames
    seconds = time.perf_counter() - start
    model = stacked(frames)
    target = learned.target

    def analytic(frames, retargeter):
        """The analytic baseline on the source skeletons SMRM saw in ``frames`` (smoothed and
        denoised) with what ``retargeter`` (the row's model) gives SMRM's prior and after it:
        its rest-pose model and its foot lock (``analytic_full``)."""
        return analytic_full(np.stack([f.source_joints for f in frames]), target,
                             rest_pose_of(retargeter), retargeter.config.foot_lock)

    mirrored_frames = functools.cache(lambda: list(mirrored.run(sequence["source_points"])))
    fitted_frames = functools.cache(lambda: streamed(fitted))
    regressed_frames = functools.cache(lambda: frames if regressed.config == learned.config
                                       else streamed(regressed))
    variant_frames = functools.cache(lambda row: streamed(fit_variants[row]))
    # The source skeleton SMRM saw, for the rows that keep it.
    seen = {"model": lambda: frames, "analytic": lambda: frames,
            "analytic, plain": lambda: frames, "regressed preset": regressed_frames,
            "model, mirrored source": mirrored_frames,
            "analytic, mirrored source": mirrored_frames,
            "model, source fit": fitted_frames, "analytic, source fit": fitted_frames,
            **{row: functools.partial(variant_frames, row) for row in fit_variants}}
    make = {"model": lambda: model,
            "regressed preset": lambda: stacked(regressed_frames()),
            "model, no refiner": lambda: stacked(streamed(unrefined)),
            "model, no denoiser": lambda: stacked(streamed(no_denoiser)),
            "model, no foot lock": lambda: stacked(streamed(no_lock)),
            "model, no rest pose": lambda: stacked(streamed(no_rest_pose)),
            "model, no facing check": lambda: stream(no_facing_check, readings(no_facing_check)),
            "model, mirrored source": lambda: stacked(mirrored_frames()),
            "paper preset": lambda: stream(paper, readings(paper)),
            "analytic": lambda: analytic(frames, learned),
            "analytic, plain": lambda: analytic_plain(
                np.stack([f.source_joints for f in frames]), target),
            "analytic, mirrored source": lambda: analytic(mirrored_frames(), mirrored),
            "model, source fit": lambda: stacked(fitted_frames()),
            "analytic, source fit": lambda: analytic(fitted_frames(), fitted),
            **{row: functools.partial(lambda row: stacked(variant_frames(row)), row)
               for row in fit_variants},
            "oracle source": lambda: stream(raw, sequence["source_joints"]),
            "oracle target": lambda: stacked(streamed(oracle_rig)),
            "oracle both": lambda: stream(oracle_rig_raw, sequence["source_joints"]),
            **{row: functools.partial(lambda r: stacked(streamed(r)), retargeter)
               for row, retargeter in leashed.items()}}
    # The retargeter each row's figures come from: the rows that run the source fit.
    made_by = {"model": learned, "regressed preset": regressed, "model, no refiner": unrefined,
               "model, no denoiser": no_denoiser, "model, no foot lock": no_lock,
               "model, no rest pose": no_rest_pose, "model, no facing check": no_facing_check,
               "model, mirrored source": mirrored, "paper preset": paper, "analytic": learned,
               "analytic, plain": learned, "analytic, mirrored source": mirrored,
               "model, source fit": fitted, "analytic, source fit": fitted, **fit_variants,
               "oracle source": raw, "oracle target": oracle_rig, "oracle both": oracle_rig_raw,
               **leashed}
    if draw is not None:
        wanted = [row for row in wanted if made_by[row].config.fit_source is not None]
    rows = {row: make[row]() for row in wanted}
    sources = {row: np.stack([f.source_joints for f in seen[row]()])
               for row in wanted if row in seen}
    sources.update({row: sequence["source_joints"] for row in wanted if "oracle" in row
                    and row != "oracle target"})
    return rows, seconds, sources


def sequence_result(rows, sources, sequence):
    """One sequence's entry of a run's "per_sequence": ``run_sequence``'s rows and source
    skeletons scored against the sequence's truth."""
    return {"sequence": str(sequence["name"]), "category": str(sequence["category"]),
            "target_body": str(sequence["target_body"]),
            "frames": len(sequence["source_points"]),
            "metrics": sequence_metrics(rows, sequence),
            "feet": feet_on_contacts(rows, sequence),
            "skeleton": skeleton_figures(rows, sources, sequence)}


def skeleton_figures(rows, sources, sequence):
    """Per row: the frames whose result has crossed feet against the target truth's
    (``metrics.crossed_feet``) and the skating steps ([count, steps],
    ``metrics.skating_steps``); where the row keeps its source skeleton, that skeleton's error
    (``metrics.joint_errors``) and crossed feet against the true source joints; the ground
    truth's skating too."""
    truth, source_truth = sequence["target_joints"], sequence["source_joints"]
    out = {}
    for name, (joints, _) in rows.items():
        skating = skating_steps(joints)
        out[name] = {"crossed_legs": int(crossed_feet(joints, truth).sum()),
                     "skating": [int(skating.sum()), int(skating.size)]}
        if name in sources:
            out[name]["source_error"] = joint_errors(sources[name], source_truth)
            out[name]["source_crossed_legs"] = int(crossed_feet(sources[name],
                                                                source_truth).sum())
    skating = skating_steps(truth)
    out["ground truth"] = {"skating": [int(skating.sum()), int(skating.size)]}
    return out


def feet_on_contacts(rows, sequence):
    """Per row and for the ground truth: [sum of toe speeds (m/s), count] over the steps where
    the ground truth's toes touch the ground."""
    truth = sequence["target_joints"]
    contacts = foot_contacts(truth, CONTACT_HEIGHT)                         # (T - 1, 2)
    everyone = [(name, joints) for name, (joints, _) in rows.items()] + [("ground truth", truth)]
    return {name: [float(foot_speeds(joints)[contacts].sum()), int(contacts.sum())]
            for name, joints in everyone}


def pooled_feet(results, keys=None):
    """Toe speed on the ground truth's contacts, pooled over the chosen sequences, per row."""
    chosen = [r for r in results if keys is None or keys(r)]
    names = results[0]["feet"].keys()
    return {name: sum(r["feet"][name][0] for r in chosen)
            / max(1, sum(r["feet"][name][1] for r in chosen)) for name in names}


def sequence_metrics(rows, sequence):
    truth_joints, truth_points = sequence["target_joints"], sequence["target_points"]
    return {name: evaluate(joints, truth_joints, vertices, truth_points,
                           rest_points=sequence["target_tpose_points"])
            for name, (joints, vertices) in rows.items()}


def frame_weighted(results, keys=None):
    """Mean of per-sequence metrics weighted by frames, per row."""
    chosen = [r for r in results if keys is None or keys(r)]
    total = sum(r["frames"] for r in chosen)
    return {row: {m: sum(r["metrics"][row][m] * r["frames"] for r in chosen) / total
                  for m in METRIC_NAMES} for row in chosen[0]["metrics"]}


def paired_difference(results, row, baseline, samples=BOOTSTRAP_SAMPLES, seed=0):
    """``row`` against ``baseline`` over the per-sequence results, per metric: the
    frame-weighted difference of their means (row minus baseline), its 95 % bootstrap interval
    (``samples`` resamplings of the sequences with replacement, the same draws for every
    metric, seeded) and the number of sequences where ``row`` is lower (better)."""
    frames = np.array([r["frames"] for r in results], dtype=np.float64)
    draws = np.random.default_rng(seed).integers(len(results), size=(samples, len(results)))
    drawn_frames = frames[draws].sum(axis=1)
    out = {}
    for metric in METRIC_NAMES:
        gap = np.array([r["metrics"][row][metric] - r["metrics"][baseline][metric]
                        for r in results])
        resampled = (gap[draws] * frames[draws]).sum(axis=1) / drawn_frames
        low, high = np.percentile(resampled, [2.5, 97.5])
        out[metric] = {"difference": float(gap @ frames / frames.sum()),
                       "ci95": [float(low), float(high)], "sequences_better": int((gap < 0).sum()),
                       "sequences": len(results)}
    return out


def check_same_sequences(planned, saved_results):
    """ValueError naming the first difference unless the (name, frames) pairs ``planned``
    (frames None: not known yet) are the saved run's sequences, in order."""
    for k, ((name, frames), theirs) in enumerate(zip(planned, saved_results)):
        if name != theirs["sequence"] or frames not in (None, theirs["frames"]):
            raise ValueError(f"--compare: sequence {k} is {name} ({frames or '?'} frames) here "
                             f"but {theirs['sequence']} ({theirs['frames']} frames) in the "
                             "saved run")
    if len(planned) != len(saved_results):
        raise ValueError(f"--compare: {len(planned)} sequences here, {len(saved_results)} in "
                         "the saved run")


def against_saved(results, saved_results):
    """This run's model row against a saved run's, sequence by sequence, as
    ``paired_difference`` (below zero: this run better). Both must hold the same sequences in
    the same order (``check_same_sequences``)."""
    check_same_sequences([(r["sequence"], r["frames"]) for r in results], saved_results)
    pairs = [{"frames": ours["frames"], "metrics": {"this run": ours["metrics"]["model"],
                                                    "saved": theirs["metrics"]["model"]}}
             for ours, theirs in zip(results, saved_results)]
    return paired_difference(pairs, "this run", "saved")


def pooled_over_draws(per_draw):
    """Each draw's pooled rows (``summarize``'s "rows", draw 0's first; the later draws' hold
    only the rows the draw moves) -> for each of those rows, its figures per draw and their
    mean over the draws (``fit_settings.over_draws``)."""
    from fit_settings import over_draws       # here, not above: fit_settings imports this
    repeated = [row for row in per_draw[1] if row not in ("paper", "ground truth")]
    return {row: {"per_draw": [rows[row] for rows in per_draw],
                  "mean": over_draws([rows[row] for rows in per_draw])["mean"]}
            for row in repeated}


def against_saved_draws(over, saved_over):
    """This run's model row against a saved run's over the same draws (both
    ``pooled_over_draws``), per pooled figure: this run minus the saved one draw by draw, the
    mean of those differences and its 95 % interval over the draws (Student's t,
    ``fit_settings.over_draws``; below zero: this run better)."""
    from fit_settings import over_draws
    ours, theirs = over["model"]["per_draw"], saved_over["model"]["per_draw"]
    paired = over_draws(ours, theirs)["minus_first"]
    return {key: {**paired[key], "per_draw": [a[key] - b[key] for a, b in zip(ours, theirs)]}
            for key in paired}


def draws_sections(saved, other=None, other_name=None):
    """What a run over several draws adds, from its "draws", "over_draws" and "per_sequence"
    (``saved``: a run's JSON): the fields for its "compared_with" (with ``other``, a saved run
    over as many draws, from the file ``other_name``: the model minus its model, draw by draw;
    else none) and the markdown: each repeated row per draw and its mean, the rows run once,
    and that comparison."""
    over, draws = saved["over_draws"], saved["draws"]
    once = [row for row in saved["per_sequence"][0]["metrics"] if row not in over]
    table = {f"{row}, {label}": figures for row, kept in over.items()
             for label, figures in [*((f"draw {d}", f) for d, f in enumerate(kept["per_draw"])),
                                    (f"mean of {draws}", kept["mean"])]}
    sections = [markdown_table(table, f"Rows with the source fit over its draws 0-{draws - 1} "
                                      "(FitSettings.draw: the points each cloud's fit reads), "
                                      "frame-weighted")
                + "\n\nRun once (no source fit: the same on every draw): "
                + (", ".join(once) or "none")]
    fields = {}
    if other is not None and "model" in over:
        fields["model minus its model, over draws"] = against_saved_draws(
            over, other["over_draws"])
        lines = [f"**Model minus the model of {other_name}, draw by draw over {draws} draws "
                 "(frame-weighted; below zero: this run better)**", "",
                 "| figure | mean difference | 95 % interval (t, over draws) | per draw |",
                 "|---|---|---|---|"]
        for key, c in fields["model minus its model, over draws"].items():
            lines.append(f"| {key} | {c['difference']:+.5f} | [{c['interval'][0]:+.5f}, "
                         f"{c['interval'][1]:+.5f}] | "
                         + ", ".join(f"{d:+.5f}" for d in c["per_draw"]) + " |")
        sections.append("\n".join(lines))
    return fields, "\n\n".join(sections)


def comparison_table(comparison, title):
    lines = [f"**{title}**", "", "| metric | difference | 95 % interval | sequences better |",
             "|---|---|---|---|"]
    for metric, c in comparison.items():
        lines.append(f"| {metric} | {c['difference']:+.5f} | [{c['ci95'][0]:+.5f}, "
                     f"{c['ci95'][1]:+.5f}] | {c['sequences_better']} of {c['sequences']} |")
    return "\n".join(lines)


def markdown_table(rows, title):
    lines = [f"**{title}**", "", "| row | " + " | ".join(METRIC_NAMES) + " |",
             "|---|" + "---|" * len(METRIC_NAMES)]
    for name, metrics in rows.items():
        lines.append(f"| {name} | " + " | ".join(f"{metrics[m]:.4f}" for m in METRIC_NAMES)
                     + " |")
    return "\n".join(lines)


def skeleton_summary(results):
    """Per row over all sequences: crossed_legs (frames of the result, summed), skating_ratio
    (pooled steps); where kept, source_error and source_error_legs (frame-weighted, metres)
    and source_crossed_legs (frames of the source skeleton, summed)."""
    total = sum(r["frames"] for r in results)
    out = {}
    for row in results[0]["skeleton"]:
        figures = [r["skeleton"][row] for r in results]
        skating = np.sum([f["skating"] for f in figures], axis=0)
        out[row] = {"skating_ratio": float(skating[0] / max(1, skating[1]))}
        if row != "ground truth":
            out[row]["crossed_legs"] = int(sum(f["crossed_legs"] for f in figures))
        if all("source_crossed_legs" in f for f in figures):
            out[row]["source_crossed_legs"] = int(sum(f["source_crossed_legs"] for f in figures))
        if all("source_error" in f for f in figures):
            for key, group in (("source_error", "all"), ("source_error_legs", "legs")):
                out[row][key] = sum(f["source_error"][group] * r["frames"]
                                    for f, r in zip(figures, results)) / total
    return out


def skeleton_table(figures, toes):
    """Markdown: each row's source skeleton error and crossed legs, the result's crossed legs,
    skating ratio and toe speed."""
    lines = ["**Skeletons and feet** (source: the skeleton SMRM saw against the true source "
             "joints, error in m, crossed legs in frames; result: the target's crossed legs "
             "against its truth, in frames; skating: the ratio of low, fast foot steps; toes: "
             "m/s on the truth's contacts)", "",
             "| row | source error | source legs | source crossed legs | crossed legs | "
             "skating ratio | toes |", "|---|---|---|---|---|---|---|"]
    for row, f in figures.items():
        error = (f"{f['source_error']:.4f} | {f['source_error_legs']:.4f}"
                 if "source_error" in f else " | ")
        lines.append(f"| {row} | {error} | {f.get('source_crossed_legs', '')} | "
                     f"{f.get('crossed_legs', '')} | {f['skating_ratio']:.4f} | "
                     f"{toes[row]:.3f} |")
    return "\n".join(lines)


def feet_table(feet):
    """Markdown: rows (and the ground truth) by column (all, then categories), m/s."""
    columns = list(feet)
    lines = ["**Toe speed on the ground truth's contacts (m/s; foot sliding)**", "",
             "| row | " + " | ".join(columns) + " |", "|---|" + "---|" * len(columns)]
    for name in feet["all"]:
        lines.append(f"| {name} | " + " | ".join(f"{feet[c][name]:.3f}" for c in columns) + " |")
    return "\n".join(lines)


def write_text(path, text):
    """Write ``text`` to ``path`` through a temporary file: a saved run is never half written
    (``--from-json X --json X`` rewrites X in place)."""
    with atomic_write(path) as file:
        file.write(text.encode())


def select_sequences(paths, quick):
    if not quick:
        return paths, None
    chosen, per_category = [], {}
    for path in sorted(paths):
        with np.load(path, allow_pickle=False) as data:
            category = str(data["category"])
        if per_category.get(category, 0) < QUICK_PER_CATEGORY:
            per_category[category] = per_category.get(category, 0) + 1
            chosen.append(path)
    return chosen, QUICK_FRAMES


# The selection sets (never the test split), by their option (--validation, ...): the split
# name a run records, and their sequences' maker in training.data.datasets.
SELECTION_SETS = {"validation": ("validation", "validation_sequences"),
                  "dances": ("training dances", "dance_sequences"),
                  "motions": ("training motions", "motion_sequences"),
                  "crossed": ("crossed legs", "crossed_sequences"),
                  "more_dances": ("more training dances", "more_dance_sequences")}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    which = parser.add_mutually_exclusive_group()    # one set of sequences a run
    which.add_argument("--quick", action="store_true", help="a fixed subset, about 3 minutes")
    parser.add_argument("--weights", help="weights file (default: the shipped weights)")
    parser.add_argument("--data", default="data", help="built data directory (uses DIR/test)")
    parser.add_argument("--cmu", default="../shared/data/cmu", help="CMU data, to build DIR")
    which.add_argument("--validation", action="store_true",
                        help="score validation trials instead (training.data.datasets."
                             "validation_sequences: 12 trials, 1,396 frames), to choose "
                             "between weights without looking at the test split")
    which.add_argument("--dances", action="store_true",
                        help="score 16 dance and martial-arts trials of the training split on "
                             "held-out validation bodies instead (training.data.datasets."
                             "dance_sequences: 6,954 frames): motion validation lacks")
    which.add_argument("--motions", action="store_true",
                        help="score up to four trials of each other motion category of the "
                             "training split (walks, runs, jumps, climbs, sports, sitting...) on "
                             "held-out validation bodies instead (training.data.datasets."
                             "motion_sequences: 28 trials, 4,883 frames)")
    which.add_argument("--crossed", action="store_true",
                        help="score the dance trials with a leg crossed over the other every "
                             "second or so on held-out validation bodies instead "
                             "(training.data.datasets.crossed_sequences): legs that cross")
    which.add_argument("--more-dances", action="store_true",
                        help="score every other dance, salsa and martial-arts trial of the "
                             "training split (240 frames at most) on held-out validation bodies "
                             "instead (training.data.datasets.more_dance_sequences: 39 trials, "
                             "8,267 frames): the widest dance motion the training split holds")
    parser.add_argument("--rows", nargs="+", choices=ROWS + LEASH_ROWS + FIT_ROWS,
                        default=list(ROWS),
                        metavar="ROW", help="the rows to compute, each quoted (default: all "
                        "but the foot-leash rows; model always)")
    parser.add_argument("--json", help="write the results as JSON here")
    parser.add_argument("--markdown", help="write the tables as markdown here")
    parser.add_argument("--from-json", metavar="SAVED.json",
                        help="print the tables of a saved run (its per-sequence results) "
                             "instead of running; with --json, write it back with them")
    parser.add_argument("--compare", metavar="OTHER.json",
                        help="also compare the model with the model of a saved run on the "
                             "same sequences (other weights, say), sequence by sequence")
    parser.add_argument("--draws", type=int, default=1, metavar="K",
                        help="run the rows with the source fit (the model's, when it is the "
                             "default) on the draws 0..K-1 of the points each cloud's fit "
                             "reads (FitSettings.draw) and give their figures per draw and "
                             "mean; the others once (default 1: the shipped draw only)")
    parser.add_argument("--build", action="store_true",
                        help="build DIR/test first if it is absent (about 13 minutes)")
    add_report_option(parser)
    args = parser.parse_args(argv)
    selection = next((key for key in SELECTION_SETS if getattr(args, key)), None)
    if args.from_json:
        given = [option for option, value in (
            ("--quick", args.quick), (f"--{selection}", selection), ("--weights", args.weights),
            ("--rows", args.rows != list(ROWS)), ("--build", args.build),
            ("--draws", args.draws != 1),
            ("--report", args.report)) if value]
        if given:
            parser.error(f"--from-json prints a saved run: {', '.join(given)} would not apply")
    elif args.report and selection:
        parser.error(f"--report is for the test split; --{selection} needs none")
    if args.draws < 1:
        parser.error(f"--draws must be at least 1, got {args.draws}")
    saved = load_results(args.from_json) if args.from_json else None
    split = (saved["split"] if saved else SELECTION_SETS[selection][0] if selection
             else "test")
    if split == "test" and not saved:       # refused before anything is built or read
        refuse_test_split(parser, args)
    quick = saved.get("quick", False) if saved else args.quick
    other = None
    if args.compare:        # refused now, not after a run of many minutes
        compared = load_results(args.compare)
        if (compared["split"], compared.get("quick", False)) != (split, quick):
            parser.error(f"--compare: {args.compare} scored {compared['split']} sequences"
                         f"{' (quick)' if compared.get('quick') else ''}, this run "
                         f"{split}{' (quick)' if quick else ''}")
        draws = saved.get("draws", 1) if saved else args.draws
        if compared.get("draws", 1) != draws:
            parser.error(f"--compare: {args.compare} ran the source fit on "
                         f"{compared.get('draws', 1)} draws, this run on {draws}: the "
                         "differences are paired draw by draw")
        other = compared
    if saved:
        summary = summarize(saved["per_sequence"], saved["split"], other, args.compare)
        text = summary.pop("text")
        if saved.get("draws", 1) > 1:
            compared, more = draws_sections(saved, other, args.compare)
            summary.get("compared_with", {}).update(compared)
            text += "\n\n" + more
        text += "\n\n" + weights_note(saved)
        print(text)
        if args.markdown:
            write_text(args.markdown, text + "\n")
        if args.json:
            write_text(args.json, json.dumps({**saved, **summary}, indent=2))
        return
    wanted = ["model"] + [row for row in args.rows if row != "model"]
    weights, record = load_measured(args.weights)
    test_dir = Path(args.data) / "test"
    build = [sys.executable, "-m", "training.data", "build", "--cmu", args.cmu, "--out",
             args.data, "--only", "test"]
    if split == "test" and not test_dir.is_dir():
        if not args.build:
            parser.error(f"{test_dir} is absent: build it ({' '.join(build[1:])}), or add "
                         "--build")
        print(f"{test_dir} is absent: building it first", flush=True)
        subprocess.run(build, check=True, env=training_env())
    if split != "test" and not Path(args.cmu).is_dir():
        parser.error(f"--cmu {args.cmu}: no such folder (the {split} trials are read there)")
    if split != "test":
        from training.data import datasets
        held_out = getattr(datasets, SELECTION_SETS[selection][1])(args.cmu)
        loaders = [sequence.build for sequence in held_out]
        planned = [(sequence.name, sequence.frames) for sequence in held_out]
    else:
        paths, frames = select_sequences(sorted(test_dir.glob("*.npz")), args.quick)
        loaders = [functools.partial(load_sequence, path, frames) for path in paths]
        planned = [(path.stem, None) for path in paths]    # lengths known once loaded
    if other is not None:   # refused now, not after the run
        try:
            check_same_sequences(planned, other["per_sequence"])
        except ValueError as error:
            parser.error(str(error))
    started, results, model_seconds = time.perf_counter(), [], 0.0
    later_draws = [[] for _ in range(1, args.draws)]    # draws 1..K-1: the rows they move
    for index, load in enumerate(loaders):
        sequence = load()
        rows, seconds, sources = run_sequence(weights, sequence, wanted)
        model_seconds += seconds
        results.append(sequence_result(rows, sources, sequence))
        for draw, kept in enumerate(later_draws, 1):
            rows, _, sources = run_sequence(weights, sequence, wanted, draw)
            kept.append(sequence_result(rows, sources, sequence))
        print(f"[{index + 1}/{len(loaders)}] {results[-1]['sequence']} "
              f"({results[-1]['frames']} frames): model MPJPE "
              f"{results[-1]['metrics']['model']['MPJPE']:.4f}", flush=True)

    seconds = time.perf_counter() - started
    summary = summarize(results, split, other, args.compare)
    text = summary.pop("text")
    if args.draws > 1:      # draw 0's figures stay where one draw's are; the others beside
        summary.update(draws=args.draws, over_draws=pooled_over_draws(
            [summary["rows"]] + [summarize(kept, split)["rows"] for kept in later_draws]))
        compared, more = draws_sections({**summary, "per_sequence": results}, other,
                                        args.compare)
        summary.get("compared_with", {}).update(compared)
        text += "\n\n" + more
    text += "\n\n" + weights_note(record)
    total_frames = summary["frames"]
    print(text)
    print(f"\n{total_frames} frames in {seconds:.0f} s; model (all stages; SKR and refiner "
          f"batched over the frames) {1e3 * model_seconds / total_frames:.1f} ms per frame")
    if args.markdown:
        write_text(args.markdown, text + "\n")
    if args.json:
        write_text(args.json, json.dumps(
            {**summary, "per_sequence": results, **record,
             "quick": args.quick, "seconds": round(seconds, 1)}, indent=2))


def summarize(results, split, other=None, other_name=None):
    """The tables of a run from its per-sequence results: a dict of the JSON's summary fields
    and ``text``, the markdown of every table; with ``other`` (a saved run, ``load_results``,
    from the file ``other_name``) also the model against its model, and which weights that
    run measured (kept, so that the comparison still says so once the file is gone)."""
    overall = {**frame_weighted(results), "paper": PAPER}
    total_frames = sum(r["frames"] for r in results)
    by_body = {body: frame_weighted(results, lambda r, b=body: r["target_body"] == b)
               for body in sorted({r["target_body"] for r in results})}
    by_category = {c: frame_weighted(results, lambda r, c=c: r["category"] == c)
                   for c in sorted({r["category"] for r in results})}
    sections = [markdown_table(overall, f"All {split} sequences ({len(results)} sequences, "
                                        f"{total_frames} frames; paper: its own test set)")]
    sections += [markdown_table(rows, f"Target body {body}") for body, rows in by_body.items()]
    sections += [markdown_table(rows, f"Category {c}") for c, rows in by_category.items()]
    categories = sorted({r["category"] for r in results})
    feet = {"all": pooled_feet(results), **{c: pooled_feet(results, lambda r, c=c: r["category"]
                                                           == c) for c in categories}}
    sections.append(feet_table(feet))
    if all("skeleton" in r for r in results):     # runs saved before these figures lack them
        figures = skeleton_summary(results)
        sections.append(skeleton_table(figures, feet["all"]))
        for row, values in figures.items():
            overall.setdefault(row, {}).update(values, toe_speed=feet["all"][row])
    paired = {f"{row} minus {baseline}": paired_difference(results, row, baseline)
              for row, baseline in PAIRS
              if row in results[0]["metrics"] and baseline in results[0]["metrics"]}
    sections += [comparison_table(comparison, f"{name.capitalize()}, per sequence "
                                              f"(frame-weighted; below zero: the first better)")
                 for name, comparison in paired.items()]
    compared = {}
    if other is not None:
        measured = {key: other.get(key) for key in ("weights", "weights_sha256",
                                                    "weights_metadata")}
        compared = {"compared_with": {"run": other_name, **measured,
                                      "model minus its model": against_saved(
                                          results, other["per_sequence"])}}
        sections.append(comparison_table(compared["compared_with"]["model minus its model"],
                                         f"Model minus the model of {other_name}, per sequence "
                                         "(frame-weighted; below zero: this run better)"))
    return {"rows": overall, "frames": total_frames, "sequences": len(results),
            "by_target_body": by_body, "by_category": by_category,
            "feet_on_truth_contacts": feet, "paired_differences": paired, "split": split,
            **compared, "text": "\n\n".join(sections)}


if __name__ == "__main__":
    command_line(main)
