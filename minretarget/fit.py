"""Stage 1e, the source fit: track one calibrated body in every source cloud.

SKR reads each cloud on its own: it has no memory of which leg is which, no fixed bone
lengths, and no notion that a bone lies inside the cloud. A body model has all three. The fit
poses a linear body model (``BodyModel``: Q surface points and the 22 joints, both linear in K
shape coefficients, posed by FK and linear blend skinning with fixed weights) so that its
surface meets the cloud, frame after frame, and hands on the model's joints:

1. Shape. The first ``calibration_frames`` frames calibrate the shape coefficients (for a
   fixed pose the posed points are linear in them: one Gauss-Newton step on every frame kept
   so far, after each frame's pose, then ``settle_rounds`` rounds of every kept frame's pose
   (``settle_steps`` steps) and the shape after the last: a leg's length and how far its
   joints bend trade off against each other, and settle together only over many rounds);
   then they are kept, so bone lengths are constant over the rest of the stream. The
   calibration is the fit's slow part: each of its frames steps the shape on all the frames
   kept so far, and the last one (or, if it has no body, the next that has) settles them
   all.
2. Pose. ``iterations`` Gauss-Newton steps (damped, each joint's turn capped) on the root
   translation and one world-frame rotation vector per joint (which turns the joint's subtree
   about it), minimising robust (Geman-McClure) point-to-plane distances from each cloud
   point to its nearest model point and, weaker, from each model point to its nearest cloud
   point, plus pulls of the joints towards SKR's reading and towards the last frame's joints
   moved on by half their last step (the motion continued, damped). The reading's pull is
   per joint, weaker where a joint is read far from that prediction (``reading_width``,
   Geman-McClure): a leg read on the wrong side, a body read turned, would drag the fit off
   the cloud.
3. Starts. A frame starts from the last frame's pose, so left and right carry over. When that
   fit and SKR's reading disagree (by default: always), the frame is also fitted from the
   reading's pose (the analytic bone alignment of the model onto it); after
   ``race_iterations`` steps from each, the one that meets the cloud better goes on: a lost
   track recovers, a leg never passes through empty space to follow the reading. When the
   better one explains the cloud poorly (``swap_legs_cost``), or the reading puts a lower
   leg's joint far from the motion's prediction (``swap_legs_distance``; only after a frame
   with the body), the reading with its lower legs swapped is a third start (SKR reads some
   crossed legs swapped); it does not win where a garment covers the thighs at both poses
   (``covered_thighs``: a coat's tube hides them, and then a swap meets the cloud as well as
   the truth does). When the
   better one leaves cloud points far from the model's legs (``stray_points``,
   ``stray_share``: a foot raised across the other knee, the fit's shin left lying on the
   other leg; a thigh raised in a pirouette), each thigh turned at its hip and each shin at
   its knee to point at them (``aim_bone``) is a start too; each that beats the better one
   goes on beside it, and the lowest cost once all have settled wins (a short race can favour
   a start that settles worse). When a start going on leaves a shin or foot in empty space
   (``lost_legs``: a kick neither start followed), its next steps run at a wider robust width
   without the reading's pull, to reach the leg's points again. Where the chosen start's
   cost still fell by more than ``still_falling`` from its race to its settling (the steps
   have not converged: a fast limb), ``more_iterations`` steps more (``still_falling_told``
   where the frame is told its viewpoint). A cloud where the body
   is not found (``LOST_COST``) is skipped: the last pose is held through it.
4. One camera. Given where the one depth camera that saw the cloud stands (``viewpoint``),
   the model -> cloud term pairs only the model points it would see at each step's pose
   (``seen_points``: facing it, not hidden behind the model itself), the lost-leg test counts
   only those, and the reading's pull leaves each joint's depth along its ray to the motion
   (SKR, trained on whole bodies, reads one side's joints towards the camera).

Lengths are metres; the solver works in float64.
"""
import functools
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ._jit import kernel
from .analytic import _analytic_frame
from .conventions import JOINT_INDEX, NUM_JOINTS, PARENTS
from .nearest import _nearest_both_ways_kernel, _nearest_kernel, build_grid
from .kinematics import (_matrix_to_quaternion_one, _quaternion_to_matrix_kernel,
                         _quaternion_to_matrix_one)
from .sampling import seeded_subset
from .validation import as_float32_array

BODY_MODEL = Path(__file__).with_name("data") / "body_model.npz"
_PARENTS = np.asarray(PARENTS, dtype=np.int64)
PARAMETERS = 3 + 3 * NUM_JOINTS      # root translation, then one rotation vector per joint
MAX_TURN, MAX_SHIFT = 0.3, 0.1       # radians per joint, metres: the largest step taken
TRUNCATE = 0.05                      # metres: the farthest a point counts in a fit's cost
# A frame whose fit costs more has lost the body (validation frames cost 0.028-0.043 m; a
# cloud that misses the model entirely costs 0.075: every distance past TRUNCATE): the fit
# holds the last pose through it instead of following SKR's reading of it.
LOST_COST = 0.06
# What one camera sees of the model (``_seen_kernel``): a point more than HIDDEN_DEPTH behind
# the model's nearest surface along its ray, in cells SEEN_CELL wide, is hidden (metres).
HIDDEN_DEPTH, SEEN_CELL = 0.08, 0.03
# Metres: a model point nearer the camera's image plane than this (or behind it) is not seen,
# and stays out of the image (a perspective image of it would be unbounded).
NEAR_PLANE = 0.05
# Robust widths (metres) of the first frame's rounds of pose and shape: wide first, so that a
# body far from the mean is pulled in before it is fitted.
CALIBRATION_WIDTHS = (0.2, 0.1, 0.07, 0.05, 0.03, 0.03, 0.03, 0.03)
# Each joint's lower leg (0 left, 1 right, -1 neither): the bones a model point moves with
# most that make it a shin or foot point (``lost_legs``).
_LOWER_LEGS = np.full(NUM_JOINTS, -1, np.int64)
for _side, _name in enumerate(("left", "right")):
    for _joint in ("knee", "ankle", "foot"):
        _LOWER_LEGS[JOINT_INDEX[f"{_name}_{_joint}"]] = _side
# Each hip joint's thigh (0 left, 1 right, -1 any other bone): ``lost_legs`` on thighs.
_THIGHS = np.full(NUM_JOINTS, -1, np.int64)
_THIGHS[JOINT_INDEX["left_hip"]], _THIGHS[JOINT_INDEX["right_hip"]] = 0, 1
# The joints whose bones are the legs' (thigh, shin, foot, toes): ``stray_points``.
_LEGS = np.zeros(NUM_JOINTS, np.bool_)
for _name in ("left", "right"):
    for _joint in ("hip", "knee", "ankle", "foot"):
        _LEGS[JOINT_INDEX[f"{_name}_{_joint}"]] = True
# The joints the stray points' starts turn (``aim_bone``): each thigh at its hip, each shin
# at its knee; and each one's child, the bone's other end.
_AIMED = tuple(JOINT_INDEX[f"{name}_{joint}"] for name in ("left", "right")
               for joint in ("hip", "knee"))
_CHILD = {JOINT_INDEX[f"{name}_{joint}"]: JOINT_INDEX[f"{name}_{child}"]
          for name in ("left", "right") for joint, child in (("hip", "knee"), ("knee", "ankle"))}
# Joint order with the lower legs' joints (knee, ankle, foot) of the two sides exchanged:
# ``joints[_SWAPPED_LEGS]`` puts each leg where the other was, the hips where they are.
_SWAPPED_LEGS = np.arange(NUM_JOINTS)
for _joint in ("knee", "ankle", "foot"):
    _left, _right = JOINT_INDEX[f"left_{_joint}"], JOINT_INDEX[f"right_{_joint}"]
    _SWAPPED_LEGS[_left], _SWAPPED_LEGS[_right] = _right, _left


class BodyModel(NamedTuple):
    """A linear body model in the canonical T-pose (``training.body_model`` makes it)."""
    points: np.ndarray         # (Q, 3) float64 surface points of the mean body, metres
    points_basis: np.ndarray   # (K, Q, 3) their change per unit shape coefficient
    normals: np.ndarray        # (Q, 3) unit surface normals of the mean body
    joints: np.ndarray         # (J, 3) joints of the mean body, metres
    joints_basis: np.ndarray   # (K, J, 3)
    bone_index: np.ndarray     # (Q, B) int64 the bones that move each point (padded with 0)
    bone_weight: np.ndarray    # (Q, B) float64 their skinning weights (padded with 0), sum 1


def load_body_model(path=None):
    """Read and check a body model ``.npz`` (None: the shipped ``data/body_model.npz``)."""
    path = BODY_MODEL if path is None else Path(path)
    with np.load(path, allow_pickle=False) as data:
        missing = set(BodyModel._fields) - set(data.files)
        if missing:
            raise ValueError(f"{path}: not a body model, missing {sorted(missing)}")
        arrays = {key: data[key] for key in BodyModel._fields}
    points = as_float32_array(arrays["points"], f"{path}: points", (None, 3))
    count = len(points)
    shapes = {"points_basis": (None, count, 3), "normals": (count, 3),
              "joints": (NUM_JOINTS, 3), "joints_basis": (len(arrays["points_basis"]),
                                                          NUM_JOINTS, 3),
              "bone_index": (count, None), "bone_weight": (count, None)}
    for key, shape in shapes.items():
        as_float32_array(arrays[key], f"{path}: {key}", shape)
    index, weight = arrays["bone_index"], arrays["bone_weight"]
    if (index.shape != weight.shape or index.min() < 0 or index.max() >= NUM_JOINTS
            or weight.min() < 0 or np.abs(weight.sum(axis=1) - 1).max() > 1e-3):
        raise ValueError(f"{path}: bone_index and bone_weight must pair joints 0..21 with "
                         "weights >= 0 summing to 1 per point")
    return BodyModel(*(np.ascontiguousarray(arrays[key], np.int64 if key == "bone_index"
                                            else np.float64) for key in BodyModel._fields))


@functools.lru_cache(maxsize=1)
def body_model():
    """The shipped body model, read once per process."""
    return load_body_model()


class FitSettings(NamedTuple):
    """How the fit runs; the defaults are the shipped choice (docs/source_fit.md)."""
    iterations: int = 4            # Gauss-Newton steps per start per frame
    cloud_points: int = 1024       # cloud points used per frame (a seeded random subset)
    robust_width: float = 0.03     # metres: distances well past it count little
    model_to_cloud: float = 0.5    # weight of model -> cloud beside cloud -> model
    reading_pull: float = 0.005    # weight of the joints' pull towards SKR's reading
    reading_width: float = 0.1     # metres: a joint read this far from where the motion puts
                                   # it (the held pose after a frame without the body) is
                                   # pulled a quarter as hard (0: every joint alike)
    motion_pull: float = 0.005     # weight of the pull towards the last frames' motion
    reseed_distance: float = 0.0   # metres: a fit farther than this from SKR's reading
                                   # (mean over joints) is tried again from the reading
    race_iterations: int = 2       # steps from each start before the best one goes on
    model_stride: int = 1          # every k-th model point meets the cloud (model -> cloud)
    calibration_frames: int = 15   # frames whose clouds calibrate the shape
    settle_rounds: int = 40        # rounds of poses and shape on them all, after the last,
    settle_steps: int = 1          # each round's poses taking this many Gauss-Newton steps:
                                   # a leg's length and its joints' bend converge slowly
                                   # together (docs/source_fit.md)
    lost_leg_width: float = 0.1    # metres: robust width of the steps that find a lost lower
                                   # leg again (0: never looked for)
    lost_leg_distance: float = 0.08  # metres: a lower leg's model point this far from the
                                     # cloud lies in empty space
    lost_leg_share: float = 0.3    # the share of a lower leg's points in empty space past
                                   # which it is lost
    swap_legs_cost: float = 0.04   # metres: a frame whose better start costs more is also
                                   # fitted from SKR's reading with its legs swapped (0: not
                                   # for its cost)
    swap_legs_distance: float = 0.1  # metres: ... and so is a frame whose reading puts a lower
                                     # leg's joint this far from the motion's (0: not for
                                     # that)
    swap_legs_hidden: float = 0.04  # metres: ... but it does not win where a garment
    swap_legs_covered: float = 0.1  # covers the thighs at its pose and at the better start's
                                    # (a thigh with more than lost_leg_share of its model
                                    # points farther than swap_legs_hidden from the cloud,
                                    # and neither with that share farther than
                                    # swap_legs_covered): only the thighs tell the legs
                                    # apart, and under a coat both starts meet it alike
                                    # (swap_legs_hidden 0: no such condition; else
                                    # swap_legs_covered must be the larger)
    stray_share: float = 0.03      # a frame whose cloud has more than this share of points
                                   # farther than lost_leg_distance from the fitted model,
                                   # nearest its legs, also tries each thigh and shin aimed
                                   # at those points (0: never)
    more_iterations: int = 4       # steps more where the chosen start's cost still fell by
    still_falling: float = 0.002   # more than this (metres) from its race to its settling
    still_falling_told: float = 0.005  # the same for a frame told its viewpoint: fewer
                                       # steps suit one view (docs/single_view.md)
    draw: int = 0                  # which seeded subset of each cloud is read: 0 the one a
                                   # pipeline thinned to cloud_points reads too; others, to
                                   # see how far the fit moves with the points drawn


def check_fit_settings(settings):
    """``settings`` if it is a ``FitSettings`` of sensible values, else a TypeError or a
    ValueError naming the field; None passes (no fit)."""
    if settings is None:
        return None
    if not isinstance(settings, FitSettings):
        raise TypeError(f"fit_source must be a fit.FitSettings or None, got "
                        f"{type(settings).__name__}")
    for name in ("iterations", "cloud_points", "race_iterations", "model_stride",
                 "calibration_frames", "settle_steps"):
        value = getattr(settings, name)
        if not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"FitSettings.{name} must be an integer >= 1, got {value!r}")
    for name in ("settle_rounds", "draw", "more_iterations"):
        value = getattr(settings, name)
        if not isinstance(value, (int, np.integer)) or value < 0:
            raise ValueError(f"FitSettings.{name} must be an integer >= 0, got {value!r}")
    for name in ("robust_width", "model_to_cloud", "reading_pull", "reading_width",
                 "motion_pull", "reseed_distance", "lost_leg_width", "lost_leg_distance",
                 "swap_legs_cost", "swap_legs_distance", "swap_legs_hidden",
                 "swap_legs_covered", "stray_share", "still_falling", "still_falling_told"):
        value = getattr(settings, name)
        positive = name in ("robust_width", "lost_leg_distance")
        if not np.isfinite(value) or value < 0 or (positive and value == 0):
            raise ValueError(f"FitSettings.{name} must be a finite number "
                             f"{'> 0' if positive else '>= 0'}, got {value!r}")
    hidden, covered = settings.swap_legs_hidden, settings.swap_legs_covered
    if hidden > 0 and not covered > hidden:
        raise ValueError(f"FitSettings.swap_legs_covered must be > swap_legs_hidden "
                         f"({hidden!r}) where that is on, got {covered!r}")
    share = settings.lost_leg_share
    if not np.isfinite(share) or not 0 < share <= 1:
        raise ValueError(f"FitSettings.lost_leg_share must be a number in (0, 1], got "
                         f"{share!r}")
    return settings


class FitState(NamedTuple):
    """What the fit carries from frame to frame (arrays float64)."""
    frames: int                 # frames fitted so far
    shape: np.ndarray           # (K,) shape coefficients
    local: np.ndarray           # (J, 3, 3) the last frame's local rotations
    root: np.ndarray            # (3,) its pelvis position, metres
    joints: np.ndarray          # (2, J, 3) the last two frames' joints (older first)
    calibration: tuple          # ((cloud (P, 3), its grid, local, root, viewpoint (3,) or
                                # None), ...), calibrating
    cost: float = 0.0           # the last frame's fit cost (``fit_pose``), metres


# ----------------------------------------------------------------------------- kernels

@kernel
def _forward_kernel(local, root, tpose, parents, rotations, joints):
    """FK with matrices: local (J, 3, 3), root (3,), tpose (J, 3) -> rotations, joints.
    Scalar loops: numba's ``@`` calls BLAS on 3 x 3 blocks and costs seconds to compile."""
    for a in range(3):
        joints[0, a] = root[a]
        for b in range(3):
            rotations[0, a, b] = local[0, a, b]
    for j in range(1, local.shape[0]):
        p = parents[j]
        for a in range(3):
            offset = 0.0
            for b in range(3):
                total = 0.0
                for c in range(3):
                    total += rotations[p, a, c] * local[j, c, b]
                rotations[j, a, b] = total
                offset += rotations[p, a, b] * (tpose[j, b] - tpose[p, b])
            joints[j, a] = joints[p, a] + offset


@kernel
def _pose_points_kernel(rest, tpose, bone_index, bone_weight, normals, rotations, joints,
                        chain_count, chain_reach, chain_joints, slots, slot_count, links,
                        link_count, posed, posed_normals, lever):
    """LBS of the model's points, and each point's lever about each joint of its chain
    (``Chains``): lever[q, u] = sum over the bones k at or below joint j = chain_joints[q, u]
    of w_qk (bone k's move of q - joint j), so that turning j by d moves q by d x lever[q, u].
    Only the chain's joints, and for each bone the chain's places it moves, listed once per
    model: a (Q, J, 3) lever, mostly zeros, and a test of every bone against every joint cost
    more than the sums (issue 39). Scalar loops: numba's ``@`` on 3-vectors allocates and
    calls BLAS."""
    for q in range(rest.shape[0]):
        posed[q] = 0.0
        posed_normals[q] = 0.0
        for u in range(chain_count[q]):
            lever[q, u] = 0.0
        for t in range(slot_count[q]):
            b = slots[q, t]
            w = bone_weight[q, b]
            k = bone_index[q, b]
            for a in range(3):
                moved = joints[k, a]
                turned = 0.0
                for c in range(3):
                    moved += rotations[k, a, c] * (rest[q, c] - tpose[k, c])
                    turned += rotations[k, a, c] * normals[q, c]
                posed[q, a] += w * moved
                posed_normals[q, a] += w * turned
                for e in range(link_count[q, t]):
                    lever[q, links[q, t, e], a] += w * moved
        norm = np.sqrt(posed_normals[q, 0] ** 2 + posed_normals[q, 1] ** 2
                       + posed_normals[q, 2] ** 2)
        for a in range(3):
            posed_normals[q, a] /= norm
        for u in range(chain_count[q]):
            j = chain_joints[q, u]
            for a in range(3):
                lever[q, u, a] -= chain_reach[q, u] * joints[j, a]


@kernel
def _plane_row(q, target, weight, posed, posed_normals, lever, chain_joints, chain_count,
               entries, columns):
    """One pair's weighted point-to-plane row: row . step = the change of sqrt(w) n . (x - y).
    Its entries that are not zero go to ``entries``, their columns (ascending, by 3 x 3
    blocks: the translation, then each joint of the point's chain) to ``columns``; returns
    (their count, sqrt(w) n . (x - y))."""
    s = np.sqrt(weight)
    n = posed_normals[q]
    count = 0
    for a in range(3):
        entries[count] = s * n[a]
        columns[count] = a
        count += 1
    for u in range(chain_count[q]):
        j = chain_joints[q, u]
        l = lever[q, u]                                # d(n . x)/d(turn j) = lever x n
        entries[count] = s * (l[1] * n[2] - l[2] * n[1])
        entries[count + 1] = s * (l[2] * n[0] - l[0] * n[2])
        entries[count + 2] = s * (l[0] * n[1] - l[1] * n[0])
        for a in range(3):
            columns[count] = 3 + 3 * j + a
            count += 1
    value = 0.0
    for a in range(3):
        value += n[a] * (posed[q, a] - target[a])
    return count, s * value


@kernel
def _plane_normal_equations_kernel(model_index, targets, weights, posed, posed_normals, lever,
                                   chain_joints, chain_count, hessian, gradient):
    """The pairs' normal equations, added to a symmetric ``hessian``: hessian += sum row
    row^T, gradient += sum row value (rows as ``_plane_row``), by 3 x 3 blocks over the joints
    that move each point (the translation as block 0). The blocks on and above the diagonal
    are summed in a packed copy, each block's 9 numbers in a row, then written back and
    mirrored below: the same sums in the same order as into the dense matrix, in 30 % less
    time with the block's 9 products written out (issue 39). Not a BLAS product: at this size
    BLAS's threads cost more than they give."""
    blocks = hessian.shape[0] // 3
    first = np.empty(blocks, np.int64)          # packed[first[u] + v]: block (u, v), v >= u
    packed = np.empty((blocks * (blocks + 1) // 2, 9))
    for u in range(blocks):
        first[u] = u * blocks - u * (u - 1) // 2 - u
        for v in range(u, blocks):
            for x in range(3):
                for y in range(3):
                    packed[first[u] + v, 3 * x + y] = hessian[3 * u + x, 3 * v + y]
    entries = np.empty(hessian.shape[0])
    columns = np.empty(hessian.shape[0], np.int64)
    moved = np.empty(blocks, np.int64)
    for i in range(model_index.shape[0]):
        count, value = _plane_row(model_index[i], targets[i], weights[i], posed, posed_normals,
                                  lever, chain_joints, chain_count, entries, columns)
        for u in range(count // 3):
            moved[u] = columns[3 * u] // 3
        for u in range(count // 3):
            a = 3 * moved[u]
            e0, e1, e2 = entries[3 * u], entries[3 * u + 1], entries[3 * u + 2]
            gradient[a] += e0 * value
            gradient[a + 1] += e1 * value
            gradient[a + 2] += e2 * value
            start = first[moved[u]]
            for v in range(u, count // 3):
                f0, f1, f2 = entries[3 * v], entries[3 * v + 1], entries[3 * v + 2]
                block = start + moved[v]
                packed[block, 0] += e0 * f0
                packed[block, 1] += e0 * f1
                packed[block, 2] += e0 * f2
                packed[block, 3] += e1 * f0
                packed[block, 4] += e1 * f1
                packed[block, 5] += e1 * f2
                packed[block, 6] += e2 * f0
                packed[block, 7] += e2 * f1
                packed[block, 8] += e2 * f2
    for u in range(blocks):
        for v in range(u, blocks):
            for x in range(3):
                for y in range(3):
                    hessian[3 * u + x, 3 * v + y] = packed[first[u] + v, 3 * x + y]
                    if v > u:
                        hessian[3 * v + y, 3 * u + x] = packed[first[u] + v, 3 * x + y]


@kernel
def _apply_step_kernel(local, rotations, step, parents, out):
    """Turn each joint's subtree by its world rotation vector: out[j] = R_p^T T_j R_p local[j]
    (R_p the parent's world rotation), rounded back onto a rotation through a quaternion."""
    turn, quaternion = np.empty((3, 3)), np.empty(4)
    moved, product = np.empty((3, 3)), np.empty((3, 3))
    for j in range(local.shape[0]):
        x, y, z = step[3 + 3 * j], step[4 + 3 * j], step[5 + 3 * j]
        angle = np.sqrt(x * x + y * y + z * z)
        half = 0.5 * angle
        scale = np.sin(half) / angle if angle > 1e-12 else 0.5
        quaternion[0], quaternion[1] = np.cos(half), scale * x
        quaternion[2], quaternion[3] = scale * y, scale * z
        _quaternion_to_matrix_one(quaternion, turn)
        if j == 0:
            for a in range(3):
                for b in range(3):
                    total = 0.0
                    for c in range(3):
                        total += turn[a, c] * local[0, c, b]
                    moved[a, b] = total
        else:                   # written out: numba's ``@`` calls BLAS on 3 x 3 blocks
            parent = rotations[parents[j]]
            for a in range(3):
                for b in range(3):
                    total = 0.0
                    for c in range(3):
                        total += parent[a, c] * local[j, c, b]
                    moved[a, b] = total                              # R_p local
            for a in range(3):
                for b in range(3):
                    total = 0.0
                    for c in range(3):
                        total += turn[a, c] * moved[c, b]
                    product[a, b] = total                            # T_j R_p local
            for a in range(3):
                for b in range(3):
                    total = 0.0
                    for c in range(3):
                        total += parent[c, a] * product[c, b]
                    moved[a, b] = total                              # R_p^T T_j R_p local
        _matrix_to_quaternion_one(moved, quaternion)
        _quaternion_to_matrix_one(quaternion, out[j])


@kernel
def _pull_normal_equations_kernel(joints, goal, weight, parents, hessian, gradient):
    """The pull of the joints (J, 3) towards ``goal`` (J, 3), joint k's with ``weight[k]``
    (J,) (spread over the joints), added to the normal equations: joint k moves by t + sum
    over its strict ancestors j of d_j x (p_k - p_j), so its rows are [I, -skew(p_k - p_j),
    ...]."""
    blocks = np.empty((joints.shape[0], 3, 3))           # the joint's 3 x 3 block per column
    columns = np.empty(joints.shape[0], np.int64)
    for k in range(joints.shape[0]):
        scale = weight[k] / joints.shape[0]              # the rows' square: sqrt(w / J)^2
        count = 1
        columns[0] = 0                                   # the translation: identity
        blocks[0] = 0.0
        for a in range(3):
            blocks[0, a, a] = 1.0
        j = parents[k]
        while j >= 0:
            l0, l1, l2 = (joints[k, 0] - joints[j, 0], joints[k, 1] - joints[j, 1],
                          joints[k, 2] - joints[j, 2])
            b = blocks[count]                            # -skew(l): d x l = -skew(l) d
            b[0, 0], b[0, 1], b[0, 2] = 0.0, l2, -l1
            b[1, 0], b[1, 1], b[1, 2] = -l2, 0.0, l0
            b[2, 0], b[2, 1], b[2, 2] = l1, -l0, 0.0
            columns[count] = 1 + j
            count += 1
            j = parents[j]
        for u in range(count):
            a = 3 * columns[u]
            for x in range(3):
                for r in range(3):
                    gradient[a + x] += scale * blocks[u, r, x] * (joints[k, r] - goal[k, r])
            for v in range(count):
                b = 3 * columns[v]
                for x in range(3):
                    for y in range(3):
                        total = 0.0
                        for r in range(3):
                            total += blocks[u, r, x] * blocks[v, r, y]
                        hessian[a + x, b + y] += scale * total


@kernel
def _surface_pairs_kernel(posed, cloud, cloud_origin, cloud_cell, cloud_dims, cloud_order,
                          cloud_starts, robust_width, model_to_cloud, model_stride, seen):
    """``surface_terms`` on arrays: -> model index (N,), targets (N, 3), weights (N,), cost.
    ``seen`` (Q,) bool: the model points the outward term may pair (all, unless one camera
    saw the cloud: ``_seen_kernel``)."""
    # Both ways in one pass over the cloud's grid (``nearest``): each cloud point's nearest
    # model point (inward), each stride-th model point's nearest cloud point (outward).
    nearest_distance, nearest_index = np.empty(len(posed)), np.empty(len(posed), np.int64)
    inward_distance = np.empty(len(cloud))
    inward_index = np.empty(len(cloud), np.int64)
    _nearest_both_ways_kernel(cloud, cloud_origin, cloud_cell, cloud_dims, cloud_order,
                              cloud_starts, posed, model_stride, nearest_distance,
                              nearest_index, inward_distance, inward_index)
    outward_count = 0                                      # every stride-th point seen
    for q in range(0, len(posed), model_stride):
        if seen[q]:
            outward_count += 1
    outward_model = np.empty(outward_count, np.int64)
    outward_distance = np.empty(outward_count)
    outward_nearest = np.empty(outward_count, np.int64)
    i = 0
    for q in range(0, len(posed), model_stride):
        if seen[q]:
            outward_model[i] = q
            outward_distance[i] = nearest_distance[q]
            outward_nearest[i] = nearest_index[q]
            i += 1
    # Pairs that share a model point share its row (``_plane_row`` depends on the point alone):
    # summed per model point, their weights and weighted targets give the same normal
    # equations from at most Q rows instead of P + Q / stride.
    total, weighted_targets = np.empty(len(posed)), np.empty((len(posed), 3))
    total[:] = 0.0
    weighted_targets[:] = 0.0
    inward_cost, outward_cost = 0.0, 0.0
    for i in range(len(cloud)):
        w = _robust_weight(inward_distance[i], robust_width) / len(cloud)
        total[inward_index[i]] += w
        for a in range(3):
            weighted_targets[inward_index[i], a] += w * cloud[i, a]
        inward_cost += min(inward_distance[i], TRUNCATE)
    for i in range(outward_count):
        w = (model_to_cloud * _robust_weight(outward_distance[i], robust_width)
             / outward_count)
        total[outward_model[i]] += w
        for a in range(3):
            weighted_targets[outward_model[i], a] += w * cloud[outward_nearest[i], a]
        outward_cost += min(outward_distance[i], TRUNCATE)
    count = 0
    for q in range(len(posed)):
        if total[q] > 0.0:
            count += 1
    paired, targets, weights = np.empty(count, np.int64), np.empty((count, 3)), np.empty(count)
    count = 0
    for q in range(len(posed)):
        if total[q] > 0.0:
            paired[count], weights[count] = q, total[q]
            for a in range(3):
                targets[count, a] = weighted_targets[q, a] / total[q]
            count += 1
    cost = inward_cost / len(cloud)
    if outward_count > 0:
        cost += model_to_cloud * outward_cost / outward_count
    return paired, targets, weights, cost


@kernel
def _seen_kernel(posed, posed_normals, viewpoint, hidden_depth, cell, seen):
    """Which posed model points (Q, 3), unit normals (Q, 3), a camera at ``viewpoint`` (3,)
    would see -> ``seen`` (Q,) bool: those in front of it (past ``NEAR_PLANE`` along the view
    to the points' centre), facing it and not hidden behind the model's own surface, i.e. no
    model point in the 3 x 3 cells around its ray (``cell`` metres wide at the model's
    distance) more than ``hidden_depth`` nearer. A z-buffer of the model's own points, as
    model-based depth trackers test their model's visibility."""
    count = posed.shape[0]
    centre = np.zeros(3)
    for q in range(count):
        for a in range(3):
            centre[a] += posed[q, a] / count
    axis = centre - viewpoint
    distance = np.sqrt(axis[0] ** 2 + axis[1] ** 2 + axis[2] ** 2)
    axis /= distance
    # right = axis x the world axis least along the view's, up = axis x right; written out:
    # np.cross and np.argmin cost seconds to compile
    least = 0
    for a in range(1, 3):
        if abs(axis[a]) < abs(axis[least]):
            least = a
    right, up = np.empty(3), np.empty(3)
    for a in range(3):
        b, c = (a + 1) % 3, (a + 2) % 3
        right[a] = (axis[b] if c == least else 0.0) - (axis[c] if b == least else 0.0)
    norm = np.sqrt(right[0] ** 2 + right[1] ** 2 + right[2] ** 2)
    for a in range(3):
        right[a] /= norm
    for a in range(3):
        b, c = (a + 1) % 3, (a + 2) % 3
        up[a] = axis[b] * right[c] - axis[c] * right[b]
    depth, across, along = np.empty(count), np.empty(count), np.empty(count)
    low_x, low_y, high_x, high_y = np.inf, np.inf, -np.inf, -np.inf
    for q in range(count):
        ray = posed[q] - viewpoint
        depth[q] = ray[0] * axis[0] + ray[1] * axis[1] + ray[2] * axis[2]
        if depth[q] <= NEAR_PLANE:
            continue
        scale = distance / depth[q]             # a perspective image, in metres at the model
        across[q] = scale * (ray[0] * right[0] + ray[1] * right[1] + ray[2] * right[2])
        along[q] = scale * (ray[0] * up[0] + ray[1] * up[1] + ray[2] * up[2])
        low_x, high_x = min(low_x, across[q]), max(high_x, across[q])
        low_y, high_y = min(low_y, along[q]), max(high_y, along[q])
    if not low_x <= high_x:                     # every point at or behind the camera
        seen[:] = False
        return
    width = int((high_x - low_x) / cell) + 1
    height = int((high_y - low_y) / cell) + 1
    nearest = np.empty((width, height))
    nearest[:] = np.inf
    column, row = np.empty(count, np.int64), np.empty(count, np.int64)
    for q in range(count):
        if depth[q] <= NEAR_PLANE:
            continue
        column[q] = int((across[q] - low_x) / cell)
        row[q] = int((along[q] - low_y) / cell)
        nearest[column[q], row[q]] = min(nearest[column[q], row[q]], depth[q])
    for q in range(count):
        facing = 0.0
        for a in range(3):
            facing += posed_normals[q, a] * (viewpoint[a] - posed[q, a])
        seen[q] = facing > 0.0 and depth[q] > NEAR_PLANE
        if not seen[q]:
            continue
        for x in range(max(column[q] - 1, 0), min(column[q] + 2, width)):
            for y in range(max(row[q] - 1, 0), min(row[q] + 2, height)):
                if nearest[x, y] < depth[q] - hidden_depth:
                    seen[q] = False


@kernel
def _shape_rows_kernel(points_basis, joints_basis, bone_index, bone_weight, parents,
                       rotations, model_index, normals, rows):
    """rows[i, k] = n . d(posed point)/d(shape k) at model point model_index[i] with unit
    normal normals[i], for a fixed pose (world rotations (J, 3, 3)) and root: the point moves
    with its bones' joints and turns with their rotations."""
    shapes, bodies = joints_basis.shape[0], joints_basis.shape[1]
    moved = np.empty((shapes, bodies, 3))     # each joint's move per coefficient, root fixed
    moved[:] = 0.0
    for k in range(shapes):
        for j in range(1, bodies):
            p = parents[j]
            for a in range(3):
                total = moved[k, p, a]
                for c in range(3):
                    total += rotations[p, a, c] * (joints_basis[k, j, c] - joints_basis[k, p, c])
                moved[k, j, a] = total
    for i in range(len(model_index)):
        q = model_index[i]
        for k in range(shapes):
            along = 0.0
            for b in range(bone_index.shape[1]):
                w = bone_weight[q, b]
                if w == 0.0:
                    continue
                bone = bone_index[q, b]
                for a in range(3):
                    change = moved[k, bone, a]
                    for c in range(3):
                        change += rotations[bone, a, c] * (points_basis[k, q, c]
                                                           - joints_basis[k, bone, c])
                    along += w * normals[i, a] * change
            rows[i, k] = along


@kernel
def _solve_positive_definite(matrix, rhs, out):
    """out = -matrix^-1 rhs, the Gauss-Newton step, for a symmetric positive definite
    ``matrix`` (n, n), by Cholesky: matrix = L L^T, L written over its lower triangle
    (``matrix`` is spent). The normal equations are positive definite by construction
    (J^T W J, W >= 0, plus a damped diagonal with a floor); np.linalg.solve's LU gives the
    same step to rounding, and its LAPACK wrapper costs seconds to compile (issue 40)."""
    n = matrix.shape[0]
    for j in range(n):
        pivot = matrix[j, j]
        for k in range(j):
            pivot -= matrix[j, k] * matrix[j, k]
        if not pivot > 0.0:
            raise ValueError("the fit's normal equations are not positive definite")
        pivot = np.sqrt(pivot)
        matrix[j, j] = pivot
        for i in range(j + 1, n):
            total = matrix[i, j]
            for k in range(j):
                total -= matrix[i, k] * matrix[j, k]
            matrix[i, j] = total / pivot
    for i in range(n):                      # L y = rhs
        total = rhs[i]
        for k in range(i):
            total -= matrix[i, k] * out[k]
        out[i] = total / matrix[i, i]
    for i in range(n - 1, -1, -1):          # L^T x = y
        total = out[i]
        for k in range(i + 1, n):
            total -= matrix[k, i] * out[k]
        out[i] = total / matrix[i, i]
    for i in range(n):
        out[i] = -out[i]


@kernel
def _robust_weight(distance, width):
    """Geman-McClure IRLS weight: 1 at 0, falling as (width / d)^4 far away."""
    ratio = distance / width
    return 1.0 / (1.0 + ratio * ratio) ** 2


@kernel
def _damped_step_kernel(hessian, gradient, step):
    """The Gauss-Newton step from the normal equations (``hessian`` is spent): Levenberg-
    Marquardt's damping and a floor, the Cholesky solve, then the root's shift capped to
    MAX_SHIFT and each joint's turn to MAX_TURN."""
    parameters = hessian.shape[0]
    for a in range(parameters):
        hessian[a, a] += 1e-3 * hessian[a, a] + 1e-5
    _solve_positive_definite(hessian, gradient, step)
    for block in range(parameters // 3):
        limit = MAX_SHIFT if block == 0 else MAX_TURN
        norm = np.sqrt(step[3 * block] ** 2 + step[3 * block + 1] ** 2
                       + step[3 * block + 2] ** 2)
        if norm > limit:
            for a in range(3):
                step[3 * block + a] *= limit / norm


def _gauss_newton(iterations, rest, tpose, bone_index, bone_weight, normals, parents,
                  chain_count, chain_reach, chain_joints, slots, slot_count, links,
                  link_count, cloud, cloud_origin, cloud_cell, cloud_dims, cloud_order,
                  cloud_starts, robust_width, model_to_cloud, model_stride, pull_weight,
                  pull_goal, viewpoint, local, root, joints):
    """``fit_pose``'s Gauss-Newton steps, in place on ``local`` (J, 3, 3) and ``root`` (3,);
    ``joints`` (J, 3) gets the result's; returns the cost measured before the last step.
    ``viewpoint``: None, or the (3,) camera that saw the cloud (the outward term then pairs
    only the model points it would see, at each step's pose).
    Python over the step's kernels, not one kernel around them: numba would compile such a
    kernel with all of them linked in and optimised again (issue 40)."""
    count, bodies = rest.shape[0], tpose.shape[0]
    parameters = 3 + 3 * bodies
    rotations = np.empty((bodies, 3, 3))
    posed, posed_normals = np.empty((count, 3)), np.empty((count, 3))
    lever = np.empty((count, chain_joints.shape[1], 3))
    turned = np.empty_like(local)
    hessian = np.empty((parameters, parameters))
    gradient, step = np.empty(parameters), np.empty(parameters)
    seen = np.ones(count, np.bool_)
    cost = 0.0
    for _ in range(iterations):
        _forward_kernel(local, root, tpose, parents, rotations, joints)
        _pose_points_kernel(rest, tpose, bone_index, bone_weight, normals, rotations, joints,
                            chain_count, chain_reach, chain_joints, slots, slot_count, links,
                            link_count, posed, posed_normals, lever)
        if viewpoint is not None:
            _seen_kernel(posed, posed_normals, viewpoint, HIDDEN_DEPTH, SEEN_CELL, seen)
        paired, targets, weights, cost = _surface_pairs_kernel(
            posed, cloud, cloud_origin, cloud_cell, cloud_dims, cloud_order, cloud_starts,
            robust_width, model_to_cloud, model_stride, seen)
        hessian[:] = 0.0
        gradient[:] = 0.0
        _plane_normal_equations_kernel(paired, targets, weights, posed, posed_normals, lever,
                                       chain_joints, chain_count, hessian, gradient)
        if pull_weight.any():
            _pull_normal_equations_kernel(joints, pull_goal, pull_weight, parents, hessian,
                                          gradient)
        _damped_step_kernel(hessian, gradient, step)
        _apply_step_kernel(local, rotations, step, parents, turned)
        local[...] = turned
        root += step[:3]
    _forward_kernel(local, root, tpose, parents, rotations, joints)
    return cost


@kernel
def _heaviest_bone(bone_index, bone_weight, q):
    """The bone (joint index) that moves model point q most (the first of equals)."""
    heaviest, weight = 0, -1.0
    for b in range(bone_index.shape[1]):
        if bone_weight[q, b] > weight:
            heaviest, weight = bone_index[q, b], bone_weight[q, b]
    return heaviest


@kernel
def _skin_point(rest, tpose, bone_index, bone_weight, rotations, joints, q, out):
    """Model point q posed by LBS (no normals, no levers: ``_pose_points_kernel`` has them)
    into ``out`` (3,)."""
    for a in range(3):
        out[a] = 0.0
    for b in range(bone_index.shape[1]):
        w = bone_weight[q, b]
        if w == 0.0:
            continue
        k = bone_index[q, b]
        for a in range(3):
            moved = joints[k, a]
            for c in range(3):
                moved += rotations[k, a, c] * (rest[q, c] - tpose[k, c])
            out[a] += w * moved


@kernel
def _stray_points_kernel(rest, tpose, bone_index, bone_weight, rotations, joints, legs,
                         cloud, cloud_origin, cloud_cell, cloud_dims, cloud_order, cloud_starts,
                         far, stray):
    """``stray_points`` on arrays: stray (P,) bool gets, per cloud point (the grid's order),
    whether every model point, posed by LBS, lies farther than ``far`` and the nearest is a
    leg's (``legs`` (J,) bool: the joints whose bones are the legs')."""
    posed = np.empty((rest.shape[0], 3))
    for q in range(rest.shape[0]):
        _skin_point(rest, tpose, bone_index, bone_weight, rotations, joints, q, posed[q])
    distances, indices = np.empty(len(posed)), np.empty(len(posed), np.int64)
    back_distances, back_indices = np.empty(len(cloud)), np.empty(len(cloud), np.int64)
    # Only the cloud's side is wanted: a stride past the last query skips the model's searches
    _nearest_both_ways_kernel(cloud, cloud_origin, cloud_cell, cloud_dims, cloud_order,
                              cloud_starts, posed, len(posed) + 1, distances, indices,
                              back_distances, back_indices)
    for n in range(len(cloud)):
        stray[n] = False
        if back_distances[n] > far:
            stray[n] = legs[_heaviest_bone(bone_index, bone_weight, back_indices[n])]


@kernel
def _lost_legs_kernel(rest, tpose, bone_index, bone_weight, rotations, joints, parts,
                      seen, cloud, cloud_origin, cloud_cell, cloud_dims, cloud_order,
                      cloud_starts, far, shares):
    """``lost_legs`` on arrays: shares (2,) gets, per side, the share of its model points
    (those whose heaviest bone is one of the side's, ``parts`` (J,) 0 or 1, else -1, and
    ``seen`` (Q,) bool), posed by LBS, that lie farther than ``far`` from the cloud."""
    leg = np.empty(rest.shape[0], np.int64)
    count = 0
    for q in range(rest.shape[0]):
        leg[q] = parts[_heaviest_bone(bone_index, bone_weight, q)] if seen[q] else -1
        if leg[q] >= 0:
            count += 1
    points = np.empty((count, 3))
    sides = np.empty(count, np.int64)
    count = 0
    for q in range(rest.shape[0]):
        if leg[q] < 0:
            continue
        _skin_point(rest, tpose, bone_index, bone_weight, rotations, joints, q, points[count])
        sides[count] = leg[q]
        count += 1
    distances, nearest = np.empty(count), np.empty(count, np.int64)
    _nearest_kernel(cloud, cloud_origin, cloud_cell, cloud_dims, cloud_order, cloud_starts,
                    points, distances, nearest)
    totals = np.empty(2)
    for s in range(2):
        totals[s] = 0.0
        shares[s] = 0.0
    for i in range(count):
        totals[sides[i]] += 1.0
        if distances[i] > far:
            shares[sides[i]] += 1.0
    for s in range(2):
        if totals[s] > 0.0:
            shares[s] /= totals[s]


# ----------------------------------------------------------------------------- posing

_SHAPED = [None]


def shaped(model, shape):
    """(K,) shape coefficients -> T-pose surface points (Q, 3) and joints (J, 3), metres. The
    last answer is kept: after the calibration every frame asks for the same shape (the
    arrays are shared: not to be written to)."""
    shape = np.asarray(shape, np.float64)
    key = shape.tobytes()
    kept = _SHAPED[0]
    if kept is None or kept[0] is not model or kept[1] != key:
        rest = model.points + np.tensordot(shape, model.points_basis, 1)
        kept = _SHAPED[0] = (model, key, (rest, model.joints
                                          + np.tensordot(shape, model.joints_basis, 1)))
    return kept[2]


def forward(local, root, tpose_joints):
    """local (J, 3, 3), root (3,), T-pose joints (J, 3) -> world rotations (J, 3, 3), joints
    (J, 3)."""
    rotations, joints = np.empty((NUM_JOINTS, 3, 3)), np.empty((NUM_JOINTS, 3))
    _forward_kernel(local, root, tpose_joints, _PARENTS, rotations, joints)
    return rotations, joints


class Chains(NamedTuple):
    """The joints that move each model point (``model_chains``): a body model's, once."""
    joints: np.ndarray      # (Q, L) int64 ascending, padded with -1 (L: the longest chain)
    count: np.ndarray       # (Q,) int64 how many
    reach: np.ndarray       # (Q, L) the sum of the point's bone weights at or below each
    slots: np.ndarray       # (Q, B) int64 its bone slots of weight > 0, ascending, padded -1
    slot_count: np.ndarray  # (Q,) int64 how many
    links: np.ndarray       # (Q, B, L) int64 per slot, the chain's places at or above its
    link_count: np.ndarray  # (Q, B) int64 bone, ascending, padded -1; and how many

    def arguments(self):
        """As ``_pose_points_kernel`` takes them."""
        return (self.count, self.reach, self.joints, self.slots, self.slot_count, self.links,
                self.link_count)


_CHAINS = {}


def model_chains(model):
    """``Chains`` of a body model, computed on its first use and kept (for a few models, by
    their bone arrays' identity). In NumPy, once: a kernel would cost its compile (0.5 s)."""
    key = (id(model.bone_index), id(model.bone_weight))
    kept = _CHAINS.get(key)
    if kept is None or kept[0] is not model.bone_index or kept[1] is not model.bone_weight:
        chains = _chains(model.bone_index, model.bone_weight)
        if len(_CHAINS) >= 4:
            _CHAINS.clear()
        kept = _CHAINS[key] = (model.bone_index, model.bone_weight, chains)
    return kept[2]


def _chains(bone_index, bone_weight):
    below = np.zeros((NUM_JOINTS, NUM_JOINTS), np.bool_)     # below[k, j]: k is j or below j
    for k in range(NUM_JOINTS):
        j = k
        while j >= 0:
            below[k, j] = True
            j = PARENTS[j]
    active = bone_weight != 0.0                                          # (Q, B)
    full = np.zeros((len(bone_index), NUM_JOINTS))
    for b in range(bone_index.shape[1]):      # slot by slot: the sums in the kernels' order
        full += np.where(active[:, b, None] & below[bone_index[:, b]], bone_weight[:, b, None],
                         0.0)

    def first(mask):
        """Per row (last axis), the places where ``mask`` holds, ascending, padded with -1."""
        count = mask.sum(-1)
        places = np.argsort(~mask, axis=-1, kind="stable")
        return np.where(np.arange(mask.shape[-1]) < count[..., None], places, -1), count

    joints, count = first(full > 0.0)
    width = max(int(count.max()), 1)
    joints = np.ascontiguousarray(joints[:, :width])
    reach = np.where(joints >= 0, np.take_along_axis(full, np.maximum(joints, 0), 1), 0.0)
    slots, slot_count = first(active)
    bones = np.take_along_axis(bone_index, np.maximum(slots, 0), 1)      # (Q, B)
    moves = (below[bones[:, :, None], np.maximum(joints, 0)[:, None, :]]
             & (slots >= 0)[:, :, None] & (joints >= 0)[:, None, :])    # (Q, B, L)
    links, link_count = first(moves)
    as_int = functools.partial(np.ascontiguousarray, dtype=np.int64)
    return Chains(as_int(joints), as_int(count), np.ascontiguousarray(reach), as_int(slots),
                  as_int(slot_count), as_int(links), as_int(link_count))


class Posed(NamedTuple):
    points: np.ndarray      # (Q, 3) posed surface points, metres
    normals: np.ndarray     # (Q, 3) their unit normals
    lever: np.ndarray       # (Q, L, 3) about each joint of the point's chain: see
    chains: Chains          # _pose_points_kernel


def pose_model(model, rest, tpose_joints, rotations, joints):
    """The model's points posed by LBS, with what their Jacobian needs (``Posed``)."""
    count, chains = len(rest), model_chains(model)
    posed = Posed(np.empty((count, 3)), np.empty((count, 3)),
                  np.empty((count, chains.joints.shape[1], 3)), chains)
    _pose_points_kernel(rest, tpose_joints, model.bone_index, model.bone_weight, model.normals,
                        rotations, joints, *chains.arguments(), *posed[:3])
    return posed


def apply_step(local, root, rotations, step):
    """A Gauss-Newton step (PARAMETERS,) applied: -> new local (J, 3, 3), root (3,)."""
    new = np.empty_like(local)
    _apply_step_kernel(local, rotations, step, _PARENTS, new)
    return new, root + step[:3]


def lost_legs(model, rest, tpose_joints, local, root, cloud_grid, far, viewpoint=None,
              parts=_LOWER_LEGS):
    """Per lower leg (left, right), the share of its model points (shin and foot: those whose
    heaviest skinning bone is the knee's, the ankle's or the foot's; or per side of ``parts``)
    that lie farther than ``far`` metres from the cloud (``cloud_grid``,
    ``nearest.build_grid``) at the pose ``local`` (J, 3, 3), ``root`` (3,) of the shaped model
    (``shaped``) -> (2,) float64.
    A leg mostly in empty space is lost: the fit's robust terms no longer reach its cloud.
    ``parts``: (J,) each bone's side (0 left, 1 right, -1 neither) if not the lower legs'
    (``_THIGHS``: the thighs, whose points far from the cloud are hidden, under a coat).
    ``viewpoint``: None, or the (3,) camera that saw the cloud: only the points it would see
    count (the back of a shin seen from the front is far from every cloud point)."""
    local = np.ascontiguousarray(local, np.float64)
    root = np.ascontiguousarray(root, np.float64)
    if local.shape != (NUM_JOINTS, 3, 3) or root.shape != (3,) or far <= 0:
        raise ValueError(f"lost_legs: local must be (22, 3, 3), root (3,) and far > 0, got "
                         f"{local.shape}, {root.shape}, {far!r}")
    rotations, joints = forward(local, root, tpose_joints)
    seen = (np.ones(len(rest), np.bool_) if viewpoint is None else
            seen_points(pose_model(model, rest, tpose_joints, rotations, joints), viewpoint))
    shares = np.empty(2)
    _lost_legs_kernel(rest, tpose_joints, model.bone_index, model.bone_weight, rotations,
                      joints, parts, seen, cloud_grid.points, cloud_grid.origin,
                      cloud_grid.cell, cloud_grid.dims, cloud_grid.order, cloud_grid.starts,
                      float(far), shares)
    return shares


def covered_thighs(model, rest, tpose_joints, local, root, cloud_grid, settings,
                   viewpoint=None):
    """Whether a garment covers the thighs at the pose ``local`` (J, 3, 3), ``root`` (3,) of
    the shaped model: a thigh has more than ``settings.lost_leg_share`` of its model points
    farther than ``swap_legs_hidden`` from the cloud (``cloud_grid``), yet neither has that
    share farther than ``swap_legs_covered`` (the cloud passes near them, not on them: a coat's
    tube 3-8 cm off; where the thighs are merely cut away, nothing is near). False where
    ``swap_legs_hidden`` is 0. ``viewpoint`` as ``lost_legs``'s."""
    if settings.swap_legs_hidden == 0:
        return False
    def far(distance):
        return lost_legs(model, rest, tpose_joints, local, root, cloud_grid, distance,
                         viewpoint, _THIGHS).max() > settings.lost_leg_share
    return far(settings.swap_legs_hidden) and not far(settings.swap_legs_covered)


def stray_points(model, rest, tpose_joints, local, root, cloud_grid, far):
    """The cloud's points (``cloud_grid``'s, ``nearest.build_grid``) farther than ``far``
    metres from every model point at the pose ``local`` (J, 3, 3), ``root`` (3,) of the
    shaped model (``shaped``), and nearest to a leg's (a point whose heaviest bone is a hip's,
    knee's, ankle's or foot's) -> (S, 3): what the model's legs leave unexplained (a raised
    foot or thigh the fit left hanging; a lost hand's points, nearest the arm, are not
    these)."""
    rotations, joints = forward(local, root, tpose_joints)
    stray = np.empty(len(cloud_grid.points), np.bool_)
    _stray_points_kernel(rest, tpose_joints, model.bone_index, model.bone_weight, rotations,
                         joints, _LEGS, cloud_grid.points, cloud_grid.origin, cloud_grid.cell,
                         cloud_grid.dims, cloud_grid.order, cloud_grid.starts, float(far),
                         stray)
    return cloud_grid.points[stray]


def aim_bone(local, root, tpose_joints, joint, strays):
    """``local`` (J, 3, 3) with ``joint`` (a hip or a knee: its thigh or shin) turned so that
    its bone points at the mean of the ``strays`` (S, 3) within reach of the joint (1.5 bones);
    None where fewer than 10 are, or their mean is on the joint. What hangs below turns with
    it. A hip's reach (about 0.6 m) takes in the other leg's strays too."""
    child = _CHILD[joint]
    rotations, joints = forward(local, root, tpose_joints)
    bone = np.linalg.norm(tpose_joints[child] - tpose_joints[joint])
    near = strays[np.linalg.norm(strays - joints[joint], axis=1) < 1.5 * bone]
    if len(near) < 10:
        return None
    now = joints[child] - joints[joint]
    goal = near.mean(0) - joints[joint]
    if np.linalg.norm(goal) < 1e-6:     # no direction to aim at
        return None
    turn = _rotation_between(now / np.linalg.norm(now), goal / np.linalg.norm(goal))
    parent = rotations[_PARENTS[joint]]
    aimed = np.array(local)
    aimed[joint] = parent.T @ turn @ parent @ local[joint]
    return aimed


def _rotation_between(a, b):
    """The smallest rotation (3, 3) taking unit vector a to unit vector b."""
    axis, cosine = np.cross(a, b), float(a @ b)
    sine = np.linalg.norm(axis)
    if sine < 1e-9:
        return np.eye(3) if cosine > 0 else (2 * np.outer(_any_normal(a), _any_normal(a))
                                             - np.eye(3))
    k = axis / sine
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + sine * cross + (1 - cosine) * cross @ cross


def _any_normal(a):
    other = np.eye(3)[np.argmin(np.abs(a))]
    n = np.cross(a, other)
    return n / np.linalg.norm(n)


# ----------------------------------------------------------------------------- one frame

def surface_terms(posed, cloud, cloud_grid, settings, viewpoint=None):
    """Both directions' nearest pairs, each cloud point with its nearest model point and
    (every ``model_stride``-th) model point with its nearest cloud point, robustly weighted
    (Geman-McClure at ``robust_width``) and summed per model point -> model index (N,),
    targets (N, 3), weights (N,), and the fit's cost: the mean truncated distance cloud ->
    model plus ``model_to_cloud`` times model -> cloud (metres). ``viewpoint``: None, or the
    (3,) camera that saw the cloud: only the model points it would see pair outward."""
    return _surface_pairs_kernel(posed.points, cloud, cloud_grid.origin, cloud_grid.cell,
                                 cloud_grid.dims, cloud_grid.order, cloud_grid.starts,
                                 float(settings.robust_width), float(settings.model_to_cloud),
                                 int(settings.model_stride), seen_points(posed, viewpoint))


def seen_points(posed, viewpoint):
    """Which of the ``posed`` model's points (``Posed``) a camera at ``viewpoint`` (3,) would
    see (facing it, not hidden behind the model's own surface: ``_seen_kernel``) -> (Q,)
    bool; all where ``viewpoint`` is None (the cloud covers the whole body)."""
    seen = np.ones(len(posed.points), np.bool_)
    if viewpoint is not None:
        _seen_kernel(posed.points, posed.normals, np.asarray(viewpoint, np.float64),
                     HIDDEN_DEPTH, SEEN_CELL, seen)
    return seen


def combined_pull(pulls):
    """Several pulls of the joints, ((weight, goal (J, 3)), ...), each weight a number or
    per joint (J,), as one: per joint the weights' sum (J,) towards their weighted mean goal
    (J, 3) (the same quadratic, up to a constant)."""
    total, weighted = np.zeros(NUM_JOINTS), np.zeros((NUM_JOINTS, 3))
    for weight, goal in pulls:
        weight = np.broadcast_to(np.asarray(weight, np.float64), (NUM_JOINTS,))
        if not weight.any():                   # off: its goal may be anything, even nan
            continue
        total = total + weight
        weighted = weighted + weight[:, None] * goal
    return total, weighted / np.where(total > 0, total, 1.0)[:, None]


def fit_pose(model, rest, tpose_joints, cloud, cloud_grid, local, root, settings, pulls=(),
             viewpoint=None):
    """Gauss-Newton on one frame's pose.

    Args:
        rest, tpose_joints: the shaped model (``shaped``).
        cloud: (P, 3) float64 points; cloud_grid: theirs (``nearest.build_grid``).
        local, root: the start, (J, 3, 3) and (3,).
        pulls: ((weight: a number or per joint (J,), goal joints (J, 3)), ...).
        viewpoint: None, or the (3,) camera that saw the cloud (metres): the model -> cloud
            term then pairs only the model points it would see (``seen_points``).
    Returns:
        local, root, joints (J, 3), cost: the mean truncated distance cloud -> model plus
        ``model_to_cloud`` times model -> cloud (metres, ``surface_terms``), measured before
        the last step (which only refines it).
    """
    pull_weight, pull_goal = combined_pull(pulls)
    local = np.array(local, np.float64, order="C")
    root = np.array(root, np.float64)
    joints = np.empty((NUM_JOINTS, 3))
    chains = model_chains(model)
    cost = _gauss_newton(
        settings.iterations, rest, tpose_joints, model.bone_index, model.bone_weight,
        model.normals, _PARENTS, *chains.arguments(), cloud, cloud_grid.origin,
        cloud_grid.cell, cloud_grid.dims,
        cloud_grid.order, cloud_grid.starts, float(settings.robust_width),
        float(settings.model_to_cloud), int(settings.model_stride), pull_weight, pull_goal,
        None if viewpoint is None else np.asarray(viewpoint, np.float64), local, root, joints)
    return local, root, joints, cost


def shape_rows(model, rotations, model_index, normals):
    """n . d(posed point)/d(shape) at the model points ``model_index`` (N,) with unit normals
    (N, 3), for a fixed pose (world rotations (J, 3, 3)) and root: (N, K)."""
    rows = np.empty((len(model_index), len(model.points_basis)))
    _shape_rows_kernel(model.points_basis, model.joints_basis, model.bone_index,
                       model.bone_weight, _PARENTS, rotations, model_index, normals, rows)
    return rows


def fit_shape(model, shape, frames, settings, width):
    """One Gauss-Newton step on the shape coefficients over frames ((cloud, its grid, local,
    root, viewpoint: None or (3,)), ...) at robust width ``width``; a faint ridge keeps
    unobserved coefficients near the mean."""
    hessian = 1e-7 * np.eye(len(shape))
    gradient = 1e-7 * shape
    rest, tpose_joints = shaped(model, shape)
    settings = settings._replace(robust_width=width)
    for cloud, grid, local, root, viewpoint in frames:
        rotations, joints = forward(local, root, tpose_joints)
        posed = pose_model(model, rest, tpose_joints, rotations, joints)
        index, targets, weights, _ = surface_terms(posed, cloud, grid, settings, viewpoint)
        normals = posed.normals[index]
        along = shape_rows(model, rotations, index, normals) * np.sqrt(weights)[:, None]
        distance = np.einsum("na,na->n", normals, posed.points[index] - targets)
        hessian += along.T @ along
        gradient += along.T @ (distance * np.sqrt(weights))
    return shape - np.linalg.solve(hessian, gradient)


def settle_shape(model, shape, frames, settings):
    """The calibration's last word: ``settings.settle_rounds`` rounds of every kept frame's
    pose fitted again on the current shape (``settle_steps`` steps, no pulls), then a shape
    step on them all."""
    posing = settings._replace(iterations=settings.settle_steps)
    for _ in range(settings.settle_rounds):
        rest, tpose_joints = shaped(model, shape)
        frames = [(cloud, grid, *fit_pose(model, rest, tpose_joints, cloud, grid, local, root,
                                          posing, viewpoint=viewpoint)[:2], viewpoint)
                  for cloud, grid, local, root, viewpoint in frames]
        shape = fit_shape(model, shape, frames, settings, settings.robust_width)
    return shape


def local_from_joints(joints, tpose_joints):
    """Local rotations (J, 3, 3) that pose the model's T-pose like ``joints`` (J, 3)
    (``analytic.analytic_rotations``)."""
    # analytic_rotations and quaternion_to_matrix's kernels, without their checks and
    # reshapes (the joints are the runtime's own, checked): 5 us instead of 28, each frame
    quaternions = np.empty((NUM_JOINTS, 4), np.float32)
    _analytic_frame(joints.astype(np.float32), tpose_joints.astype(np.float32), quaternions,
                    np.empty((NUM_JOINTS, 3, 3)))
    matrices = np.empty((NUM_JOINTS, 3, 3), np.float32)
    _quaternion_to_matrix_kernel(quaternions, matrices)
    return matrices.astype(np.float64)


def subsample(cloud, count, frame, draw=0):
    """``count`` points of a cloud (P, 3), drawn with the frame's index as seed -> float64
    (``sampling.seeded_subset``: draw 0 gives the points a pipeline thinned to ``count``
    reads too; another draw seeds with (draw, frame), another subset of every frame)."""
    return np.asarray(seeded_subset(cloud, count, frame if draw == 0 else (draw, frame)),
                      np.float64)


def reading_weight(settings, misread):
    """The reading's pull, per joint (J,) where ``settings.reading_width`` is set: SKR's
    joints far from where the motion puts them (``misread`` (J,), metres) are likely
    misread (a leg read on the wrong side, a body read turned), and their pull would drag
    the fit off the cloud; Geman-McClure in that distance. Otherwise the one weight."""
    if not settings.reading_width:
        return settings.reading_pull
    ratio = misread / settings.reading_width
    return settings.reading_pull / (1.0 + ratio * ratio) ** 2


def _depth_from(reading, predicted, viewpoint):
    """SKR's reading (J, 3) with each joint's depth along its ray from ``viewpoint`` (3,)
    taken from ``predicted`` (J, 3): what one view says of a joint is across its ray."""
    rays = reading - viewpoint
    rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-9)
    return reading + np.einsum("ja,ja->j", predicted - reading, rays)[:, None] * rays


def start_fit(model, settings, cloud, reading, viewpoint=None):
    """The first frame: shape and pose in alternation, from the mean body on SKR's reading
    -> FitState, joints (J, 3). ``viewpoint``: None, or the (3,) camera that saw the cloud
    (``fit_frame``)."""
    cloud = subsample(cloud, settings.cloud_points, 0, settings.draw)
    reading = np.asarray(reading, np.float64)
    grid = build_grid(cloud)
    shape = np.zeros(len(model.points_basis))
    rest, tpose_joints = shaped(model, shape)
    local, root = local_from_joints(reading, tpose_joints), reading[0].copy()
    for width in CALIBRATION_WIDTHS:
        local, root, _, _ = fit_pose(model, rest, tpose_joints, cloud, grid, local, root,
                                     settings._replace(robust_width=width),
                                     ((settings.reading_pull, reading),), viewpoint)
        shape = fit_shape(model, shape, [(cloud, grid, local, root, viewpoint)], settings,
                          width)
        rest, tpose_joints = shaped(model, shape)
    local, root, joints, cost = fit_pose(model, rest, tpose_joints, cloud, grid, local, root,
                                         settings, ((settings.reading_pull, reading),),
                                         viewpoint)
    state = FitState(1, shape, local, root, np.stack([joints, joints]),
                     ((cloud, grid, local, root, viewpoint),), cost)
    return state, joints


def _settle(model, settings, rest, tpose_joints, cloud, grid, viewpoint, race, pulls, local,
            root, joints, cost):
    """A start that won its race, fitted on: a lost lower leg looked for, then the steps the
    race left (``fit_frame``) -> local, root, joints, cost. On a stray frame every aimed start
    that beat the race's winner is settled too (each aimed from the winner alone, not one
    after another), so the lost-leg check runs once per start."""
    if settings.lost_leg_width > 0 and (lost_legs(
            model, rest, tpose_joints, local, root, grid, settings.lost_leg_distance,
            viewpoint).max() > settings.lost_leg_share):
        # A shin in empty space (a kick neither start followed): the robust terms no longer
        # reach its cloud, and SKR's reading, as lost there, holds it. Steps at a wider width
        # without the reading's pull reach out for it.
        local, root, joints, cost = fit_pose(
            model, rest, tpose_joints, cloud, grid, local, root,
            race._replace(robust_width=settings.lost_leg_width), pulls[1:], viewpoint)
    if settings.iterations > race.iterations:          # the better start goes on
        local, root, joints, cost = fit_pose(
            model, rest, tpose_joints, cloud, grid, local, root,
            settings._replace(iterations=settings.iterations - race.iterations), pulls,
            viewpoint)
    return local, root, joints, cost


def fit_frame(model, settings, state, cloud, reading, viewpoint=None, reading_depth=False):
    """One frame after the first: -> FitState, joints (J, 3) float64, and whether the fit
    from SKR's reading (or from it with its legs swapped) won. ``viewpoint``: None (the cloud
    covers the body), or the (3,) world position of the one depth camera that saw it: the
    model's points it would not see are not pulled to the cloud, and, unless
    ``reading_depth``, the reading's pull leaves the joints' depth along their rays to the
    motion (SKR, trained on whole bodies, reads one side's joints towards the camera; the
    one-view SKR, trained on such clouds, reads their depth better than the motion foretells
    it: docs/single_view.md)."""
    t = state.frames
    cloud = subsample(cloud, settings.cloud_points, t, settings.draw)
    reading = np.asarray(reading, np.float64)
    grid = build_grid(cloud)
    rest, tpose_joints = shaped(model, state.shape)
    before, last = state.joints
    # After a frame without the body, its motion is stale: no pull to it, and the frame found
    # starts the motion again (a body that jumped would otherwise be pulled back for good);
    # the reading's joints are then weighed against the held pose.
    moving = state.cost <= LOST_COST
    predicted = last + 0.5 * (last - before) if moving else last
    if viewpoint is not None and not reading_depth:
        reading = _depth_from(reading, predicted, viewpoint)
    misread = np.linalg.norm(reading - predicted, axis=1)        # (J,) metres
    pulls = ((reading_weight(settings, misread), reading),)
    if moving:
        pulls += ((settings.motion_pull, predicted),)
    race = settings._replace(iterations=min(settings.race_iterations, settings.iterations))
    local, root, joints, cost = fit_pose(model, rest, tpose_joints, cloud, grid, state.local,
                                         state.root, race, pulls, viewpoint)
    reseeded = False
    if np.linalg.norm(joints - reading, axis=1).mean() > settings.reseed_distance:
        fresh = fit_pose(model, rest, tpose_joints, cloud, grid,
                         local_from_joints(reading, tpose_joints), reading[0].copy(), race,
                         pulls, viewpoint)
        if fresh[3] < cost:
            (local, root, joints, cost), reseeded = fresh, True
    if ((settings.swap_legs_cost > 0 and cost > settings.swap_legs_cost)
            or (settings.swap_legs_distance > 0 and moving
                and misread[_LOWER_LEGS >= 0].max() > settings.swap_legs_distance)):
        # The better start explains the cloud poorly, or SKR's legs are not where the motion
        # puts them: SKR may have read the legs swapped (a leg across the other, the body
        # turned), and the track may have followed. The reading with its legs swapped is
        # fitted too; if it meets the cloud better, it is this frame's reading from here on,
        # unless a garment covers both poses' thighs: only they tell the legs apart, and a
        # wrong swap, once won, would win again frame after frame.
        swapped = reading[_SWAPPED_LEGS]
        swapped_pulls = ((reading_weight(settings, np.linalg.norm(swapped - predicted, axis=1)),
                          swapped),) + pulls[1:]
        other = fit_pose(model, rest, tpose_joints, cloud, grid,
                         local_from_joints(swapped, tpose_joints), swapped[0].copy(), race,
                         swapped_pulls, viewpoint)
        if other[3] < cost and not all(
                covered_thighs(model, rest, tpose_joints, pose_local, pose_root, grid,
                               settings, viewpoint)
                for pose_local, pose_root in ((local, root), other[:2])):
            (local, root, joints, cost), pulls, reseeded = other, swapped_pulls, True
    starts = [(local, root, joints, cost)]
    if settings.stray_share > 0:
        strays = stray_points(model, rest, tpose_joints, local, root, grid,
                              settings.lost_leg_distance)
        if len(strays) > settings.stray_share * len(cloud):
            # Cloud points the model's legs leave far away: a lower leg the fit left lying on
            # the other (a foot raised across the other knee, where SKR reads it down too), a
            # thigh raised in a pirouette. Each thigh and shin aimed at them, from the race's
            # winner, is a start; every one that beats the winner goes on beside it, and the
            # lowest settled cost wins (an aimed shin can win a short race and settle worse).
            for joint in _AIMED:
                aimed = aim_bone(local, root, tpose_joints, joint, strays)
                if aimed is not None:
                    other = fit_pose(model, rest, tpose_joints, cloud, grid, aimed, root, race,
                                     pulls, viewpoint)
                    if other[3] < cost:
                        starts.append(other)
    settled = [_settle(model, settings, rest, tpose_joints, cloud, grid, viewpoint, race,
                       pulls, *start) for start in starts]
    chosen = min(range(len(settled)), key=lambda index: settled[index][3])
    local, root, joints, cost = settled[chosen]
    falling = settings.still_falling if viewpoint is None else settings.still_falling_told
    if settings.more_iterations > 0 and starts[chosen][3] - cost > falling:
        # Its cost still fell fast: the fit has not converged (a fast limb); steps more.
        local, root, joints, cost = fit_pose(
            model, rest, tpose_joints, cloud, grid, local, root,
            settings._replace(iterations=settings.more_iterations), pulls, viewpoint)
    if cost > LOST_COST:        # no body here: hold the last pose, keep the motion as it was
        return state._replace(frames=t + 1, cost=cost), last, reseeded
    shape, calibration = state.shape, state.calibration
    if t < settings.calibration_frames:
        calibration = calibration + ((cloud, grid, local, root, viewpoint),)
        shape = fit_shape(model, shape, calibration, settings, settings.robust_width)
    if calibration and t >= settings.calibration_frames - 1:
        # The calibration's last frame settles it; if that frame had no body, the next that
        # has one does (the settling is most of the calibration: it must not be skipped).
        shape = settle_shape(model, shape, calibration, settings)
        rest, tpose_joints = shaped(model, shape)
        local, root, joints, cost = fit_pose(model, rest, tpose_joints, cloud, grid, local,
                                             root, settings, pulls, viewpoint)
        calibration = ()                 # calibrated: the clouds are no longer needed
    return (FitState(t + 1, shape, local, root, np.stack([last if moving else joints, joints]),
                     calibration, cost),
            joints, reseeded)


def fit_state_arrays(state):
    """A ``FitState`` as flat arrays (for a checkpoint ``.npz``): its fields, and the
    calibration frames' clouds concatenated with their counts (grids are rebuilt on load)."""
    calibration = state.calibration
    return {"frames": np.array(state.frames, np.int64), "shape": state.shape,
            "local": state.local, "root": state.root, "joints": state.joints,
            "cost": np.array(state.cost),
            "calibration_points": (np.concatenate([frame[0] for frame in calibration])
                                   if calibration else np.empty((0, 3))),
            "calibration_counts": np.array([len(frame[0]) for frame in calibration], np.int64),
            "calibration_local": np.array([frame[2] for frame in calibration]).reshape(
                -1, NUM_JOINTS, 3, 3),
            "calibration_root": np.array([frame[3] for frame in calibration]).reshape(-1, 3),
            "calibration_viewpoints": np.array(     # nan: a whole cloud, no camera
                [np.full(3, np.nan) if frame[4] is None else frame[4] for frame in calibration]
            ).reshape(-1, 3)}


def fit_state_from_arrays(arrays, model):
    """``fit_state_arrays``'s inverse, checked against the body model (ValueError)."""
    shapes = {"shape": (len(model.points_basis),), "local": (NUM_JOINTS, 3, 3), "root": (3,),
              "joints": (2, NUM_JOINTS, 3)}
    for key, shape in shapes.items():
        if np.shape(arrays[key]) != shape:
            raise ValueError(f"the fit's {key} has shape {np.shape(arrays[key])}, not {shape}")
    counts = np.asarray(arrays["calibration_counts"], np.int64)
    clouds = np.split(np.asarray(arrays["calibration_points"], np.float64),
                      np.cumsum(counts)[:-1]) if len(counts) else []
    # Checkpoints from before single views have no viewpoints: whole clouds.
    viewpoints = (arrays["calibration_viewpoints"] if "calibration_viewpoints" in arrays
                  else np.full((len(counts), 3), np.nan))
    calibration = tuple((cloud, build_grid(cloud), np.asarray(local, np.float64),
                         np.asarray(root, np.float64),
                         None if np.isnan(viewpoint).any() else np.asarray(viewpoint, np.float64))
                        for cloud, local, root, viewpoint in zip(
                            clouds, arrays["calibration_local"], arrays["calibration_root"],
                            viewpoints))
    return FitState(int(arrays["frames"]), *(np.asarray(arrays[key], np.float64)
                                             for key in ("shape", "local", "root", "joints")),
                    calibration, float(arrays["cost"]))


def track(model, settings, clouds, readings, viewpoints=None, reading_depth=False):
    """A whole stream, online (frame t sees frames <= t only): clouds (T, P, 3) (or any
    iterable of (P, 3)), SKR's readings (T, J, 3), and the cameras that saw them (T, 3) (None:
    whole clouds; ``reading_depth`` as ``fit_frame``'s) -> fitted joints (T, J, 3) float32,
    and which frames the fit from the reading won (T,) bool."""
    fitted, reseeded = [], []
    state = None
    if viewpoints is None:
        viewpoints = [None] * len(readings)
    for cloud, reading, viewpoint in zip(clouds, readings, viewpoints):
        if state is None:
            state, joints = start_fit(model, settings, cloud, reading, viewpoint)
            won = True
        else:
            state, joints, won = fit_frame(model, settings, state, cloud, reading, viewpoint,
                                           reading_depth)
        fitted.append(joints)
        reseeded.append(won)
    return np.asarray(fitted, np.float32), np.asarray(reseeded)
