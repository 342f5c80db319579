"""CMU motion capture (the cgspeed "Daz-friendly" BVH files) -> the 22-joint canonical skeleton.

Data layout (see ../shared/data/cmu/README.md)::

    <cmu_dir>/cgspeed/NN/NN_MM.bvh.gz      subjects 01-14, descriptions in cgspeed/CMU-INDEX.md
    <cmu_dir>/aclstm/<style>/MM.bvh.gz     style in salsa, martial, indian

All files share one 43-joint skeleton (hip, abdomen, chest, neck, head, l/rCollar, l/rShldr,
l/rForeArm, l/rHand, l/rButtock, l/rThigh, l/rShin, l/rFoot, plus eyes and fingers, ignored).

Mapping (DESIGN.md, "Motions")
    ``minretarget.skeletons`` holds the CMU joint table and the mapping (the runtime reads BVH
    sources with it too): each canonical joint takes the world orientation of one CMU joint
    relative to the zero pose; spine3 and the balls of the feet, which CMU lacks, move rigidly
    with their parent. The local rotation is ``R[j] = G[parent]^T @ G[j]``; FK of R on
    ``tpose_joints`` reproduces the BVH positions of the mapped joints (the buttock joints
    between hip and thigh carry zero rotation in every file, so dropping them loses nothing).
Axes
    The CMU zero pose already faces +Z (toes at +Z) with the left hand at +X, +Y up (checked
    in tests/test_cmu_mapping.py on the file), so no axis change is applied.
Units
    The files are in centimetres (standing hip height about 85): scaled by 0.01 to metres.
Frames
    The first 8 frames of every file are a lead-in added by the conversion, not captured
    motion: frame 0 is a reference stance (root rotation exactly zero, joint angles near zero)
    and frames 1-7 swing from it into the capture (median over the files of the mean joint
    displacement per frame, relative to the rest of the file: 41, 23, 20, 14, 5.7, 1.1, 3.3,
    2.2, then 0.7 as later on). They are dropped (``LEAD_IN_FRAMES``).
"""
import functools
import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from minretarget.bvh import read_bvh, resample
from minretarget.conventions import FPS, JOINT_INDEX, PARENTS, UP_AXIS
from minretarget.kinematics import forward_kinematics, matrix_to_quaternion
from minretarget.skeletons import canonical_world

CENTIMETRES = 0.01

# True capture rate of each collection. Every header says Frame Time 0.0083333 (120 fps).
# - aclstm/framerates.txt: salsa 60, martial 120, indian 120.
# - cgspeed/CGSPEED.md: the conversion "preserves the 120fps of the original CMU dataset"; it
#   names no 60 fps trial. The trials present (subjects 01-14) check out as 120 fps
#   physically: read at 120 fps, the trunk's peak downward acceleration in the runs (09_*)
#   and jumps (13_11, 13_39-42) is 11-17 m/s^2, about g as in a flight phase; read at 60 fps
#   it would be 3-4 m/s^2, too little for leaving the ground.
SOURCE_FPS = {"cgspeed": 120, "salsa": 60, "martial": 120, "indian": 120}

# Test split of DESIGN.md ("Accuracy protocol"): CMU subjects and aclstm styles never trained on.
TEST_SUBJECTS = frozenset({"08", "11", "12", "14", "indian"})

LEAD_IN_FRAMES = 8       # conversion artefacts at the start of every file (module docstring)

# Broken captures, left out of training and validation (``list_trials``; the test split has
# none): their bodies sink through the floor, which every other trial stands on. Over each
# trial the lowest of the feet and ankles has a 2nd-percentile height (``floor_height``) of
# -0.83 (07_12), -0.76 (01_14) and -0.72 m (09_10), against -0.19 to +0.08 m (median +0.03)
# in the 182 others. The poses are off too: 09_10 ("run") has its ankles a median 1.53 m apart
# sideways and its pelvis 0.41 m above its lowest foot (0.83 standing), and through the
# runtime its source skeleton was 0.22 m off (the other runs' 0.03 to 0.04) and its 32 frames
# made a third of the validation MPJPE; 07_12 ("brisk walk") has its ankles 0.30 m apart
# sideways (07_01, a walk of the same session: 0.06); 01_14 (a playground climb) has its
# pelvis down to 0.44 m below the floor.
BROKEN_TRIALS = frozenset({"01_14", "07_12", "09_10"})
BROKEN_FLOOR_HEIGHT = -0.3    # metres: ``floor_height`` below this marks a broken capture

# Broken feet, frame by frame: in 602 frames of 13 training trials (subject 05's dances and
# four salsa trials; none in the test split) a foot turns further from its shin than an ankle
# can, rolled sole-up or folded onto the shin. They put impossible feet into training clouds
# and truth skeletons, so builds cut them out (``clean_segments``), and so does the benchmark
# of training dances (``datasets.dance_sequences``). Of every trial's 72,820 frames, the
# larger ankle turn is past 150 degrees in 600, 100-150 in 17 and within 100 in the rest: the
# limit sits in the gap (docs/training_notes.md, "Broken feet in the training dances").
ANKLE_LIMIT_DEGREES = 120.0
_ANKLES = (JOINT_INDEX["left_ankle"], JOINT_INDEX["right_ankle"])
MIN_SEGMENT_FRAMES = 30       # shorter clean runs between broken frames are dropped too

# Ball-of-foot (foot End Site) height above the floor with the foot flat: the median, over the
# files, of the 2nd percentile of the lower foot End Site's height is 0.027 m.
_BALL_HEIGHT = 0.025

# First matching rule gives a cgspeed trial's category, from its CMU-INDEX.md description.
_CATEGORY_RULES = (
    ("dance", ("dance",)), ("basketball", ("basketball",)), ("soccer", ("soccer",)),
    ("fight", ("punch", "boxing", "swordplay")), ("exercise", ("jumping jacks",)),
    ("climb", ("climb",)), ("sit", ("sit ",)), ("run", ("run",)), ("walk", ("walk",)),
    ("jump", ("jump",)),
)


@dataclass(frozen=True, eq=False)
class Motion:
    """One CMU trial on the canonical skeleton.

    Attributes:
        name: trial name, e.g. "08_01" (cgspeed) or "salsa_01" (aclstm); a run of a trial
            cut around broken feet (``clean_segments``) is "<trial>@<first frame>".
        rotations: (T, 22, 4) float32 local joint quaternions (w, x, y, z), w >= 0.
        root: (T, 3) float32 world position of the pelvis (CMU hip joint), metres, +Y up,
            canonical axes; the capture floor is near y = 0.
        fps: frame rate of ``rotations`` and ``root``.
        category: e.g. "walk", "run", "dance", "salsa", "martial", "indian".
        source_fps: the capture frame rate that was resampled from.
    """
    name: str
    rotations: np.ndarray
    root: np.ndarray
    fps: int
    category: str
    source_fps: float


@dataclass(frozen=True)
class Trial:
    """One file of the collection: ``split`` is "test" or "train" (DESIGN.md)."""
    name: str
    path: Path
    subject: str
    category: str
    split: str


# ----------------------------------------------------------------------------- broken feet

def broken_ankle_frames(rotations):
    """(T, J, 4) local quaternions (w, x, y, z) -> (T,) bool: the frames where either ankle
    turns its foot more than ``ANKLE_LIMIT_DEGREES`` from the foot's T-pose place on the
    shin."""
    w = np.clip(np.abs(np.asarray(rotations)[:, _ANKLES, 0]), 0.0, 1.0)         # (T, 2)
    return (np.degrees(2.0 * np.arccos(w)) > ANKLE_LIMIT_DEGREES).any(axis=1)


def trial_of(name):
    """The trial a motion's ``name`` comes from: "salsa_01@449" -> "salsa_01" (and "08_01"
    -> "08_01")."""
    return name.split("@")[0]


def clean_segments(motion):
    """``motion`` without its broken-ankle frames (``broken_ankle_frames``): the runs of
    frames between them of at least ``MIN_SEGMENT_FRAMES``, each a Motion named
    "<name>@<first frame>"; ``[motion]`` itself when no frame is broken."""
    broken = broken_ankle_frames(motion.rotations)
    if not broken.any():
        return [motion]
    # Edges of the clean runs: where broken turns to clean (a start) and back (an end).
    edges = np.flatnonzero(np.diff(np.concatenate([[True], broken, [True]]).astype(np.int8)))
    return [replace(motion, name=f"{motion.name}@{start}", rotations=motion.rotations[start:end],
                    root=motion.root[start:end])
            for start, end in zip(edges[::2], edges[1::2]) if end - start >= MIN_SEGMENT_FRAMES]


# ----------------------------------------------------------------------------- the collection

def list_trials(cmu_dir, include_broken=False):
    """Every ``.bvh.gz`` trial present under ``cmu_dir``, sorted by path, without the
    ``BROKEN_TRIALS`` unless ``include_broken``.

    Returns:
        list of Trial; subject is "NN" for cgspeed/NN/NN_MM and the style for aclstm/<style>.
    """
    cmu_dir = Path(cmu_dir)
    paths = sorted(cmu_dir.glob("cgspeed/*/*.bvh.gz")) + sorted(cmu_dir.glob("aclstm/*/*.bvh.gz"))
    trials = []
    for path in paths:
        if not include_broken and trial_name(path) in BROKEN_TRIALS:
            continue
        subject = path.parent.name
        trials.append(Trial(name=trial_name(path), path=path, subject=subject,
                            category=trial_category(path),
                            split="test" if subject in TEST_SUBJECTS else "train"))
    return trials


def _collection(path):
    """"cgspeed" or the aclstm style of a trial path, from its folders; None if neither."""
    path = Path(path)
    if path.parent.parent.name == "cgspeed":
        return "cgspeed"
    if path.parent.parent.name == "aclstm":
        return path.parent.name
    return None


def trial_name(path):
    """"NN_MM" for cgspeed files, "<style>_MM" for aclstm files, else the bare file name."""
    path = Path(path)
    stem = path.name.split(".")[0]
    collection = _collection(path)
    return stem if collection in (None, "cgspeed") else f"{collection}_{stem}"


def capture_fps(path):
    """The true capture frame rate of a trial (``SOURCE_FPS``), or None if its folder layout
    is not the collection's."""
    return SOURCE_FPS.get(_collection(path))


def trial_category(path):
    """Motion category: the aclstm style, or from the CMU-INDEX.md description for cgspeed
    (``_CATEGORY_RULES``, "everyday" when none matches), else the file's folder name."""
    path = Path(path)
    collection = _collection(path)
    if collection != "cgspeed":
        return collection or path.parent.name
    description = _index(path.parent.parent / "CMU-INDEX.md").get(trial_name(path), "")
    for category, words in _CATEGORY_RULES:
        if any(word in description for word in words):
            return category
    return "everyday"


@functools.lru_cache(maxsize=4)
def _index(index_path):
    """{"NN_MM": lower-case description} from a CMU-INDEX.md; empty if the file is absent."""
    try:
        text = Path(index_path).read_text(encoding="utf-8", errors="replace")
    except FileNotFoundError:
        return {}
    return {m.group(1): m.group(2).lower()
            for m in re.finditer(r"^(\d+_\d+)\s+(.+?)\s*$", text, flags=re.MULTILINE)}


# ----------------------------------------------------------------------------- the mapping

def load_motion(path, fps=FPS, source_fps=None):
    """Load one CMU trial as local rotations and a root path on the canonical skeleton.

    Args:
        path: a trial ``.bvh`` / ``.bvh.gz`` file on the CMU skeleton.
        fps: output frame rate.
        source_fps: true capture rate; None looks it up (``capture_fps``), falling back to
            the header for a file outside the collection's folders.
    Returns:
        Motion (lead-in frames dropped, resampled to ``fps``).
    """
    bvh = read_bvh(path, scale=CENTIMETRES)
    if source_fps is None:
        source_fps = capture_fps(path) or bvh.fps
    bvh = resample(replace(bvh, values=bvh.values[LEAD_IN_FRAMES:]), fps=fps,
                   source_fps=source_fps)
    positions, rotations = canonical_world(bvh, "cmu")
    return Motion(name=trial_name(path), rotations=local_quaternions(rotations),
                  root=positions[:, 0].astype(np.float32), fps=int(fps),
                  category=trial_category(path), source_fps=float(source_fps))


def local_quaternions(rotations):
    """(T, J, 3, 3) world joint rotations -> (T, J, 4) float32 local quaternions (w, x, y, z),
    w >= 0: ``R[j] = G[parent]^T @ G[j]``, the root keeping its world rotation."""
    parents = np.array((0,) + PARENTS[1:])
    local = np.swapaxes(rotations[:, parents], -1, -2) @ rotations           # (T, J, 3, 3)
    local[:, 0] = rotations[:, 0]
    return matrix_to_quaternion(local)


def tpose_joints(bvh):
    """(J, 3) float32 canonical T-pose joints of a CMU skeleton, metres: its zero pose with the
    pelvis above the origin and the feet flat on the floor y = 0."""
    zero_pose = replace(bvh, values=np.zeros((1, bvh.values.shape[1])))
    joints = canonical_world(zero_pose, "cmu")[0][0]                         # (J, 3)
    joints -= joints[0]
    joints[:, 1] += _BALL_HEIGHT - joints[[JOINT_INDEX["left_foot"],
                                           JOINT_INDEX["right_foot"]], 1].min()
    return joints.astype(np.float32)


def floor_height(motion, tpose):
    """The 2nd percentile over a motion's frames of its lowest foot or ankle's height, metres:
    about +0.03 for a capture on the floor, below ``BROKEN_FLOOR_HEIGHT`` for a broken one.

    Args:
        motion: Motion. tpose: (J, 3) its actor's T-pose joints (``cmu_tpose_joints``).
    """
    feet = [JOINT_INDEX[name] for name in ("left_ankle", "right_ankle", "left_foot",
                                           "right_foot")]
    joints = forward_kinematics(motion.rotations, motion.root, tpose)[0]     # (T, J, 3)
    return float(np.percentile(joints[:, feet, UP_AXIS].min(axis=1), 2))


def cmu_tpose_joints(path):
    """(J, 3) float32 T-pose joints of the CMU actor in metres, read from any trial file (they
    share one skeleton). ``[0, 1]`` (0.855) is the hip height used to scale root paths; note
    that CMU's pelvis (its hip joint) sits 2.6 cm below its thigh joints."""
    return tpose_joints(read_bvh(path, scale=CENTIMETRES))
