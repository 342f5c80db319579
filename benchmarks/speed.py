"""Speed of the minretarget runtime, against the torch reference and onnxruntime.

    python benchmarks/speed.py [--quick] [--weights FILE] [--threads N] [--json OUT.json]
    python benchmarks/speed.py --neighbour [--weights FILE] [--json OUT.json]

One process, batch 1 streaming (one frame at a time, as online use), with N threads everywhere
(BLAS under numba, torch, onnxruntime):
  * the headline: the shipped default pipeline (``minretarget.pipeline.DEFAULT_PRESET``, with
    the source fit) on a real body stream, the shipped sample's 68 clouds (P = 2,048,
    V = 13,718, the default setting) through ``Retargeter.step``, several passes: median ms
    per frame after the fit's calibration frames, those frames' total, and the 60 frames/s
    (16.67 ms) check. Random clouds would not do here: the fit finds no body in them and takes
    its cheaper lost-body path every frame;
  * the engines like for like: minretarget running what the torch reference
    (training/models/pipeline.py) runs, ``RUNTIME_CONFIG`` there (SKR, refiner, denoiser,
    SMRM, FK, LBS; no fit, smoothing or foot lock), against that reference in eager mode and,
    at the default setting, under torch.compile, and onnxruntime on the same step exported to
    ONNX; the same weights, target and clouds for every engine (at the default setting the
    sample's, elsewhere random body-sized clouds); ms per frame of each of its stages and end
    to end, at P source points in {1024, 2048, 6890} and V target points in {6890, 13718}
    (--quick: the default setting only), and their floating-point operations per frame;
  * this machine's float32 matrix-multiply peak (the best of a few products), and SKR's
    fraction of it;
  * numba's compile time with an empty cache and import + first frame from the on-disk cache,
    each in a fresh process, apart from the steady state;
  * resident memory along a 10,000-frame stream of the default pipeline (--quick: 2,000; the
    sample played forwards and backwards, over and over), which must stay flat;
  * offline throughput of the default pipeline: the sample as one sequence through
    ``Retargeter.retarget_sequence``.
--neighbour measures only this, without torch: the shipped sample's 68 clouds (P = 2,048,
V = 13,718) streamed through ``Retargeter.step`` with 1 and 2 BLAS threads, alone and beside
a busy neighbour (another process spinning on one core, as on a shared machine), with the
``regressed`` and ``fitted`` pipeline presets (``minretarget.pipeline``): median ms per frame
after the fit's calibration frames, and those frames' total.
Ratios > 1 mean minretarget is faster. Without --weights it uses the shipped weights.
Needs the ``bench`` extra (torch, onnxruntime, onnxscript, threadpoolctl).
"""
import argparse
import importlib.util
import json
import logging
import os
import platform
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from minretarget.cli import int_at_least
from minretarget.denoise import denoise_joints, hidden_shape
from minretarget.fit import FitSettings
from minretarget.kinematics import forward_kinematics, skinning_transforms
from minretarget.pipeline import DEFAULT_PRESET
from minretarget.refine import MAX_POINTS, refine_joints
from minretarget.retargeter import Retargeter
from minretarget.skin import linear_blend_skinning
from minretarget.skr import regress_joints
from minretarget.smrm import retarget_step
from minretarget.sources import load_sample

sys.path.insert(0, str(Path(__file__).resolve().parent))
from accuracy import command_line, load_measured, write_text  # noqa: E402

DEFAULT_SETTING = (2048, 13718)        # the shipped sample's clouds and target
SETTINGS = [(p, v) for p in (1024, 2048, 6890) for v in (6890, 13718)]
TARGET_FPS = 60                         # issue 39: end to end, one thread, the default setting
# What the stages are called in a pipeline's label (``pipeline_label``), by stage name.
STAGE_LABELS = {"thinning": "thinning", "skr": "SKR", "facing_check": "facing check",
                "source_fit": "source fit", "smoothing": "smoothing", "denoiser": "denoiser",
                "smrm": "SMRM", "fk": "FK", "foot_lock": "foot lock", "lbs": "LBS"}


# ----------------------------------------------------------------------------- inputs

def body_cloud(rng, count):
    """A body-sized Gaussian cloud (count, 3), metres (speed does not depend on its shape)."""
    return (rng.standard_normal((count, 3)) * [0.25, 0.45, 0.12] + [0, 0.9, 0]).astype(np.float32)


def setting_inputs(points, vertices):
    """(target points (V, 3), its faces or None, 8 or more source clouds (P, 3)) for a setting:
    the shipped sample's at the default setting, random body-sized clouds elsewhere."""
    if (points, vertices) == DEFAULT_SETTING:
        source, target_points, faces, _ = load_sample()
        return target_points, faces, list(source.frames)
    rng = np.random.default_rng(0)
    return body_cloud(rng, vertices), None, [body_cloud(rng, points) for _ in range(8)]


def cycling(frames):
    """A function giving ``frames`` in turn, over and over, one a call."""
    counter = iter(range(10 ** 9))
    return lambda: frames[next(counter) % len(frames)]


def pipeline_label(retargeter):
    """The stages a retargeter's frames go down, as "SKR->refiner->...->LBS"."""
    labels = [STAGE_LABELS[stage.name] for stage in retargeter.stages]
    if retargeter.config.refine and retargeter.weights.refine is not None:
        labels.insert(labels.index("SKR") + 1, "refiner")
    return "->".join(labels)


def time_per_call(function, repeats, warmup=3):
    """Median seconds per call after ``warmup`` calls."""
    for _ in range(warmup):
        function()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


# ----------------------------------------------------------------------------- FLOPs

def _chain_macs(in_width, widths):
    """Multiply-adds per row of linear layers in_width -> widths[0] -> widths[1] ..."""
    total = 0
    for width in widths:
        total += in_width * width
        in_width = width
    return total


def stage_flops(config, points, vertices):
    """Floating-point operations per frame of each stage (2 per multiply-add; biases,
    activations and the max-pool left out), for P = ``points`` and V = ``vertices``."""
    w, heads, j = config.skr_point_widths, config.skr_head_widths, config.num_joints
    per_point = (_chain_macs(3, w) + _chain_macs(w[0], w)          # the two STNs' point layers
                 + _chain_macs(3, w) + 3 * 3 + w[0] * w[0])         # regressor + x T_3, x T_w0
    per_cloud = sum(_chain_macs(w[-1], list(heads) + [out]) for out in (9, w[0] ** 2, j * 3))
    h = config.smrm_hidden
    gru = 0
    for in_width in (j * 3 + 3, h + j * 3):                          # encoder, decoder
        for layer in range(config.smrm_layers):
            gru += 3 * h * ((in_width if layer == 0 else h) + h)
    return {"skr": 2 * (points * per_point + per_cloud),
            "smrm_step": 2 * (gru + h * (j * 4 + 3)),
            "fk": 2 * j * (27 + 9),                                  # R_parent R_local, R t
            "lbs": 2 * vertices * j * 12 + 2 * vertices * 12,        # blend maps, apply
            "refine": refine_flops(config, points), "denoise": denoise_flops(config)}


def denoise_flops(config):
    """The skeleton denoiser's FLOPs per frame: its GRU layers and head, on the skeleton and
    on its mirror image."""
    h, j = config.denoise_hidden, config.num_joints
    gru = sum(3 * h * ((j * 3 + 3 if layer == 0 else h) + h)
              for layer in range(config.denoise_layers))
    return 2 * 2 * (gru + h * j * 3) if config.denoises else 0


def refine_flops(config, points):
    """The joint refiner's FLOPs per frame: every joint's K nearest points through the point
    layers, then the head once per joint (the neighbour search left out)."""
    if not config.refines:
        return 0
    j, widths = config.num_joints, config.refine_point_widths
    k = min(config.refine_neighbours, -(-points // -(-points // MAX_POINTS)))   # after thinning
    head = _chain_macs(widths[-1] + 4 * j, list(config.refine_head_widths) + [3])
    return 2 * j * (k * _chain_macs(3, widths) + head)


def matmul_peak(threads, repeats=5):
    """float32 GFLOP/s of NumPy's BLAS with ``threads`` threads: the best over square
    products and SKR's own widest layer (one size alone can under-read the peak)."""
    rng = np.random.default_rng(0)
    best = 0.0
    for m, k, n in ((512, 512, 512), (1024, 1024, 1024), (2048, 2048, 2048),
                    (2048, 128, 256), (8192, 256, 256)):
        a = rng.standard_normal((m, k)).astype(np.float32)
        b = rng.standard_normal((k, n)).astype(np.float32)
        with threadpool_limits(threads, user_api="blas"):
            seconds = time_per_call(lambda: a @ b, repeats, warmup=2)
        best = max(best, 2 * m * k * n / seconds / 1e9)
    return best


# ----------------------------------------------------------------------------- minretarget

def minretarget_stages(weights, config, target_points, faces, frames, repeats, workers):
    """ms per frame of each runtime stage, and end to end through ``Retargeter.step`` with
    ``config``, streaming ``frames`` in turn; and that retargeter."""
    retargeter = Retargeter(weights, config, warn=False, workers=workers)
    retargeter.set_target(target_points, faces)
    target = retargeter.target
    source_joints = regress_joints(frames[0], weights.skr)
    rotations, root, state = retarget_step(weights.smrm, None, source_joints, target.tpose_joints)
    joints, global_rotations = forward_kinematics(rotations, root, target.tpose_joints)
    transforms = skinning_transforms(joints, global_rotations, target.tpose_joints)
    denoise_hidden = np.zeros(hidden_shape(weights.denoise), np.float32)
    cloud = cycling(frames)
    stages = {
        "skr": lambda: regress_joints(cloud(), weights.skr, workers),
        "refine": lambda: (refine_joints(cloud(), source_joints, weights.refine,
                                         weights.config.refine_neighbours)
                           if weights.refine is not None else None),
        "denoise": lambda: (denoise_joints(weights.denoise, denoise_hidden, source_joints,
                                           source_joints[0])
                            if weights.denoise is not None else None),
        "smrm_step": lambda: retarget_step(weights.smrm, state, source_joints,
                                           target.tpose_joints,
                                           target_leg_length=target.leg_length),
        "fk": lambda: forward_kinematics(rotations, root, target.tpose_joints),
        "lbs": lambda: linear_blend_skinning(target.points, target.skin_weights, transforms),
        "end_to_end": lambda: retargeter.step(cloud()),
    }
    ms = {name: 1e3 * time_per_call(f, repeats) for name, f in stages.items()}
    return ms, retargeter


# ----------------------------------------------------------------------------- torch, ONNX

def torch_reference(weights, target):
    """The torch ReferenceRetargeter holding the same weights and the runtime's target rig."""
    import torch

    from training.export import import_weights
    from training.models.pipeline import ReferenceRetargeter
    reference = ReferenceRetargeter(weights.config)
    import_weights(weights, reference.skr, reference.smrm, reference.skin, reference.refine,
                   reference.denoise)
    reference.eval()
    reference.target_points = torch.from_numpy(target.points)
    reference.tpose_joints = torch.from_numpy(target.tpose_joints)
    reference.skin_weights = torch.from_numpy(target.skin_weights)
    reference.leg_length = torch.tensor(target.leg_length, dtype=torch.float32)
    return reference


def max_difference_vs_torch(retargeter, reference, frames):
    """The largest |minretarget - torch| (metres) over the posed target points of ``frames``
    streamed through both from a stream's start: the check that the two engines compute the
    same thing before they are timed against each other."""
    import torch
    retargeter.reset()
    reference.state = None
    return max(float(np.abs(retargeter.step(cloud).vertices
                            - reference.step(torch.from_numpy(cloud))["vertices"].numpy()).max())
               for cloud in frames)


def torch_times(reference, frames, repeats, compile_too):
    """ms per frame: torch eager SKR and end to end; torch.compile end to end (or why not)."""
    import torch
    tensor = cycling([torch.from_numpy(f) for f in frames])
    with torch.no_grad():
        _, state = reference(tensor(), None)
        out = {"skr": 1e3 * time_per_call(lambda: reference.skr(tensor()[None]), repeats),
               "end_to_end": 1e3 * time_per_call(lambda: reference(tensor(), state), repeats)}
        if compile_too:
            try:
                compiled = torch.compile(reference)
                start = time.perf_counter()
                compiled(tensor(), state)
                out["compile_s"] = time.perf_counter() - start
                out["compiled_end_to_end"] = 1e3 * time_per_call(
                    lambda: compiled(tensor(), state), repeats)
            except Exception as error:   # a missing compiler, an unsupported op: report it
                out["compile_error"] = f"{type(error).__name__}: {str(error)[:300]}"
    return out


def onnx_times(reference, frames, threads, repeats):
    """ms per frame of onnxruntime on the step exported to ONNX (state as inputs/outputs)."""
    import onnxruntime
    import torch

    from training.models.smrm import MotionState

    class FlatStep(torch.nn.Module):
        """ReferenceRetargeter.forward with the recurrent state as plain tensors."""

        def __init__(self, reference):
            super().__init__()
            self.reference = reference

        def forward(self, points, *state):
            smrm = MotionState(*state[:len(MotionState._fields)])
            out, (smrm, denoise) = self.reference(
                points, (smrm, state[len(MotionState._fields):] or None))
            return (out["vertices"], out["joints"], out["rotations"], out["root"], *smrm,
                    *(denoise or ()))

    with torch.no_grad():
        _, (smrm_state, denoise_state) = reference(torch.from_numpy(frames[0]), None)
    state = tuple(smrm_state) + tuple(denoise_state or ())
    inputs = (torch.from_numpy(frames[1]),) + state
    names = ["points", *MotionState._fields] + (["denoise_hidden", "denoise_root"]
                                                if denoise_state else [])
    start = time.perf_counter()
    # The exporter's notices (torchvision absent, GRU weights re-assigned while tracing, a
    # deprecated pytree check) say nothing about this model: keep the benchmark's output
    # readable.
    logging.getLogger("torch.onnx").setLevel(logging.ERROR)
    with torch.no_grad(), tempfile.TemporaryDirectory() as directory, \
            warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="The tensor attributes", category=UserWarning)
        warnings.filterwarnings("ignore", message=".*LeafSpec", category=FutureWarning)
        path = os.path.join(directory, "step.onnx")
        torch.onnx.export(FlatStep(reference).eval(), inputs, path, input_names=names,
                          dynamo=True, external_data=False, verbose=False)
        with open(path, "rb") as file:
            model = file.read()
    export_s = time.perf_counter() - start
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.graph_optimization_level = onnxruntime.GraphOptimizationLevel.ORT_ENABLE_ALL
    session = onnxruntime.InferenceSession(model, options,
                                           providers=["CPUExecutionProvider"])
    feeds = [{"points": f, **{n: s.numpy() for n, s in zip(names[1:], state)}} for f in frames]
    # Check it computes what torch does before timing it.
    vertices = session.run(None, feeds[1])[0]
    with torch.no_grad():
        expected = reference(torch.from_numpy(frames[1]),
                             (smrm_state, denoise_state))[0]["vertices"].numpy()
    error = float(np.abs(vertices - expected).max())
    feed = cycling(feeds)
    ms = 1e3 * time_per_call(lambda: session.run(None, feed()), repeats)
    return {"end_to_end": ms, "export_s": export_s, "max_abs_diff_vs_torch_m": error}


# ----------------------------------------------------------------------------- cold start

COMPILE_SCRIPT = """
import json, time; start, cpu_start = time.perf_counter(), time.process_time()
from numba.core import event

kernels, stack = {{}}, []     # "module.name" -> [signatures compiled, CPU s less nested ones]


class Compiles(event.Listener):
    def on_start(self, ev):
        stack.append([time.process_time(), 0.0])

    def on_end(self, ev):
        began, nested = stack.pop()
        took = time.process_time() - began
        if stack:
            stack[-1][1] += took
        function = ev.data["dispatcher"].py_func
        entry = kernels.setdefault(f"{{function.__module__}}.{{function.__qualname__}}", [0, 0.0])
        entry[0] += 1
        entry[1] += took - nested


event.register("numba:compile", Compiles())
import numpy as np
from minretarget.retargeter import Retargeter
imported = time.perf_counter()
r = Retargeter.from_weights({weights!r}, {preset!r}, warn=False)
rng = np.random.default_rng(0)
cloud = lambda n: (rng.standard_normal((n, 3)) * [0.25, 0.45, 0.12] + [0, 0.9, 0])
r.set_target(cloud(13718).astype(np.float32)); r.step(cloud(2048).astype(np.float32))
import resource
children = resource.getrusage(resource.RUSAGE_CHILDREN)
print(json.dumps({{"import_s": imported - start,
                  "import_to_first_frame_s": time.perf_counter() - start,
                  "cpu_s": time.process_time() - cpu_start,
                  "second_process_cpu_s": children.ru_utime + children.ru_stime,
                  "kernels": kernels}}))
"""


def first_frame(weights_path, preset, cache, ahead=True):
    """One fresh process with numba's cache in ``cache``: import and total time (wall) to the
    first retargeted frame of ``preset`` (the weights and the first target included), its CPU
    time (steadier than the wall time on a shared machine) and that of the second process
    that compiles the later stages meanwhile (``minretarget._compile_ahead``; ``ahead``
    False: switched off, all in one process), the load average before it, and what numba
    compiled in the first process: signatures, and the top kernels by CPU seconds of their
    own compile (less the kernels and numba overloads compiled inside it)."""
    load = os.getloadavg()[0]
    result = subprocess.run(
        [sys.executable, "-c", COMPILE_SCRIPT.format(weights=weights_path, preset=preset)],
        env={**os.environ, "NUMBA_CACHE_DIR": cache,
             "MINRETARGET_COMPILE_AHEAD": "1" if ahead else "0"},
        capture_output=True, text=True, check=True)
    run = json.loads(result.stdout.splitlines()[-1])
    kernels = run.pop("kernels")
    top = sorted(kernels.items(), key=lambda item: -item[1][1])[:15]
    return {**run, "load_average_before": load,
            "signatures_compiled": sum(count for count, _ in kernels.values()),
            "top_compiles": [{"kernel": name, "signatures": count, "cpu_s": round(seconds, 3)}
                             for name, (count, seconds) in top]}


def compile_times(weights_path, preset="default", repeats=1):
    """Numba's cold start (issue 40): ``repeats`` times, a fresh process with an empty cache
    (as a fresh install runs it: the later stages compiled in a second process), one with an
    empty cache compiling everything itself, then one from the cache (``first_frame`` each).
    "cold", "cold_one_process" and "warm" are the runs of median wall time; "cold_runs" has
    every cold run's wall and CPU seconds and load."""
    colds, singles, warms = [], [], []
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as cache:
            colds.append(first_frame(weights_path, preset, cache))
            warms.append(first_frame(weights_path, preset, cache))
        with tempfile.TemporaryDirectory() as cache:
            singles.append(first_frame(weights_path, preset, cache, ahead=False))

    def median(runs):
        return sorted(runs, key=lambda run: run["import_to_first_frame_s"])[len(runs) // 2]

    def summary(runs):
        return [{key: run[key] for key in ("import_to_first_frame_s", "cpu_s",
                                           "second_process_cpu_s", "load_average_before")}
                for run in runs]
    return {"preset": preset, "cold": median(colds), "cold_one_process": median(singles),
            "warm": median(warms), "cold_runs": summary(colds),
            "cold_one_process_runs": summary(singles)}


# ----------------------------------------------------------------------------- memory, offline

def resident_mb():
    """This process's resident set size, MB (Linux /proc)."""
    with open("/proc/self/statm") as file:
        return int(file.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2 ** 20


def stream_memory(retargeter, frames, count, every=500):
    """Resident MB sampled every ``every`` frames along a ``count``-frame stream."""
    retargeter.reset()
    samples = []
    for index in range(count):
        retargeter.step(frames[index % len(frames)])
        if (index + 1) % every == 0:
            samples.append(round(resident_mb(), 2))
    return samples


def offline_fps(retargeter, frames, repeats=3):
    """Frames per second of ``retarget_sequence`` on ``frames`` as one sequence (the median of
    ``repeats`` runs, after one warm-up run)."""
    sequence = np.stack(frames)
    return len(frames) / time_per_call(lambda: retargeter.retarget_sequence(sequence), repeats,
                                       warmup=1)


# ----------------------------------------------------------------------------- the sample

def sample_stream_times(weights, preset, blas_threads, workers=1):
    """(median ms per frame after the calibration frames, seconds of those frames) of the
    shipped sample streamed through ``Retargeter.step``, after one warm-up pass."""
    source, target_points, faces, _ = load_sample()
    clouds = list(source.frames)
    kept = FitSettings().calibration_frames
    retargeter = Retargeter(weights, preset, warn=False, workers=workers)
    retargeter.set_target(target_points, faces)
    with threadpool_limits(blas_threads, user_api="blas"):
        for points in clouds[:kept + 2]:                                  # warm-up
            retargeter.step(points)
        retargeter.reset()
        seconds = []
        for points in clouds:
            start = time.perf_counter()
            retargeter.step(points)
            seconds.append(time.perf_counter() - start)
    return 1e3 * float(np.median(seconds[kept:])), float(np.sum(seconds[:kept]))


def default_pipeline_figures(weights, blas_threads, workers, passes, memory_frames):
    """The headline: the shipped default pipeline on the sample at the default setting.
    ``passes`` times ``sample_stream_times`` (a fresh retargeter each): the median over the
    passes of their ms per frame after the fit's calibration frames, its spread (min, max,
    every pass), the calibration frames' seconds and the 60 frames/s check; then, on one more
    retargeter, resident memory along ``memory_frames`` frames (``stream_memory``) and offline
    frames/s (``offline_fps``)."""
    runs = [sample_stream_times(weights, "default", blas_threads, workers)
            for _ in range(passes)]
    ms, calibration_s = [run[0] for run in runs], [run[1] for run in runs]
    median = float(np.median(ms))
    target_points, faces, clouds = setting_inputs(*DEFAULT_SETTING)
    retargeter = Retargeter(weights, warn=False, workers=workers)
    retargeter.set_target(target_points, faces)
    # Played forwards then backwards, over and over: the body never jumps, so the fit keeps
    # tracking it (a jump from the last cloud to the first loses it for a few frames).
    rss = stream_memory(retargeter, clouds + clouds[-2:0:-1], memory_frames)
    return {"preset": DEFAULT_PRESET, "pipeline": pipeline_label(retargeter),
            "P": DEFAULT_SETTING[0], "V": DEFAULT_SETTING[1], "stream_frames": len(clouds),
            "calibration_frames": FitSettings().calibration_frames, "passes": passes,
            "ms_per_frame": median, "ms_per_frame_min": min(ms), "ms_per_frame_max": max(ms),
            "ms_per_frame_passes": ms, "fps": 1e3 / median,
            "calibration_frames_s": float(np.median(calibration_s)),
            "calibration_frames_s_passes": calibration_s,
            "target_fps": TARGET_FPS, "target_ms": 1e3 / TARGET_FPS,
            "meets_target_fps": median <= 1e3 / TARGET_FPS,
            "memory_rss_mb": rss, "memory_frames": memory_frames,
            "memory_growth_mb": rss[-1] - rss[1] if len(rss) > 1 else 0.0,
            "offline_fps": offline_fps(retargeter, clouds)}


def neighbour_times(weights):
    """ms per frame for each (preset, BLAS threads, busy neighbour) on the shipped sample."""
    rows = []
    for preset in ("regressed", "fitted"):
        for blas_threads in (1, 2):
            for busy in (False, True):
                neighbour = (subprocess.Popen([sys.executable, "-c", "while True: pass"])
                             if busy else None)
                try:
                    ms, calibration_s = sample_stream_times(weights, preset, blas_threads)
                finally:
                    if neighbour is not None:
                        neighbour.kill()
                        neighbour.wait()
                rows.append({"preset": preset, "blas_threads": blas_threads,
                             "busy_neighbour": busy, "ms_per_frame": ms,
                             "fps": 1e3 / ms, "first_frames_s": calibration_s,
                             "load_average": os.getloadavg()})
                print(f"{preset:>9}, BLAS threads {blas_threads}, busy "
                      f"neighbour {busy!s:>5}: {ms:7.2f} ms/frame ({1e3 / ms:6.1f} frames/s); "
                      f"first {FitSettings().calibration_frames} frames {calibration_s:.2f} s",
                      flush=True)
    return rows


# ----------------------------------------------------------------------------- main

# The modules the engines' comparison imports (setup.py's "bench" extra).
COMPARED_ENGINES = ("torch", "onnxruntime", "onnx", "onnxscript")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="the default setting only")
    parser.add_argument("--weights", help="a weights file (default: the shipped weights)")
    parser.add_argument("--threads", type=int_at_least(1), default=os.cpu_count(),
                        help="threads for BLAS, torch and onnxruntime (default: all cores)")
    parser.add_argument("--workers", type=int_at_least(1), default=1,
                        help="minretarget's SKR threads (Retargeter(workers=...)); over 1, "
                             "each with one BLAS thread; default 1, the runtime's default, "
                             "where BLAS gets --threads")
    parser.add_argument("--json", help="write the results here")
    parser.add_argument("--neighbour", action="store_true",
                        help="only the busy-neighbour and source-fit streams (no torch)")
    args = parser.parse_args()
    if args.neighbour:
        weights, record = load_measured(args.weights)
        results = {**record, "neighbour": neighbour_times(weights),
                   "machine": {"processor": platform.processor() or platform.machine(),
                               "cores": os.cpu_count()}}
        if args.json:
            write_text(args.json, json.dumps(results, indent=2))
        return
    # Checked now, not after minutes of timing: the engines compared with (the bench extra)
    missing = [name for name in COMPARED_ENGINES if importlib.util.find_spec(name) is None]
    if missing:
        parser.error(f"the engines compared with are not installed ({', '.join(missing)}): "
                     f"pip install -e \".[bench]\" (or run --neighbour, which needs none)")
    workers = args.workers
    blas_threads = 1 if workers > 1 else args.threads
    import torch

    from training.models.pipeline import RUNTIME_CONFIG
    torch.set_num_threads(args.threads)
    weights, record = load_measured(args.weights)
    repeats = 15 if args.quick else 30
    results = {**record, "quick": args.quick, "threads": args.threads,
               "minretarget_workers": workers, "minretarget_blas_threads": blas_threads,
               "config": json.loads(weights.config.to_json()),
               "machine": {"processor": platform.processor() or platform.machine(),
                           "cores": os.cpu_count()},
               "settings": []}
    with threadpool_limits(blas_threads, user_api="blas"):
        results["matmul_peak_gflops"] = matmul_peak(args.threads)
        print(f"float32 matmul peak, {args.threads} threads: "
              f"{results['matmul_peak_gflops']:.1f} GFLOP/s")
        results["compile"] = compile_times(args.weights)
        print(f"numba: {json.dumps(results['compile'])}")
        stream = results["default_pipeline_stream"] = default_pipeline_figures(
            weights, blas_threads, workers, passes=5 if args.quick else 10,
            memory_frames=2000 if args.quick else 10000)
        rss = stream["memory_rss_mb"]
        verdict = (f"{TARGET_FPS} frames/s ({stream['target_ms']:.2f} ms) "
                   f"{'met' if stream['meets_target_fps'] else 'NOT met'}")
        print(f"the default pipeline ({stream['preset']}: {stream['pipeline']}) on the shipped "
              f"sample, P={stream['P']}, V={stream['V']}, {stream['passes']} passes: "
              f"{stream['ms_per_frame']:.2f} ms/frame after the first "
              f"{stream['calibration_frames']} frames (passes {stream['ms_per_frame_min']:.2f}"
              f"-{stream['ms_per_frame_max']:.2f}), {stream['fps']:.1f} frames/s: {verdict}; "
              f"the first {stream['calibration_frames']} frames "
              f"{stream['calibration_frames_s']:.2f} s; "
              f"resident memory {rss[0]:.1f} -> {rss[-1]:.1f} MB over "
              f"{stream['memory_frames']} frames; offline {stream['offline_fps']:.1f} frames/s",
              flush=True)
        header = ("P", "V", "skr", "refine", "denoise", "smrm_step", "fk", "lbs", "end_to_end",
                  "fps", "torch", "compiled", "onnxrt")
        print("engines, the same computation (training/models/pipeline.py's RUNTIME_CONFIG), "
              "ms per frame:")
        print(" ".join(f"{h:>10}" for h in header))
        for p, v in [DEFAULT_SETTING] if args.quick else SETTINGS:
            target_points, faces, frames = setting_inputs(p, v)
            ms, retargeter = minretarget_stages(weights, RUNTIME_CONFIG, target_points, faces,
                                                frames, repeats, workers)
            reference = torch_reference(weights, retargeter.target)
            row = {"P": p, "V": v, "pipeline": pipeline_label(retargeter),
                   "sample_clouds": (p, v) == DEFAULT_SETTING, "ms": ms,
                   "max_abs_diff_vs_torch_m": max_difference_vs_torch(retargeter, reference,
                                                                      frames[:8]),
                   "fps_end_to_end": 1e3 / ms["end_to_end"],
                   "flops": stage_flops(weights.config, p, v),
                   "torch": torch_times(reference, frames, repeats,
                                        compile_too=(p, v) == DEFAULT_SETTING),
                   "onnxruntime": onnx_times(reference, frames, args.threads, repeats)}
            results["settings"].append(row)
            print(" ".join(f"{x:>10}" for x in (p, v)) + " " + " ".join(
                f"{ms[k]:>8.3f}ms" for k in ("skr", "refine", "denoise", "smrm_step", "fk",
                                             "lbs", "end_to_end"))
                + f" {row['fps_end_to_end']:>10.1f} {row['torch']['end_to_end']:>8.3f}ms "
                + (f"{row['torch']['compiled_end_to_end']:>8.3f}ms"
                   if "compiled_end_to_end" in row["torch"] else f"{'-':>10}")
                + f" {row['onnxruntime']['end_to_end']:>8.3f}ms", flush=True)
    row = next(r for r in results["settings"] if (r["P"], r["V"]) == DEFAULT_SETTING)
    ours = row["ms"]["end_to_end"]
    compiled = row["torch"].get("compiled_end_to_end")
    engines = results["engine_comparison"] = {
        "pipeline": row["pipeline"], "config": "training.models.pipeline.RUNTIME_CONFIG",
        "P": DEFAULT_SETTING[0], "V": DEFAULT_SETTING[1], "clouds": "the shipped sample's",
        "max_abs_diff_vs_torch_m": row["max_abs_diff_vs_torch_m"],
        "minretarget_ms": ours, "torch_eager_ms": row["torch"]["end_to_end"],
        "torch_compile_ms": compiled, "onnxruntime_ms": row["onnxruntime"]["end_to_end"],
        "ratio_vs_torch": row["torch"]["end_to_end"] / ours,
        "ratio_vs_torch_compile": compiled / ours if compiled is not None else None,
        "ratio_vs_onnxruntime": row["onnxruntime"]["end_to_end"] / ours}
    results.update({
        "skr_gflops": row["flops"]["skr"] / row["ms"]["skr"] / 1e6,
        "skr_fraction_of_peak": row["flops"]["skr"] / row["ms"]["skr"] / 1e6
        / results["matmul_peak_gflops"],
        "warm_start_s": results["compile"]["warm"]["import_to_first_frame_s"],
    })
    compiled = (f"{engines['ratio_vs_torch_compile']:.2f}x torch.compile"
                if compiled is not None
                else f"torch.compile failed ({row['torch']['compile_error']})")
    print(f"engines at P={DEFAULT_SETTING[0]}, V={DEFAULT_SETTING[1]} ({engines['pipeline']}, "
          f"the sample's clouds; outputs within {engines['max_abs_diff_vs_torch_m']:.1e} m of "
          f"torch's): minretarget {ours:.2f} ms, {engines['ratio_vs_torch']:.2f}x "
          f"torch eager, {compiled}, {engines['ratio_vs_onnxruntime']:.2f}x onnxruntime; SKR at "
          f"{results['skr_gflops']:.1f} GFLOP/s = {100 * results['skr_fraction_of_peak']:.0f}% "
          f"of peak; warm start {results['warm_start_s']:.2f} s")
    print(f"the default pipeline ({stream['preset']}) on the sample: "
          f"{stream['ms_per_frame']:.2f} ms/frame, {stream['fps']:.1f} frames/s, {verdict}")
    if args.json:
        write_text(args.json, json.dumps(results, indent=2))


if __name__ == "__main__":
    command_line(main)
