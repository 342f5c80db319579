"""The conventions every part of minretarget and training/ follows. Stated once, here.

Units
    Metres for every length. Time in frames at ``FPS`` (30) frames per second.

Axes
    Right-handed, +Y up. In the T-pose the body faces +Z and its left hand points to +X
    (the SMPL and glTF convention).

Skeleton
    22 joints in SMPL body order (``JOINT_NAMES``); ``PARENTS[j]`` is the parent of joint j,
    -1 for the root (pelvis). Parents always come before their children, so a single pass in
    index order is a valid forward-kinematics traversal.

Rotations
    Unit quaternions ordered (w, x, y, z). A joint's rotation is local to its parent and is
    expressed in the T-pose's world-aligned frames, so identity everywhere gives the T-pose:
    global rotation ``G[j] = G[PARENTS[j]] @ R[j]`` and position
    ``p[j] = p[PARENTS[j]] + G[PARENTS[j]] @ (t[j] - t[PARENTS[j]])`` for T-pose joints ``t``.
    The root (pelvis) also carries a world translation: ``p[0] = root``.

Shapes
    Letters used in docstrings and comments: B batch, T frames, P points of a source frame,
    V points/vertices of the target, J joints (22), H hidden width. Runtime arrays are float32
    and C-contiguous.
"""

FPS = 30

JOINT_NAMES = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck",
    "left_collar", "right_collar", "head", "left_shoulder", "right_shoulder",
    "left_elbow", "right_elbow", "left_wrist", "right_wrist",
)
PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19)
NUM_JOINTS = len(JOINT_NAMES)
JOINT_INDEX = {name: index for index, name in enumerate(JOINT_NAMES)}
# MIRROR[j]: the joint that j becomes in the body's mirror image (left and right swapped).
MIRROR = tuple(JOINT_INDEX[name.replace("left", "<").replace("right", "left")
                          .replace("<", "right")] for name in JOINT_NAMES)

UP_AXIS = 1          # +Y
FORWARD_AXIS = 2     # +Z: the T-pose body faces this way
LEFT_AXIS = 0        # +X: the T-pose body's left hand points this way

# Smallest source or target cloud the networks accept: PointNet's max-pool needs enough points
# to see the whole body.
MIN_POINTS = 64

assert len(PARENTS) == NUM_JOINTS
assert all(PARENTS[j] < j for j in range(1, NUM_JOINTS)) and PARENTS[0] == -1
