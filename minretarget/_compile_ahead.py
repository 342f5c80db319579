"""The cold start split over two processes: while a retargeter compiles the stages that read
the cloud (SKR, the refiner, the source fit), a second process compiles the stages after
them (smoothing to LBS) into numba's on-disk cache, where the first one then finds them.

numba compiles on one core at a time (its compiler holds a global lock), and a fresh
install's first frame compiles about 130 kernel signatures; on a machine with two or more
cores the second process takes about half of them off the critical path. It starts only
when numba first compiles one of minretarget's kernels in a process (a warm cache never
starts it), and at most once per pipeline config per process; it shares numba's cache
location (the package's ``__pycache__`` or ``NUMBA_CACHE_DIR``) through its environment.
Set ``MINRETARGET_COMPILE_AHEAD=0`` to compile everything in the calling process.

Its stages see the shipped weights and, as a target, the shipped body model's mean body
(its skeleton given, SKIN run on it): numba compiles per argument type, not value, so any
weights and target of the same dtypes give the same kernels. If it fails or is not done in ``WAIT_S``, the caller compiles what
is missing itself, as without it.

    python -m minretarget._compile_ahead '<PipelineConfig JSON>'
"""
import gc
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from .fit import body_model, local_from_joints
from .nearest import build_grid, nearest
from .pipeline import PipelineConfig
from .weights import load_weights

SWITCH = "MINRETARGET_COMPILE_AHEAD"
WAIT_S = 300.0

_started = set()        # the configs (JSON) a second process was started for in this process


def _cores():
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:                          # not Linux
        return os.cpu_count() or 1


def start(config):
    """A second process compiling the skeleton stages of ``config`` (a ``PipelineConfig``),
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
        return subprocess.Popen(
            [sys.executable, "-m", "minretarget._compile_ahead", key],
            env={**os.environ, SWITCH: "0", "PYTHONPATH": path}, stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    except OSError:                                 # cannot start a process here: go on alone
        return None


def join(process):
    """Wait for ``process`` (from ``start``) to finish; past ``WAIT_S`` it is stopped, and
    the caller compiles what it has not."""
    try:
        process.wait(timeout=WAIT_S)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


def main(argv=None):
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
    # reading (``local_from_joints``) and its cloud's grid and nearest points on its first
    # frame; then the later stages.
    retargeter.set_target(points, tpose_joints=tpose_joints)
    if config.fit_source is not None:
        local_from_joints(tpose_joints, tpose_joints)
        cloud = model.points.copy()                 # float64, as the fit's subsample
        nearest(build_grid(cloud), cloud)
    retargeter.warm_up(skeleton=True)


if __name__ == "__main__":
    main()
