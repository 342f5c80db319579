"""Throughput of ``minretarget batch``: 1 and 2 local workers, the overhead per pair, Ray.

    python benchmarks/batch.py [--quick] [--repeats N] [--quiet-wait S] [--preset NAME]
                               [--json OUT.json]

The job: the shipped sample's source (CMU walk 08_01, 2048-point clouds) played forward and
backward, tiled to 300 frames (--quick: its 68 frames), onto its target and three stretched
copies of it: 2 sources x 4 targets = 8 pairs, written as npz and bvh, with the pipeline
``--preset`` (the job's option ``preset``; default: ``default``, the package's default preset,
named in the JSON as ``pipeline``); the frames alone and the ``retarget`` processes run the
same pipeline. Measured, each batch started in this process (``batch.run_batch``) with every
pair's frames counted:
  * frames/s with 1 and 2 local workers, and ``scaling_2_workers``, their ratio;
  * ``overhead_fraction``: the time a pair costs in the 1-worker batch beyond retargeting its
    frames (wall / pairs minus the frames' time, measured in this process on a set-up,
    compiled retargeter), over the wall time of one ``minretarget retarget`` process for one
    pair (import, weights, target set-up and frames: what a shell loop pays per pair);
  * ``overhead_split``: that overhead split into what a batch pays once and what each pair
    adds, from the 1-worker batch of the 8 pairs against one of 4 of them (both sources onto
    two of the targets, so the targets per pair stay the same): ``pair_marginal_seconds``, a
    pair's cost, (wall of 8 - wall of 4) / 4; ``batch_fixed_seconds``, the rest of the wall
    of 8 (the workers' start, the job check, the pool's end); ``pair_marginal_overhead_
    seconds``, the marginal pair's cost beyond its frames (its share of the target set-ups);
    ``fixed_seconds_per_pair``, the fixed seconds over 8 pairs. The overhead per pair is
    their sum. ``local_1_pair_seconds``: each pair's seconds in the best 1-worker batch, in
    the order run (the first pays the worker's set-up, each new target its set-up);
    ``overhead_parts``: that batch's overhead (times 8) split without a second batch: its
    wall time outside its pairs (the job check, the worker's start and exit), and its pairs'
    own seconds beyond 8 times the frames' time, and its cheapest pair's seconds (a pair
    whose target its worker had set up: frames and the per-pair costs);
    ``overhead_fraction_in_batch``: that batch's seconds per pair beyond its cheapest pair,
    over the one-pair run: the overhead from one run, no baseline measured at another time
    or in another process; ``overhead_fraction_cpu``: ``overhead_fraction`` from CPU seconds
    (``cpu_seconds``, each run's: this process and its children; the frames' own), which
    other users' work changes less than wall times;
  * ``ray_overhead_fraction``: a 2-actor Ray batch on a local instance (started for that run
    alone, not timed) against the 2-worker local batch, and ``ray_identical``: the same bytes.
Every process has one BLAS thread. Each time is the best of N runs (default 2), the settings
taking turns: the least disturbed by other work. Ray runs only during its own runs: its idle
processes (about 0.03 cores) took from the 2-worker local runs, which use both cores, and not
from the 1-worker ones. On a shared machine the figures are noisy: the load average is
recorded before and after, and for each run but Ray's the cores that other users' processes
kept busy meanwhile (``other_users_cores_busy``, from /proc/stat: Linux only);
``--quiet-wait S`` waits, before each run, up to S seconds for them to fall below 0.1 cores.
``scaling_2_workers_each_repeat`` is the ratio within each repeat.
The machine's own ceiling for that ratio, with no pool: ``ceiling_2_processes``, 2 x the wall
time of one ``minretarget retarget`` process for the first pair (``single``) over that of two
such processes run at once (``single_2_at_once``, each into its own folder); also per repeat.
"""
import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from minretarget import batch
from minretarget.atomic import atomic_write
from minretarget.cli import (blas_threads, int_at_least, load_retargeter, pipeline_config,
                             retarget_to_files, set_target)
from minretarget.formats.mesh import write_mesh
from minretarget.pipeline import PRESETS, preset
from minretarget.sources import SAMPLE, load_sample, open_source
from minretarget.units import CANONICAL

FORMATS = ["npz", "bvh"]
QUIET = 0.1            # cores other users may keep busy for the machine to count as quiet
RAY_SETTLE = 5         # seconds for a new Ray instance's processes to finish starting
STRETCH = {"base": (1.0, 1.0, 1.0), "tall": (1.0, 1.12, 1.0), "short": (0.95, 0.88, 0.95),
           "wide": (1.15, 1.0, 1.2)}      # target name -> (x, y, z) scale of the sample's


def make_job(folder, frames, pipeline="default"):
    """Write the job's sources, targets and ``job.json`` (its pairs run the preset
    ``pipeline``) into ``folder``; returns the job."""
    with np.load(SAMPLE, allow_pickle=False) as data:
        clouds = data["source_points"].astype(np.float32)                    # (T, P, 3)
        points, faces = data["target_points"], data["target_faces"]
    loop = np.concatenate([clouds, clouds[::-1]])                            # (2T, P, 3)
    tiled = np.resize(loop, (frames,) + clouds.shape[1:])                     # (frames, P, 3)
    np.save(folder / "walk.npy", tiled)
    np.save(folder / "walk_back.npy", tiled[::-1].copy())
    for name, scale in STRETCH.items():
        write_mesh(folder / f"{name}.ply", points * scale, faces)
    return write_job(folder / "job.json", list(STRETCH), pipeline)


def write_job(path, targets, pipeline="default"):
    """Write a job of both sources onto ``targets`` (names in STRETCH) at ``path``, with the
    preset ``pipeline``."""
    path.write_text(json.dumps({"sources": ["walk.npy", "walk_back.npy"],
                                "targets": [f"{name}.ply" for name in targets],
                                "options": {"format": FORMATS, "preset": pipeline}}))
    return path


def files(folder):
    """{relative path: bytes} of a batch's outputs (its markers and summary aside)."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(Path(folder).rglob("*"))
            if p.is_file() and p.name not in (batch.SUMMARY, batch.DONE)}


def run_order(out, summary):
    """[[pair, seconds]] of a batch's pairs in the order they ran (by their done-markers'
    times: the summary lists them longest first)."""
    ended = {entry["pair"]: (out / entry["pair"] / batch.DONE).stat().st_mtime_ns
             for entry in summary["pairs"]}
    return [[entry["pair"], entry["seconds"]] for entry in
            sorted(summary["pairs"], key=lambda entry: ended[entry["pair"]])]


def busy_seconds():
    """(CPU seconds of the whole machine, of this process and its waited-for children) so
    far: their difference over a run is the other users' work."""
    with open("/proc/stat") as stat:
        user, nice, system, _, _, irq, softirq, steal = map(int, stat.readline().split()[1:9])
    ours = sum(getattr(resource.getrusage(who), field) for who in (resource.RUSAGE_SELF,
               resource.RUSAGE_CHILDREN) for field in ("ru_utime", "ru_stime"))
    return (user + nice + system + irq + softirq + steal) / os.sysconf("SC_CLK_TCK"), ours


def single_run_seconds(folder, pipeline, *outs):
    """Wall time of one `minretarget retarget` process (``--preset pipeline``) for the first
    pair, or of as many run at once as ``outs`` (each into its own folder): independent
    processes, no pool."""
    start = time.perf_counter()
    runs = [subprocess.Popen([sys.executable, "-m", "minretarget", "retarget",
                              str(folder / "walk.npy"), str(folder / "base.ply"), "--out",
                              str(out), "--format", ",".join(FORMATS), "--threads", "1",
                              "--preset", pipeline],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                             env={**os.environ, "OPENBLAS_NUM_THREADS": "1",
                                  "OMP_NUM_THREADS": "1"}) for out in outs]
    assert all(run.wait() == 0 for run in runs)
    return time.perf_counter() - start


def frames_seconds(folder, out, pipeline="default"):
    """(Seconds, CPU seconds) to retarget and write the first pair's frames with the preset
    ``pipeline``, the retargeter set up (the first call in a process also compiles the
    kernels), with one
    BLAS thread as in a worker and in ``retarget --threads 1`` (``cli.blas_threads``: also
    SciPy's BLAS, which SKR's kernels call and which ``threadpool_limits`` misses when SciPy
    loads after it: with 2 threads, these frames ran faster on an idle machine and several
    times slower on a busy one)."""
    # The pipeline a pair of the job runs: retarget's options, as the batch parses them.
    retargeter = load_retargeter(config=pipeline_config(batch.parse_options(
        "source", "target", "out", {"format": FORMATS, "preset": pipeline})))
    points, faces, _ = load_sample()[1:]
    set_target(retargeter, points, faces, "base")
    with blas_threads(1):
        start, cpu = time.perf_counter(), time.process_time()
        retarget_to_files(retargeter, lambda first: open_source(folder / "walk.npy", CANONICAL,
                                                                start=first),
                          out, FORMATS, CANONICAL, {"points": None, "seed": 0}, progress=False)
        return time.perf_counter() - start, time.process_time() - cpu


def others_busy(seconds):
    """Cores that other users' processes kept busy over the next ``seconds``."""
    machine, ours = busy_seconds()
    time.sleep(seconds)
    machine, ours = np.subtract(busy_seconds(), (machine, ours))
    return (machine - ours) / seconds


def wait_for_quiet(limit, threshold=QUIET):
    """Wait, at most ``limit`` seconds, until other users' processes have kept fewer than
    ``threshold`` cores busy over 3 s; returns the seconds waited (0 when ``limit`` is 0)."""
    start = time.perf_counter()
    while time.perf_counter() - start < limit and others_busy(3) >= threshold:
        pass
    return time.perf_counter() - start


def start_ray():
    """A local Ray instance of 2 CPUs, settled (its processes' start-up done), not timed."""
    import ray
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False,
             _node_ip_address="127.0.0.1")
    time.sleep(RAY_SETTLE)
    return ray


def run(quick, repeats, quiet_wait=0, pipeline="default"):
    results = {"quick": quick, "repeats": repeats, "started": time.strftime("%Y-%m-%d %H:%M"),
               "load_average_before": os.getloadavg(),
               "cpus": os.cpu_count(), "quiet_wait_seconds": quiet_wait, "preset": pipeline,
               "pipeline": preset(pipeline).preset_name()}
    length, pairs = (68 if quick else 300), 8                    # frames per pair, pairs
    settings = {"local_1": ("job", {"workers": 1}), "local_2": ("job", {"workers": 2}),
                "ray_2": ("job", {"workers": 2, "ray": "auto"}),
                "local_1_half": ("half", {"workers": 1})}          # 4 of the pairs
    seconds = {name: [] for name in [*settings, "single", "frames", "single_2_at_once"]}
    # Other users' busy cores during each run (not Ray's: its processes are not ours).
    others = {name: [] for name in seconds if name != "ray_2"}
    cpu = {name: [] for name in others}            # CPU seconds of this process and children
    waited = []                                    # seconds waited for a quiet machine
    pair_seconds = []                               # each local_1 run's pairs, in order run

    def timed(name, measure):
        """``measure()`` -> seconds (or (seconds, CPU seconds) of a part of it), recorded
        with the other users' busy cores meanwhile and the CPU seconds of this process and
        its children."""
        waited.append(wait_for_quiet(quiet_wait))
        machine, ours = busy_seconds()
        start = time.perf_counter()
        value = measure()
        wall = time.perf_counter() - start
        machine, ours = np.subtract(busy_seconds(), (machine, ours))
        value, used = value if isinstance(value, tuple) else (value, ours)
        seconds[name].append(value)
        if name in others:
            others[name].append((machine - ours) / wall)
            cpu[name].append(used)

    with tempfile.TemporaryDirectory() as temporary, threadpool_limits(1):
        folder = Path(temporary)
        jobs = {"job": make_job(folder, length, pipeline),
                "half": write_job(folder / "half.json", list(STRETCH)[:2], pipeline)}
        frames_seconds(folder, folder / "compile", pipeline)
        for index in range(repeats):   # interleaved: a change of load touches every setting
            for name, (job, options) in settings.items():
                # Ray runs only while its own batch is timed: its idle processes (about
                # 0.03 cores) would otherwise take from the local 2-worker runs alone.
                ray = start_ray() if options.get("ray") else None
                try:
                    def measure():
                        summary = batch.run_batch(jobs[job], folder / f"{name}_{index}",
                                                  progress=False, **options)
                        assert summary["done"] == (pairs if job == "job" else pairs // 2)
                        return summary["seconds"]
                    timed(name, measure)
                finally:
                    if ray is not None:
                        ray.shutdown()
                        time.sleep(RAY_SETTLE)          # its processes gone before the next
                if name == "local_1":
                    summary = json.loads((folder / f"{name}_{index}" / batch.SUMMARY)
                                         .read_text())
                    pair_seconds.append(run_order(folder / f"{name}_{index}", summary))
            timed("single", lambda: single_run_seconds(folder, pipeline,
                                                       folder / f"single_{index}"))
            timed("frames", lambda: frames_seconds(folder, folder / f"frames_{index}",
                                                   pipeline))
            timed("single_2_at_once", lambda: single_run_seconds(
                folder, pipeline, *(folder / f"single_{index}_{k}" for k in (1, 2))))
        identical = {name: files(folder / f"{name}_0") == files(folder / "local_1_0")
                     for name in ("local_2", "ray_2")}
    local_1, local_2, on_ray, half, single, frames, two = (min(seconds[name])
                                                           for name in seconds)
    best = int(np.argmin(seconds["local_1"]))
    in_pairs = sum(each for _, each in pair_seconds[best])     # its pairs' own seconds
    cheapest = min(each for _, each in pair_seconds[best])
    cpu_1, cpu_single, cpu_frames = (min(cpu[name]) for name in ("local_1", "single", "frames"))
    total = pairs * length
    marginal = (local_1 - half) / (pairs - pairs // 2)       # seconds a pair adds
    fixed = local_1 - pairs * marginal                       # seconds a batch pays once
    results.update(
        pairs=pairs, frames_per_pair=length,
        frames_per_second_1_worker=total / local_1,
        frames_per_second_2_workers=total / local_2,
        scaling_2_workers=local_1 / local_2,
        scaling_2_workers_each_repeat=[on_1 / on_2 for on_1, on_2 in
                                       zip(seconds["local_1"], seconds["local_2"])],
        ceiling_2_processes=2 * single / two,
        ceiling_2_processes_each_repeat=[2 * one / both for one, both in
                                         zip(seconds["single"], seconds["single_2_at_once"])],
        seconds=seconds, single_run_seconds=single, frames_seconds_per_pair=frames,
        overhead_seconds_per_pair=local_1 / pairs - frames,
        overhead_fraction=(local_1 / pairs - frames) / single,
        overhead_parts={"outside_pairs_seconds": local_1 - in_pairs,
                        "pairs_beyond_frames_seconds": in_pairs - pairs * frames,
                        "cheapest_pair_seconds": cheapest},
        overhead_fraction_in_batch=(local_1 / pairs - cheapest) / single,
        cpu_seconds=cpu,
        overhead_fraction_cpu=(cpu_1 / pairs - cpu_frames) / cpu_single,
        overhead_split={"batch_fixed_seconds": fixed, "pair_marginal_seconds": marginal,
                        "pair_marginal_overhead_seconds": marginal - frames,
                        "fixed_seconds_per_pair": fixed / pairs,
                        "half_job_pairs": pairs // 2},
        local_1_pair_seconds=pair_seconds[best],
        single_run_overhead_fraction=(single - frames) / single,
        ray_overhead_fraction=on_ray / local_2 - 1,
        ray_identical=identical["ray_2"], local_identical=identical["local_2"],
        other_users_cores_busy=others, seconds_waited_for_quiet=sum(waited),
        load_average_after=os.getloadavg(), ended=time.strftime("%Y-%m-%d %H:%M"))
    return results


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="68-frame pairs, not 300")
    parser.add_argument("--repeats", type=int_at_least(1), default=2,
                        help="runs of each setting, the best kept (default 2)")
    parser.add_argument("--quiet-wait", type=float, default=0, metavar="SECONDS",
                        help="before each run, wait at most SECONDS for other users' "
                        f"processes to keep fewer than {QUIET} cores busy (default 0: no "
                        "wait; a shared machine)")
    parser.add_argument("--preset", choices=["default", *PRESETS], default="default",
                        help="the pipeline every pair runs (the job's option preset, "
                        "retarget's --preset; default: the package's default)")
    parser.add_argument("--json", default=None, help="write the results to this file")
    args = parser.parse_args()
    results = run(args.quick, args.repeats, args.quiet_wait, args.preset)
    text = json.dumps(results, indent=2)
    print(text)
    if args.json:
        with atomic_write(args.json) as file:
            file.write(text.encode())


if __name__ == "__main__":
    main()
