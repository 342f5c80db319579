"""The runtime never needs torch, and its kernels also run as plain Python."""
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

# Make any import of torch fail, then retarget the golden stream with the runtime alone.
SCRIPT = """
import builtins, sys
real_import = builtins.__import__
def guarded(name, *args, **kwargs):
    if name == "torch" or name.startswith("torch."):
        raise ImportError("torch is blocked in this test")
    return real_import(name, *args, **kwargs)
builtins.__import__ = guarded
sys.path.insert(0, {tests!r})
import numpy as np, minretarget
from conftest import GOLDEN
from minretarget.weights import load_weights
with np.load(GOLDEN / "tiny_stream.npz") as data:
    target, counts = data["target"], data["source_counts"][:{frames}]
    points, want = data["source_points"][:counts.sum()], data["torch_vertices"]
retargeter = minretarget.Retargeter(load_weights(GOLDEN / "tiny_weights.npz"),
                                    minretarget.PipelineConfig(
                                        smoothing=None, foot_lock=None, mirror_target=False,
                                        facing_check=False))
retargeter.set_target(target)
frames = np.split(points, np.cumsum(counts)[:-1])
error = max(np.abs(f.vertices - want[t]).max() for t, f in enumerate(retargeter.run(frames)))
assert error < 1e-4, error
assert "torch" not in sys.modules
print("ok", error)
"""


def run_script(frames, **environment):
    script = SCRIPT.format(tests=str(ROOT / "tests"), frames=frames)
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                            cwd=ROOT, env={**os.environ, **environment}, timeout=300)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("ok")


def test_runtime_imports_and_runs_without_torch():
    run_script(frames=60)


def test_kernels_run_as_plain_python_with_jit_disabled():
    run_script(frames=3, NUMBA_DISABLE_JIT="1")
