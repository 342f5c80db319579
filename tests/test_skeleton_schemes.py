"""Any BVH skeleton onto the 22 canonical joints (issue 41): small hand-written BVHs of each
common naming scheme, mapped from their names and trees and retargeted with no option but the
files; a skeleton map for the rest; a zero pose that is not a T-pose."""
import json
from dataclasses import replace

import numpy as np
import pytest

from conftest import CMU_DIR, GOLDEN, needs_cmu
from minretarget import cli
from minretarget.bvh import (axis_rotation, local_rotations, matrix_to_euler, parse_bvh,
                             read_bvh, world_transforms)
from minretarget.conventions import JOINT_NAMES
from minretarget.formats.mesh import write_mesh
from minretarget.skeletons import _ancestors, canonical_world, map_skeleton, skeleton_of

WEIGHTS = str(GOLDEN / "tiny_weights.npz")
SIDES = {"left": 1, "right": -1}


def joint(name, offset, *children, end=None):
    """A BVH joint: (name, OFFSET (3,) in cm, children, End Site OFFSET or None)."""
    return name, np.asarray(offset, float), children, end


def bvh_text(root, frames=3, seed=0):
    """BVH text of a hierarchy (``joint``): the root's position and ZXY rotations, the
    others' ZXY rotations; frame 0 the zero pose, then random turns of up to 30 degrees."""
    lines, count = ["HIERARCHY"], [0]

    def write(node, depth, keyword):
        name, offset, children, end = node
        pad = "  " * depth
        channels = ("Xposition Yposition Zposition " if keyword == "ROOT" else "") + \
            "Zrotation Xrotation Yrotation"
        lines.extend([f"{pad}{keyword} {name}", pad + "{",
                      f"{pad}  OFFSET {' '.join(f'{v:g}' for v in offset)}",
                      f"{pad}  CHANNELS {len(channels.split())} {channels}"])
        count[0] += len(channels.split())
        for child in children:
            write(child, depth + 1, "JOINT")
        if end is not None:
            lines.extend([f"{pad}  End Site", pad + "  {",
                          f"{pad}    OFFSET {' '.join(f'{v:g}' for v in end)}", pad + "  }"])
        lines.append(pad + "}")

    write(root, 0, "ROOT")
    values = np.random.default_rng(seed).uniform(-30, 30, (frames, count[0]))
    values[:, :3] = root[1] + np.arange(frames)[:, None] * [2.0, 0, 1.0]     # walks along X
    values[0, 3:] = 0
    lines += ["MOTION", f"Frames: {frames}", "Frame Time: 0.0333333"]
    lines += [" ".join(f"{v:.6f}" for v in row) for row in values]
    return "\n".join(lines) + "\n"


def leg(side, hip, knee, ankle, toe=None, pelvic=None, twist=None):
    """A leg from the pelvis down (cm; T-pose facing +Z, left at +X): ``toe`` a joint, or
    None for the ankle's End Site; ``pelvic`` a joint first at the pelvis (CMU's LHipJoint);
    ``twist`` a leaf beside the knee (game rigs' twist bones)."""
    foot = (joint(ankle, (0, -42, 0), joint(toe, (0, -6, 12), end=(0, 0, 5))) if toe else
            joint(ankle, (0, -42, 0), end=(0, -6, 12)))
    extra = [joint(twist, (0, -20, 0), end=(0, -5, 0))] if twist else []
    chain = joint(hip, (9 * SIDES[side], -5, 0), joint(knee, (0, -42, 0), foot), *extra)
    return joint(pelvic, (0, 0, 0), chain) if pelvic else chain


def arm(side, collar, shoulder, elbow, wrist, fingers=()):
    """An arm from the top of the spine out: ``collar`` (or None), shoulder, elbow, wrist and
    a leaf per finger name."""
    x = SIDES[side]
    hand = joint(wrist, (25 * x, 0, 0), *[joint(f, (8 * x, 0, 2 * i), end=(3 * x, 0, 0))
                                          for i, f in enumerate(fingers)],
                 end=None if fingers else (8 * x, 0, 0))
    upper = joint(shoulder, (15 * x, 2, 0), joint(elbow, (28 * x, 0, 0), hand))
    return joint(collar, (3 * x, 8, 0), upper) if collar else joint(
        shoulder, (18 * x, 10, 0), *upper[2])


def body(pelvis, spine, necks, head, legs, arms, root=None):
    """A whole skeleton: ``spine`` joints up from the pelvis (30 cm to the neck in all), the
    arms from the last of them, the necks and the head; the legs from the pelvis; ``root`` a
    joint at the ground above it all (game rigs)."""
    step = (0, 30 / (len(spine) + 1), 0)
    top = joint(head, (0, 8, 0), end=(0, 15, 0))
    for number, name in reversed(list(enumerate(necks))):
        top = joint(name, step if number == 0 else (0, 6, 0), top)
    chest = (top, *arms)
    for name in reversed(spine):
        chest = (joint(name, step, *chest),)
    hips = joint(pelvis, (0, 95, 0), *legs, *chest)
    return joint(root, (0, -95, 0), hips) if root else hips


def sided(template):
    """{"left": ..., "right": ...} names from a template: {Side} Left, {S} L, {s} l."""
    return {side: template.format(Side=side.title(), S=side[0].upper(), s=side[0])
            for side in SIDES}


def scheme(pelvis, spine, necks, head, leg_names, arm_names, root=None, pelvic=None,
           fingers=(), twist=None):
    """(hierarchy, {canonical joint: its BVH joint}) of a scheme given name templates."""
    legs, arms, expected = [], [], {"pelvis": pelvis, "neck": necks[0], "head": head}
    for side in SIDES:
        names = [None if t is None else sided(t)[side] for t in leg_names]
        legs.append(leg(side, *names, pelvic=pelvic and sided(pelvic)[side],
                        twist=twist and sided(twist)[side]))
        expected.update({f"{side}_{part}": name for part, name in
                         zip(("hip", "knee", "ankle", "foot"), names) if name})
        names = [None if t is None else sided(t)[side] for t in arm_names]
        arms.append(arm(side, *names, fingers=[sided(f)[side] for f in fingers]))
        expected.update({f"{side}_{part}": name for part, name in
                         zip(("collar", "shoulder", "elbow", "wrist"), names) if name})
    if len(spine) >= 3:
        expected.update(spine1=spine[0], spine2=spine[len(spine) // 2], spine3=spine[-1])
    elif len(spine) == 2:
        expected.update(spine1=spine[0], spine2=spine[1])
    elif spine:
        expected.update(spine2=spine[0])
    return body(pelvis, spine, necks, head, legs, arms, root), expected


SCHEMES = {
    "cmu_standard": scheme("Hips", ["LowerBack", "Spine", "Spine1"], ["Neck", "Neck1"], "Head",
                           ["{Side}UpLeg", "{Side}Leg", "{Side}Foot", "{Side}ToeBase"],
                           ["{Side}Shoulder", "{Side}Arm", "{Side}ForeArm", "{Side}Hand"],
                           pelvic="{S}HipJoint", fingers=["{Side}FingerBase", "{S}Thumb"]),
    "mixamo": scheme("mixamorig:Hips", ["mixamorig:Spine", "mixamorig:Spine1",
                                        "mixamorig:Spine2"], ["mixamorig:Neck"],
                     "mixamorig:Head", ["mixamorig:{Side}UpLeg", "mixamorig:{Side}Leg",
                                        "mixamorig:{Side}Foot", "mixamorig:{Side}ToeBase"],
                     ["mixamorig:{Side}Shoulder", "mixamorig:{Side}Arm",
                      "mixamorig:{Side}ForeArm", "mixamorig:{Side}Hand"],
                     fingers=["mixamorig:{Side}HandIndex1"]),
    "mixamo_no_prefix": scheme("Hips", ["Spine", "Spine1"], ["Neck"], "Head",
                               ["{Side}UpLeg", "{Side}Leg", "{Side}Foot", "{Side}ToeBase"],
                               ["{Side}Shoulder", "{Side}Arm", "{Side}ForeArm", "{Side}Hand"],
                               fingers=["{Side}HandThumb1"]),
    "rokoko": scheme("Hips", ["Spine1", "Spine2", "Spine3", "Spine4"], ["Neck"], "Head",
                     ["{Side}Thigh", "{Side}Shin", "{Side}Foot", "{Side}Toe"],
                     ["{Side}Shoulder", "{Side}Arm", "{Side}ForeArm", "{Side}Hand"]),
    "unreal": scheme("pelvis", ["spine_01", "spine_02", "spine_03", "spine_04", "spine_05"],
                     ["neck_01", "neck_02"], "head",
                     ["thigh_{s}", "calf_{s}", "foot_{s}", "ball_{s}"],
                     ["clavicle_{s}", "upperarm_{s}", "lowerarm_{s}", "hand_{s}"],
                     root="root", twist="calf_twist_01_{s}", fingers=["index_01_{s}"]),
    "smpl": scheme("Pelvis", ["Spine1", "Spine2", "Spine3"], ["Neck"], "Head",
                   ["{S}_Hip", "{S}_Knee", "{S}_Ankle", "{S}_Foot"],
                   ["{S}_Collar", "{S}_Shoulder", "{S}_Elbow", "{S}_Wrist"],
                   fingers=["{S}_Hand"]),
    "biovision": scheme("Hips", ["Chest"], ["Neck"], "Head",
                        ["{Side}Hip", "{Side}Knee", "{Side}Ankle", None],
                        ["{Side}Collar", "{Side}Shoulder", "{Side}Elbow", "{Side}Wrist"]),
    "3ds_max_biped": scheme("Bip01_Pelvis", ["Bip01_Spine", "Bip01_Spine1", "Bip01_Spine2"],
                            ["Bip01_Neck"], "Bip01_Head",
                            ["Bip01_{S}_Thigh", "Bip01_{S}_Calf", "Bip01_{S}_Foot",
                             "Bip01_{S}_Toe0"],
                            ["Bip01_{S}_Clavicle", "Bip01_{S}_UpperArm", "Bip01_{S}_Forearm",
                             "Bip01_{S}_Hand"], root="Bip01", fingers=["Bip01_{S}_Finger0"]),
    "motionbuilder": scheme("Character1_Hips", ["Character1_Spine", "Character1_Spine1"],
                            ["Character1_Neck"], "Character1_Head",
                            ["Character1_{Side}UpLeg", "Character1_{Side}Leg",
                             "Character1_{Side}Foot", "Character1_{Side}ToeBase"],
                            ["Character1_{Side}Shoulder", "Character1_{Side}Arm",
                             "Character1_{Side}ForeArm", "Character1_{Side}Hand"]),
    "no_collars": scheme("Hips", ["Spine", "Chest"], ["Neck"], "Head",
                         ["{Side}UpLeg", "{Side}LowLeg", "{Side}Foot", None],
                         [None, "{Side}UpArm", "{Side}LowArm", "{Side}Hand"]),
}


def motion_of(name, frames=3):
    return parse_bvh(bvh_text(SCHEMES[name][0], frames), source=f"{name}.bvh")


@pytest.mark.parametrize("name", SCHEMES)
def test_each_scheme_maps_its_joints(name):
    """Every canonical joint the scheme has is its joint, in every frame; the others lie on
    the way from their parent to a joint it has (the spine, the collars) or at the ankle's
    End Site (the balls of the feet); left is left."""
    motion = motion_of(name)
    expected = SCHEMES[name][1]
    positions, _ = canonical_world(motion, source=f"{name}.bvh")           # (T, J, 3)
    world, _ = world_transforms(motion)
    for j, canonical in enumerate(JOINT_NAMES):
        if canonical in expected:
            np.testing.assert_allclose(positions[:, j], world[:, motion.names.index(
                expected[canonical])], atol=1e-9, err_msg=canonical)
    placed = {j for j in JOINT_NAMES if j not in expected}
    assert set(skeleton_of(motion)[1].rigid) == placed
    zero = positions[0]                                       # the zero pose: a T-pose
    for part in ("hip", "knee", "ankle", "foot", "collar", "shoulder", "elbow", "wrist"):
        assert zero[JOINT_NAMES.index(f"left_{part}"), 0] > zero[0, 0] > \
            zero[JOINT_NAMES.index(f"right_{part}"), 0], part
    heights = zero[[JOINT_NAMES.index(j) for j in ("pelvis", "spine1", "spine2", "spine3",
                                                    "neck", "head")], 1]
    assert (np.diff(heights) > 0).all(), heights


def test_the_known_tables_still_come_first():
    assert skeleton_of(motion_of("mixamo"))[0] == "mixamo"
    assert skeleton_of(motion_of("rokoko"))[0] == "found from its names"


@pytest.mark.parametrize("name", ["cmu_standard", "unreal", "biovision"])
def test_a_scheme_retargets_with_no_option(tmp_path, capsys, name):
    """The file and a body, nothing else: centimetres told from the skeleton."""
    path = tmp_path / f"{name}.bvh"
    path.write_text(bvh_text(SCHEMES[name][0], frames=4))
    target = np.random.default_rng(0).uniform([-0.8, 0, -0.1], [0.8, 1.7, 0.1], (300, 3))
    write_mesh(tmp_path / "target.ply", target.astype(np.float32))
    assert cli.main(["retarget", str(path), str(tmp_path / "target.ply"), "--out",
                     str(tmp_path / "out"), "--format", "npz", "--weights", WEIGHTS]) == 0
    assert "source: centimetres (detected)" in capsys.readouterr().out
    with np.load(tmp_path / "out" / "result.npz") as result:
        assert result["source_joints"].shape == (4, 22, 3)


def test_a_skeleton_map_names_what_the_names_do_not(tmp_path, capsys):
    """Joints named in no known way: refused with what is missing, then mapped by a file."""
    hierarchy, expected = SCHEMES["smpl"]
    renamed = {"L_Knee": "Jnt_07", "R_Knee": "Jnt_08"}
    text = bvh_text(hierarchy)
    for old, new in renamed.items():
        text = text.replace(f" {old}\n", f" {new}\n")
    path = tmp_path / "studio.bvh"
    path.write_text(text)
    target = tmp_path / "target.ply"
    write_mesh(target, np.random.default_rng(0).uniform([-0.8, 0, -0.1], [0.8, 1.7, 0.1],
                                                        (300, 3)).astype(np.float32))
    args = ["retarget", str(path), str(target), "--out", str(tmp_path / "out"), "--format",
            "npz", "--weights", WEIGHTS]
    assert cli.main(args) == 1
    err = capsys.readouterr().err
    assert "studio.bvh: cannot tell which of its joints are left_knee, right_knee" in err
    assert "--skeleton-map" in err
    (tmp_path / "map.json").write_text(json.dumps({"left_knee": "Jnt_07",
                                                   "right_knee": "Jnt_08"}))
    assert cli.main(args + ["--skeleton-map", str(tmp_path / "map.json")]) == 0
    motion = parse_bvh(text)
    world, _ = world_transforms(motion)
    with np.load(tmp_path / "out" / "result.npz") as result:
        knee = result["source_joints"][:, JOINT_NAMES.index("left_knee")]
    assert np.linalg.norm(knee[0] - world[0, motion.names.index("Jnt_07")] / 100) < 0.05


def test_inspect_prints_what_maps_to_what(tmp_path, capsys):
    path = tmp_path / "biovision.bvh"
    path.write_text(bvh_text(SCHEMES["biovision"][0]))
    assert cli.main(["inspect", str(path)]) == 0
    out = capsys.readouterr().out
    assert "skeleton found from its names" in out
    assert "left_hip" in out and "LeftHip" in out
    assert "spine1" in out and "between Hips and Chest" in out
    assert "left_foot" in out and "End Site of LeftAnkle" in out


def test_a_zero_pose_that_is_not_a_t_pose_changes_nothing():
    """A skeleton source is retargeted from its joint positions: the same motion written over
    a zero pose with the arms hanging down maps to the same canonical joints."""
    t_pose = motion_of("mixamo_no_prefix")
    offsets, rotations = t_pose.offsets.copy(), local_rotations(t_pose)   # (T, J', 3, 3)
    for side, sign in SIDES.items():
        down = axis_rotation("Z", -90 * sign)          # the arm's rest turned down by this
        first = t_pose.names.index(f"{side.title()}Arm")
        arm = [first] + [j for j in range(len(offsets)) if first in _ancestors(t_pose.parents, j)]
        for j in arm:
            parent = t_pose.parents[j]
            offsets[j] = down @ offsets[j] if parent in arm else offsets[j]
            # world rotations G' = G C^T over offsets C o: R' = C_parent R C^T
            rotations[:, j] = (down if parent in arm else np.eye(3)) @ rotations[:, j] @ down.T
        t_pose.end_sites.update({j: down @ t_pose.end_sites[j] for j in arm
                                 if j in t_pose.end_sites})
    values = t_pose.values.copy()
    for j, channels in enumerate(t_pose.channels):
        start = t_pose.channel_starts[j] + len(channels) - 3             # ZXY, last three
        values[:, start:start + 3] = matrix_to_euler(rotations[:, j], "ZXY")
    arms_down = replace(t_pose, offsets=offsets, values=values)
    zero, _ = world_transforms(replace(arms_down, values=np.zeros_like(values)))
    assert zero[0, t_pose.names.index("LeftHand"), 1] < zero[0, t_pose.names.index("LeftArm"),
                                                              1] - 40          # arms down
    np.testing.assert_allclose(canonical_world(arms_down)[0],
                               canonical_world(motion_of("mixamo_no_prefix"))[0],
                               atol=1e-6)


@needs_cmu(CMU_DIR / "cgspeed" / "08" / "08_01.bvh.gz")
def test_names_and_tree_alone_find_the_cmu_table_on_a_real_file():
    """The CMU "Daz" conversion, mapped without its table, gives the table's joints."""
    motion = read_bvh(CMU_DIR / "cgspeed" / "08" / "08_01.bvh.gz")
    found = map_skeleton(motion)
    assert found.rigid["spine3"] == ("between", "neck", 0.5)
    np.testing.assert_allclose(canonical_world(motion, found)[0],
                               canonical_world(motion, "cmu")[0], atol=1e-9)
