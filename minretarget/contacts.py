"""Stage 2b: foot contacts. A foot that stops on the ground stays where it stopped.

SMRM's target feet inherit SKR's frame-to-frame error (a few centimetres), so a foot that
should stand still slides about on the ground. Per frame and per leg, after SMRM:
    1. the toe (``left_foot``/``right_foot`` joint) position is low-passed (cutoff
       ``speed_cutoff``) and its speed measured on the filtered track;
    2. a toe slower than ``plant_speed`` and no higher than the other toe plus
       ``height_margin`` plants where it is shown (its anchor);
    3. a planted toe lifts when it is faster than ``lift_speed`` or higher than the other
       toe plus the margin. While it stays, its anchor creeps toward SMRM's (filtered) toe by
       ``anchor_follow`` of the gap each frame, so the legs stay near SMRM's pose over a long
       contact, and it is never more than ``max_offset`` from SMRM's toe: a toe SMRM drags
       along is dragged on a leash, smoothly, instead of dropped and planted again. The
       anchor holds the toe's place on the ground only: its height is always SMRM's toe's
       (sliding is horizontal; holding the height too fought SMRM's heel-to-toe roll and
       cost PA-MPJPE for no less sliding);
    4. while planted the leg is bent so that the toe sits on its anchor: the whole foot moves
       by offset = anchor - toe, SMRM's foot orientation is kept, and a two-bone inverse
       kinematics carries the ankle: the knee flexes about its hinge (the thigh's left axis),
       then the leg swings about the hip. After lifting, the offset shrinks by
       ``release_decay`` per frame, so the foot eases back to SMRM's instead of jumping.
The height test compares the two toes, not a floor (none is known online): in a jump both
feet can plant near the top and are held in place over the ground (their height is SMRM's), at
most ``max_offset`` away, until they speed up.
Only the hip, knee and ankle rotations of a leg change: the skeleton, the root and the other
joints stay as SMRM made them, and LBS of the new rotations keeps the skin on the rig.
The state (filtered toes, anchors, offsets, which foot is planted) is a ``FeetState``, kept
with the stream's, so a stream saved and resumed goes on exactly.

The defaults were chosen on validation motion, never the test split
(``python -m training.tune_contacts``), by a rule written before the run: among the settings
of a grid whose toes move no faster over the ground truth's contacts than the truth's own,
those within 0.01 mm of the least PA-MPJPE, and of those the slowest toes. They were chosen
for the SMRM and the mirror-averaged skeleton denoiser (``minretarget.denoise``) they run
after, so a new SMRM or denoiser needs the tuner run again. The leash matters most: the
grid's other settings score alike at the same leash. The figures of each choice:
docs/runtime_notes.md, "Foot contacts".
"""
from typing import NamedTuple

import numpy as np

from ._jit import kernel
from .conventions import FPS, JOINT_INDEX, LEFT_AXIS, NUM_JOINTS, UP_AXIS
from .kinematics import _PARENTS, _place_joint, check_quaternion_norms, forward_kinematics
from .validation import as_float32_array

_LEFT = tuple(float(v) for v in np.eye(3)[LEFT_AXIS])  # the T-pose's left axis: knees flex
#                                                         about it
# Per leg: hip, knee, ankle, toe; legs in order left, right.
LEGS = np.array([[JOINT_INDEX[f"{side}_{name}"] for name in ("hip", "knee", "ankle", "foot")]
                 for side in ("left", "right")], dtype=np.int64)


class FootLock(NamedTuple):
    plant_speed: float = 2.0        # m/s: a slower toe (filtered) plants
    lift_speed: float = 2.0         # m/s: a faster one lifts
    speed_cutoff: float = 12.0      # Hz: low-pass of the toe track the speed is measured on
    height_margin: float = 0.05     # m: a toe plants only this close above the other toe
    max_offset: float = 0.01        # m: a planted toe is held (over the ground; its height is
    #                                 SMRM's) at most this far from SMRM's toe: beyond, its
    #                                 anchor is dragged along (a leash)
    release_decay: float = 0.5      # fraction of the offset kept each frame after lifting
    anchor_follow: float = 0.0      # fraction of the way a planted toe's anchor moves each
    #                                 frame toward SMRM's (filtered) toe: a slow creep that
    #                                 keeps the legs near SMRM's pose over long contacts


def check_foot_lock(foot_lock):
    """A FootLock (or its 7 values in order) with speeds, cutoff and offset finite and > 0,
    plant_speed <= lift_speed, decay and follow in [0, 1); or None (off)."""
    if foot_lock is None:
        return None
    try:
        if len(foot_lock) != len(FootLock._fields):
            raise ValueError
        foot_lock = FootLock(*map(float, foot_lock))
    except (TypeError, ValueError):
        raise ValueError(f"foot_lock must be a FootLock (its {len(FootLock._fields)} values) "
                         f"or None, got {foot_lock!r}") from None
    positive = foot_lock[:5]
    if not (all(0 < value < np.inf for value in positive)
            and foot_lock.plant_speed <= foot_lock.lift_speed
            and 0 <= foot_lock.release_decay < 1 and 0 <= foot_lock.anchor_follow < 1):
        raise ValueError(f"foot_lock: speeds, cutoff and max_offset must be finite and > 0, "
                         f"plant_speed <= lift_speed, release_decay and anchor_follow in "
                         f"[0, 1); got {foot_lock}")
    return foot_lock


class FeetState(NamedTuple):
    """Per leg (left, right):"""
    toe_filtered: np.ndarray     # (2, 3) float32 the target's low-passed toe positions, metres
    toe_anchor: np.ndarray       # (2, 3) float32 where each planted toe stays over the ground
                                 # (its height is SMRM's), metres
    foot_offset: np.ndarray      # (2, 3) float32 the move the feet get from the lock, metres
    feet_planted: np.ndarray     # (2,) bool


def check_feet(state):
    """A FeetState checked: finite (2, 3) toe_filtered, toe_anchor, foot_offset
    (C-contiguous float32) and a (2,) bool feet_planted (a copy). ValueError names the
    field."""
    if not isinstance(state, FeetState):
        raise ValueError(f"the foot lock's state must be a FeetState, got "
                         f"{type(state).__name__}")
    feet = [as_float32_array(getattr(state, name), f"foot_lock.{name}", (2, 3))
            for name in ("toe_filtered", "toe_anchor", "foot_offset")]
    planted = np.asarray(state.feet_planted)
    if planted.shape != (2,) or planted.dtype != bool:
        raise ValueError(f"foot_lock.feet_planted must be a (2,) bool array, got "
                         f"{planted.dtype} {planted.shape}")
    return FeetState(*feet, planted.copy())


def plant_feet(rotations, root, tpose_joints, state, foot_lock=FootLock()):
    """One frame of foot contacts on SMRM's output.

    Args:
        rotations: (J, 4) float32 SMRM's local quaternions (w, x, y, z).
        root: (3,) float32 pelvis position, metres.
        tpose_joints: (J, 3) float32 the target's T-pose skeleton, metres.
        state: FeetState after the last frame, or None at a stream's start.
        foot_lock: FootLock.
    Returns:
        the (J, 4) float32 rotations with the legs bent to the anchors, and the new state.
    """
    rotations = as_float32_array(rotations, "rotations", (NUM_JOINTS, 4))
    check_quaternion_norms(rotations, "rotations")
    root = as_float32_array(root, "root", (3,))
    tpose_joints = as_float32_array(tpose_joints, "tpose_joints", (NUM_JOINTS, 3))
    foot_lock = check_foot_lock(foot_lock)
    if foot_lock is None:
        raise ValueError("plant_feet needs a FootLock")
    if state is not None:
        state = check_feet(state)
    joints, global_rotations = forward_kinematics(rotations, root, tpose_joints)
    return plant_checked(rotations, joints, global_rotations, tpose_joints, state, foot_lock)


def plant_checked(rotations, joints, global_rotations, tpose_joints, state, foot_lock):
    """``plant_feet`` on checked inputs and the pose's FK (``joints`` (J, 3) and
    ``global_rotations`` (J, 3, 3), float32), which it updates in place for the legs it
    bends: the pipeline's foot-lock stage, after FK."""
    first = state is None
    if first:
        feet = np.zeros((2, 3), dtype=np.float32)
        state = FeetState(feet, feet, feet, np.zeros(2, dtype=bool))
    rotations, *feet = _plant_feet_kernel(rotations, joints, global_rotations, tpose_joints,
                                          _PARENTS, LEGS, *state, first, *foot_lock)
    return rotations, FeetState(*feet)


# ----------------------------------------------------------------------------- quaternions
# Quaternions (w, x, y, z) and vectors as float64 tuples: numba compiles tuple arithmetic much
# faster than the small arrays it would otherwise build for each (issue 40's cold start).

@kernel
def _smoothing_factor(cutoff):
    """Exponential low-pass factor a(f) = 1 - 1 / (1 + 2 pi f / fps) for a cutoff of f Hz."""
    return np.float32(1.0) - np.float32(1.0) / (np.float32(1.0)
                                                + np.float32(2 * np.pi / FPS) * cutoff)


@kernel
def _multiply(a, b):
    """Hamilton product a * b of quaternions."""
    return (a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
            a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
            a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
            a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0])


@kernel
def _conjugate(q):
    return (q[0], -q[1], -q[2], -q[3])


@kernel
def _quaternion(rotations, j):
    """Row j of (J, 4) float32 quaternions as a float64 tuple."""
    return (np.float64(rotations[j, 0]), np.float64(rotations[j, 1]),
            np.float64(rotations[j, 2]), np.float64(rotations[j, 3]))


@kernel
def _row(points, j):
    """Row j of (J, 3) float64 points as a tuple."""
    return (points[j, 0], points[j, 1], points[j, 2])


@kernel
def _add(u, v):
    return (u[0] + v[0], u[1] + v[1], u[2] + v[2])


@kernel
def _sub(u, v):
    return (u[0] - v[0], u[1] - v[1], u[2] - v[2])


@kernel
def _scale(u, k):
    return (k * u[0], k * u[1], k * u[2])


@kernel
def _dot(u, v):
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


@kernel
def _cross(u, v):
    return (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])


@kernel
def _rotate(q, v):
    """The vector v rotated by the unit quaternion q."""
    turned = _multiply(_multiply(q, (0.0, v[0], v[1], v[2])), _conjugate(q))
    return (turned[1], turned[2], turned[3])


@kernel
def _axis_angle(axis, angle):
    """Unit quaternion of the turn by ``angle`` (radians) about ``axis`` (any length)."""
    norm = np.sqrt(_dot(axis, axis))
    s = np.sin(0.5 * angle)
    return (np.cos(0.5 * angle), s * (axis[0] / norm), s * (axis[1] / norm), s * (axis[2] / norm))


@kernel
def _turn_between(u, v):
    """Unit quaternion of the smallest turn taking direction u to direction v."""
    u = _scale(u, 1.0 / np.sqrt(_dot(u, u)))
    v = _scale(v, 1.0 / np.sqrt(_dot(v, v)))
    axis = _cross(u, v)
    sine = np.sqrt(_dot(axis, axis))
    if sine < 1e-9:     # parallel (no turn); opposite cannot happen for a leg's small offsets
        return (1.0, 0.0, 0.0, 0.0)
    return _axis_angle(axis, np.arctan2(sine, _dot(u, v)))


# ----------------------------------------------------------------------------- the stage

@kernel
def _bend_leg(rotations, joints, global_pelvis, leg, goal):
    """Two-bone IK in place: turn the leg's hip and knee so its ankle reaches ``goal`` (as
    near as the bone lengths allow), keeping the ankle's world orientation.

    rotations (J, 4) local quaternions, float32, changed in place; joints (J, 3) float64 the
    pose's joints; global_pelvis a quaternion; leg (4,) hip, knee, ankle, toe; goal a vector."""
    hip, knee, ankle = leg[0], leg[1], leg[2]
    global_hip = _multiply(global_pelvis, _quaternion(rotations, hip))
    global_knee = _multiply(global_hip, _quaternion(rotations, knee))
    hip_at, knee_at = _row(joints, hip), _row(joints, knee)
    thigh, shank = _sub(knee_at, hip_at), _sub(_row(joints, ankle), knee_at)
    thigh_length = np.sqrt(_dot(thigh, thigh))
    shank_length = np.sqrt(_dot(shank, shank))
    to_goal = _sub(goal, hip_at)
    reach = np.sqrt(_dot(to_goal, to_goal))
    # 1. Bend the knee about its hinge, the T-pose's left axis carried by the thigh (a knee
    #    flexes about it whatever the skeleton's rest bend), by the angle t whose hip-ankle
    #    distance is the reach: with the shank v = v_along + v_across about the hinge n,
    #    |thigh + v(t)|^2 = reach^2 gives A cos t + B sin t = C (A = thigh . v_across,
    #    B = thigh . (n x v_across)). Of its two roots, the smaller turn that does not bend
    #    the knee backwards.
    hinge = _rotate(global_hip, _LEFT)
    along = _scale(hinge, _dot(shank, hinge))
    across = _sub(shank, along)
    a = _dot(thigh, across)
    b = _dot(thigh, _cross(hinge, across))
    c = 0.5 * (reach ** 2 - thigh_length ** 2 - shank_length ** 2) - _dot(thigh, along)
    radius = np.sqrt(a * a + b * b)
    turn = 0.0
    if radius > 1e-9:
        phase = np.arctan2(b, a)
        spread = np.arccos(min(max(c / radius, -1.0), 1.0))     # the nearest when unreachable
        flexion = np.arctan2(_dot(_cross(thigh, shank), hinge), _dot(thigh, shank))
        best = np.inf
        for root in (phase - spread, phase + spread):
            root = (root + np.pi) % (2 * np.pi) - np.pi           # into [-pi, pi)
            cost = abs(root) + (0.0 if flexion + root >= 0 else np.pi)  # backwards: last
            if cost < best:
                best, turn = cost, root
    knee_turn = _axis_angle(hinge, turn)
    ankle_bent = _add(knee_at, _rotate(knee_turn, shank))
    # 2. Swing the whole leg about the hip so that the ankle points at the goal.
    hip_turn = _turn_between(_sub(ankle_bent, hip_at), to_goal)
    # World turns -> local rotations: hip' = P^-1 D2 P hip, knee' = H^-1 D1 H knee,
    # ankle' = K^-1 (D2 D1)^-1 K ankle (P, H, K: old global pelvis, hip, knee).
    _turn_local(rotations, hip, global_pelvis, hip_turn)
    _turn_local(rotations, knee, global_hip, knee_turn)
    _turn_local(rotations, ankle, global_knee, _conjugate(_multiply(hip_turn, knee_turn)))


@kernel
def _turn_local(rotations, joint, frame, turn):
    """Joint's local rotation turned by the world turn ``turn`` given its parent's old world
    rotation ``frame``: frame^-1 turn frame local, normalised, in place."""
    local = _multiply(_multiply(_multiply(_conjugate(frame), turn), frame),
                      _quaternion(rotations, joint))
    norm = np.sqrt(local[0] * local[0] + local[1] * local[1] + local[2] * local[2]
                   + local[3] * local[3])
    for k in range(4):
        rotations[joint, k] = np.float32(local[k] / norm)


@kernel
def _plant_feet_kernel(rotations, posed, global_rotations, tpose, parents, legs, toe_filtered,
                       toe_anchor, foot_offset, feet_planted, first, plant_speed, lift_speed,
                       speed_cutoff, height_margin, max_offset, release_decay, anchor_follow):
    """-> rotations, and the FeetState's four fields; ``posed`` (J, 3) and
    ``global_rotations`` (J, 3, 3), the FK of ``rotations``, are placed again along the legs
    it bends."""
    # Scalar loops into float64 scratch, not array expressions, copies or row assignments:
    # numba compiles those (and their shape checks' error messages) slowly (issue 40).
    joints = np.empty((posed.shape[0], 3))
    for j in range(posed.shape[0]):
        for k in range(3):
            joints[j, k] = posed[j, k]
    a = np.float64(_smoothing_factor(np.float32(speed_cutoff)))
    toes, filtered = np.empty((2, 3)), np.empty((2, 3))
    anchor, offset = np.empty((2, 3)), np.empty((2, 3))
    for side in range(2):
        for k in range(3):
            toes[side, k] = joints[legs[side, 3], k]
            filtered[side, k] = toes[side, k] if first else (
                toe_filtered[side, k] + a * (toes[side, k] - toe_filtered[side, k]))
            anchor[side, k] = toe_anchor[side, k]
            offset[side, k] = foot_offset[side, k]
    planted = np.empty(2, dtype=np.bool_)
    out = np.empty((rotations.shape[0], 4), dtype=np.float32)
    for j in range(rotations.shape[0]):
        for k in range(4):
            out[j, k] = rotations[j, k]
    global_pelvis = _quaternion(rotations, 0)
    for side in range(2):
        planted[side] = feet_planted[side]
        moved = _sub(_row(filtered, side), (np.float64(toe_filtered[side, 0]),
                                            np.float64(toe_filtered[side, 1]),
                                            np.float64(toe_filtered[side, 2])))
        speed = 0.0 if first else np.sqrt(_dot(moved, moved)) * FPS
        low = toes[side, UP_AXIS] <= toes[1 - side, UP_AXIS] + height_margin
        if planted[side]:
            planted[side] = low and speed <= lift_speed
        elif not first and low and speed < plant_speed:
            planted[side] = True
            for k in range(3):                           # where the toe is shown: no jump
                anchor[side, k] = toes[side, k] + offset[side, k]
        if planted[side]:
            for k in range(3):
                anchor[side, k] = anchor[side, k] + anchor_follow * (filtered[side, k]
                                                                     - anchor[side, k])
            anchor[side, UP_AXIS] = toes[side, UP_AXIS]  # held over the ground only: the height
            #                                             stays SMRM's (the creep's is dropped)
            gap = _sub(_row(anchor, side), _row(toes, side))
            distance = np.sqrt(_dot(gap, gap))
            if distance > max_offset:                    # the leash: dragged, not dropped
                for k in range(3):
                    anchor[side, k] = toes[side, k] + gap[k] * (max_offset / distance)
            for k in range(3):
                offset[side, k] = anchor[side, k] - toes[side, k]
        else:
            for k in range(3):
                offset[side, k] = release_decay * offset[side, k]
        shift = _row(offset, side)
        if np.sqrt(_dot(shift, shift)) > 1e-5:           # under 0.01 mm: leave the leg
            ankle = legs[side, 2]
            _bend_leg(out, joints, global_pelvis, legs[side],
                      (joints[ankle, 0] + shift[0], joints[ankle, 1] + shift[1],
                       joints[ankle, 2] + shift[2]))
            local = np.empty((3, 3), dtype=np.float32)
            for j in legs[side]:                             # hip, knee, ankle, toe: a chain
                _place_joint(out, tpose, parents, posed, global_rotations, j, local)
    feet = np.empty((3, 2, 3), dtype=np.float32)         # filtered, anchor, offset
    for side in range(2):
        for k in range(3):
            feet[0, side, k] = filtered[side, k]
            feet[1, side, k] = anchor[side, k]
            feet[2, side, k] = offset[side, k]
    return out, feet[0], feet[1], feet[2], planted
