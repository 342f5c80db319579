"""The BVH reader: parsing, Euler conventions, forward kinematics, resampling, errors."""
import gzip
import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from minretarget.bvh import (BVHError, euler_to_matrix, matrix_to_euler, parse_bvh, read_bvh,
                             resample, scale_motion, world_transforms)

# A 3-joint chain along +Y: root (6 channels), j1 and j2 one unit apart, an End Site above j2.
# Frame 0: root at (1, 2, 3) turned 90 degrees about Z, so the chain points to -X.
# Frame 1: the same, and j1 turns another 90 degrees about Z, so j2's bone points to -Y.
CHAIN = """HIERARCHY
ROOT root
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT j1
  {
    OFFSET 0 1 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT j2
    {
      OFFSET 0 1 0
      CHANNELS 3 Zrotation Xrotation Yrotation
      End Site
      {
        OFFSET 0 1 0
      }
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.0333333
1 2 3 90 0 0 0 0 0 0 0 0
1 2 3 90 0 0 90 0 0 0 0 0
"""


def one_joint(channels, values, frame_time=1 / 30):
    """A root and one child at OFFSET (0, 1, 0) whose rotation channels are ``channels``;
    ``values`` (T, K) are the child's channel values, the root stays at the origin."""
    lines = ["HIERARCHY", "ROOT root", "{", "OFFSET 0 0 0",
             "CHANNELS 3 Xposition Yposition Zposition", "JOINT arm", "{", "OFFSET 1 0 0",
             f"CHANNELS {len(channels)} {' '.join(channels)}", "End Site", "{", "OFFSET 0 1 0",
             "}", "}", "}", "MOTION", f"Frames: {len(values)}", f"Frame Time: {frame_time}"]
    lines += ["0 0 0 " + " ".join(str(v) for v in row) for row in values]
    return "\n".join(lines) + "\n"


def end_site_position(motion, joint, frame=0):
    positions, rotations = world_transforms(motion)
    return positions[frame, joint] + rotations[frame, joint] @ motion.end_sites[joint]


# ----------------------------------------------------------------------------- parsing

def test_parses_the_hierarchy_and_motion():
    motion = parse_bvh(CHAIN)
    assert motion.names == ("root", "j1", "j2")
    assert motion.parents.tolist() == [-1, 0, 1]
    np.testing.assert_array_equal(motion.offsets, [[0, 0, 0], [0, 1, 0], [0, 1, 0]])
    assert motion.channels[0] == ("Xposition", "Yposition", "Zposition",
                                  "Zrotation", "Xrotation", "Yrotation")
    assert motion.channel_starts.tolist() == [0, 6, 9]
    assert list(motion.end_sites) == [2]
    assert motion.values.shape == (2, 12) and motion.values.dtype == np.float64
    assert motion.frame_time == pytest.approx(1 / 30) and motion.fps == 30.0


def test_chain_positions_by_hand():
    positions, rotations = world_transforms(parse_bvh(CHAIN))
    np.testing.assert_allclose(positions[0], [[1, 2, 3], [0, 2, 3], [-1, 2, 3]], atol=1e-12)
    np.testing.assert_allclose(positions[1], [[1, 2, 3], [0, 2, 3], [0, 1, 3]], atol=1e-12)
    rz90 = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    np.testing.assert_allclose(rotations[1, 0], rz90, atol=1e-12)
    np.testing.assert_allclose(rotations[1, 2], rz90 @ rz90, atol=1e-12)


def test_channel_order_is_intrinsic_and_per_joint():
    # z = 90, x = 90. ZXY: R = Rz Rx maps the End Site (0, 1, 0) to (0, 0, 1);
    # XYZ: R = Rx Rz maps it to (-1, 0, 0).
    zxy = parse_bvh(one_joint(["Zrotation", "Xrotation", "Yrotation"], [[90, 90, 0]]))
    xyz = parse_bvh(one_joint(["Xrotation", "Yrotation", "Zrotation"], [[90, 0, 90]]))
    np.testing.assert_allclose(end_site_position(zxy, 1), [1, 0, 1], atol=1e-12)
    np.testing.assert_allclose(end_site_position(xyz, 1), [0, 0, 0], atol=1e-12)


def test_position_channels_replace_the_offset_and_partial_rotations_work():
    text = one_joint(["Yposition", "Zrotation"], [[5, 90]])
    motion = parse_bvh(text)
    positions, _ = world_transforms(motion)
    np.testing.assert_allclose(positions[0, 1], [1, 5, 0])          # OFFSET y replaced by 5
    np.testing.assert_allclose(end_site_position(motion, 1), [0, 5, 0], atol=1e-12)


def test_crlf_mixed_line_ends_and_case_of_channel_names():
    lf = parse_bvh(CHAIN)
    crlf = parse_bvh(CHAIN.replace("\n", "\r\n"))
    # The CMU files switch from LF to CRLF mid-file.
    head, tail = CHAIN.split("JOINT j2")
    mixed = parse_bvh(head + "JOINT j2" + tail.replace("\n", "\r\n").replace("Zrotation",
                                                                             "ZROTATION"))
    for other in (crlf, mixed):
        assert other.names == lf.names and other.channels == lf.channels
        np.testing.assert_array_equal(other.values, lf.values)


def test_reads_plain_and_gzip_files(tmp_path):
    (tmp_path / "a.bvh").write_text(CHAIN)
    with gzip.open(tmp_path / "a.bvh.gz", "wt") as f:
        f.write(CHAIN)
    (tmp_path / "gzip_without_suffix.bvh").write_bytes((tmp_path / "a.bvh.gz").read_bytes())
    for name in ("a.bvh", "a.bvh.gz", "gzip_without_suffix.bvh"):
        np.testing.assert_array_equal(read_bvh(tmp_path / name).values, parse_bvh(CHAIN).values)


def test_scale_changes_lengths_only():
    motion = parse_bvh(CHAIN)
    scaled = parse_bvh(CHAIN, scale=0.01)
    p, r = world_transforms(motion)
    ps, rs = world_transforms(scaled)
    np.testing.assert_allclose(ps, 0.01 * p, atol=1e-14)
    np.testing.assert_allclose(rs, r)
    np.testing.assert_allclose(scaled.end_sites[2], [0, 0.01, 0])
    np.testing.assert_array_equal(scale_motion(motion, 0.01).values, scaled.values)


def test_axes_mapping():
    # Turn the world 90 degrees about +Y: x -> -z, z -> x.
    axes = np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    motion = parse_bvh(CHAIN)
    p, r = world_transforms(motion)
    pa, ra = world_transforms(motion, axes=axes)
    np.testing.assert_allclose(pa, p @ axes.T, atol=1e-12)
    np.testing.assert_allclose(ra, axes @ r @ axes.T, atol=1e-12)
    with pytest.raises(ValueError):
        world_transforms(motion, axes=np.diag([1, 1, -1]))                # a mirror


# ----------------------------------------------------------------------------- Euler angles

@pytest.mark.parametrize("order", ["".join(p) for p in itertools.permutations("XYZ")])
def test_matrix_to_euler_inverts_euler_to_matrix(order):
    rng = np.random.default_rng(0)
    angles = rng.uniform(-180, 180, (500, 3))
    angles[:, 1] = rng.uniform(-89, 89, 500)
    matrices = euler_to_matrix(angles, order)
    np.testing.assert_allclose(matrix_to_euler(matrices, order), angles, atol=1e-9)
    # Gimbal lock: the angles are not unique, the rotation is.
    angles[:, 1] = 90.0
    matrices = euler_to_matrix(angles, order)
    np.testing.assert_allclose(euler_to_matrix(matrix_to_euler(matrices, order), order),
                               matrices, atol=1e-9)


def test_euler_to_matrix_composes_in_listed_order():
    rz = euler_to_matrix([90.0], "Z")
    rx = euler_to_matrix([90.0], "X")
    np.testing.assert_allclose(euler_to_matrix([90.0, 90.0], "ZX"), rz @ rx, atol=1e-15)
    np.testing.assert_allclose(rz @ [1, 0, 0], [0, 1, 0], atol=1e-15)     # right-handed
    np.testing.assert_array_equal(euler_to_matrix(np.zeros((4, 0)), ""), np.tile(np.eye(3),
                                                                                 (4, 1, 1)))


# ----------------------------------------------------------------------------- resampling

def test_resample_60_to_30_keeps_every_other_frame():
    rng = np.random.default_rng(1)
    values = rng.uniform(-170, 170, (11, 3))                  # beyond any canonical range
    motion = parse_bvh(one_joint(["Zrotation", "Xrotation", "Yrotation"], values, 1 / 60))
    half = resample(motion, fps=30)
    assert half.num_frames == 6 and half.frame_time == pytest.approx(1 / 30)
    np.testing.assert_array_equal(half.values, motion.values[::2])
    assert resample(motion, fps=30, source_fps=120).num_frames == 3   # overrides the header


def test_resample_interpolates_positions_linearly_and_rotations_by_slerp():
    text = one_joint(["Zrotation", "Xrotation", "Yrotation"], [[0, 0, 0], [90, 0, 0]], 0.1)
    text = text.replace("0 0 0 90 0 0", "2 0 0 90 0 0")       # the root moves 2 along x
    motion = resample(parse_bvh(text), fps=20)
    assert motion.num_frames == 3
    np.testing.assert_allclose(motion.values[1], [1, 0, 0, 45, 0, 0], atol=1e-4)
    # Slerp takes the short way round: 170 -> -170 passes through 180, not 0.
    wrap = resample(parse_bvh(one_joint(["Zrotation"] + ["Xrotation", "Yrotation"],
                                        [[170, 0, 0], [-170, 0, 0]], 0.1)), fps=20)
    assert abs(abs(wrap.values[1, 3]) - 180) < 1e-3


# ----------------------------------------------------------------------------- errors

def broken(old, new, count=1):
    assert old in CHAIN
    return CHAIN.replace(old, new, count)


@pytest.mark.parametrize("text, line, words", [
    (broken("1 2 3 90 0 0 90 0 0 0 0 0", "1 2 3 90 0 0 90 0 0 0 0"), 25, "expected 12 values"),
    (broken("Yrotation\n  JOINT j1", "Wrotation\n  JOINT j1"), 5, "unknown channel"),
    (broken("OFFSET 0 1 0", "OFFSET 0 x 0"), 8, "bad number"),
    (broken("1 2 3 90 0 0 0", "1 2 3 9O 0 0 0"), 24, "bad number"),
    (broken("1 2 3 90 0 0 0", "1 2 3 nan 0 0 0"), 24, "bad number"),
    (broken("      End Site", "      End Sight"), 14, "Site"),
    (broken("    }\n  }\n}", "    }\n  }"), 19, "end of HIERARCHY"),
    (broken("  {\n    OFFSET 0 1 0", "    OFFSET 0 1 0"), 7, "expected '{'"),
    (broken("Frames: 2", "Frames: 3"), 25, "ends after 2 of 3 frames"),
    (broken("Frames: 2", "Frames: 1"), 25, "more frame lines"),
    (broken("Frames: 2", "Frames: two"), 22, "Frames:"),
    (broken("Frame Time: 0.0333333", "Frame Time: 0"), 23, "frame time"),
    (broken("CHANNELS 3 Zrotation Xrotation Yrotation", "CHANNELS 3 Zrotation Xrotation"), 10,
     "unknown channel"),
    (broken("Xrotation Yrotation\n  JOINT", "Zrotation Yrotation\n  JOINT"), 5, "repeated"),
    (CHAIN.replace("MOTION", "MOTIONS"), 25, "no MOTION"),
    (CHAIN.replace("}\nMOTION", "}\nROOT other\n{\n}\nMOTION"), 21, "only one ROOT"),
])
def test_malformed_input_names_file_and_line(text, line, words):
    with pytest.raises(BVHError, match=rf"^walk\.bvh:{line}: .*{words}"):
        parse_bvh(text, source="walk.bvh")


def test_corrupt_gzip_names_the_file(tmp_path):
    path = tmp_path / "cut.bvh.gz"
    path.write_bytes(gzip.compress(CHAIN.encode())[:40])
    with pytest.raises(BVHError, match="cut.bvh.gz"):
        read_bvh(path)


# Any cut before the last value of the last frame must be refused (a cut inside that value
# may still leave a valid number, which no reader can tell).
_LAST_VALUE = CHAIN.rstrip().rindex(" ") + 1


@settings(max_examples=300, deadline=None)
@given(st.integers(min_value=0, max_value=_LAST_VALUE), st.booleans())
def test_any_truncation_raises_bvh_error(cut, crlf):
    text = CHAIN[:cut]
    with pytest.raises(BVHError, match=r"^<string>:\d+: "):
        parse_bvh(text.replace("\n", "\r\n") if crlf else text)
