"""Bad input at every public entry: clear errors naming the file, frame and value; warnings
with a way out for likely mistakes (units, up axis, T-pose); damaged files of every kind;
the shipped weights' checksum."""
import gzip
import io
import shutil
import warnings
import zipfile

import numpy as np
import pytest

from conftest import GOLDEN
from minretarget import Retargeter, checksum, cli, weights
from minretarget.bvh import format_bvh, read_bvh
from minretarget.formats.mesh import read_points, write_mesh
from minretarget.kinematics import forward_kinematics, quaternion_to_matrix
from minretarget.skeletons import rig_to_bvh
from minretarget.sources import open_source
from minretarget.units import CANONICAL, from_canonical, make_space
from minretarget.validation import (FitWarning, InputWarning, TPoseWarning, UnitsWarning,
                                    UpAxisWarning, check_body)
from minretarget.weights import flatten_weights, load_weights, save_weights

trimesh = pytest.importorskip("trimesh")
WEIGHTS = str(GOLDEN / "tiny_weights.npz")


def body(arms_down=False, points=600, seed=0):
    """(N, 3) canonical cloud of a 1.7 m body: a trunk and legs, and arms either horizontal
    (T-pose, 1.6 m from hand to hand) or along the body (0.6 m)."""
    rng = np.random.default_rng(seed)
    trunk = rng.uniform([-0.2, 0.0, -0.1], [0.2, 1.7, 0.1], (points // 2, 3))
    reach = 0.3 if arms_down else 0.8
    arms = rng.uniform([-reach, 1.0 if arms_down else 1.35, -0.05], [reach, 1.45, 0.05],
                       (points - points // 2 - 4, 3))
    ends = [[0, 0, 0], [0, 1.7, 0], [-reach, 1.4, 0], [reach, 1.4, 0]]   # exact extents
    return np.concatenate([trunk, arms, ends]).astype(np.float32)


def caught(function, *args, **kwargs):
    """Run ``function``; return the InputWarnings it issued about its input (not the source
    fit's of a cloud it finds no body in: these bodies are 1,700 m tall)."""
    with warnings.catch_warnings(record=True) as records:
        warnings.simplefilter("always")
        function(*args, **kwargs)
    return [r for r in records if issubclass(r.category, InputWarning)
            and not issubclass(r.category, FitWarning)]


# ----------------------------------------------------------------------------- warnings

@pytest.mark.parametrize("scale, advice", [(1000, "millimetres (use --units mm"),
                                           (100, "centimetres (use --units cm")])
def test_units_warning_names_the_likely_units(scale, advice):
    [warning] = caught(check_body, body() * scale, "target.ply", tpose=True)
    assert warning.category is UnitsWarning
    message = str(warning.message)
    assert message.startswith("target.ply: the body is") and advice in message
    assert f"{1.7 * scale:.4g} m tall" in message


def test_units_advice_follows_the_units_given():
    """A millimetre file read as centimetres: 17 m tall; the advice is still mm."""
    space = make_space("cm", "y")
    [warning] = caught(check_body, body() * 10, "t.ply", space=space)
    assert "(1700 cm) tall" in str(warning.message) and "--units mm" in str(warning.message)


@pytest.mark.parametrize("given, advice", [("y", "--up-axis z"), ("z", "--up-axis y")])
def test_up_axis_warning(given, advice):
    lying = body()[:, [0, 2, 1]]                        # height along Z
    [warning] = caught(check_body, lying, "t.ply", space=make_space("m", given), tpose=True)
    assert warning.category is UpAxisWarning and advice in str(warning.message)
    assert "lies along Z (1.7 m along Z" in str(warning.message)


def test_tpose_warning_and_none_for_a_good_body():
    [warning] = caught(check_body, body(arms_down=True), "a.ply", tpose=True)
    assert warning.category is TPoseWarning
    assert "the target should be in T-pose" in str(warning.message)
    assert "a ratio of 0.35" in str(warning.message)
    assert caught(check_body, body(), "b.ply", tpose=True) == []
    assert caught(check_body, body(arms_down=True), "source frame") == []   # sources: any pose


def test_retargeter_warns_on_target_and_first_frame_only(tiny_weights):
    retargeter = Retargeter(tiny_weights)
    assert [w.category for w in caught(retargeter.set_target, body() * 1000)] == [UnitsWarning]
    retargeter.set_target(body())
    [first] = caught(retargeter.step, body(seed=1) * 1000)
    assert "source points, frame 0" in str(first.message)
    assert caught(retargeter.step, body(seed=2) * 1000) == []       # only the stream's start
    quiet = Retargeter(tiny_weights, warn=False)
    assert caught(quiet.set_target, body() * 1000) == []


def test_cli_prints_warnings_as_one_line_each_and_goes_on(tmp_path, capsys):
    """Millimetre, Z-up files read as metres, Y-up with --force: a warning per mistake, naming
    the option for that file; with no option the units and axes are told from the bodies.
    A target not in T-pose is a warning, not a refusal."""
    space = make_space("mm", "z")
    write_mesh(tmp_path / "character.ply", from_canonical(body(), space))
    frames = np.stack([body(arms_down=True, seed=s) for s in range(3)])
    np.save(tmp_path / "walk.npy", from_canonical(frames, space))
    args = ["retarget", tmp_path / "walk.npy", tmp_path / "character.ply", "--format", "npz",
            "--weights", WEIGHTS]
    assert cli.main([str(a) for a in args + ["--out", tmp_path / "a", "--units", "m",
                                             "--up-axis", "y", "--force"]]) == 0
    err = [line for line in capsys.readouterr().err.splitlines()      # the input's warnings
           if "warning" in line and "source fit" not in line]
    assert len(err) == 4 and all(line.startswith("minretarget: warning: ") for line in err)
    assert "character.ply: the body is 1700 m tall" in err[0]
    assert "looks like millimetres (use --target-units mm" in err[0]
    assert "character.ply: the body lies along Z (1700 m along Z" in err[1]
    assert "(use --target-up z)" in err[1]
    assert "walk.npy: frame 0: the body is 1700 m tall" in err[2]
    assert "--source-units mm" in err[2]
    assert "walk.npy: frame 0: the body lies along Z" in err[3] and "--source-up z" in err[3]
    # With no option: no warning at all.
    assert cli.main([str(a) for a in args + ["--out", tmp_path / "b"]]) == 0
    assert not [line for line in capsys.readouterr().err.splitlines()
                if "warning" in line and "source fit" not in line]
    write_mesh(tmp_path / "arms_down.ply", from_canonical(body(arms_down=True), space))
    assert cli.main([str(a) for a in args[:2] + [tmp_path / "arms_down.ply"] + args[3:]
                     + ["--out", tmp_path / "c"]]) == 0
    [warning] = [line for line in capsys.readouterr().err.splitlines() if "warning" in line]
    assert "arms_down.ply: the arms look far from horizontal" in warning


# ----------------------------------------------------------------------------- errors

def test_public_functions_refuse_bad_arrays(tiny_weights):
    retargeter = Retargeter(tiny_weights, warn=False)
    retargeter.set_target(body())
    cases = [
        (retargeter.step, (np.zeros((0, 3)),), r"has 0 points; at least 64"),
        (retargeter.step, (np.zeros(300),), r"must have shape \(any, 3\), got \(300,\)"),
        (retargeter.step, (np.ones((100, 3), complex),), "real numeric array, got dtype complex"),
        (retargeter.step, (np.ones((100, 3), bool),), "dtype bool"),
        (retargeter.step, (np.full((100, 3), np.nan),), r"non-finite value nan at index \(0, 0"),
        (retargeter.step, (np.where(np.arange(300).reshape(100, 3) == 7, 1e300, 1.0),),
         r"value past float32's range 1e\+300 at index \(2, 1\)"),
        (retargeter.step_skeleton, (np.zeros((21, 3)),), r"must have shape \(22, 3\)"),
        (retargeter.set_target, (np.zeros((63, 3)),), "has 63 points; at least 64"),
        (retargeter.pose, (np.zeros((22, 3)), np.zeros(3)), r"rotations must have shape \(22, 4"),
        (forward_kinematics, (np.zeros((22, 4)), np.zeros(3), np.zeros((22, 3))),
         r"norm 0 at index \(0,\)"),
        (quaternion_to_matrix, ([[1, 0, 0, 0], [1e20, 0, 0, 0]],), r"norm 1e\+20 at index \(1,"),
        # Past 10 km float32 cannot hold a body to a millimetre (SKR overflowed at 1e12).
        (retargeter.step, (np.where(np.arange(300).reshape(100, 3) == 7, 1e12, 1.0),),
         r"source points has a coordinate 1e\+12 at index \(2, 1\), over 10000 m"),
        (retargeter.set_target, (body() - [2e4, 0, 0],), r"target points has a coordinate -1999\d\.\d+ at index \(0, 0\)"),
        (lambda: Retargeter(tiny_weights, workers="2"), (), "workers must be a positive "
         "integer, got '2'"),
        (lambda: Retargeter(tiny_weights, workers=0), (), "got 0"),
        (lambda: Retargeter(tiny_weights, workers=2.0), (), "got 2.0"),
    ]
    for function, args, message in cases:
        with warnings.catch_warnings():
            warnings.simplefilter("error")          # the error says it all: no warning first
            with pytest.raises(ValueError, match=message):
                function(*args)
    with pytest.raises(ValueError, match=r"frame 2: source points has a non-finite value inf"):
        list(retargeter.run([body(), body(), np.full((100, 3), np.inf)]))


def damaged_files(folder):
    """{name: (path, the message expected)} of damaged or malformed files of every kind."""
    folder.mkdir(exist_ok=True)
    rng = np.random.default_rng(0)
    cloud = rng.normal(size=(70, 3)).astype(np.float32)
    mesh = trimesh.creation.box()
    write_mesh(folder / "good.ply", mesh.vertices, mesh.faces)
    ply = (folder / "good.ply").read_bytes()
    cases = {}

    def put(name, data, message):
        (folder / name).write_bytes(data if isinstance(data, bytes) else data.encode())
        cases[name] = (folder / name, message)

    put("truncated.ply", ply[:len(ply) - 40], "truncated.ply: cannot read points")
    put("header.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex -3\nend_header\n",
        "header.ply: cannot read points")
    put("outside.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", "outside.obj")
    put("nan.xyz", "0 0 0\n1 nan 0\n", "nan.xyz: point 1 is not finite")
    put("words.xyz", "x y z\n", "words.xyz: cannot read points")
    np.save(folder / "pickled.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    cases["pickled.npy"] = (folder / "pickled.npy", "pickled.npy: not a readable .npy")
    np.save(folder / "whole.npy", cloud)
    put("truncated.npy", (folder / "whole.npy").read_bytes()[:200], "truncated.npy")
    put("header.npy", b"\x93NUMPY\x01\x00v\x00{'descr': '<f4', 'shape': (3, " + b" " * 100,
        "header.npy: not a readable .npy")
    np.save(folder / "scalar.npy", np.float32(0.0))
    cases["scalar.npy"] = (folder / "scalar.npy", r"scalar.npy: expected \(N, 3\)")
    put("claims.npy", claiming_npy((10**12, 3)), r"claims.npy: .*truncated: its header says "
        r"float32 \(1000000000000, 3\)")       # found by fuzzing: NumPy allocated 11 TiB
    return cases


def claiming_npy(shape):
    """An .npy whose header claims ``shape`` float32 but which holds 12 bytes of data."""
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, {"descr": "<f4", "fortran_order": False,
                                                  "shape": shape})
    return buffer.getvalue() + bytes(12)


def test_damaged_point_files_name_the_file(tmp_path):
    for name, (path, message) in damaged_files(tmp_path).items():
        with pytest.raises(ValueError, match=message):
            read_points(path)


def test_damaged_sources_name_the_file_and_frame(tmp_path):
    frames = np.random.default_rng(0).normal(size=(4, 70, 3)).astype(np.float32)
    np.save(tmp_path / "frames.npy", frames)
    data = (tmp_path / "frames.npy").read_bytes()
    (tmp_path / "cut.npy").write_bytes(data[:len(data) // 2])
    np.savez_compressed(tmp_path / "frames.npz", points=frames)
    data = bytearray((tmp_path / "frames.npz").read_bytes())
    (tmp_path / "cut.npz").write_bytes(bytes(data[:len(data) // 2]))
    data[len(data) // 3] ^= 0xFF                                 # inside the deflate stream
    (tmp_path / "flipped.npz").write_bytes(bytes(data))
    np.save(tmp_path / "complex.npy", frames.astype(complex))
    bvh = format_bvh(rig_to_bvh(np.random.default_rng(1).normal(size=(22, 3)),
                                np.tile([1.0, 0, 0, 0], (3, 22, 1)), np.zeros((3, 3)), 1 / 30))
    (tmp_path / "cut.bvh").write_text(bvh[:len(bvh) - 30])
    (tmp_path / "cut.bvh.gz").write_bytes(gzip.compress(bvh.encode())[:300])
    (tmp_path / "slow.bvh").write_text(bvh.replace("Frame Time: 0.03333333333333333",
                                                   "Frame Time: 1000"))
    (tmp_path / "text.npz").write_text("hello")         # NumPy would say "pickled data"
    infinite = frames.copy()
    infinite[1, 7, 1] = np.inf                           # not smeared by the units' product
    np.save(tmp_path / "inf.npy", infinite)
    (tmp_path / "folder").mkdir()
    np.save(tmp_path / "folder" / "f1.npy", frames[0])
    (tmp_path / "folder" / "f2.xyz").write_text("0 0 0\n")
    expected = {
        "cut.npy": "cut.npy: not a readable .npy",
        "cut.npz": r"cut.npz: not a readable .npz \(File is not a zip file\)",
        "text.npz": r"text.npz: not a readable .npz \(File is not a zip file\)",
        "inf.npy": r"inf.npy: frame 1: source points has a non-finite value inf at index \(7, 1\)",
        "missing": "missing: no such file or folder",
        "flipped.npz": "flipped.npz: .*array 'points'",
        "complex.npy": r"complex.npy: expected an array of frames \(T, P, 3\) of numbers",
        "cut.bvh": "cut.bvh:",
        "cut.bvh.gz": "cut.bvh.gz:0: cannot decompress",
        "slow.bvh": "slow.bvh: a source at 0.001 fps .* too slow to resample",
    }
    for name, message in expected.items():
        with warnings.catch_warnings():
            warnings.simplefilter("error")          # the error says it all: no warning first
            with pytest.raises(ValueError, match=message):
                source = open_source(tmp_path / name, make_space("cm"))
                for frame in source.frames:
                    pass
    retargeter = Retargeter.from_weights(WEIGHTS, warn=False)
    retargeter.set_target(body())
    source = open_source(tmp_path / "folder", CANONICAL)
    frames = iter(source.frames)
    retargeter.step(next(frames))
    with pytest.raises(ValueError, match="has 1 points"):
        retargeter.step(next(frames))
    assert source.frame_name(1).endswith("folder/f2.xyz")


def test_cli_reports_damaged_files_in_one_line(tmp_path, capsys):
    cases = damaged_files(tmp_path / "damaged")
    np.save(tmp_path / "frames.npy", np.stack([body(seed=s) for s in range(2)]))
    write_mesh(tmp_path / "target.ply", body())
    runs = [(["retarget", tmp_path / "frames.npy", path], name)
            for name, (path, _) in cases.items() if name != "scalar.npy"]
    (tmp_path / "bad_weights.npz").write_bytes(open(WEIGHTS, "rb").read()[:5000])
    runs.append((["retarget", tmp_path / "frames.npy", tmp_path / "target.ply", "--weights",
                  tmp_path / "bad_weights.npz"], "bad_weights.npz"))
    for args, name in runs:
        if "--weights" not in args:
            args = args + ["--weights", WEIGHTS]
        code = cli.main([str(a) for a in args + ["--out", tmp_path / "out"]])
        err = capsys.readouterr().err
        assert code == 1 and name in err and err.count("\n") == 1, (name, err)
        assert err.startswith("minretarget: error: ") and "Traceback" not in err


def test_internal_errors_are_one_line_too(monkeypatch, capsys):
    def broken(*args):
        raise ZeroDivisionError("a bug")
    monkeypatch.setattr(cli, "render", broken)
    assert cli.main(["render", "x.npz", "--out", "x.png"]) == 4
    err = capsys.readouterr().err
    assert err.startswith("minretarget: internal error: ZeroDivisionError: a bug")
    assert "MINRETARGET_TRACEBACK=1" in err and err.count("\n") == 1


# ----------------------------------------------------------------------------- weights

@pytest.fixture
def default_weights(tmp_path, monkeypatch):
    """A default-like weights file in a temporary data folder, installed as the default."""
    path = tmp_path / "data" / "default_weights.npz"
    path.parent.mkdir()
    shutil.copy(WEIGHTS, path)
    monkeypatch.setattr(weights, "DEFAULT_WEIGHTS", path)
    monkeypatch.setattr(cli, "DEFAULT_WEIGHTS", path)
    return path


def test_default_weights_are_checked_against_the_recorded_checksum(default_weights, capsys):
    with pytest.raises(ValueError, match="no readable recorded checksum .*python -m "
                                         "minretarget.checksum"):
        load_weights()
    assert checksum.main([]) == 0
    record = default_weights.with_suffix(".sha256").read_text()
    assert record == f"{weights.file_sha256(default_weights)}  default_weights.npz\n"
    assert "recorded in" in capsys.readouterr().out
    assert load_weights().config == load_weights(WEIGHTS).config
    assert load_weights(str(default_weights)).config            # the same file by its path

    # A modified copy: still a valid weights file, but not the one recorded.
    modified = flatten_weights(load_weights())
    modified["skin.output.bias"] = modified["skin.output.bias"] + np.float32(1e-3)
    save_weights(default_weights, weights.weights_from_arrays(modified))
    with pytest.raises(ValueError, match=r"default_weights.npz: SHA-256 [0-9a-f]{64} differs "
                                         r"from the recorded [0-9a-f]{64}.*damaged or was "
                                         r"replaced"):
        load_weights()
    shutil.copy(default_weights, default_weights.parent / "mine.npz")
    load_weights(default_weights.parent / "mine.npz")            # other paths: not checked
    np.save(default_weights.parent / "frames.npy", np.stack([body(seed=s) for s in range(2)]))
    write_mesh(default_weights.parent / "t.ply", body())
    assert cli.main(["retarget", str(default_weights.parent / "frames.npy"),
                     str(default_weights.parent / "t.ply"), "--out",
                     str(default_weights.parent / "out")]) == 1
    err = capsys.readouterr().err
    assert "differs from the recorded" in err and err.count("\n") == 1


def test_weights_member_claiming_a_huge_array(tmp_path):
    path = tmp_path / "claims.npz"
    shutil.copy(WEIGHTS, path)
    with zipfile.ZipFile(path, "a") as archive:
        archive.writestr("extra.npy", claiming_npy((10**12,)))
    with pytest.raises(ValueError, match=r"claims.npz: not a readable .npz \(member extra.npy "
                                         r"is truncated"):
        load_weights(path)


def test_recording_refuses_a_broken_file(default_weights, capsys):
    default_weights.write_bytes(b"PK\x03\x04 not weights")
    assert checksum.main([]) == 1
    assert "not a readable .npz" in capsys.readouterr().err
    assert not default_weights.with_suffix(".sha256").exists()


def test_the_shipped_default_weights_match_their_checksum():
    assert weights.DEFAULT_WEIGHTS.is_file(), "the default weights must ship with the package"
    weights.verify_checksum(weights.DEFAULT_WEIGHTS)


def test_bvh_reader_names_the_line(tmp_path):
    path = tmp_path / "bad.bvh"
    path.write_text("HIERARCHY\nROOT hip\n{\nOFFSET 0 0 x\n")
    with pytest.raises(ValueError, match=r"bad.bvh:\d+:"):
        read_bvh(path)
