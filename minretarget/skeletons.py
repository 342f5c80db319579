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
    World rotations are relative to the BVH zero pose, where every world rotation is the
    identity, so a canonical joint's world rotation is its BVH joint's world rotation.

Writing: a retargeted rig -> BVH (``rig_to_bvh``)
    The 22 canonical names in depth-first order (what a BVH hierarchy lists), OFFSETs from the
    T-pose skeleton, the root's position channels, ZXY Euler rotation channels, and an End Site
    on each leaf joint half its parent bone long (the rig has no bone beyond a leaf; viewers
    want one to draw).
"""
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
        End Site OFFSET (kind "end_site").
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


def _key(name):
    """A joint name as matched: no namespace prefix, lower case."""
    return name.rsplit(":", 1)[-1].lower()


def _needed(skeleton):
    return {b for b in skeleton.bones.values() if b} | {r[1] for r in skeleton.rigid.values()}


def find_skeleton(names, source="BVH"):
    """The name of the first scheme of ``SKELETONS`` whose joints ``names`` all contain.

    Raises:
        ValueError naming ``source`` and, for the closest scheme, the joints it misses.
    """
    present = {_key(name) for name in names}
    missing = {key: sorted(b for b in _needed(s) if _key(b) not in present)
               for key, s in SKELETONS.items()}
    for key, absent in missing.items():
        if not absent:
            return key
    closest = min(missing, key=lambda k: len(missing[k]))
    raise ValueError(f"{source}: its joint names match no known skeleton "
                     f"({', '.join(SKELETONS)}); closest is {closest}, which lacks "
                     f"{', '.join(missing[closest][:8])}")


def canonical_world(bvh, skeleton=None, source="BVH"):
    """World positions and rotations of the 22 canonical joints, frame by frame.

    Args:
        bvh: BVHMotion (any units; the result is in the same ones).
        skeleton: a key of ``SKELETONS``; None finds it from the joint names.
        source: names the file in errors.
    Returns:
        positions: (T, J, 3) float64: each mapped joint at its BVH joint, the others carried
            rigidly by their parent (module docstring).
        rotations: (T, J, 3, 3) float64 world rotations relative to the zero pose.
    """
    table = SKELETONS[skeleton or find_skeleton(bvh.names, source)]
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
        if kind == "offset":
            offset = bvh.offsets[i]
        elif i in bvh.end_sites:
            offset = bvh.end_sites[i]
        else:
            raise ValueError(f"{source}: joint {bvh.names[i]!r} has no End Site, needed to "
                             f"place {name}")
        parent = PARENTS[j]
        rotations[:, j] = rotations[:, parent]
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
