"""The online retargeter: a target body, then source frames one at a time.

    retargeter = Retargeter.from_weights()            # the shipped default weights
    retargeter.set_target(target_points)              # (V, 3) T-pose: skeleton + skinning, once
    for points in frames:                             # (P, 3) each, any P >= 64, any order
        frame = retargeter.step(points)               # frame.vertices (V, 3) in target order
"""
import os
import threading
import warnings
from collections.abc import Iterable, Iterator
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from .contacts import plant_feet
from .facing import CONFIRM, TRIGGER, _check_facing
from .fit import LOST_COST, body_model, fit_frame, start_fit
from .heading import heading_angles
from .conventions import MIN_POINTS, NUM_JOINTS
from .kinematics import forward_kinematics, skinning_transforms
from .pipeline import PipelineConfig, as_config, check_pipeline
from .refine import refine_joints
from .sampling import seeded_subset
from .skin import linear_blend_skinning, skinning_weights
from .skr import mirror_averaged, regress_joints
from .smrm import MotionState, check_state, retarget_step
from .validation import FitWarning, as_float32_array, as_point_cloud, as_workers, check_body
from .weights import Weights, load_weights


class Target(NamedTuple):
    """What is computed once per target body."""
    points: np.ndarray          # (V, 3) float32 T-pose points, metres
    faces: np.ndarray           # (F, 3) int64 triangle indices into points, or None
    tpose_joints: np.ndarray    # (J, 3) float32 its skeleton (SKR), metres
    skin_weights: np.ndarray    # (V, J) float32 its skinning weights (SKIN)


class RetargetedFrame(NamedTuple):
    vertices: np.ndarray        # (V, 3) float32 the target's points posed, target order, metres
    joints: np.ndarray          # (J, 3) float32 the target's posed joints, metres
    rotations: np.ndarray       # (J, 4) float32 local joint quaternions (w, x, y, z)
    root: np.ndarray            # (3,) float32 pelvis position, metres
    source_joints: np.ndarray   # (J, 3) float32 the source skeleton SMRM saw, metres


class Retargeter:
    def __init__(self, weights: Weights, config: PipelineConfig | str = "default", *,
                 warn: bool = True, workers: int = 1) -> None:
        """``weights``: a ``weights.Weights`` (``load_weights``; ``from_weights`` reads a file).
        ``config``: the pipeline (``pipeline.PipelineConfig``, or a preset's name: "default",
        "paper", "regressed", "fitted"), checked against what the weights were trained for
        (``pipeline.check_pipeline``); ``config`` can be set again between streams.
        ``warn``: issue ``validation.InputWarning``s for a target or a stream's first frame
        that looks like wrong units, a wrong up axis or (targets) not a T-pose.
        ``workers``: threads sharing SKR's work on each cloud (``skr.regress_joints``; give
        BLAS one thread when > 1)."""
        if not isinstance(weights, Weights):
            raise TypeError(f"weights must be a minretarget.weights.Weights (load_weights(path)),"
                            f" got {type(weights).__name__}; Retargeter.from_weights(path) "
                            "reads a file")
        if not isinstance(warn, (bool, np.bool_)):
            raise TypeError(f"warn must be True or False, got {warn!r}")
        self.weights = weights
        self.warn = bool(warn)
        self.workers = as_workers(workers)
        self._config = None
        self.config = config
        self.target = None
        self.reset()

    @classmethod
    def from_weights(cls, path: str | os.PathLike | None = None,
                     config: PipelineConfig | str = "default", *, warn: bool = True,
                     workers: int = 1) -> "Retargeter":
        """A retargeter with the weights file at ``path`` (None: the shipped default)."""
        return cls(load_weights(path), config, warn=warn, workers=workers)

    @property
    def config(self) -> PipelineConfig:
        """The pipeline this retargeter runs (``pipeline.PipelineConfig``)."""
        return self._config

    @config.setter
    def config(self, config: PipelineConfig | str) -> None:
        config = check_pipeline(self.weights, as_config(config))
        if self._config is not None and self._state is not None and (
                self._config.denoise != config.denoise and self.weights.denoise is not None):
            raise ValueError("a stream keeps the denoiser it began with: call reset() before "
                             "switching denoise")
        self._config = config

    def set_target(self, points: ArrayLike, faces: ArrayLike | None = None,
                   tpose_joints: ArrayLike | None = None,
                   skin_weights: ArrayLike | None = None) -> None:
        """Set the body to animate and restart the stream.

        Args:
            points: (V, 3) target points or mesh vertices in T-pose, metres, +Y up, facing +Z.
            faces: optional (F, 3) integer triangles, kept with the target for writers.
            tpose_joints: optional (J, 3) the target's own T-pose skeleton, metres, to use
                instead of SKR's (a rigged character).
            skin_weights: optional (V, J) its own skinning weights, to use instead of SKIN's;
                rows must be >= 0 and sum to 1.
        """
        points = as_point_cloud(points, "target points", MIN_POINTS)
        if faces is not None:
            faces = np.asarray(faces)
            if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype,
                                                                            np.integer):
                raise ValueError(f"faces must be an (F, 3) integer array, got {faces.shape} "
                                 f"{faces.dtype}")
            if faces.size and (faces.min() < 0 or faces.max() >= len(points)):
                raise ValueError(f"faces index vertices outside [0, {len(points)})")
            # No triangles is a point cloud, as the file readers give it.
            faces = faces.astype(np.int64) if len(faces) else None
        if tpose_joints is None:
            tpose_joints = self._skr(points, self.config.mirror_target)
        tpose_joints = as_float32_array(tpose_joints, "tpose_joints", (NUM_JOINTS, 3))
        if skin_weights is None:
            skin_weights = skinning_weights(points, tpose_joints, self.weights.skin)
        skin_weights = as_float32_array(skin_weights, "skin_weights", (len(points), NUM_JOINTS))
        if (skin_weights < 0).any() or np.abs(skin_weights.sum(axis=1) - 1).max() > 1e-3:
            raise ValueError("skin_weights must be >= 0 and each row must sum to 1")
        if self.warn:
            check_body(points, "target points", tpose=True)
        self.target = Target(points, faces, tpose_joints, skin_weights)
        self.reset()

    def reset(self) -> None:
        """Forget the motion seen so far (the target stays). The calling thread owns the new
        stream: a stream carries state from frame to frame, so frames from two threads would
        mix two motions into one; another thread's frame is refused (``_check_owner``) until
        it calls ``reset`` (or ``set_target``) itself."""
        self._state = None
        self.fit_state = None
        self._owner = threading.get_ident()

    def _check_owner(self):
        """RuntimeError unless the calling thread owns the stream (the one that last called
        ``reset``, ``set_target`` or set ``state``)."""
        if self._owner != threading.get_ident():
            raise RuntimeError("this Retargeter's stream belongs to another thread (the one "
                               "that last called reset, set_target or set its state); use one "
                               "Retargeter per thread, or call reset() in this one first")

    def warm_up(self, skeleton: bool = False) -> None:
        """Compile every kernel that a stream of clouds (``skeleton``: of joints) uses with
        this retargeter's settings, or load them from numba's on-disk cache, by retargeting
        two frames of the target's own points (about 1,000 of them; or its T-pose joints);
        then restart the stream. Takes milliseconds with a warm cache, about 30 s with a cold
        one: call it before timing or showing progress."""
        if self.target is None:
            raise RuntimeError("call set_target before warm_up")
        points = np.ascontiguousarray(                                          # (~1024, 3)
            self.target.points[::max(1, len(self.target.points) // 1024)])
        for _ in range(2):
            joints = self.target.tpose_joints if skeleton else self._skr(points,
                                                                         self.config.mirror_source)
            self._step_joints(joints, None if skeleton else points)
        self.reset()

    @property
    def state(self) -> MotionState | None:
        """The recurrent state after the frames seen so far (``smrm.MotionState``), or None
        at a stream's start. Save it to continue the stream later in another process: set
        it back, on a retargeter with the same weights and target, and the next frames come
        out exactly as if the stream had never stopped. With ``fit_source`` on, the fit's
        state is apart (``fit_state``, a ``fit.FitState`` held in memory, not in checkpoint
        files yet): set it back too; setting ``state`` to None forgets it as well."""
        return self._state

    @state.setter
    def state(self, state: MotionState | None) -> None:
        self._state = None if state is None else check_state(self.weights.smrm, state,
                                                             self.denoiser)
        self._owner = threading.get_ident()
        if state is None:
            self.fit_state = None

    @property
    def denoiser(self):
        """The weights' denoiser if ``denoise`` is on and they have one, else None."""
        return self.weights.denoise if self.config.denoise else None

    @property
    def rest_pose_model(self):
        """The weights' rest-pose model if ``rest_pose`` is on and they have one, else None."""
        return self.weights.rest_pose if self.config.rest_pose else None

    def step(self, points: ArrayLike) -> RetargetedFrame:
        """Retarget one source frame: (P, 3) points, metres, any order -> RetargetedFrame."""
        if self.target is None:
            raise RuntimeError("call set_target before step")
        points = as_point_cloud(points, "source points", MIN_POINTS)
        if self.warn and self._state is None:
            check_body(points, "source points, frame 0")
        points = self._thinned(points, self._frame())
        return self._step_joints(self._skr(points, self.config.mirror_source), points)

    def step_skeleton(self, source_joints: ArrayLike,
                      points: ArrayLike | None = None) -> RetargetedFrame:
        """Retarget one frame given the source skeleton (J, 3) directly (skips SKR; like
        SKR's, it is smoothed unless ``smoothing`` is None, and denoised if ``denoise``).
        ``points``: the (P, 3) cloud the skeleton was found in (``skeleton``), if any: the
        facing check then runs SKR on it again, half turned, when the skeleton faces away;
        without it every skeleton stands as given."""
        if self.target is None:
            raise RuntimeError("call set_target before step_skeleton")
        source_joints = as_float32_array(source_joints, "source joints", (NUM_JOINTS, 3))
        if points is not None:
            points = self._thinned(as_point_cloud(points, "source points", MIN_POINTS),
                                   self._frame())
        if self.warn and self._state is None:
            check_body(source_joints, "source joints, frame 0")
        return self._step_joints(source_joints, points)

    def _frame(self):
        """The index in the stream of the frame about to be retargeted."""
        return 0 if self._state is None else self._state.frames_seen

    def _thinned(self, points, frame):
        """(P, 3) points thinned to the config's ``cloud_points`` (seeded by ``frame``)."""
        count = self.config.cloud_points
        return points if count is None else seeded_subset(points, count, frame)

    def _step_joints(self, source_joints, points=None):
        rotations, root = self._retarget_step(source_joints, points)
        vertices, joints = self.pose(rotations, root)
        # A copy: the state's own array must not change if the caller edits the frame's.
        return RetargetedFrame(vertices, joints, rotations, root,
                               self._state.previous_joints.copy())

    def skeleton(self, points: ArrayLike) -> np.ndarray:
        """The source skeleton(s) SKR finds, cloud by cloud: mirror-averaged if
        ``mirror_source``, refined if ``refine``; what ``step`` reads before the facing check,
        smoothing and denoising.

        Args:
            points: (P, 3) or (T, P, 3) float32 source clouds, metres; with the config's
                ``cloud_points``, thinned as a stream's frames 0, 1, ... (one cloud: 0).
        Returns:
            (J, 3) or (T, J, 3) float32 joints, metres; ``step_skeleton`` takes them (with
            their clouds, for the facing check and the source fit).
        """
        points = as_float32_array(points, "source points", (..., None, 3))
        if points.ndim not in (2, 3) or points.shape[-2] < MIN_POINTS or not len(points):
            raise ValueError(f"source points must have shape (P, 3) or (T, P, 3) with T >= 1 "
                             f"and P >= {MIN_POINTS}, got {points.shape}")
        if points.ndim == 3:
            points = np.stack([self._thinned(cloud, t) for t, cloud in enumerate(points)])
        return self._skr(self._thinned(points, 0) if points.ndim == 2 else points,
                         self.config.mirror_source)

    def _skr(self, points, mirrored):
        """The skeletons of (P, 3) or (B, P, 3) clouds: SKR, then the refiner (if the weights
        have one and ``refine`` is on); with ``mirrored``, that on each cloud and on its
        mirror image, averaged (``skr.mirror_averaged``)."""
        def skeleton(clouds):
            joints = regress_joints(clouds, self.weights.skr, self.workers)
            if self.config.refine and self.weights.refine is not None:
                joints = refine_joints(clouds, joints, self.weights.refine,
                                       self.weights.config.refine_neighbours)
            return joints
        return mirror_averaged(skeleton, points) if mirrored else skeleton(points)

    def _retarget_step(self, source_joints, points=None):
        """The facing check (given the frame's ``points``), smoothing, denoising, SMRM then
        the foot contacts on one frame's source skeleton -> rotations, root."""
        self._check_owner()
        if self.config.facing_check and points is not None:
            reference, away = ((np.nan, 0) if self._state is None else
                               (self._state.facing_reference, self._state.facing_away_frames))
            # step and step_skeleton have checked the joints and the cloud already
            source_joints, reference, away = _check_facing(
                source_joints, points, reference, away,
                lambda clouds: self._skr(clouds, self.config.mirror_source), TRIGGER, CONFIRM)
        else:      # tracked all the same, so that the check can be switched on mid-stream
            reference, away = float(heading_angles(source_joints)), 0
        if self.config.fit_source is not None and points is not None:
            source_joints = self._fit(points, source_joints)
        rotations, root, state = retarget_step(self.weights.smrm, self._state, source_joints,
                                               self.target.tpose_joints, self.config.smoothing,
                                               self.denoiser, self.rest_pose_model)
        self._state = state._replace(facing_reference=reference, facing_away_frames=away)
        rotations, self._state = plant_feet(rotations, root, self.target.tpose_joints,
                                            self._state, self.config.foot_lock)
        return rotations, root

    def _fit(self, points, reading):
        """The source fit on one cloud and its reading -> the fitted joints (J, 3) float32."""
        if self.fit_state is None:
            self.fit_state, joints = start_fit(body_model(), self.config.fit_source, points,
                                               reading)
        else:
            self.fit_state, joints, _ = fit_frame(body_model(), self.config.fit_source,
                                                  self.fit_state, points, reading)
        if self.fit_state.cost > LOST_COST:
            warnings.warn(f"frame {self.fit_state.frames - 1}: the source fit found no body "
                          f"in this cloud (mean distance {100 * self.fit_state.cost:.1f} cm); "
                          "it holds the last frame's pose until the body is back",
                          FitWarning, stacklevel=4)
        return joints.astype(np.float32)

    def pose(self, rotations: ArrayLike, root: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Pose the target: (J, 4) local quaternions and (3,) root, metres -> its (V, 3)
        vertices and (J, 3) joints, exactly as ``step`` does after SMRM and the foot
        contacts; or T frames at once: (T, J, 4) and (T, 3) -> (T, V, 3) and (T, J, 3)."""
        if self.target is None:
            raise RuntimeError("call set_target before pose")
        target = self.target
        frames = (None,) if np.ndim(rotations) > 2 else ()                 # (T,) or one frame
        rotations = as_float32_array(rotations, "rotations", frames + (NUM_JOINTS, 4))
        root = as_float32_array(root, "root", rotations.shape[:-2] + (3,))
        joints, global_rotations = forward_kinematics(rotations, root, target.tpose_joints)
        transforms = skinning_transforms(joints, global_rotations, target.tpose_joints)
        return linear_blend_skinning(target.points, target.skin_weights, transforms), joints

    def retarget_sequence(self, frames: ArrayLike) -> RetargetedFrame:
        """Retarget a whole recorded sequence at once (offline): the same result as ``run``,
        up to float32 rounding, faster per frame.

        SKR runs cloud after cloud (on ``workers`` threads each), SMRM's recurrence frame by
        frame, then ``pose`` takes all frames (LBS blends many frames per matrix product).
        The stream restarts first, and ``state`` is left after the last frame, so ``step``
        can go on.

        Args:
            frames: (T, P, 3) float32 source clouds, metres (the same P in every frame).
        Returns:
            RetargetedFrame whose fields have a leading T axis: vertices (T, V, 3), joints
            (T, J, 3), rotations (T, J, 4), root (T, 3), source_joints (T, J, 3).
        """
        if self.target is None:
            raise RuntimeError("call set_target before retarget_sequence")
        frames = as_float32_array(frames, "source frames", (None, None, 3))
        if len(frames) == 0 or frames.shape[1] < MIN_POINTS:
            raise ValueError(f"source frames must hold at least one frame of at least "
                             f"{MIN_POINTS} points, got shape {frames.shape}")
        if self.warn:
            check_body(frames[0], "source points, frame 0")
        self.reset()
        frames = np.stack([self._thinned(cloud, t) for t, cloud in enumerate(frames)])
        source_joints = self._skr(frames, self.config.mirror_source)
        rotations = np.empty((len(frames), NUM_JOINTS, 4), dtype=np.float32)
        root = np.empty((len(frames), 3), dtype=np.float32)
        for t, joints in enumerate(source_joints):
            rotations[t], root[t] = self._retarget_step(joints, frames[t])
            source_joints[t] = self._state.previous_joints
        vertices, joints = self.pose(rotations, root)
        return RetargetedFrame(vertices, joints, rotations, root, source_joints)

    def run(self, frames: Iterable[ArrayLike]) -> Iterator[RetargetedFrame]:
        """Retarget an iterable of (P, 3) source frames lazily, one RetargetedFrame each.

        Memory stays constant in the number of frames: nothing is kept between frames but
        the recurrent state. The stream restarts (``reset``) first.
        """
        self.reset()
        for index, points in enumerate(frames):
            try:
                yield self.step(points)
            except ValueError as error:
                raise ValueError(f"frame {index}: {error}") from None
