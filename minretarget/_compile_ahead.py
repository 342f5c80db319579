"""The cold start split over two processes: while a retargeter's first frame compiles its
stages first to last, a second process compiles the stages after the cloud's (smoothing to
LBS) last to first into numba's on-disk cache, where the first one finds them when it gets
there; they meet in the middle, and the first frame stops it.

numba compiles on one core at a time (its compiler holds a global lock), and a fresh
install's first frame compiles about 100 kernel signatures; on a machine with two or more
cores the second process takes a share of them off the critical path. Before the later
stages it compiles what the first process meets last on its way to them (SKIN at the end of
``set_target``; with the source fit, its pose from a reading, its shape's rows and the end
of its Gauss-Newton step). It says which later stage it is compiling, and the stream waits
for that one rather than compile it too. It starts only when numba first compiles one of
minretarget's kernels in a process (a warm cache never starts it), and at most once per
pipeline config per process; it shares numba's cache location (the package's
``__pycache__`` or ``NUMBA_CACHE_DIR``) through its environment. Set
``MINRETARGET_COMPILE_AHEAD=0`` to compile everything in the calling process.

Its stages see the shipped weights and, as a target, the shipped body model's mean body
(its skeleton given, SKIN run on it), and a T-pose frame: numba compiles per argument type,
not value, so any weights, target and frame of the same dtypes and layouts give the same
kernels. What it has not compiled when it is stopped, or if it fails, the caller compiles.

    python -m minretarget._compile_ahead '<PipelineConfig JSON>'
"""
import gc
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np

from .conventions import NUM_JOINTS
from .fit import PARAMETERS, apply_step, body_model, local_from_joints, shape_rows
from .pipeline import PipelineConfig
from .stages import Frame
from .weights import load_weights

SWITCH = "MINRETARGET_COMPILE_AHEAD"
STOP_S = 2.0          # seconds a stopped process is given to leave before it is killed
WAIT_S = 60.0         # the most a stream waits for a stage being compiled there
BEGIN, END = "begin", "end"     # what it says of each later stage

_started = set()        # the configs (JSON) a second process was started for in this process


def _cores():
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:                          # not Linux
        return os.cpu_count() or 1


def start(config):
    """A ``SecondProcess`` compiling the later stages of ``config`` (a ``PipelineConfig``),
    or None: switched off, one core, no Python executable known, or already started for
    this config in this process."""
    key = config.to_json()
    if (os.environ.get(SWITCH, "1") == "0" or _cores() < 2 or not sys.executable
            or key in _started):
        return None
    _started.add(key)
    # This very package first on its path (a checkout on sys.path, not installed, too), so
    # it compiles the same source files into the same cache.
    package_root = str(Path(__file__).resolve().parents[1])
    path = os.pathsep.join(filter(None, (package_root, os.environ.get("PYTHONPATH"))))
    try:
        process = subprocess.Popen(
            [sys.executable, "-m", "minretarget._compile_ahead", key],
            env={**os.environ, SWITCH: "0", "PYTHONPATH": path}, stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    except OSError:                                 # cannot start a process here: go on alone
        return None
    return SecondProcess(process)


class SecondProcess:
    """The second process as the stream sees it: which later stages it has begun and ended
    (it says so on its standard output, a line each), so that the stream waits for one it is
    compiling (nearly done by then) rather than compile it a second time."""

    def __init__(self, process):
        self.process = process
        self._said = threading.Condition()
        self._begun, self._ended, self._gone = set(), set(), False
        threading.Thread(target=self._listen, name="minretarget-compile-ahead",
                         daemon=True).start()

    def _listen(self):
        for line in self.process.stdout:
            word, _, stage = line.strip().partition(" ")
            with self._said:
                (self._begun if word == BEGIN else self._ended).add(stage)
                self._said.notify_all()
        with self._said:
            self._gone = True
            self._said.notify_all()

    def await_stage(self, name):
        """Return once stage ``name`` is not being compiled there (at most ``WAIT_S``)."""
        with self._said:
            if name in self._begun:
                self._said.wait_for(lambda: name in self._ended or self._gone, WAIT_S)

    def stop(self):
        """Stop it, done or not: the stream has compiled the rest itself. Asked first (it
        leaves no half-written file in numba's cache), killed after ``STOP_S``."""
        self.process.terminate()
        try:
            self.process.wait(timeout=STOP_S)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()


class _Stopped(Exception):
    """Raised in this process by ``stop``'s SIGTERM: numba removes a cache file it was
    writing on any Exception."""


def _raise_stopped(signum, frame):
    raise _Stopped


def later_stages_frame(tpose_joints):
    """A frame with every field the stages after the cloud's read, of the types the calling
    process's frames have (numba compiles per type, not value): the T-pose, unturned."""
    count = len(tpose_joints)
    rotations = np.zeros((count, 4), dtype=np.float32)
    rotations[:, 0] = 1.0                            # identity quaternions (w, x, y, z)
    return Frame(0, None, tpose_joints.copy(), rotations, np.zeros(3, dtype=np.float32),
                 tpose_joints.copy(), np.tile(np.eye(3, dtype=np.float32), (count, 1, 1)))


def _fit_tail(model):
    """Compile what the fit's first frame meets last (the shape's rows, and the last kernel
    of a Gauss-Newton step, ``fit._gauss_newton``), with the arguments' types it gives them:
    the stream meets them seconds into the fit, by which time they are in the cache. (The
    two processes' shares of the work are about even so: with more here, the stream waits
    for the second process's SMRM.)"""
    local = np.tile(np.eye(3), (NUM_JOINTS, 1, 1))
    shape_rows(model, local, np.zeros(1, np.int64), np.zeros((1, 3)))
    apply_step(local, np.zeros(3), local.copy(), np.zeros(PARAMETERS))


def main(argv=None):
    signal.signal(signal.SIGTERM, _raise_stopped)
    # This process only compiles: Python's cyclic garbage collector would take about 8 % of
    # its time (docs/runtime_notes.md), and nothing it makes lives long.
    gc.disable()
    from .retargeter import Retargeter              # here: retargeter imports this module
    config_json, = sys.argv[1:] if argv is None else argv
    config = PipelineConfig.from_json(config_json)
    retargeter = Retargeter(load_weights(None), config, warn=False)
    model = body_model()
    points, tpose_joints = model.points.astype(np.float32), model.joints.astype(np.float32)
    # First what the calling process comes to last before the later stages: SKIN, at the
    # end of its set_target, and (with the fit) the fit's pose of its model like the
    # reading (``local_from_joints``) and the end of its first frame (``_fit_tail``).
    retargeter.set_target(points, tpose_joints=tpose_joints)
    if config.fit_source is not None:
        local_from_joints(tpose_joints, tpose_joints)
        _fit_tail(model)
    # Then the stages after the cloud's, last to first, each at a stream's start and after
    # it: the calling process compiles them first to last, and finds the rest here.
    for stage in reversed([stage for stage in retargeter.stages if not stage.reads_cloud]):
        print(BEGIN, stage.name, flush=True)
        state, _ = stage.step(None, later_stages_frame(tpose_joints))
        stage.step(state, later_stages_frame(tpose_joints))
        print(END, stage.name, flush=True)


if __name__ == "__main__":
    main()
