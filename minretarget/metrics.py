"""Accuracy metrics of the retargeting benchmark (DESIGN.md, "Accuracy protocol").

NumPy functions (MEDL's loop over edges is a numba kernel), float64 inside whatever the input
dtype. Every metric compares a
predicted sequence ``pred`` with the ground truth ``gt`` of the same shape (T, N, 3): T frames
of N points, N = J = 22 joints or N = V target points. Lengths are metres; time is in frames
at ``conventions.FPS`` (30) frames per second.

MPJPE, MPVD (metres)
    Mean over frames and points of the Euclidean distance between predicted and true points.
    MPJPE is taken on the joints, MPVD (mean per-vertex distance) on the target's points.
PA-MPJPE, PA-MPVD (metres)
    The same after aligning each predicted frame onto its ground-truth frame with the
    similarity (rotation, uniform scale, translation) that minimises the sum of squared
    distances (``procrustes_align``; proper rotations only). They measure the error in pose
    and shape that is left once global placement, orientation and size are forgiven. The
    alignment minimises squared distances, not their mean, so PA-MPJPE can exceed MPJPE (one
    outlier joint, say).
Acc, PA-Acc (metres per frame^2)
    Mean over the T - 2 interior frames and the points of the norm of the difference between
    the predicted and the true second finite differences ``x[t+1] - 2 x[t] + x[t-1]``.
    The unit is metres per frame^2, NOT metres per s^2: multiply by ``FPS ** 2`` (900) for
    m/s^2. They measure jitter and temporal inconsistency. PA-Acc is taken on the per-frame
    aligned prediction. ``evaluate`` reports both on the joints.
Jitter (metres per frame^2)
    ``jitter``: mean over the T - 2 interior frames and the points of the norm of the second
    finite difference of one sequence alone (no ground truth): how much it shakes.
Foot sliding (metres per second)
    ``foot_sliding``: mean horizontal speed of the feet (joints ``left_foot`` and
    ``right_foot``) over the steps t -> t+1 where that foot is in contact with the ground.
    Contact is judged from height alone, per foot: the foot is within ``contact_height`` of
    its own lowest height in the sequence in both frames of the step. The floor is each foot's
    own lowest point, not y = 0, so that a sequence floating above or sunk below y = 0 (or a
    result placed a little off the truth) is judged on its own; the price is that a foot that
    never touches the ground gets its lowest moment counted as contact.
MEDL (metres)
    Mean absolute edge-length difference: the undirected k-nearest-neighbour graph (k = 6,
    each edge once) is built once on the ground-truth points of the first frame (or on given
    rest points, e.g. the target's T-pose), and the metric averages
    ``| |pred_i - pred_j| - |gt_i - gt_j| |`` over its edges and all frames. It measures local
    stretching and tearing of the target surface, whatever its placement.
"""
import numpy as np
from scipy.spatial import cKDTree

from ._jit import kernel
from .conventions import FPS, JOINT_INDEX, UP_AXIS

# Each metric's name in the tables, in the order ``evaluate`` returns them.
METRIC_NAMES = ("MPJPE", "PA-MPJPE", "Acc", "PA-Acc", "MPVD", "PA-MPVD", "MEDL")
# The fewest frames a sequence needs for a second difference (Acc, PA-Acc, jitter).
ACCELERATION_FRAMES = 3


# ----------------------------------------------------------------------------- input checks

def _as_float64(value, name, sequence=False):
    """Check a (..., N, 3) array, or with ``sequence`` a (T, N, 3) one, with N >= 1 and finite
    values; return it as float64. ValueError naming ``name`` otherwise."""
    array = np.asarray(value)
    if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise ValueError(f"{name} must be a real numeric array, got dtype {array.dtype}")
    if (array.ndim != 3 if sequence else array.ndim < 2) or array.shape[-1] != 3:
        pattern = "(T, N, 3)" if sequence else "(..., N, 3)"
        raise ValueError(f"{name} must have shape {pattern}, got {array.shape}")
    if array.shape[-2] == 0:
        raise ValueError(f"{name} has no points: shape {array.shape}")
    array = array.astype(np.float64, copy=False)
    if not np.isfinite(array).all():
        bad = np.argwhere(~np.isfinite(array))[0]
        raise ValueError(f"{name} has a non-finite value {array[tuple(bad)]} at index "
                         f"{tuple(int(i) for i in bad)}")
    return array


def _as_pair(pred, gt, names=("pred", "gt"), min_frames=1):
    """Check two (T, N, 3) sequences of the same shape with T >= ``min_frames``."""
    pred = _as_float64(pred, names[0], sequence=True)
    gt = _as_float64(gt, names[1], sequence=True)
    if pred.shape != gt.shape:
        raise ValueError(f"{names[0]} and {names[1]} must have the same shape (T, N, 3), got "
                         f"{names[0]} {pred.shape} and {names[1]} {gt.shape}")
    if pred.shape[0] < min_frames:
        raise ValueError(f"{names[0]} and {names[1]} need at least {min_frames} frame(s), got "
                         f"T = {pred.shape[0]} (shape {pred.shape})")
    return pred, gt


# ----------------------------------------------------------------------------- alignment

def procrustes_align(pred, gt):
    """Align each set of points of ``pred`` onto ``gt`` with the best similarity transform.

    For every leading index, finds the scale s >= 0, proper rotation R (det R = +1, never a
    reflection) and translation t that minimise ``sum_n |s R pred[n] + t - gt[n]|^2``
    (Umeyama 1991) and returns ``s R pred + t``. Vectorised over the leading dimensions.

    Args:
        pred: (..., N, 3) points, metres.
        gt: (..., N, 3) points, metres, same shape as ``pred``.
    Returns:
        (..., N, 3) float64, ``pred`` aligned onto ``gt``. Where all the points of a ``pred``
        set coincide, the scale is 0 and every aligned point lands on the ``gt`` centroid.
    """
    pred = _as_float64(pred, "pred")
    gt = _as_float64(gt, "gt")
    if pred.shape != gt.shape:
        raise ValueError(f"pred and gt must have the same shape (..., N, 3), got pred "
                         f"{pred.shape} and gt {gt.shape}")
    # 1. Centre both sets.
    pred_mean = pred.mean(axis=-2, keepdims=True)                   # (..., 1, 3)
    gt_mean = gt.mean(axis=-2, keepdims=True)                       # (..., 1, 3)
    x = pred - pred_mean                                            # (..., N, 3)
    y = gt - gt_mean                                                # (..., N, 3)
    # 2. Cross-covariance sum_n y_n x_n^T and its SVD.
    covariance = np.swapaxes(y, -1, -2) @ x                         # (..., 3, 3)
    u, singular, vt = np.linalg.svd(covariance)         # U (..., 3, 3), D (..., 3), V^T (..., 3, 3)
    # 3. Flip the weakest axis when U V^T is a reflection, so that det R = +1.
    sign = np.sign(np.linalg.det(u) * np.linalg.det(vt))            # (...,), each +1 or -1
    flip = np.ones(singular.shape)                                  # (..., 3)
    flip[..., 2] = sign
    rotation = (u * flip[..., None, :]) @ vt                        # (..., 3, 3)
    # 4. Scale: trace(D S) / sum |x|^2; 0 for a set collapsed to one point.
    spread = np.sum(x * x, axis=(-2, -1))                           # (...,)
    scale = np.sum(singular * flip, axis=-1) / np.where(spread > 0, spread, 1.0)  # (...,)
    scale = np.where(spread > 0, scale, 0.0)
    # 5. Apply s R x + gt centroid.
    return scale[..., None, None] * (x @ np.swapaxes(rotation, -1, -2)) + gt_mean  # (..., N, 3)


# ----------------------------------------------------------------------------- metrics

def _mean_distance(pred, gt):
    """(T, N, 3), (T, N, 3) float64 -> mean Euclidean distance over frames and points."""
    return float(np.linalg.norm(pred - gt, axis=-1).mean())


def _second_difference(x):
    """(T, N, 3) -> (T - 2, N, 3), x[t+1] - 2 x[t] + x[t-1] for t = 1 .. T-2."""
    return x[2:] - 2.0 * x[1:-1] + x[:-2]


def mean_point_error(pred, gt):
    """Mean Euclidean distance between corresponding points, over frames and points.

    Args:
        pred: (T, N, 3) predicted points, metres.
        gt: (T, N, 3) ground-truth points, metres.
    Returns:
        float, metres.
    """
    pred, gt = _as_pair(pred, gt)
    return _mean_distance(pred, gt)


def pa_mean_point_error(pred, gt):
    """``mean_point_error`` after aligning each frame of ``pred`` onto ``gt`` (Procrustes).

    Args:
        pred: (T, N, 3) predicted points, metres.
        gt: (T, N, 3) ground-truth points, metres.
    Returns:
        float, metres.
    """
    pred, gt = _as_pair(pred, gt)
    return _mean_distance(procrustes_align(pred, gt), gt)


def acceleration_error(pred, gt):
    """Acc: mean norm of the difference of second finite differences, over T - 2 frames and N.

    Args:
        pred: (T, N, 3) predicted points, metres, T >= 3, consecutive frames at 30 fps.
        gt: (T, N, 3) ground-truth points, metres.
    Returns:
        float, metres per frame^2 (not per s^2: multiply by FPS ** 2 = 900 for m/s^2).
    """
    pred, gt = _as_pair(pred, gt, min_frames=ACCELERATION_FRAMES)
    return _mean_distance(_second_difference(pred), _second_difference(gt))


def pa_acceleration_error(pred, gt):
    """PA-Acc: ``acceleration_error`` of the per-frame Procrustes-aligned ``pred``.

    Args:
        pred: (T, N, 3) predicted points, metres, T >= 3.
        gt: (T, N, 3) ground-truth points, metres.
    Returns:
        float, metres per frame^2.
    """
    pred, gt = _as_pair(pred, gt, min_frames=ACCELERATION_FRAMES)
    aligned = procrustes_align(pred, gt)                            # (T, N, 3)
    return _mean_distance(_second_difference(aligned), _second_difference(gt))


def mpjpe(pred, gt):
    """MPJPE: (T, J, 3), (T, J, 3) joints in metres -> mean joint distance, metres."""
    return mean_point_error(pred, gt)


def pa_mpjpe(pred, gt):
    """PA-MPJPE: (T, J, 3), (T, J, 3) joints in metres -> mean distance after per-frame
    similarity Procrustes alignment, metres."""
    return pa_mean_point_error(pred, gt)


def mpvd(pred, gt):
    """MPVD: (T, V, 3), (T, V, 3) target points in metres -> mean point distance, metres."""
    return mean_point_error(pred, gt)


def pa_mpvd(pred, gt):
    """PA-MPVD: (T, V, 3), (T, V, 3) target points in metres -> mean distance after per-frame
    similarity Procrustes alignment, metres."""
    return pa_mean_point_error(pred, gt)


def knn_edges(points, k=6):
    """The undirected k-nearest-neighbour graph of a point set.

    Each point is joined to its k nearest other points (Euclidean); an edge found from both
    ends is kept once. Ties at equal distance are broken by scipy's cKDTree.

    Args:
        points: (V, 3) points, metres.
        k: neighbours per point, 1 <= k < V.
    Returns:
        (E, 2) int64 array of edges (i, j) with i < j, sorted, V * k / 2 <= E <= V * k.
    """
    points = _as_float64(points, "points")
    if points.ndim != 2:
        raise ValueError(f"points must have shape (V, 3), got {points.shape}")
    count = points.shape[0]
    if not 1 <= k < count:
        raise ValueError(f"k must satisfy 1 <= k < V, got k = {k} for {count} points")
    _, index = cKDTree(points).query(points, k=k + 1)               # (V, k + 1)
    # Drop each point itself; with duplicate points it need not be in column 0, or at all.
    own = index == np.arange(count)[:, None]                        # (V, k + 1)
    keep = ~own
    keep[~own.any(axis=1), -1] = False
    neighbours = index[keep].reshape(count, k)                      # (V, k)
    edges = np.stack([np.repeat(np.arange(count), k), neighbours.ravel()], axis=1)  # (V*k, 2)
    edges.sort(axis=1)
    return np.unique(edges, axis=0).astype(np.int64)


def medl(pred, gt, k=6, rest=None):
    """MEDL: mean absolute edge-length difference over a k-nearest-neighbour graph.

    The graph (``knn_edges``) is built once, on ``rest`` when given (e.g. the target's T-pose
    points) and otherwise on the first ground-truth frame ``gt[0]``, then used for every frame.

    Args:
        pred: (T, V, 3) predicted target points, metres.
        gt: (T, V, 3) ground-truth target points, metres, in the same order.
        k: neighbours per point in the graph (the paper: 6).
        rest: optional (V, 3) points to build the graph on, metres.
    Returns:
        float, metres: mean over edges and frames of ``| |pred_i - pred_j| - |gt_i - gt_j| |``.
    """
    pred, gt = _as_pair(pred, gt)
    if rest is None:
        graph_points = gt[0]
    else:
        graph_points = _as_float64(rest, "rest")
        if graph_points.shape != gt.shape[1:]:
            raise ValueError(f"rest must have shape (V, 3) with V = {gt.shape[1]} as in gt, got "
                             f"rest {graph_points.shape} and gt {gt.shape}")
    edges = knn_edges(graph_points, k)                              # (E, 2)
    return float(_edge_length_difference_sum(pred, gt, edges) / (pred.shape[0] * len(edges)))


@kernel
def _edge_length_difference_sum(pred, gt, edges):
    """Sum over frames and edges of | |pred_i - pred_j| - |gt_i - gt_j| |: (T, V, 3) float64,
    (E, 2) int64. A loop, not (T, E, 3) temporaries, which on a dense target are large and
    read once."""
    total = 0.0
    for t in range(pred.shape[0]):
        for e in range(edges.shape[0]):
            a, b = edges[e, 0], edges[e, 1]
            p = np.sqrt((pred[t, a, 0] - pred[t, b, 0]) ** 2 + (pred[t, a, 1] - pred[t, b, 1]) ** 2
                        + (pred[t, a, 2] - pred[t, b, 2]) ** 2)
            g = np.sqrt((gt[t, a, 0] - gt[t, b, 0]) ** 2 + (gt[t, a, 1] - gt[t, b, 1]) ** 2
                        + (gt[t, a, 2] - gt[t, b, 2]) ** 2)
            total += abs(p - g)
    return total


def jitter(points):
    """Mean acceleration magnitude of one sequence (no ground truth), metres per frame^2.

    Args:
        points: (T, N, 3) points (joints, say), metres, T >= 3 frames.
    Returns:
        float: mean over the T - 2 interior frames and the N points of
        ``|x[t+1] - 2 x[t] + x[t-1]|``; multiply by ``FPS ** 2`` for m/s^2.
    """
    points = _as_float64(points, "points", sequence=True)
    if points.shape[0] < ACCELERATION_FRAMES:
        raise ValueError(f"points need at least {ACCELERATION_FRAMES} frames, got shape "
                         f"{points.shape}")
    return float(np.linalg.norm(_second_difference(points), axis=-1).mean())


FOOT_JOINTS = ("left_foot", "right_foot")


def foot_contacts(joints, contact_height=0.03, feet=FOOT_JOINTS):
    """Which steps t -> t+1 each foot is in contact with the ground (see ``foot_sliding``).

    Args:
        joints: (T, J, 3) joints in ``conventions.JOINT_NAMES`` order, metres, +Y up, T >= 2.
        contact_height: metres above the foot's own lowest height that still count as contact.
        feet: joint names of the feet.
    Returns:
        (T - 1, F) bool, F = len(feet): the foot is at most ``contact_height`` above its
        lowest height over the sequence in both frames t and t + 1.
    """
    joints = _as_float64(joints, "joints", sequence=True)
    if joints.shape[0] < 2:
        raise ValueError(f"joints need at least 2 frames, got shape {joints.shape}")
    height = joints[:, [JOINT_INDEX[name] for name in feet], UP_AXIS]   # (T, F)
    low = height - height.min(axis=0) <= contact_height                 # (T, F)
    return low[:-1] & low[1:]


def foot_sliding(joints, fps=FPS, contact_height=0.03, feet=FOOT_JOINTS):
    """Mean horizontal speed of the feet while they touch the ground, metres per second.

    A step t -> t+1 of a foot counts as contact when the foot's height is at most
    ``contact_height`` above that foot's own lowest height over the sequence in both frames
    (``foot_contacts``; see the module docstring for why the floor is per foot). Its speed is
    the horizontal (x, z) displacement over the step times ``fps``. The contact steps of all
    feet are pooled.

    Args:
        joints: (T, J, 3) joints in ``conventions.JOINT_NAMES`` order, metres, +Y up, T >= 2.
        fps: frames per second.
        contact_height: metres above the foot's lowest height that still count as contact
            (default 3 cm).
        feet: joint names of the feet.
    Returns:
        float, m/s: mean speed over the contact steps; nan if there are none.
    """
    contact = foot_contacts(joints, contact_height, feet)               # (T-1, F)
    speed = foot_speeds(joints, fps, feet)
    return float(speed[contact].mean()) if contact.any() else float("nan")


def foot_speeds(joints, fps=FPS, feet=FOOT_JOINTS):
    """(T, J, 3) joints, metres, T >= 2 -> (T - 1, F) horizontal (x, z) speed of each foot
    over each step t -> t+1, metres per second."""
    joints = _as_float64(joints, "joints", sequence=True)
    if joints.shape[0] < 2:
        raise ValueError(f"joints need at least 2 frames, got shape {joints.shape}")
    horizontal = [axis for axis in range(3) if axis != UP_AXIS]
    feet_xz = joints[:, [JOINT_INDEX[name] for name in feet]][..., horizontal]  # (T, F, 2)
    return np.linalg.norm(np.diff(feet_xz, axis=0), axis=-1) * fps      # (T-1, F)


def evaluate(pred_joints, gt_joints, pred_points, gt_points, k=6, rest_points=None):
    """Every metric of the accuracy protocol for one retargeted sequence.

    Args:
        pred_joints: (T, J, 3) predicted joints, metres, T >= 3 frames at 30 fps.
        gt_joints: (T, J, 3) ground-truth joints, metres.
        pred_points: (T, V, 3) predicted target points, metres.
        gt_points: (T, V, 3) ground-truth target points, metres, same order.
        k: neighbours of the MEDL graph.
        rest_points: optional (V, 3) points to build the MEDL graph on (default ``gt_points[0]``).
    Returns:
        dict of floats with the keys of ``METRIC_NAMES``: "MPJPE", "PA-MPJPE", "MPVD",
        "PA-MPVD" and "MEDL" in metres; "Acc" and "PA-Acc", taken on the joints, in metres
        per frame^2.
    """
    pred_joints, gt_joints = _as_pair(pred_joints, gt_joints, ("pred_joints", "gt_joints"),
                                      ACCELERATION_FRAMES)
    pred_points, gt_points = _as_pair(pred_points, gt_points, ("pred_points", "gt_points"),
                                      ACCELERATION_FRAMES)
    if pred_joints.shape[0] != pred_points.shape[0]:
        raise ValueError(f"joints and points must have the same number of frames T, got "
                         f"pred_joints {pred_joints.shape} and pred_points {pred_points.shape}")
    aligned_joints = procrustes_align(pred_joints, gt_joints)       # (T, J, 3)
    aligned_points = procrustes_align(pred_points, gt_points)       # (T, V, 3)
    accel_gt = _second_difference(gt_joints)                        # (T-2, J, 3)
    return {
        "MPJPE": _mean_distance(pred_joints, gt_joints),
        "PA-MPJPE": _mean_distance(aligned_joints, gt_joints),
        "Acc": _mean_distance(_second_difference(pred_joints), accel_gt),
        "PA-Acc": _mean_distance(_second_difference(aligned_joints), accel_gt),
        "MPVD": _mean_distance(pred_points, gt_points),
        "PA-MPVD": _mean_distance(aligned_points, gt_points),
        "MEDL": medl(pred_points, gt_points, k=k, rest=rest_points),
    }


JOINT_GROUPS = {
    "torso": ("pelvis", "spine1", "spine2", "spine3", "neck", "head", "left_collar",
              "right_collar"),
    "legs": ("left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
             "left_foot", "right_foot"),
    "arms": ("left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist",
             "right_wrist"),
}


def _same_shape(joints, truth):
    """Both as float64 (T, J, 3) sequences; ValueError unless their shapes are equal."""
    joints = _as_float64(joints, "joints", sequence=True)
    truth = _as_float64(truth, "truth", sequence=True)
    if joints.shape != truth.shape:
        raise ValueError(f"joints {joints.shape} and truth {truth.shape} must have one shape")
    return joints, truth


def joint_errors(joints, truth):
    """Mean joint position error of a skeleton sequence, all joints and per ``JOINT_GROUPS``.

    Args:
        joints, truth: (T, J, 3) joints, metres.
    Returns:
        dict: "all", "torso", "legs", "arms" -> float, metres (no alignment).
    """
    joints, truth = _same_shape(joints, truth)
    errors = np.linalg.norm(joints - truth, axis=-1)                                   # (T, J)
    return {"all": float(errors.mean()), **{
        group: float(errors[:, [JOINT_INDEX[name] for name in names]].mean())
        for group, names in JOINT_GROUPS.items()}}


def crossed_feet(joints, truth, margin=0.05):
    """Frames whose ankles lie on the wrong sides of each other, against the truth's.

    Each skeleton's side-to-side axis is its own hips' (left minus right, horizontal); the
    ankles' offset along it (left minus right) has the wrong sign where the truth's is at
    least ``margin`` (metres) from zero: the legs are crossed, or read swapped.

    Args:
        joints, truth: (T, J, 3) joints, metres, +Y up.
    Returns:
        (T,) bool.
    """
    def side(skeleton):
        across = skeleton[:, JOINT_INDEX["left_hip"]] - skeleton[:, JOINT_INDEX["right_hip"]]
        across[:, UP_AXIS] = 0.0
        across /= np.maximum(np.linalg.norm(across, axis=1, keepdims=True), 1e-9)
        ankles = (skeleton[:, JOINT_INDEX["left_ankle"]]
                  - skeleton[:, JOINT_INDEX["right_ankle"]])
        return np.einsum("ta,ta->t", ankles, across)
    joints, truth = _same_shape(joints, truth)
    ours, theirs = side(joints), side(truth)
    return (np.sign(ours) != np.sign(theirs)) & (np.abs(theirs) >= margin)


def skating_steps(joints, height=0.05, speed=0.5, window=5, fps=FPS, feet=FOOT_JOINTS):
    """The common skating measure: steps t -> t+1 where a foot is low in both frames (at most
    ``height`` above its own lowest height over the sequence) while its horizontal speed,
    averaged over ``window`` (odd) steps centred on it, exceeds ``speed`` (m/s).

    Args:
        joints: (T, J, 3) joints, metres, +Y up, T >= 2.
    Returns:
        (T - 1, F) bool; its mean is the skating ratio.
    """
    if window < 1 or window % 2 == 0:
        raise ValueError(f"window must be an odd number of steps, got {window}")
    low = foot_contacts(joints, height, feet)                               # (T - 1, F)
    speeds = foot_speeds(joints, fps, feet)                                 # (T - 1, F)
    kernel = np.ones(window) / window
    padded = np.pad(speeds, ((window // 2, window // 2), (0, 0)), mode="edge")
    averaged = np.stack([np.convolve(padded[:, f], kernel, mode="valid")
                         for f in range(speeds.shape[1])], axis=1)
    return low & (averaged > speed)
