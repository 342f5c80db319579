"""Fuzz minretarget's file parsers: PLY, OBJ, XYZ, NPY and NPZ points and frames, BVH, weights.

    python benchmarks/fuzz_parsers.py --minutes 10 [--findings fuzz_findings]

Each input's first byte picks a parser, the rest is the file's content; the parser reads it
as the command line would (every frame of a source, the whole weights file). The only
documented failure is a ValueError (``BVHError`` included) naming the file; anything else
(another exception type, a non-finite or mis-shaped result) is a finding: its input is saved
in ``--findings`` and the run goes on. The summary lists each distinct finding once.

Coverage-guided with atheris (libFuzzer) when it is installed (``pip install atheris``),
starting from a small valid file of every kind; without it, random mutations of those files.
"""
import argparse
import collections
import gzip
import hashlib
import io
import os
import random
import shutil
import sys
import tempfile
import time
import traceback
import types
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

try:
    import atheris
except ImportError:
    atheris = None


import trimesh  # noqa: E402

from minretarget import bvh, skeletons, sources, units, validation, weights  # noqa: E402
from minretarget.formats import mesh, npz  # noqa: E402
from minretarget.formats.mesh import read_points  # noqa: E402
from minretarget.sources import open_source  # noqa: E402
from minretarget.units import CANONICAL  # noqa: E402
from minretarget.validation import as_float32_array  # noqa: E402
from minretarget.weights import load_weights  # noqa: E402

PARSER_MODULES = (bvh, skeletons, sources, units, validation, weights, mesh, npz)


def instrument():
    """Coverage for atheris: the functions of our parser modules, of trimesh's readers and of
    NumPy's .npy header reader. Numba kernels live in other modules and stay as they are
    (numba cannot compile instrumented code)."""
    modules = list(PARSER_MODULES) + [m for name, m in list(sys.modules.items())
                                      if name.startswith("trimesh.exchange")
                                      or name == "numpy.lib._format_impl"]
    for module in modules:
        for value in list(vars(module).values()):
            members = vars(value).values() if type(value) is type else [value]
            for function in members:
                if type(function) is types.FunctionType and \
                        function.__code__.co_filename == module.__file__:
                    atheris.instrument_func(function)


# (name, suffix, how the command line reads it)
KINDS = [("ply", ".ply", "points"), ("obj", ".obj", "points"), ("xyz", ".xyz", "points"),
         ("npy", ".npy", "points"), ("frames_npy", ".npy", "source"),
         ("frames_npz", ".npz", "source"), ("bvh", ".bvh", "source"),
         ("bvh_gz", ".bvh.gz", "source"), ("weights", ".npz", "weights")]


def seeds():
    """A small valid file of every kind: {kind index: bytes}."""
    from minretarget.bvh import format_bvh
    from minretarget.config import ModelConfig
    from minretarget.skeletons import rig_to_bvh
    from minretarget.weights import FORMAT_VERSION, _leaves, weight_template

    rng = np.random.default_rng(0)
    cube = trimesh.creation.box()
    frames = rng.normal(size=(2, 6, 3)).astype(np.float32)

    def npy(array):
        buffer = io.BytesIO()
        np.save(buffer, array)
        return buffer.getvalue()

    def npz(compress=False, **arrays):
        buffer = io.BytesIO()
        (np.savez_compressed if compress else np.savez)(buffer, **arrays)
        return buffer.getvalue()

    rotations = np.tile([1.0, 0, 0, 0], (2, 22, 1))
    bvh = format_bvh(rig_to_bvh(rng.normal(size=(22, 3)), rotations, rng.normal(size=(2, 3)),
                                1 / 30)).encode()
    # The smallest model config, every width 1, so that the weights file is a few kB.
    config = ModelConfig((1, 1, 1), (1, 1), 1, 1, (1,))
    weights = {key: np.zeros(shape, np.float16) for stage, tree in weight_template(config).items()
               for key, shape in _leaves(tree, stage)}
    weights.update(format_version=np.array(FORMAT_VERSION), config=np.array(config.to_json()),
                   metadata=np.array("{}"))
    files = {
        "ply": [cube.export(file_type="ply"), cube.export(file_type="ply", encoding="ascii"),
                trimesh.PointCloud(frames[0]).export(file_type="ply")],
        "obj": [cube.export(file_type="obj").encode()],
        "xyz": [b"# x y z\n" + b"".join(b"%g %g %g 0 1\n" % tuple(p) for p in frames[0])],
        "npy": [npy(frames[0]), npy(frames[0].astype(np.float64).T.copy().T)],
        "frames_npy": [npy(frames), npy(np.asfortranarray(frames))],
        "frames_npz": [npz(points=frames), npz(True, source_points=frames, other=frames[0])],
        "bvh": [bvh], "bvh_gz": [gzip.compress(bvh, mtime=0)],
        "weights": [npz(**weights)],
    }
    names = [k[0] for k in KINDS]
    return [bytes([names.index(name)]) + data for name, group in files.items() for data in group]


class Harness:
    """Runs one input; records findings (anything but a documented error)."""

    def __init__(self, folder, findings, seconds, exit_at_deadline):
        self.folder, self.findings = Path(folder), Path(findings)
        self.seen = collections.OrderedDict()          # signature -> (count, example, text)
        self.runs = 0
        self.start = time.perf_counter()
        self.deadline = self.start + seconds
        self.exit_at_deadline = exit_at_deadline

    def __call__(self, data):
        self.runs += 1
        if self.exit_at_deadline and time.perf_counter() > self.deadline:
            # libFuzzer never returns to Python: report and leave from here.
            self.summary()
            sys.stdout.flush()
            shutil.rmtree(self.folder, ignore_errors=True)
            os._exit(1 if self.seen else 0)
        if not data:
            return
        name, suffix, how = KINDS[data[0] % len(KINDS)]
        path = self.folder / f"input{suffix}"
        path.write_bytes(data[1:])
        try:
            self.parse(path, how)
        except (ValueError, FileNotFoundError):
            pass                                       # documented: a clear error
        except Exception as error:                     # noqa: BLE001  (a finding)
            self.record(name, error, data)

    @staticmethod
    def parse(path, how):
        if how == "points":
            points, faces = read_points(path)
            assert points.dtype == np.float32 and points.ndim == 2 and points.shape[1] == 3
            assert np.isfinite(points).all(), "non-finite points returned"
            assert faces is None or (faces.ndim == 2 and faces.shape[1] == 3 and (
                faces.size == 0 or (faces.min() >= 0 and faces.max() < len(points)))), \
                "faces out of range"
        elif how == "source":
            source = open_source(path, CANONICAL)
            count = 0
            for frame in source.frames:
                as_float32_array(frame, "frame", (None, 3))
                count += 1
            assert count == source.count, f"{count} frames of {source.count}"
        else:
            load_weights(path)

    def record(self, name, error, data):
        frame = traceback.extract_tb(error.__traceback__)[-1]
        signature = (name, type(error).__name__, frame.filename.split("site-packages/")[-1],
                     frame.lineno)
        count, example, text = self.seen.get(signature, (0, None, None))
        if example is None:
            self.findings.mkdir(parents=True, exist_ok=True)
            example = self.findings / f"{name}-{hashlib.sha1(data).hexdigest()[:12]}"
            example.write_bytes(data)
            text = f"{type(error).__name__}: {error}"[:300]
            print(f"finding: {signature}: {text} (input {example})", file=sys.stderr,
                  flush=True)
        self.seen[signature] = (count + 1, example, text)

    def summary(self):
        seconds = time.perf_counter() - self.start
        print(f"\n{self.runs} inputs in {seconds / 60:.1f} min; "
              f"{len(self.seen)} distinct findings")
        for signature, (count, example, text) in self.seen.items():
            print(f"  {count:6d}x {signature}: {text}\n          input: {example}")


def mutate(data, rng):
    """A random edit of ``data``: flip bytes, cut, duplicate or insert a chunk, splice digits."""
    data = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        choice = rng.random()
        position = rng.randrange(len(data) + 1) if data else 0
        if choice < 0.35 and data:
            data[min(position, len(data) - 1)] = rng.randrange(256)
        elif choice < 0.5:
            del data[position:]
        elif choice < 0.65:
            del data[position:position + rng.randint(1, 64)]
        elif choice < 0.8 and data:
            start = rng.randrange(len(data))
            data[position:position] = data[start:start + rng.randint(1, 64)]
        else:
            data[position:position] = rng.choice([b"0", b"-1", b"1e309", b"nan", b" ", b"\n",
                                                  b"99999999999", b"\xff\xff\xff\x7f"])
    return bytes(data[:1] or b"\0") + bytes(data[1:])


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--minutes", type=float, default=1.0)
    parser.add_argument("--findings", default="fuzz_findings", help="folder for the inputs "
                        "of findings (default fuzz_findings)")
    parser.add_argument("--max-len", type=int, default=32768, help="largest input, bytes")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    warnings.simplefilter("ignore")                    # NumPy's overflow notes and the like
    corpus = seeds()
    with tempfile.TemporaryDirectory(dir="/dev/shm" if Path("/dev/shm").is_dir() else None) \
            as folder:
        harness = Harness(folder, args.findings, args.minutes * 60, atheris is not None)
        for data in corpus:                            # the seeds themselves must parse
            harness(data)
        if atheris is not None:
            instrument()
            print(f"atheris, {args.minutes:g} min, {len(corpus)} seed files", flush=True)
            seed_dir = Path(folder) / "corpus"
            seed_dir.mkdir()
            for i, data in enumerate(corpus):
                (seed_dir / f"seed{i}").write_bytes(data)
            atheris.Setup([sys.argv[0], str(seed_dir), f"-max_len={args.max_len}",
                           "-rss_limit_mb=4096", "-timeout=60", f"-seed={args.seed + 1}"],
                          harness, internal_libfuzzer=True)
            atheris.Fuzz()                             # leaves through Harness at the deadline
        print(f"random mutations (atheris not installed), {args.minutes:g} min", flush=True)
        rng = random.Random(args.seed)
        while time.perf_counter() < harness.deadline:
            harness(mutate(rng.choice(corpus), rng)[:args.max_len])
        harness.summary()
    return 1 if harness.seen else 0


if __name__ == "__main__":
    sys.exit(main())
