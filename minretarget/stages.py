"""The per-frame pipeline as a list of stages, and the state a stream carries between frames.

``build_stages`` makes the list that a ``pipeline.PipelineConfig`` asks for, for one target,
in the order of ``pipeline``'s table; ``Retargeter`` folds each frame down it. A stage:

    name        its key in the stream's state (``StreamState.stages``) and in checkpoints
    version     of its state's layout; a checkpoint of another version is refused by name
    State       the NamedTuple it carries from frame to frame, or None (it keeps nothing)
    step(state, frame) -> (state, frame)
                one frame: ``state`` is its State after the last frame (None at a stream's
                start), ``frame`` a ``Frame`` as the stages before it left it
    checked(state) -> state                a state set back from outside, checked (ValueError)
    arrays(state) / from_arrays(arrays)    its state as flat arrays (a checkpoint's) and back

A stage checks nothing per frame: ``Retargeter`` checks the input once, at its public edge,
and each stage calls its module's kernels on it directly.
"""
import warnings
from typing import NamedTuple

import numpy as np

from .contacts import FeetState, check_feet, plant_checked
from .denoise import DenoiseState, _denoise_mirror_averaged_kernel
from .denoise import check_state as check_denoise_state
from .denoise import initial_state as initial_denoise_state
from .facing import CONFIRM, TRIGGER, FacingState, _check_facing, check_facing_state
from .fit import (LOST_COST, FitState, body_model, fit_frame, fit_state_arrays,
                  fit_state_from_arrays, start_fit)
from .heading import heading_angles
from .kinematics import _PARENTS, _forward_kinematics_kernel, skinning_transforms
from .refine import refine_checked
from .rest_pose import check_rest_pose
from .sampling import seeded_subset
from .skin import linear_blend_skinning
from .skr import mirror_averaged_checked, read_from_view, regress_checked
from .smoothing import SmoothingState, _parameters, _smooth_kernel, check_smoothing_state
from .smrm import _NO_REST_POSE, SMRMState, step_checked
from .smrm import check_state as check_smrm_state
from .validation import FitWarning, as_count


class Frame(NamedTuple):
    """One frame on its way down the stages; each fills in or changes its fields."""
    index: int                              # the frame's place in the stream
    points: np.ndarray | None               # (P, 3) float32 its cloud, metres (None: none)
    joints: np.ndarray | None               # (J, 3) float32 the source skeleton, metres
    rotations: np.ndarray | None = None     # (J, 4) float32 the target's local quaternions
    root: np.ndarray | None = None          # (3,) float32 the target's pelvis, metres
    posed_joints: np.ndarray | None = None  # (J, 3) float32 the target's joints (FK), metres
    global_rotations: np.ndarray | None = None   # (J, 3, 3) float32 their world rotations
    vertices: np.ndarray | None = None      # (V, 3) float32 the target's points, posed
    viewpoint: np.ndarray | None = None     # (3,) float32 the one camera that saw the cloud,
                                            # metres (None: it covers the body)
    view_read: bool = False                 # ``joints`` is the one-view SKR's reading (its
                                            # depth along the camera's rays its own)


class StreamState(NamedTuple):
    """What a stream carries from one frame to the next: ``Retargeter.state``."""
    frames_seen: int
    stages: dict          # stage name -> its State, for every stage that keeps one


class Stage:
    """The protocol's defaults: no state."""
    name = ""
    version = 1
    State = None
    every_frame = True      # its state exists after every frame (not only after some)
    reads_cloud = False     # it works on the frame's cloud (the stages after these see joints)

    def step(self, state, frame):
        raise NotImplementedError

    def checked(self, state):
        return state

    def arrays(self, state):
        return {name: np.asarray(value) for name, value in state._asdict().items()}

    def from_arrays(self, arrays):
        return self.checked(self.State(**{name: arrays[name] for name in self.State._fields}))


class Thinning(Stage):
    """Stage 0: each cloud thinned to ``count`` points, a subset seeded by the frame's index."""
    name = "thinning"
    reads_cloud = True

    def __init__(self, count):
        self.count = count

    def step(self, state, frame):
        if frame.points is None:
            return None, frame
        return None, frame._replace(points=seeded_subset(frame.points, self.count, frame.index))


class Reading(Stage):
    """Stage 1: SKR's skeleton of the cloud, refined, mirror-averaged, as asked; a frame that
    comes with its skeleton (``Retargeter.step_skeleton``) keeps it. A frame that comes with
    its viewpoint is read by the one-view SKR where the weights have one and ``view`` asks
    (``skr.read_from_view``), as it comes: the refiner learned whole clouds' readings (refined,
    the one-view readings measured worse: docs/single_view.md), and a mirror image would be
    another view."""
    name = "skr"
    reads_cloud = True

    def __init__(self, weights, refine, mirrored, workers, view=True):
        self.weights, self.workers = weights, workers
        self.refine = refine and weights.refine is not None
        self.mirrored = mirrored
        self.view = weights.skr_view if view else None

    def read(self, points, viewpoint=None):
        """(P, 3) or (B, P, 3) C-contiguous float32 clouds (checked), and the (3,) viewpoint
        of the one camera that saw them or None -> (J, 3) or (B, J, 3) float32 joints."""
        if viewpoint is not None and self.view is not None:
            return read_from_view(lambda clouds: regress_checked(clouds, self.view, self.workers),
                                  points, viewpoint)

        def skeleton(clouds):
            joints = regress_checked(clouds, self.weights.skr, self.workers)
            if self.refine:
                joints = refine_checked(clouds, joints, self.weights.refine,
                                        self.weights.config.refine_neighbours)
            return joints
        return mirror_averaged_checked(skeleton, points) if self.mirrored else skeleton(points)

    def step(self, state, frame):
        if frame.joints is not None:
            return None, frame
        if frame.viewpoint is None or self.view is None:
            # The points alone: a subclass's ``read(points)`` works on.
            return None, frame._replace(joints=self.read(frame.points))
        return None, frame._replace(joints=self.read(frame.points, frame.viewpoint),
                                    view_read=True)


class FacingCheck(Stage):
    """Stage 1d: a reading that faces away from the body's heading, read again half turned
    (``facing``)."""
    name = "facing_check"
    reads_cloud = True
    State = FacingState

    def __init__(self, reading):
        self.reading = reading

    def step(self, state, frame):
        if frame.points is None:            # nothing to read again: the skeleton stands
            return FacingState(float(heading_angles(frame.joints)), 0), frame
        reference, away = (np.nan, 0) if state is None else state
        joints, reference, away = _check_facing(frame.joints, frame.points, reference, away,
                                                self.reading.read, TRIGGER, CONFIRM)
        # A reading replaced by one of the cloud half turned is whole-body SKR's, not one view's.
        kept = frame.view_read and np.array_equal(joints, frame.joints)
        return FacingState(reference, away), frame._replace(joints=joints, view_read=kept)

    def checked(self, state):
        return check_facing_state(state)


class SourceFit(Stage):
    """Stage 1e: the calibrated body model tracked in the cloud; its joints replace the
    reading (``fit``). A frame without a cloud is left as it is. A told frame read by the
    one-view SKR (``Frame.view_read``) keeps that reading's depth along the camera's rays
    (``fit.fit_frame``'s ``reading_depth``); any other told reading's is the motion's."""
    name = "source_fit"
    reads_cloud = True
    State = FitState
    every_frame = False     # it runs on frames with a cloud only

    def __init__(self, settings, warn=True):
        self.settings, self.warn = settings, warn

    def step(self, state, frame):
        if frame.points is None:
            return state, frame
        if state is None:
            state, joints = start_fit(body_model(), self.settings, frame.points, frame.joints,
                                      frame.viewpoint)
        else:
            state, joints, _ = fit_frame(body_model(), self.settings, state, frame.points,
                                         frame.joints, frame.viewpoint, frame.view_read)
        if state.cost > LOST_COST and self.warn:
            warnings.warn(f"frame {frame.index}: the source fit found no body in this cloud "
                          f"(mean distance {100 * state.cost:.1f} cm); it holds the last "
                          "frame's pose until the body is back", FitWarning, stacklevel=5)
        return state, frame._replace(joints=joints.astype(np.float32))

    def checked(self, state):
        if not isinstance(state, FitState):
            raise ValueError(f"source_fit: the state must be a fit.FitState, got "
                             f"{type(state).__name__}")
        return self.from_arrays(self.arrays(state))

    def arrays(self, state):
        return fit_state_arrays(state)

    def from_arrays(self, arrays):
        return fit_state_from_arrays(arrays, body_model())


class JointSmoothing(Stage):
    """Stage 2a: the joints' alpha-beta filter over time (``smoothing``)."""
    name = "smoothing"
    State = SmoothingState

    def __init__(self, smoothing):
        self.gains = _parameters(smoothing)

    def step(self, state, frame):
        if state is None:
            state = SmoothingState(frame.joints, np.zeros_like(frame.joints))
        smoothed, velocity = _smooth_kernel(frame.joints, *state, *self.gains)
        return SmoothingState(smoothed, velocity), frame._replace(joints=smoothed)

    def checked(self, state):
        return check_smoothing_state(state)


class Denoising(Stage):
    """Stage 2b: the GRU that learned SKR's errors, mirror-averaged (``denoise``)."""
    name = "denoiser"
    State = DenoiseState

    def __init__(self, weights):
        self.weights = weights

    def step(self, state, frame):
        if state is None:
            state = initial_denoise_state(self.weights, frame.joints)
        hidden = state.hidden.copy()
        joints = _denoise_mirror_averaged_kernel(self.weights, frame.joints,
                                                 state.previous_root, hidden)
        return DenoiseState(hidden, frame.joints[0].copy()), frame._replace(joints=joints)

    def checked(self, state):
        return check_denoise_state(self.weights, state)


class Retargeting(Stage):
    """Stage 3: SMRM, the source skeleton -> the target's rotations and root (``smrm``)."""
    name = "smrm"
    State = SMRMState

    def __init__(self, weights, target, rest_pose):
        self.weights, self.tpose_joints = weights, target.tpose_joints
        self.leg_length = target.leg_length
        self.rest = _NO_REST_POSE if rest_pose is None else check_rest_pose(rest_pose).directions

    def step(self, state, frame):
        rotations, root, state = step_checked(self.weights, state, frame.joints,
                                              self.tpose_joints, self.rest, self.leg_length)
        return state, frame._replace(rotations=rotations, root=root)

    def checked(self, state):
        return check_smrm_state(self.weights, state)


class Posing(Stage):
    """Stage 4: forward kinematics of the rotations on the target's skeleton, once a frame."""
    name = "fk"

    def __init__(self, tpose_joints):
        self.tpose_joints = tpose_joints

    def step(self, state, frame):
        joints = np.empty((1,) + self.tpose_joints.shape, dtype=np.float32)
        global_rotations = np.empty(joints.shape + (3,), dtype=np.float32)
        _forward_kinematics_kernel(frame.rotations[None], frame.root[None],
                                   self.tpose_joints[None], _PARENTS, joints, global_rotations)
        return None, frame._replace(posed_joints=joints[0], global_rotations=global_rotations[0])


class FootPlanting(Stage):
    """Stage 5: planted toes held, the legs bent to them (``contacts``); the legs' FK placed
    again."""
    name = "foot_lock"
    State = FeetState

    def __init__(self, foot_lock, tpose_joints):
        self.foot_lock, self.tpose_joints = foot_lock, tpose_joints

    def step(self, state, frame):
        rotations, state = plant_checked(frame.rotations, frame.posed_joints,
                                         frame.global_rotations, self.tpose_joints, state,
                                         self.foot_lock)
        return state, frame._replace(rotations=rotations)

    def checked(self, state):
        return check_feet(state)


class Skinning(Stage):
    """Stage 6: linear blend skinning of the target's points with their skinning weights."""
    name = "lbs"

    def __init__(self, target):
        self.target = target

    def step(self, state, frame):
        return None, frame._replace(vertices=self.skin(frame.posed_joints,
                                                       frame.global_rotations))

    def skin(self, joints, global_rotations):
        """(..., J, 3) joints and (..., J, 3, 3) rotations -> (..., V, 3) posed points."""
        target = self.target
        transforms = skinning_transforms(joints, global_rotations, target.tpose_joints)
        return linear_blend_skinning(target.points, target.skin_weights, transforms)


def build_stages(weights, config, target, reading, warn=True):
    """The stages ``config`` asks for with ``weights``, for ``target`` (a
    ``retargeter.Target``), in order: a tuple. ``reading``: the SKR stage (a ``Reading``
    with the config's ``refine`` and ``mirror_source``), which the facing check reads with
    too. ``warn``: the source fit warns of a cloud it finds no body in."""
    denoiser = weights.denoise if config.denoise else None
    rest_pose = weights.rest_pose if config.rest_pose else None
    tpose = target.tpose_joints
    stages = [Thinning(config.cloud_points) if config.cloud_points is not None else None,
              reading,
              FacingCheck(reading) if config.facing_check else None,
              SourceFit(config.fit_source, warn) if config.fit_source is not None else None,
              JointSmoothing(config.smoothing) if config.smoothing is not None else None,
              Denoising(denoiser) if denoiser is not None else None,
              Retargeting(weights.smrm, target, rest_pose),
              Posing(tpose),
              FootPlanting(config.foot_lock, tpose) if config.foot_lock is not None else None,
              Skinning(target)]
    return tuple(stage for stage in stages if stage is not None)


def check_stream_state(stages, state):
    """``state`` (a StreamState) checked against ``stages``: a count, and a checked state
    for each stage that keeps one and none other (all None at a stream's start); ValueError
    names the stage and field."""
    if not isinstance(state, StreamState):
        raise ValueError(f"state must be a StreamState (Retargeter.state), got "
                         f"{type(state).__name__}")
    frames = as_count(state.frames_seen, "state.frames_seen")
    if not isinstance(state.stages, dict):
        raise ValueError(f"state.stages must be a dict of stage states, got "
                         f"{type(state.stages).__name__}")
    keeping = {stage.name: stage for stage in stages if stage.State is not None}
    unknown = set(state.stages) - set(keeping)
    if unknown:
        raise ValueError(f"state holds stages this pipeline does not run: "
                         f"{', '.join(sorted(unknown))} (a state from another config)")
    checked = {}
    for name, stage in keeping.items():
        value = state.stages.get(name)
        if value is None:
            if frames and stage.every_frame:
                raise ValueError(f"state has no {name} state after {frames} frames (a state "
                                 "from another config)")
            continue
        checked[name] = stage.checked(value)
    return StreamState(frames, checked)


def stream_arrays(stages, state):
    """A StreamState as flat arrays (a checkpoint's): ``frames_seen``, and for each stage
    with a state ``{name}.version`` and ``{name}.{key}`` of its ``arrays``."""
    arrays = {"frames_seen": np.array(state.frames_seen, np.int64)}
    for stage in stages:
        if stage.name in state.stages:
            arrays[f"{stage.name}.version"] = np.array(stage.version, np.int64)
            arrays.update({f"{stage.name}.{key}": value
                           for key, value in stage.arrays(state.stages[stage.name]).items()})
    return arrays


def stream_from_arrays(stages, arrays):
    """``stream_arrays``'s inverse, checked (ValueError names the stage and field)."""
    states = {}
    for stage in stages:
        if f"{stage.name}.version" not in arrays or stage.State is None:
            continue
        version = int(arrays[f"{stage.name}.version"])
        if version != stage.version:
            raise ValueError(f"the {stage.name} stage's state is of version {version}; this "
                             f"minretarget reads version {stage.version}")
        prefix = f"{stage.name}."
        own = {key[len(prefix):]: value for key, value in arrays.items()
               if key.startswith(prefix)}
        try:
            states[stage.name] = stage.from_arrays(own)
        except (KeyError, TypeError) as error:
            raise ValueError(f"the {stage.name} stage's state lacks or garbles {error}") \
                from None
    return check_stream_state(stages, StreamState(int(arrays["frames_seen"]), states))
