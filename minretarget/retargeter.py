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

from . import _compile_ahead
from ._jit import on_first_compile
from .conventions import MIN_POINTS, NUM_JOINTS
from .kinematics import forward_kinematics
from .kinematics import leg_length as legs_of
from .pipeline import PipelineConfig, as_config, check_pipeline
from .sampling import sample_point_clouds, seeded_subset, triangle_areas
from .skin import skinning_weights
from .smrm import check_leg_length
from .stages import (Frame, Reading, Skinning, StreamState, build_stages, check_stream_state)
from .validation import (InputWarning, as_float32_array, as_point_cloud, as_workers,
                         check_body)
from .weights import Weights, load_weights

# A target mesh's legs, which scale the root (SMRM), are read from area-uniform samples of
# its surface, the clouds SKR learned: the mean of TARGET_READS readings of
# TARGET_READ_POINTS points each, drawn with a fixed seed. Its vertices crowd where its detail
# is (the face, the hands): read from them, the legs come out 2-3 % off on some bodies, the
# arms better than from the surface (docs/source_fit.md, "The root's scale from the target's
# surface").
TARGET_READS, TARGET_READ_POINTS = 8, 2048


# Metres: a viewpoint nearer the cloud's centre than this is inside the body, or in another
# frame or unit than the points (refused); farther than MAX_VIEW_DISTANCE, past any depth
# sensor's range, it is probably in another unit (warned of on a stream's first frame).
MIN_VIEW_DISTANCE, MAX_VIEW_DISTANCE = 0.3, 20.0


class Target(NamedTuple):
    """What is computed once per target body."""
    points: np.ndarray          # (V, 3) float32 T-pose points, metres
    faces: np.ndarray           # (F, 3) int64 triangle indices into points, or None
    tpose_joints: np.ndarray    # (J, 3) float32 its skeleton (SKR), metres
    skin_weights: np.ndarray    # (V, J) float32 its skinning weights (SKIN)
    leg_length: float           # metres, its hip-knee-ankle length, which scales the root


class RetargetedFrame(NamedTuple):
    vertices: np.ndarray        # (V, 3) float32 the target's points posed, target order, metres
    joints: np.ndarray          # (J, 3) float32 the target's posed joints, metres
    rotations: np.ndarray       # (J, 4) float32 local joint quaternions (w, x, y, z)
    root: np.ndarray            # (3,) float32 pelvis position, metres
    source_joints: np.ndarray   # (J, 3) float32 the source skeleton SMRM saw, metres


def legs_from_surface(reader, points, faces):
    """The legs' length (metres) that ``reader`` (a ``stages.Reading``) reads from
    area-uniform samples of a mesh's surface ((V, 3) points, (F, 3) faces), or None if its
    triangles have no area."""
    if not triangle_areas(points, faces).sum() > 0:
        return None
    clouds = sample_point_clouds(np.broadcast_to(points, (TARGET_READS,) + points.shape),
                                 faces, TARGET_READ_POINTS, np.random.default_rng(0))
    return float(legs_of(reader.read(clouds).mean(axis=0)))


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
        self.target, self._state, self._stages = None, None, ()
        self._compiler = None           # a second process compiling the later stages, if any
        self.config = config
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
        """Mid-stream, the stages in both pipelines go on with their state; a stage switched
        on starts at the next frame as at a stream's start."""
        self._config = check_pipeline(self.weights, as_config(config))
        self._build()

    @property
    def stages(self) -> tuple:
        """The stages each frame goes down, in order (``stages.build_stages``); empty until
        ``set_target``."""
        return self._stages

    def _build(self):
        """The stage list for the config and target; states of stages gone are dropped."""
        self._stages = () if self.target is None else self._stage_list()
        if self._state is not None:
            names = {stage.name for stage in self._stages}
            self._state = self._state._replace(stages={
                name: value for name, value in self._state.stages.items() if name in names})

    def _stage_list(self, warn=True):
        """``stages.build_stages`` for this retargeter's weights, config and target."""
        return build_stages(self.weights, self._config, self.target,
                            self._reader(self._config.mirror_source), warn)

    def set_target(self, points: ArrayLike, faces: ArrayLike | None = None,
                   tpose_joints: ArrayLike | None = None,
                   skin_weights: ArrayLike | None = None,
                   leg_length: float | None = None) -> None:
        """Set the body to animate and restart the stream.

        Args:
            points: (V, 3) target points or mesh vertices in T-pose, metres, +Y up, facing +Z.
            faces: optional (F, 3) integer triangles, kept with the target for writers.
            tpose_joints: optional (J, 3) the target's own T-pose skeleton, metres, to use
                instead of SKR's (a rigged character).
            skin_weights: optional (V, J) its own skinning weights, to use instead of SKIN's;
                rows must be >= 0 and sum to 1.
            leg_length: optional, metres, its hip-knee-ankle length, which scales the root;
                by default the given skeleton's, or for a mesh read by SKR, its legs as
                read from its surface, else its skeleton's.
        """
        points = as_point_cloud(points, "target points", MIN_POINTS)
        if leg_length is not None:
            leg_length = check_leg_length(leg_length, "leg_length")
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
        # A cold numba cache: a second process (``_compile_ahead``) compiles the stages after
        # the cloud's meanwhile, last to first, while the first frame compiles them first to
        # last (``_fold`` waits for one it is compiling, and stops it after that frame).
        with on_first_compile(self._compile_ahead):
            if tpose_joints is None:
                reader = self._reader(self.config.mirror_target)
                tpose_joints = reader.read(points)
                if leg_length is None and faces is not None:
                    leg_length = legs_from_surface(reader, points, faces)
            tpose_joints = as_float32_array(tpose_joints, "tpose_joints", (NUM_JOINTS, 3))
            if leg_length is None:
                leg_length = float(legs_of(tpose_joints))
            if skin_weights is None:
                skin_weights = skinning_weights(points, tpose_joints, self.weights.skin)
        skin_weights = as_float32_array(skin_weights, "skin_weights", (len(points), NUM_JOINTS))
        if (skin_weights < 0).any() or np.abs(skin_weights.sum(axis=1) - 1).max() > 1e-3:
            raise ValueError("skin_weights must be >= 0 and each row must sum to 1")
        if self.warn:
            check_body(points, "target points", tpose=True)
        self.target = Target(points, faces, tpose_joints, skin_weights, leg_length)
        self.reset()
        self._build()

    def _compile_ahead(self):
        if self._compiler is None:
            self._compiler = _compile_ahead.start(self._config)

    def reset(self) -> None:
        """Forget the motion seen so far (the target stays). The calling thread owns the new
        stream: a stream carries state from frame to frame, so frames from two threads would
        mix two motions into one; another thread's frame is refused (``_check_owner``) until
        it calls ``reset`` (or ``set_target``) itself."""
        self._state = None
        self._owner = threading.get_ident()

    def _check_owner(self):
        """RuntimeError unless the calling thread owns the stream (the one that last called
        ``reset``, ``set_target`` or set ``state``)."""
        if self._owner != threading.get_ident():
            raise RuntimeError("this Retargeter's stream belongs to another thread (the one "
                               "that last called reset, set_target or set its state); use one "
                               "Retargeter per thread, or call reset() in this one first")

    def _require_target(self, method):
        if self.target is None:
            raise RuntimeError(f"call set_target before {method}")

    def warm_up(self, skeleton: bool = False) -> None:
        """Compile every kernel that a stream of clouds (``skeleton``: of joints) uses with
        this retargeter's settings, or load them from numba's on-disk cache, by retargeting
        two frames of the target's own points (about 1,000 of them; or its T-pose joints);
        then restart the stream. Takes milliseconds with a warm cache, 15-25 s with a cold one
        (docs/python_api.md): call it before timing or showing progress. Those frames are not
        the source's: the source fit does not warn of them."""
        self._require_target("warm_up")
        points = None if skeleton else np.ascontiguousarray(                  # (~1024, 3)
            self.target.points[::max(1, len(self.target.points) // 1024)])
        joints = self.target.tpose_joints if skeleton else None
        quiet = self._stage_list(warn=False)
        for _ in range(2):
            self._fold(Frame(self._frame(), points, joints), quiet)
        self.reset()

    @property
    def state(self) -> StreamState | None:
        """What the stream carries after the frames seen so far (``stages.StreamState``: the
        count, and each stage's own state by its name), or None at a stream's start. Save it
        to continue the stream later (``stages.stream_arrays`` makes plain arrays of it): set
        it back, on a retargeter with the same weights, config and target, and the next
        frames come out exactly as if the stream had never stopped."""
        return self._state

    @state.setter
    def state(self, state: StreamState | None) -> None:
        self._state = None if state is None else check_stream_state(self._stages, state)
        self._owner = threading.get_ident()

    def step(self, points: ArrayLike, viewpoint: ArrayLike | None = None) -> RetargetedFrame:
        """Retarget one source frame: (P, 3) points, metres, any order -> RetargetedFrame.

        ``viewpoint``: where the one depth camera that saw the cloud stands, (3,) metres, in
        the points' frame (a depth sensor's own points: its origin, moved as the points were),
        or None for a cloud over the whole body. The one-view SKR then reads the cloud (where
        the weights have one and the config's ``skr_view`` asks), and the source fit fits only
        the side of its body model that the camera sees, keeping that reading's depth
        (docs/single_view.md); a pipeline without the fit refuses it."""
        self._require_target("step")
        points = as_point_cloud(points, "source points", MIN_POINTS)
        if viewpoint is not None:
            viewpoint = self._checked_viewpoint(viewpoint, points, self._state is None)
        if self.warn and self._state is None:
            check_body(points, "source points, frame 0")
        return self._step(points, None, viewpoint)

    def _checked_viewpoint(self, viewpoint, points, first):
        """(3,) float32 ``viewpoint`` checked against ``points`` (P, 3); a far camera is
        warned of when ``first`` (a stream's first frame)."""
        if self.config.fit_source is None:
            raise ValueError(f"a viewpoint needs the source fit (it fits the side the camera "
                             f"sees), and this pipeline ({self.config.preset_name() or 'custom'})"
                             " has none: use the 'fitted' preset, or give no viewpoint")
        viewpoint = as_float32_array(viewpoint, "viewpoint", (3,))
        distance = float(np.linalg.norm(viewpoint - points.mean(axis=0)))
        if distance < MIN_VIEW_DISTANCE:
            raise ValueError(f"viewpoint {viewpoint.tolist()} is {distance:.2f} m from the "
                             f"cloud's centre: a camera that sees a body stands at least "
                             f"{MIN_VIEW_DISTANCE} m from it (is it in the points' frame and "
                             "units?)")
        if distance > MAX_VIEW_DISTANCE and self.warn and first:
            warnings.warn(f"viewpoint {viewpoint.tolist()} is {distance:.1f} m from the cloud's "
                          f"centre, past any depth sensor's range: is it in the points' units "
                          f"and frame? (the fit takes it as given)", InputWarning, stacklevel=3)
        return viewpoint

    def step_skeleton(self, source_joints: ArrayLike, points: ArrayLike | None = None,
                      viewpoint: ArrayLike | None = None) -> RetargetedFrame:
        """Retarget one frame given the source skeleton (J, 3) directly (skips SKR; like
        SKR's, it is smoothed unless ``smoothing`` is None, and denoised if ``denoise``).
        ``points``: the (P, 3) cloud the skeleton was found in (``skeleton``), if any: the
        facing check then runs SKR on it again, half turned, when the skeleton faces away,
        and the source fit tracks its body in it (``viewpoint``: the one depth camera that saw
        it, as ``step``'s); without it every skeleton stands as given."""
        self._require_target("step_skeleton")
        source_joints = as_float32_array(source_joints, "source joints", (NUM_JOINTS, 3))
        if viewpoint is not None and points is None:
            raise ValueError("a viewpoint places the camera that saw a cloud: give the points "
                             "too")
        if points is not None:
            points = as_point_cloud(points, "source points", MIN_POINTS)
            if viewpoint is not None:
                viewpoint = self._checked_viewpoint(viewpoint, points, self._state is None)
        if self.warn and self._state is None:
            check_body(source_joints, "source joints, frame 0")
        return self._step(points, source_joints, viewpoint)

    def _step(self, points, joints, viewpoint=None):
        """One checked frame down every stage -> RetargetedFrame."""
        frame = self._fold(Frame(self._frame(), points, joints, viewpoint=viewpoint),
                           self._stages)
        # A copy: a stage's state may hold the joints, which must not change if the caller
        # edits the frame's.
        return RetargetedFrame(frame.vertices, frame.posed_joints, frame.rotations,
                               frame.root, frame.joints.copy())

    def _fold(self, frame, stages):
        """``frame`` down ``stages``, each with its state; the stream's state moves on."""
        self._check_owner()
        before = {} if self._state is None else self._state.stages
        after = {}
        for stage in stages:
            if self._compiler is not None and not stage.reads_cloud:
                self._compiler.await_stage(stage.name)
            state, frame = stage.step(before.get(stage.name), frame)
            if state is not None:
                after[stage.name] = state
        self._state = StreamState(frame.index + 1, after)
        if self._compiler is not None:      # every stage compiled: it has nothing left to do
            self._compiler.stop()
            self._compiler = None
        return frame

    def _frame(self):
        """The index in the stream of the frame about to be retargeted."""
        return 0 if self._state is None else self._state.frames_seen

    def _thinned(self, points, frame):
        """(P, 3) points thinned to the config's ``cloud_points`` (seeded by ``frame``)."""
        count = self.config.cloud_points
        return points if count is None else seeded_subset(points, count, frame)

    def skeleton(self, points: ArrayLike, viewpoint: ArrayLike | None = None) -> np.ndarray:
        """The source skeleton(s) SKR finds, cloud by cloud: mirror-averaged if
        ``mirror_source``, refined if ``refine``; what ``step`` reads before the facing check,
        the source fit, smoothing and denoising.

        Args:
            points: (P, 3) or (T, P, 3) float32 source clouds, metres; with the config's
                ``cloud_points``, thinned as a stream's frames 0, 1, ... (one cloud: 0).
            viewpoint: the one depth camera that saw them, (3,) metres, or None: with one,
                the weights' one-view SKR reads them (config ``skr_view``), if they have one.
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
        points = self._thinned(points, 0) if points.ndim == 2 else points
        reader = self._reader(self.config.mirror_source)
        if viewpoint is None:           # the points alone: a subclass's ``read(points)`` works on
            return reader.read(points)
        return reader.read(points, as_float32_array(viewpoint, "viewpoint", (3,)))

    def _reader(self, mirrored):
        """SKR's stage (``stages.Reading``) with the config's refiner, ``mirrored`` or not."""
        return Reading(self.weights, self.config.refine, mirrored, self.workers,
                       self.config.skr_view)

    def pose(self, rotations: ArrayLike, root: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Pose the target: (J, 4) local quaternions and (3,) root, metres -> its (V, 3)
        vertices and (J, 3) joints, as ``step``'s last stages do after the foot lock; or T
        frames at once: (T, J, 4) and (T, 3) -> (T, V, 3) and (T, J, 3)."""
        self._require_target("pose")
        frames = (None,) if np.ndim(rotations) > 2 else ()                 # (T,) or one frame
        rotations = as_float32_array(rotations, "rotations", frames + (NUM_JOINTS, 4))
        root = as_float32_array(root, "root", rotations.shape[:-2] + (3,))
        joints, global_rotations = forward_kinematics(rotations, root, self.target.tpose_joints)
        return Skinning(self.target).skin(joints, global_rotations), joints

    def retarget_sequence(self, frames: ArrayLike,
                          viewpoint: ArrayLike | None = None) -> RetargetedFrame:
        """Retarget a whole recorded sequence at once (offline): the same result as ``run``,
        up to float32 rounding, faster per frame.

        SKR runs cloud after cloud (on ``workers`` threads each), SMRM's recurrence frame by
        frame, then ``pose`` takes all frames (LBS blends many frames per matrix product).
        The stream restarts first, and ``state`` is left after the last frame, so ``step``
        can go on.

        Args:
            frames: (T, P, 3) float32 source clouds, metres (the same P in every frame).
            viewpoint: the one depth camera that saw every cloud, (3,) metres (``step``), or
                None.
        Returns:
            RetargetedFrame whose fields have a leading T axis: vertices (T, V, 3), joints
            (T, J, 3), rotations (T, J, 4), root (T, 3), source_joints (T, J, 3).
        """
        self._require_target("retarget_sequence")
        frames = as_float32_array(frames, "source frames", (None, None, 3))
        if len(frames) == 0 or frames.shape[1] < MIN_POINTS:
            raise ValueError(f"source frames must hold at least one frame of at least "
                             f"{MIN_POINTS} points, got shape {frames.shape}")
        if viewpoint is not None:
            viewpoint = self._checked_viewpoint(viewpoint, frames[0], first=True)
        if self.warn:
            check_body(frames[0], "source points, frame 0")
        self.reset()
        # SKR on every cloud first (it is stateless: one call, ``workers`` threads), then
        # every other stage frame by frame but the skinning, then the skinning of all frames
        # at once (LBS blends many frames per matrix product).
        if viewpoint is None:        # the points alone: a subclass's ``skeleton(points)`` works on
            readings, view_read = self.skeleton(frames), False
        else:
            readings = self.skeleton(frames, viewpoint)
            view_read = self._reader(self.config.mirror_source).view is not None   # as it read
        stages = self._stages[:-1]
        out = [self._fold(Frame(t, cloud, readings[t], viewpoint=viewpoint, view_read=view_read),
                          stages) for t, cloud in enumerate(frames)]
        stacked = {name: np.stack([getattr(frame, name) for frame in out])
                   for name in ("posed_joints", "global_rotations", "rotations", "root",
                                "joints")}
        vertices = self._stages[-1].skin(stacked["posed_joints"], stacked["global_rotations"])
        return RetargetedFrame(vertices, stacked["posed_joints"], stacked["rotations"],
                               stacked["root"], stacked["joints"])

    def run(self, frames: Iterable[ArrayLike],
            viewpoint: ArrayLike | None = None) -> Iterator[RetargetedFrame]:
        """Retarget an iterable of (P, 3) source frames lazily, one RetargetedFrame each
        (``viewpoint``: the one depth camera that saw every cloud, as ``step``'s, or None).

        Memory stays constant in the number of frames: nothing is kept between frames but
        the recurrent state. The stream restarts (``reset``) first.
        """
        self.reset()
        for index, points in enumerate(frames):
            try:
                # step(points) as before where no camera is given (a subclass's step may
                # take the points alone)
                yield self.step(points) if viewpoint is None else self.step(points, viewpoint)
            except ValueError as error:
                raise ValueError(f"frame {index}: {error}") from None
