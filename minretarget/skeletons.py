"""BVH skeletons and the canonical 22-joint skeleton, both ways. NumPy only.

Reading: a BVH skeleton -> the 22 canonical joints
    A table per known naming scheme (``SKELETONS``) gives, for each canonical joint, the BVH
    joint whose world rotation and position it takes, or None for a joint the scheme lacks;
    such a joint moves rigidly with its canonical parent, at a zero-pose offset named in the
    table's ``rigid`` entry. Names match without case and without a namespace prefix
    (``mixamorig:Hips`` matches ``Hips``). Known schemes:
      - canonical: the 22 names of ``minretarget.conventions`` (what ``rig_to_bvh`` writes);
      - cmu: the CMU "Daz-friendly" conversion (hip, abdomen, chest, lThigh, ...). CMU's chest
        is one rigid segment from the chest joint up to the neck and collars: chest's rotation
        goes on spine2 and spine3 is a point on that segment halfway from chest to neck, so a
        target's spine_02 + spine_03 bend like that one segment and FK on the CMU skeleton
        stays exact. The balls of the feet are the l/rFoot End Sites, 12 cm in front of and
        4 cm below the ankles; CMU has no toe rotation, so the toes stay rigid with the ankle;
      - mixamo: Hips, Spine, Spine1, Spine2, LeftUpLeg, ... one to one.
    Any other skeleton is mapped from its joint names and its tree (``map_skeleton``): each
    name's side (``Left``/``Right``, ``L_``, ``_l``, ``lThigh``; else the side of the body
    it lies on in the zero pose) and what is left of it name the limb joints (``UpLeg``,
    ``Thigh``, ``Hip`` ... ``Hand``, ``Wrist``), each searched below the one before it; the
    pelvis is where the legs meet, the spine the joints between it and the neck: the CMU
    standard conversion (``Hips/LHipJoint/LeftUpLeg``), Mixamo with or without a prefix,
    Rokoko (``LeftThigh/LeftShin``), the Unreal mannequin (``pelvis/thigh_l/calf_l``),
    SMPL-style (``Pelvis/L_Hip``), Biovision (``Hips/Chest/LeftHip``), 3ds Max Biped
    (``Bip01_L_Thigh``: a prefix all names share is set aside) and most studios'.
    A canonical joint the skeleton lacks is placed on the way from its parent to a joint
    it has (rigid entry "between"), or at the ankle's End Site (the ball of the foot).
    ``--skeleton-map FILE.json`` ({canonical joint: BVH joint}) settles the rest.
    World rotations are relative to the BVH zero pose, where every world rotation is the
    identity, so a canonical joint's world rotation is its BVH joint's world rotation. A
    skeleton source is retargeted from its joint positions alone, so a zero pose that is not
    a T-pose changes nothing there.

Writing: a retargeted rig -> BVH (``rig_to_bvh``)
    The 22 canonical names in depth-first order (what a BVH hierarchy lists), OFFSETs from the
    T-pose skeleton, the root's position channels, ZXY Euler rotation channels, and an End Site
    on each leaf joint half its parent bone long (the rig has no bone beyond a leaf; viewers
    want one to draw).
"""
import os
import re
from typing import NamedTuple

import numpy as np

from .bvh import BVHMotion, matrix_to_euler, world_transforms
from .conventions import JOINT_NAMES, NUM_JOINTS, PARENTS
from .kinematics import quaternion_to_matrix


class Skeleton(NamedTuple):
    """How one BVH naming scheme maps onto the canonical joints.

    bones: {canonical joint: BVH joint name, or None if it moves rigidly with its parent}.
    rigid: {canonical joint: (kind, BVH joint, fraction)}: its zero-pose offset from its
        canonical parent is ``fraction`` times that BVH joint's OFFSET (kind "offset") or
        End Site OFFSET (kind "end_site"); or it lies ``fraction`` of the way from its
        canonical parent to that BVH joint, frame by frame (kind "between").
    """
    bones: dict
    rigid: dict


# Canonical joint -> the CMU (Daz) joint whose world rotation and position it takes.
CMU_BONES = {
    "pelvis": "hip", "left_hip": "lThigh", "right_hip": "rThigh", "spine1": "abdomen",
    "left_knee": "lShin", "right_knee": "rShin", "spine2": "chest",
    "left_ankle": "lFoot", "right_ankle": "rFoot", "spine3": None,
    "left_foot": None, "right_foot": None, "neck": "neck",
    "left_collar": "lCollar", "right_collar": "rCollar", "head": "head",
    "left_shoulder": "lShldr", "right_shoulder": "rShldr",
    "left_elbow": "lForeArm", "right_elbow": "rForeArm",
    "left_wrist": "lHand", "right_wrist": "rHand",
}
MIXAMO_BONES = {
    "pelvis": "Hips", "left_hip": "LeftUpLeg", "right_hip": "RightUpLeg", "spine1": "Spine",
    "left_knee": "LeftLeg", "right_knee": "RightLeg", "spine2": "Spine1",
    "left_ankle": "LeftFoot", "right_ankle": "RightFoot", "spine3": "Spine2",
    "left_foot": "LeftToeBase", "right_foot": "RightToeBase", "neck": "Neck",
    "left_collar": "LeftShoulder", "right_collar": "RightShoulder", "head": "Head",
    "left_shoulder": "LeftArm", "right_shoulder": "RightArm",
    "left_elbow": "LeftForeArm", "right_elbow": "RightForeArm",
    "left_wrist": "LeftHand", "right_wrist": "RightHand",
}
SKELETONS = {
    "canonical": Skeleton({name: name for name in JOINT_NAMES}, {}),
    "cmu": Skeleton(CMU_BONES, {"spine3": ("offset", "neck", 0.5),
                                "left_foot": ("end_site", "lFoot", 1.0),
                                "right_foot": ("end_site", "rFoot", 1.0)}),
    "mixamo": Skeleton(MIXAMO_BONES, {}),
}
EULER_ORDER = "ZXY"          # rotation channels written by rig_to_bvh


def _bare(name):
    """A joint name without its namespace ("rig:Hips") or Mixamo prefix ("mixamorigHips")."""
    return re.sub(r"^mixamorig\d*_?", "", name.rsplit(":", 1)[-1], flags=re.IGNORECASE)


def _key(name):
    """A joint name as matched: ``_bare``, lower case."""
    return _bare(name).lower()


def _needed(skeleton):
    return {b for b in skeleton.bones.values() if b} | {r[1] for r in skeleton.rigid.values()}


def find_skeleton(names):
    """The name of the first scheme of ``SKELETONS`` whose joints ``names`` all contain, or
    None."""
    present = {_key(name) for name in names}
    return next((key for key, table in SKELETONS.items()
                 if all(_key(b) in present for b in _needed(table))), None)


# Limb joints by what is left of their names once the side is taken out (lower case, letters
# and digits): a leg's from the hip down, each below the one before it, nearest the root; an
# arm's from the wrist up, each the nearest above the one before it.
LEG = (("hip", r"up(per)?leg|thigh|femur|hip"),
       ("knee", r"(low(er)?)?leg|shin|calf|knee|tibia"),
       ("ankle", r"foot|ankle"), ("foot", r"toes?0?|toebase|ball|foot"))
ARM = (("wrist", r"hand|wrist"), ("elbow", r"forearm|low(er)?arm|elbow"),
       ("shoulder", r"(up(per)?)?arm|shoulder|shldr|humerus"),
       ("collar", r"collar|clavicle|shoulder"))
_SIDE_NAMES = (r"(?i:(?P<side>left|right))[_. -]?(?P<base>.+)",
               r"(?P<side>[LlRr])(?:[_. -]|(?=[A-Z]))(?P<base>.+)",
               r"(?P<base>.+?)[_. -](?i:(?P<side>left|right|l|r))")


def shared_prefix(names):
    """The prefix that every joint name but the root's (often bare: "Bip01", "root") has, up
    to a separator ("Bip01_", "Character1_"), or ""."""
    common = os.path.commonprefix([_bare(name) for name in names[1:]]) if len(names) > 2 else ""
    return re.match(r"(.*[_:. -])?", common)[0] or ""


def split_side(name):
    """A joint name's side and what is left: "mixamorig:LeftUpLeg" -> ("left", "upleg"),
    "thigh_l" -> ("left", "thigh"), "lThigh" -> ("left", "thigh"), "Spine1" -> (None,
    "spine1")."""
    name = _bare(name)
    for pattern in _SIDE_NAMES:
        match = re.fullmatch(pattern, name)
        if match:
            side = "left" if match["side"][0] in "Ll" else "right"
            return side, re.sub(r"[^a-z0-9]", "", match["base"].lower())
    return None, re.sub(r"[^a-z0-9]", "", name.lower())


def map_skeleton(bvh, given=None, source="BVH"):
    """Map any BVH skeleton onto the canonical joints from its names and tree (module
    docstring).

    Args:
        bvh: BVHMotion.
        given: {canonical joint: BVH joint name} that overrides the search (``--skeleton-map``).
        source: names the file in errors.
    Returns:
        Skeleton.
    Raises:
        ValueError naming the file, the canonical joints not found and what to do.
    """
    index = {}
    for i, name in enumerate(bvh.names):
        index.setdefault(_key(name), i)
    chosen = {}
    for joint, name in (given or {}).items():
        if joint not in JOINT_NAMES or not isinstance(name, str) or _key(name) not in index:
            what = "a joint of the file" if joint in JOINT_NAMES else "a canonical joint"
            raise ValueError(f"{source}: the skeleton map's {joint!r}: {name!r}: not {what}")
        chosen[joint] = index[_key(name)]
    parents = bvh.parents
    zero = np.zeros((len(parents), 3))              # (J', 3) the zero pose: sides of the body
    for i, parent in enumerate(parents):
        zero[i] = bvh.offsets[i] + (zero[parent] if parent >= 0 else 0)
    margin = 0.02 * np.ptp(zero, axis=0).max()
    prefix = shared_prefix(bvh.names)
    split = [split_side(_bare(name).removeprefix(prefix)) for name in bvh.names]
    sides = [side or ("left" if x > margin else "right" if x < -margin else None)
             for (side, _), x in zip(split, zero[:, 0] - zero[0, 0])]
    lineage = [set(_ancestors(parents, i)) for i in range(len(parents))]

    def find(joint, pattern, side, near=None, below=True, deepest=False):
        """``chosen[joint]``, set if not given: the joint of ``side`` whose base name is
        ``pattern``, below (``below=False``: above) joint ``near`` (None: anywhere),
        nearest the root (``deepest``: farthest from it), or None."""
        if joint not in chosen:
            found = [i for i, (_, base) in enumerate(split)
                     if sides[i] == side and re.fullmatch(pattern, base)
                     and (near is None or (near in lineage[i] if below else i in lineage[near]))]
            chosen[joint] = min(found, default=None,
                                key=lambda i: -len(lineage[i]) if deepest else len(lineage[i]))
        return chosen[joint]

    for side in ("left", "right"):
        for chain, below in ((LEG, True), (ARM, False)):   # down the leg; up the arm
            near = None
            for number, (part, pattern) in enumerate(chain):
                if near is None and number:
                    break
                near = find(f"{side}_{part}", pattern, side, near, below,
                            deepest=near is not None and not below)
    head = find("head", "head", None)
    if head is not None:
        find("neck", r"neck\d*", None, head, below=False)
    hips = (chosen.get("left_hip"), chosen.get("right_hip"))
    if "pelvis" not in chosen and None not in hips:
        chosen["pelvis"] = next((i for i in _ancestors(parents, hips[0])
                                 if i in lineage[hips[1]]), None)
    rigid = {}
    for side in ("left", "right"):
        ankle, shoulder = chosen.get(f"{side}_ankle"), chosen.get(f"{side}_shoulder")
        if chosen.get(f"{side}_foot") is None and ankle in bvh.end_sites:
            rigid[f"{side}_foot"] = ("end_site", bvh.names[ankle], 1.0)
        if chosen.get(f"{side}_collar") is None and shoulder is not None:
            rigid[f"{side}_collar"] = ("between", bvh.names[shoulder], 0.5)
    pelvis, neck = chosen.get("pelvis"), chosen.get("neck")
    if pelvis is not None and neck is not None and pelvis in lineage[neck]:
        _map_spine(bvh, chosen, rigid, [i for i in _ancestors(parents, neck)
                                        if pelvis in lineage[i]][::-1])
    missing = [j for j in JOINT_NAMES if chosen.get(j) is None and j not in rigid]
    if missing:
        raise ValueError(f"{source}: cannot tell which of its joints are {', '.join(missing)} "
                         f"(it has {', '.join(bvh.names[:12])}"
                         f"{', ...' if len(bvh.names) > 12 else ''}): name them in a "
                         '--skeleton-map FILE.json ({"canonical joint": "its joint", ...}; '
                         "minretarget inspect FILE.bvh shows what was found)")
    return Skeleton({j: None if j in rigid else bvh.names[chosen[j]] for j in JOINT_NAMES},
                    rigid)


def _ancestors(parents, joint):
    """The ancestors of ``joint`` (indices into ``parents``), its parent first."""
    while parents[joint] >= 0:
        joint = parents[joint]
        yield joint


def _map_spine(bvh, chosen, rigid, spine):
    """Spine1-3 from the joints strictly between the pelvis and the neck, root first: the
    first, middle and last of three or more; those missing placed on the way to the next
    (fills ``chosen`` and ``rigid``)."""
    neck = bvh.names[chosen["neck"]]
    if len(spine) >= 3:
        picked = {"spine1": spine[0], "spine2": spine[len(spine) // 2], "spine3": spine[-1]}
    elif len(spine) == 2:
        picked = {"spine1": spine[0], "spine2": spine[1]}
        rigid.setdefault("spine3", ("between", neck, 0.5))
    elif len(spine) == 1:
        picked = {"spine2": spine[0]}
        rigid.setdefault("spine1", ("between", bvh.names[spine[0]], 0.5))
        rigid.setdefault("spine3", ("between", neck, 0.5))
    else:
        picked = {}
        for joint, fraction in (("spine1", 1 / 4), ("spine2", 1 / 3), ("spine3", 1 / 2)):
            rigid.setdefault(joint, ("between", neck, fraction))
    for joint, i in picked.items():
        chosen.setdefault(joint, i)
    for joint in list(rigid):
        if chosen.get(joint) is not None:          # a skeleton map's joint beats a placement
            del rigid[joint]


def skeleton_of(bvh, given=None, source="BVH"):
    """How ``bvh`` maps onto the canonical joints: (scheme, Skeleton), the table of
    ``SKELETONS`` whose joints its names all hold (never with a skeleton map ``given``),
    else ("found from its names", ``map_skeleton``)."""
    key = None if given else find_skeleton(bvh.names)
    if key is not None:
        return key, SKELETONS[key]
    return "found from its names", map_skeleton(bvh, given, source)


def mapping_lines(skeleton, names):
    """What ``skeleton`` takes each canonical joint from, a line each, then the BVH joints
    ``names`` it leaves out."""
    kinds = {"between": "between {parent} and {joint} ({fraction:g} of the way)",
             "offset": "{fraction:g} of {joint}'s OFFSET from {parent}",
             "end_site": "End Site of {joint}"}
    lines = []
    for j, name in enumerate(JOINT_NAMES):
        if skeleton.bones[name] is not None:
            lines.append(f"  {name:15} {skeleton.bones[name]}")
            continue
        kind, joint, fraction = skeleton.rigid[name]
        parent = JOINT_NAMES[PARENTS[j]]
        lines.append(f"  {name:15} " + kinds[kind].format(
            parent=skeleton.bones[parent] or parent, joint=joint, fraction=fraction))
    used = {_key(b) for b in _needed(skeleton)}
    unused = [n for n in names if _key(n) not in used]
    return lines + [f"not used: {', '.join(unused) if unused else 'none'}"]


def canonical_world(bvh, skeleton=None, source="BVH", given=None):
    """World positions and rotations of the 22 canonical joints, frame by frame.

    Args:
        bvh: BVHMotion (any units; the result is in the same ones).
        skeleton: a key of ``SKELETONS`` or a Skeleton; None finds how it maps
            (``skeleton_of``).
        source: names the file in errors.
        given: {canonical joint: BVH joint name}, a skeleton map (``map_skeleton``).
    Returns:
        positions: (T, J, 3) float64: each mapped joint at its BVH joint, the others carried
            rigidly by their parent (module docstring).
        rotations: (T, J, 3, 3) float64 world rotations relative to the zero pose.
    """
    table = (skeleton_of(bvh, given, source)[1] if skeleton is None else
             SKELETONS[skeleton] if isinstance(skeleton, str) else skeleton)
    bvh_positions, bvh_rotations = world_transforms(bvh)
    index = {}
    for i, name in enumerate(bvh.names):
        index.setdefault(_key(name), i)
    positions = np.empty((bvh.num_frames, NUM_JOINTS, 3))
    rotations = np.empty((bvh.num_frames, NUM_JOINTS, 3, 3))
    for j, name in enumerate(JOINT_NAMES):
        bone = table.bones[name]
        if bone is not None:
            positions[:, j] = bvh_positions[:, index[_key(bone)]]
            rotations[:, j] = bvh_rotations[:, index[_key(bone)]]
            continue
        kind, reference, fraction = table.rigid[name]
        i = index[_key(reference)]
        parent = PARENTS[j]
        rotations[:, j] = rotations[:, parent]
        if kind == "between":
            positions[:, j] = ((1 - fraction) * positions[:, parent]
                               + fraction * bvh_positions[:, i])
            continue
        if kind == "offset":
            offset = bvh.offsets[i]
        elif i in bvh.end_sites:
            offset = bvh.end_sites[i]
        else:
            raise ValueError(f"{source}: joint {bvh.names[i]!r} has no End Site, needed to "
                             f"place {name}")
        positions[:, j] = positions[:, parent] + rotations[:, parent] @ (fraction * offset)
    return positions, rotations


# ----------------------------------------------------------------------------- writing

def depth_first_order():
    """Canonical joint indices in depth-first order (children in index order): the order a
    BVH hierarchy lists them."""
    children = {j: [c for c in range(NUM_JOINTS) if PARENTS[c] == j] for j in range(NUM_JOINTS)}
    order, stack = [], [0]
    while stack:
        joint = stack.pop()
        order.append(joint)
        stack.extend(reversed(children[joint]))
    return order


def rig_to_bvh(tpose_joints, rotations, root, frame_time):
    """A retargeted rig as a BVHMotion on the canonical skeleton (module docstring).

    Args:
        tpose_joints: (J, 3) T-pose joint positions (any units and axes; the BVH keeps them).
        rotations: (T, J, 4) local quaternions (w, x, y, z) in those same axes.
        root: (T, 3) pelvis positions, same units and axes.
        frame_time: seconds per frame.
    Returns:
        BVHMotion whose world_transforms give back FK of the rig: joint positions (T, J', 3)
        in depth-first order (``depth_first_order``).
    """
    tpose_joints = np.asarray(tpose_joints, dtype=np.float64)
    root = np.asarray(root, dtype=np.float64)
    order = depth_first_order()
    position_in_file = {joint: k for k, joint in enumerate(order)}
    parents = [-1 if PARENTS[j] < 0 else position_in_file[PARENTS[j]] for j in order]
    offsets = np.array([tpose_joints[j] - (tpose_joints[PARENTS[j]] if PARENTS[j] >= 0 else 0)
                        for j in order])                                       # (J, 3)
    leaves = [k for k in range(NUM_JOINTS) if k not in parents]
    end_sites = {k: 0.5 * offsets[k] for k in leaves}
    rotation_channels = tuple(f"{axis}rotation" for axis in EULER_ORDER)
    channels = (("Xposition", "Yposition", "Zposition") + rotation_channels,) + \
        (rotation_channels,) * (NUM_JOINTS - 1)
    matrices = quaternion_to_matrix(np.asarray(rotations)[:, order]).astype(np.float64)
    euler = matrix_to_euler(matrices, EULER_ORDER)                             # (T, J, 3)
    values = np.concatenate([root, euler.reshape(len(root), 3 * NUM_JOINTS)], axis=1)
    return BVHMotion(names=tuple(JOINT_NAMES[j] for j in order),
                     parents=np.array(parents, dtype=np.int64), offsets=offsets,
                     channels=channels, end_sites=end_sites, values=values,
                     frame_time=float(frame_time))
