"""`minretarget batch`: a whole job checked before any work (units checks included), each pair's
outputs the bytes of its own `retarget` run with the same options (local pool and Ray alike;
units told from the files, shipped bodies by name), resume, failures kept to their pair, a
killed worker's pair run again."""
import concurrent.futures
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import GOLDEN
from minretarget import batch, cli
from minretarget.checkpoint import CHECKPOINT_EVERY
from minretarget.formats.mesh import write_mesh
from minretarget.outputs import frame_name
from minretarget.retargeter import Retargeter

trimesh = pytest.importorskip("trimesh")
WEIGHTS = str(GOLDEN / "tiny_weights.npz")
ROOT = Path(__file__).resolve().parent.parent
POINTS, SUBSET = 80, 70
OPTIONS = {"format": "ply,npz,glb,bvh", "points": SUBSET, "weights": WEIGHTS}


def walk(frames, seed):
    """(frames, POINTS, 3) float32 clouds of a body-sized blob walking along +X."""
    rng = np.random.default_rng(seed)
    path = np.linspace(0, 1, frames)[:, None, None] * [1.0, 0, 0]
    clouds = rng.normal(size=(frames, POINTS, 3)) * [0.2, 0.5, 0.1] + [0, 0.9, 0] + path
    return clouds.astype(np.float32)


@pytest.fixture(scope="module")
def library(tmp_path_factory):
    """Two sources (a long and a short array of clouds) and two T-pose-like targets."""
    folder = tmp_path_factory.mktemp("library")
    (folder / "motions").mkdir()
    np.save(folder / "motions" / "long.npy", walk(100, 0))
    np.save(folder / "motions" / "short.npy", walk(20, 1))
    mesh = trimesh.creation.icosphere(subdivisions=2)
    for name, scale in (("slim", [0.85, 0.9, 0.2]), ("wide", [0.95, 0.8, 0.3])):
        write_mesh(folder / f"{name}.ply", mesh.vertices * scale + [0, 0.9, 0], mesh.faces)
    return folder


def write_job(folder, name="job.json", **job):
    path = Path(folder) / name
    path.write_text(json.dumps({"sources": ["motions/*.npy"], "targets": ["slim.ply",
                                                                        "wide.ply"],
                                "options": OPTIONS, **job}))
    return path


def files(folder):
    """{relative path: bytes} of every file under ``folder``, summary.json aside."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(Path(folder).rglob("*"))
            if p.is_file() and p.name not in (batch.SUMMARY, batch.DONE)}


def retarget(source, target, out, *extra):
    """`minretarget retarget SOURCE TARGET --out OUT` with OPTIONS' options (and ``extra``)."""
    assert cli.main(["retarget", str(source), str(target), "--out", str(out), "--format",
                     OPTIONS["format"], "--points", str(SUBSET), "--weights", WEIGHTS,
                     *extra]) == 0


@pytest.fixture(scope="module")
def reference(library):
    """Each pair run alone by `minretarget retarget`, as one tree of files."""
    out = library / "single"
    for target in ("slim", "wide"):
        for source in ("long", "short"):
            retarget(library / "motions" / f"{source}.npy", library / f"{target}.ply",
                     out / target / source)
    return files(out)


@pytest.fixture(scope="module")
def local_run(library):
    out = library / "local"
    summary = batch.run_batch(write_job(library), out, workers=2, progress=False)
    return out, summary


def test_a_job_is_checked_whole_before_any_work(library, tmp_path):
    (tmp_path / "motions").mkdir()
    np.save(tmp_path / "motions" / "nan.npy", np.zeros((3, 5)))       # not (T, P, 3)
    job = tmp_path / "job.toml"
    job.write_text(f"""
sources = ["motions/*.npy", "missing.bvh", "{library}/motions/*.npy"]
targets = ["{library}/slim.ply", "{library}/*.obj"]
pairs = [{{source = "long", target = "fat"}}]
colour = "red"
[options]
units = "inch"
foot_lock = false
foot_leash = 0.1
smooth = false
""")
    with pytest.raises(batch.JobError) as raised:
        batch.run_batch(job, tmp_path / "out", progress=False)
    problems = "\n".join(raised.value.problems)
    for expected in ("unknown key 'colour'", "missing.bvh: no such file", "*.obj: matches "
                     "nothing", "options: units: invalid choice: 'inch'", "options: foot_leash: "
                     "not allowed with foot_lock = false", "unknown option 'smooth'",
                     "target 'fat' is not a name"):
        assert expected in problems
    assert len(raised.value.problems) == 7
    assert not (tmp_path / "out").exists()
    # Once the options parse, the files are read: a source that is not (T, P, 3) frames.
    job.write_text(f'sources = ["motions/*.npy"]\ntargets = ["{library}/slim.ply"]\n')
    with pytest.raises(batch.JobError, match="source nan: .*expected an array of frames"):
        batch.run_batch(job, tmp_path / "out", progress=False)


def test_a_units_failure_is_listed_unless_forced(library, tmp_path):
    """As `retarget` refuses a body that is not a person's size in the units given, the job
    check lists each such pair's file, its advice in a job's keys; force = true runs them."""
    job = write_job(tmp_path, sources=[str(library / "motions" / "short.npy")],
                    targets=[str(library / "slim.ply"), str(library / "wide.ply")],
                    pairs=[{"source": "short", "target": "slim",
                            "options": {"target_units": "cm"}},
                           {"source": "short", "target": "wide",
                            "options": {"source_units": "mm"}}])
    with pytest.raises(batch.JobError) as raised:
        batch.read_job(job, tmp_path / "out")
    target, source = raised.value.problems
    assert target.startswith(f"target slim: {library / 'slim.ply'}: the body is 0.018 m (1.8 "
                             "cm) tall") and 'use target_units = "m"' in target
    assert source.startswith(f"source short: {library / 'motions' / 'short.npy'}: frame 0: "
                             "the body is 0.00") and 'use source_units = "m"' in source
    assert all(p.endswith("nothing written (force = true goes on anyway)")
               for p in (target, source))
    job.write_text(job.read_text().replace('"options": {"format"',
                                           '"options": {"force": true, "format"'))
    pairs = batch.read_job(job, tmp_path / "out")
    assert [(p.name, p.options["force"], p.frames) for p in pairs] == [
        ("slim/short", True, 20), ("wide/short", True, 20)]


def test_centimetres_told_and_a_shipped_body_as_retarget_does(library, tmp_path):
    """A source in centimetres with no units given, onto a mesh and onto a shipped body by
    name: each pair's bytes are `retarget`'s (outputs in metres), and so are its lines
    about each file's units."""
    np.save(tmp_path / "walk_cm.npy", walk(8, 2) * 100)
    job = write_job(tmp_path, sources=["walk_cm.npy"], targets=[str(library / "slim.ply"),
                                                                 "child"])
    summary = batch.run_batch(job, tmp_path / "out", workers=1, progress=False)
    for target in (library / "slim.ply", "child"):
        retarget(tmp_path / "walk_cm.npy", target, tmp_path / "single" / Path(target).stem /
                 "walk_cm")
    assert files(tmp_path / "out") == files(tmp_path / "single")
    with np.load(tmp_path / "out" / "child" / "walk_cm" / "result.npz") as result:
        assert str(result["units"]) == "m" and str(result["up_axis"]) == "y"
    slim, child = summary["pairs"]
    assert child["target"] == "child" and child["options"]["source_units"] is None
    assert child["read_as"][0].startswith("target: metres (detected), Y up (detected)")
    assert child["read_as"][1].startswith("source: centimetres (detected), Y up (detected)")
    assert slim["status"] == child["status"] == "done"


def test_local_batch_writes_what_each_retarget_run_writes(local_run, reference):
    out, summary = local_run
    assert files(out) == reference
    assert [(e["pair"], e["status"], e["attempts"]) for e in summary["pairs"]] == [
        ("slim/long", "done", 1), ("wide/long", "done", 1), ("slim/short", "done", 1),
        ("wide/short", "done", 1)]                                       # longest first
    assert summary["frames"] == 240 and summary["workers"] == 2
    assert json.loads((out / "slim" / "long" / batch.DONE).read_text())["outputs"] == [
        "frame_000000.ply .. frame_000099.ply", "result.npz", "result.glb", "result.bvh"]


def test_equal_pairs_share_out_the_targets_and_longer_pairs_start_first():
    """A slot that frees takes, among the pairs as long as the longest waiting, one whose
    target its worker has set up, else one whose target no worker has: with two workers each
    target is set up by one of them, not by both; a longer pair still starts first."""
    def pair(source, target, frames):
        return batch.Pair(f"{target}/{source}", source, target,
                          {"weights": None, "refine": True}, frames, "")

    pairs = [pair("long", target, 50) for target in "xy"] + [
        pair(source, target, 10) for target in "xy" for source in "abc"]
    started = []

    def submit(slot, pair):
        started.append((slot, pair))
        future = concurrent.futures.Future()
        future.set_result({"pair": pair.name})
        return future

    ended = list(batch.schedule(pairs, ["one", "two"], submit, (), lambda: None))
    assert sorted(e["pair"] for e in ended) == sorted(p.name for p in pairs)
    assert {p.source for _, p in started[:2]} == {"long"}
    targets = {slot: {p.target for s, p in started if s == slot} for slot in ("one", "two")}
    assert sorted(map(sorted, targets.values())) == [["x"], ["y"]]


def test_a_target_handed_out_runs_as_one_read_by_the_worker(library, reference, tmp_path):
    """The batch's process reads a pair's target as it hands the pair out (``with_target``),
    so that a worker needs no mesh reader: the pair's files and its summary entry (the lines
    about units, the warnings) are those of a worker reading it; a target that does not
    read then is left to the worker, which fails the pair with the reason."""
    pairs = batch.read_job(write_job(library), tmp_path / "job")
    pair = next(p for p in pairs if p.name == "wide/short")
    handed = batch.with_target(pair._replace(folder=str(tmp_path / "handed")))
    assert handed.target_read is not None and pair.target_read is None
    read = batch.run_pair(pair._replace(folder=str(tmp_path / "read")))
    entry = batch.run_pair(handed)
    assert read["read_as"][0].startswith("target: ") and read["warnings"]   # a T-pose warning
    assert {**entry, "seconds": 0} == {**read, "seconds": 0}
    assert files(tmp_path / "handed") == files(tmp_path / "read") == {
        k.removeprefix("wide/short/"): v for k, v in reference.items()
        if k.startswith("wide/short/")}
    gone = pair._replace(target=str(tmp_path / "gone.ply"), folder=str(tmp_path / "gone"))
    assert batch.with_target(gone) is gone
    failed = batch.run_pair(gone)
    assert failed["status"] == "failed" and "gone.ply" in failed["error"]


def test_a_worker_warms_up_once_per_target_and_pipeline(library, reference, tmp_path,
                                                       monkeypatch):
    """``retarget_to_files`` warms up every stream; a worker does it once per target and
    pipeline, and each pair's files and summary entry are those of a worker warming up for it
    (the warm-up's frames give no warnings: ``Retargeter.warm_up``)."""
    warmed = []
    real = Retargeter.warm_up
    monkeypatch.setattr(Retargeter, "warm_up", lambda self, skeleton=False: (
        warmed.append(self.target.points.shape), real(self, skeleton))[1])
    monkeypatch.setattr(batch, "_WARMED", set())
    pairs = {p.name: p for p in batch.read_job(write_job(library), tmp_path / "job")}
    entries = {name: batch.run_pair(pairs[name]._replace(folder=str(tmp_path / "a" / name)))
               for name in ("slim/long", "slim/short", "wide/short")}
    assert len(warmed) == 2                             # slim once, wide once
    monkeypatch.setattr(batch, "_WARMED", set())        # a fresh worker for slim/short alone
    alone = batch.run_pair(pairs["slim/short"]._replace(folder=str(tmp_path / "b")))
    assert len(warmed) == 3
    assert {**alone, "seconds": 0} == {**entries["slim/short"], "seconds": 0}
    # the source's own frame 1 warns (the tiny weights read no body); the warm-up's does not
    assert sum("frame 1: the source fit found no body" in w for w in alone["warnings"]) == 1
    assert files(tmp_path / "a") == {k: v for k, v in reference.items()
                                     if k.split("/")[1] != "long" or k.startswith("slim/")}


def test_pairs_of_other_pipelines_on_one_target_run_as_retarget_does(library, tmp_path):
    """A target's set-up (its skeleton, then its skinning weights) depends on the pipeline's
    mirror_target: a worker that set it up for one preset's pair sets it up again for
    another's, and each pair writes what `retarget --preset` writes."""
    job = write_job(tmp_path, sources=[str(library / "motions" / "long.npy"),
                                       str(library / "motions" / "short.npy")],
                    targets=[str(library / "slim.ply")],
                    pairs=[{"source": "long", "target": "slim",
                            "options": {"preset": "paper"}},
                           {"source": "short", "target": "slim"}])
    summary = batch.run_batch(job, tmp_path / "out", workers=1, progress=False)
    assert [(e["pair"], e["options"]["preset"]) for e in summary["pairs"]] == [
        ("slim/long", "paper"), ("slim/short", "default")]
    retarget(library / "motions" / "long.npy", library / "slim.ply",
             tmp_path / "single" / "slim" / "long", "--preset", "paper")
    retarget(library / "motions" / "short.npy", library / "slim.ply",
             tmp_path / "single" / "slim" / "short")
    assert files(tmp_path / "out") == files(tmp_path / "single")


def test_a_kill_while_a_pair_is_marked_done_leaves_nothing_behind(library, reference,
                                                                   tmp_path):
    """A worker killed while it wrote a pair's done-marker leaves the marker's temporary file
    and no marker: the pair runs again, and the temporary goes."""
    job = write_job(tmp_path, sources=[str(library / "motions" / "short.npy")],
                    targets=[str(library / "wide.ply")])
    out = tmp_path / "out"
    batch.run_batch(job, out, workers=1, progress=False)
    (out / "wide" / "short" / batch.DONE).unlink()
    (out / "wide" / "short" / f".{batch.DONE}.0123456789ab.tmp").write_text('{"pair"')
    summary = batch.run_batch(job, out, workers=1, resume=True, progress=False)
    assert summary["done"] == 1 and summary["skipped"] == 0
    assert (out / "wide" / "short" / batch.DONE).is_file()
    assert files(out) == {k: v for k, v in reference.items() if k.startswith("wide/short/")}


def test_a_failing_pair_does_not_stop_the_others(library, reference, tmp_path, capsys):
    clouds = walk(20, 1)
    clouds[5, 3] = np.nan
    np.save(tmp_path / "broken.npy", clouds)
    job = write_job(tmp_path, sources=[str(library / "motions" / "short.npy"), "broken.npy"],
                    targets=[str(library / "slim.ply")])
    assert cli.main(["batch", str(job), "--out", str(tmp_path / "out"), "--workers", "1"]) == 1
    summary = json.loads((tmp_path / "out" / batch.SUMMARY).read_text())
    failed = [e for e in summary["pairs"] if e["status"] == "failed"]
    assert [e["pair"] for e in failed] == ["slim/broken"] and "frame 5" in failed[0]["error"]
    assert "slim/broken" in capsys.readouterr().err
    done = files(tmp_path / "out" / "slim" / "short")
    assert done == {k.removeprefix("slim/short/"): v for k, v in reference.items()
                    if k.startswith("slim/short/")}


def test_resume_skips_the_pairs_done(library, local_run, tmp_path):
    out = tmp_path / "out"
    job = write_job(library)
    with pytest.raises(batch.JobError, match="add --resume"):
        batch.run_batch(job, local_run[0], progress=False)
    # An earlier run finished two pairs (copied from the local run) and left nothing else.
    for name in ("slim/long", "wide/short"):
        (out / name).mkdir(parents=True)
        for path in (local_run[0] / name).iterdir():
            (out / name / path.name).write_bytes(path.read_bytes())
    summary = batch.run_batch(job, out, workers=1, resume=True, progress=False)
    assert files(out) == files(local_run[0])
    assert {e["pair"] for e in summary["pairs"] if e.get("skipped")} == {"slim/long",
                                                                         "wide/short"}
    assert summary["frames"] == 120


def worker_pids(parent):
    """The pids of the pool processes a batch process started (not its resource tracker)."""
    children = Path(f"/proc/{parent}/task/{parent}/children").read_text().split()
    return [int(pid) for pid in children
            if b"spawn_main" in Path(f"/proc/{pid}/cmdline").read_bytes()]


def start_batch(job, out, *extra):
    return subprocess.Popen([sys.executable, "-m", "minretarget", "batch", str(job), "--out",
                             str(out), *extra], cwd=ROOT,
                            env={**os.environ, "PYTHONPATH": str(ROOT)},
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def wait_for(path, process, seconds=120):
    deadline = time.monotonic() + seconds
    while not path.exists():
        assert process.poll() is None and time.monotonic() < deadline, process.communicate()
        time.sleep(0.01)


def running(pid):
    """Whether process ``pid`` still runs: not gone, nor a zombie (dead, its exit status not
    yet collected: the init process that adopts a dead batch's workers here collects it up
    to 2 s later)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state not in ("Z", "X")


AFTER_CHECKPOINT = frame_name(CHECKPOINT_EVERY, "ply")   # its file: the checkpoint is saved


def test_a_killed_worker_is_replaced_and_its_pair_resumed(library, local_run, tmp_path):
    out = tmp_path / "out"
    process = start_batch(write_job(library), out, "--workers", "2")
    wait_for(out / "slim" / "long" / AFTER_CHECKPOINT, process)
    os.kill(worker_pids(process.pid)[0], signal.SIGKILL)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 0, stderr
    assert files(out) == files(local_run[0])
    summary = json.loads((out / batch.SUMMARY).read_text())
    assert max(e["attempts"] for e in summary["pairs"]) == 2


def test_a_killed_batch_resumes_without_redoing_finished_pairs(library, local_run, tmp_path):
    out = tmp_path / "out"
    process = start_batch(write_job(library), out, "--workers", "1")
    wait_for(out / "wide" / "long" / AFTER_CHECKPOINT, process)       # slim/long is done
    workers = worker_pids(process.pid)
    process.kill()
    process.communicate(timeout=60)
    assert not (out / "wide" / "long" / batch.DONE).exists(), "killed too late: wide/long done"
    deadline = time.monotonic() + 10                  # its workers die with it
    while any(running(pid) for pid in workers):
        assert time.monotonic() < deadline
        time.sleep(0.01)
    finished = (out / "slim" / "long" / batch.DONE).stat().st_mtime_ns
    summary = batch.run_batch(write_job(library), out, workers=1, resume=True, progress=False)
    assert files(out) == files(local_run[0])
    assert (out / "slim" / "long" / batch.DONE).stat().st_mtime_ns == finished
    assert summary["frames"] == 140                   # wide/long and the two short pairs


def test_ray_writes_the_same_bytes(library, local_run, tmp_path):
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False,
             _node_ip_address="127.0.0.1")
    try:
        summary = batch.run_batch(write_job(library), tmp_path / "out", ray="auto",
                                  progress=False)
    finally:
        ray.shutdown()
    assert summary["engine"] == "ray" and summary["workers"] == 2
    assert files(tmp_path / "out") == files(local_run[0])


def test_a_viewpoint_is_a_job_key_as_retarget_takes_it():
    """``viewpoint = "X,Y,Z"`` is ``--viewpoint X,Y,Z``; a malformed one is named in a job's
    terms."""
    args = batch.parse_options("s.npy", "t.ply", "out", {"viewpoint": "-0.5,1.2,2.5"})
    assert args.viewpoint == "-0.5,1.2,2.5"
    with pytest.raises(ValueError, match="viewpoint.*must be three numbers X,Y,Z"):
        batch.parse_options("s.npy", "t.ply", "out", {"viewpoint": "1,2"})
