"""Plain NumPy twins of the runtime's numba kernels: slow, obvious, float64.

Each twin restates the maths from its docstring in the most direct NumPy form, so a kernel
and its twin can only agree if both implement the same equations.
"""
import numpy as np

from minretarget.conventions import MIRROR, PARENTS


def quaternion_to_matrix(q):
    """(..., 4) (w, x, y, z) -> (..., 3, 3), via the unit quaternion."""
    q = np.asarray(q, np.float64)
    w, x, y, z = np.moveaxis(q / np.linalg.norm(q, axis=-1, keepdims=True), -1, 0)
    return np.stack([
        np.stack([w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z], -1),
    ], -2)


def forward_kinematics(rotations, root, tpose):
    """(J, 4), (3,), (J, 3) -> joints (J, 3), global rotations (J, 3, 3)."""
    local = quaternion_to_matrix(rotations)
    joints, globals_ = [np.asarray(root, np.float64)], [local[0]]
    for j in range(1, len(PARENTS)):
        p = PARENTS[j]
        globals_.append(globals_[p] @ local[j])
        joints.append(joints[p] + globals_[p] @ (tpose[j] - tpose[p]))
    return np.stack(joints), np.stack(globals_)


def dense(x, layer, relu):
    y = np.asarray(x, np.float64) @ layer.weight + layer.bias
    return np.maximum(y, 0) if relu else y


def mlp(x, weights):
    for layer in weights.hidden:
        x = dense(x, layer, True)
    return dense(x, weights.output, False)


def pointnet(points, weights):
    """(P, 3) -> (J, 3): SKR as described in minretarget.skr."""
    def features(x, net, first):
        for layer in net.point[first:]:
            x = dense(x, layer, True)
        return x.max(axis=0, keepdims=True)

    def transform(x, net):
        k = x.shape[1]
        return mlp(features(x, net, 0), net.head).reshape(k, k) + np.eye(k)

    centroid = points.mean(axis=0, dtype=np.float64)
    x = points - centroid
    x = x @ transform(x, weights.input_transform)
    x = dense(x, weights.regressor.point[0], True)
    x = x @ transform(x, weights.feature_transform)
    return mlp(features(x, weights.regressor, 1), weights.regressor.head).reshape(-1, 3) + centroid


def refine_joints(points, joints, weights, neighbours, max_points=2048, scale=0.1):
    """(P, 3), (J, 3) -> (J, 3): the joint refiner as described in minretarget.refine, with a
    full sort for the nearest points and one joint at a time."""
    points = points[::-(-len(points) // max_points)]
    k = min(neighbours, len(points))
    refined = np.empty(joints.shape)
    for j, joint in enumerate(joints):
        nearest = np.argsort(((points - joint) ** 2).sum(axis=1))[:k]
        x = (points[nearest] - joint) / scale
        for layer in weights.point:
            x = dense(x, layer, True)
        one_hot = np.eye(len(joints))[j]
        head_input = np.concatenate([x.max(axis=0), (joints - joint).ravel(), one_hot])
        refined[j] = joint + scale * mlp(head_input[None], weights.head)[0]
    return refined


def gru_layer_step(x, h, layer):
    """torch.nn.GRU's cell: gates ordered reset, update, new."""
    sigmoid = lambda v: 1 / (1 + np.exp(-v))  # noqa: E731
    x_reset, x_update, x_new = np.split(x @ layer.input_weight + layer.input_bias, 3, axis=-1)
    h_reset, h_update, h_new = np.split(h @ layer.hidden_weight + layer.hidden_bias, 3, axis=-1)
    reset, update = sigmoid(x_reset + h_reset), sigmoid(x_update + h_update)
    n = np.tanh(x_new + reset * h_new)
    return (1 - update) * n + update * h


def heading_features(joints, previous_root):
    """(J, 3) joints -> SMRM's and the denoiser's input (1, J*3 + 3) and the heading turn
    (3, 3): the turn about +Y taking +Z onto the facing direction (across x up)."""
    across = joints[1] - joints[2] + joints[16] - joints[17]
    facing = np.cross(across, [0.0, 1.0, 0.0])
    facing /= np.linalg.norm(facing)
    turn = np.array([[facing[2], 0, facing[0]], [0, 1, 0], [-facing[0], 0, facing[2]]])
    features = np.concatenate([((joints - joints[0]) @ turn).ravel(),
                               (joints[0] - previous_root) @ turn])[None]
    return features, turn


def mirrored(joints):
    """(..., J, 3) joints of the mirror image: x -> -x, left and right joints swapped."""
    return joints[..., list(MIRROR), :] * np.array([-1.0, 1.0, 1.0], joints.dtype)


def denoise(frames, weights):
    """(T, J, 3) a stream's source joints -> the denoiser's output (T, J, 3), from zeros: the
    average of one view's on the frames and, mirrored back, on their mirror images."""
    return (_denoise_one_view(frames, weights)
            + mirrored(_denoise_one_view(mirrored(frames), weights))) / 2


def _denoise_one_view(frames, weights):
    hidden = np.zeros((len(weights.gru), 1, weights.gru[0].hidden_weight.shape[0]))
    out, previous_root = [], frames[0, 0]
    for joints in frames:
        x, turn = heading_features(joints, previous_root)
        for i, layer in enumerate(weights.gru):
            x = hidden[i] = gru_layer_step(x, hidden[i], layer)
        out.append(joints + dense(x, weights.head, False).reshape(-1, 3) @ turn.T)
        previous_root = joints[0]
    return np.stack(out)


def skinning_weights(points, tpose_joints, weights):
    """(V, 3), (J, 3) -> (V, J) softmax of the MLP of the offsets."""
    offsets = (points[:, None, :] - tpose_joints[None, :, :]).reshape(len(points), -1)
    logits = mlp(offsets, weights)
    e = np.exp(logits - logits.max(axis=1, keepdims=True))
    return e / e.sum(axis=1, keepdims=True)


def linear_blend_skinning(points, skin_weights, transforms):
    """(V, 3), (V, J), (J, 3, 4) -> (V, 3): sum_j w_vj (A_j [x; 1])."""
    homogeneous = np.concatenate([points, np.ones((len(points), 1))], axis=1)     # (V, 4)
    per_joint = np.einsum("jab,vb->vja", transforms.astype(np.float64), homogeneous)
    return np.einsum("vj,vja->va", skin_weights, per_joint)


def alpha_beta(frames, position_gain, velocity_gain, fps=30.0):
    """(T, J, 3) joints -> (T, J, 3) alpha-beta filtered, float64 (minretarget.smoothing's
    kernel, written as the Kalman filter's predict-update with a fixed gain: state
    s = (position, velocity), s <- F s + K (x - H F s), F = [[1, 1/fps], [0, 1]], H = [1, 0],
    K = [alpha, beta fps])."""
    frames = np.asarray(frames, np.float64)
    transition = np.array([[1.0, 1.0 / fps], [0.0, 1.0]])
    gain = np.array([position_gain, velocity_gain * fps])
    state = np.stack([frames[0], np.zeros_like(frames[0])], axis=-1)          # (J, 3, 2)
    out = np.empty_like(frames)
    out[0] = frames[0]
    for t in range(1, len(frames)):
        predicted = state @ transition.T
        state = predicted + (frames[t] - predicted[..., 0])[..., None] * gain
        out[t] = state[..., 0]
    return out


def _turn(axis, angle):
    """3 x 3 rotation by ``angle`` about ``axis`` (Rodrigues' formula)."""
    x, y, z = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    cross = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


def _matrix_to_quaternion(m):
    """3 x 3 rotation -> (w, x, y, z) via the largest-diagonal branch (w >= 0 not forced)."""
    trace = np.trace(m)
    if trace > 0:
        s = 2 * np.sqrt(1 + trace)
        q = [s / 4, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2 * np.sqrt(1 + m[i, i] - m[j, j] - m[k, k])
        q = np.empty(4)
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i], q[1 + j], q[1 + k] = s / 4, (m[j, i] + m[i, j]) / s, (m[k, i] + m[i, k]) / s
    return np.asarray(q)


def plant_feet(rotations, root, tpose, lock, fps=30.0):
    """(T, J, 4), (T, 3), (J, 3), FootLock -> new rotations (T, J, 4) and planted (T, 2):
    minretarget.contacts over a whole sequence, with rotation matrices instead of
    quaternions. Two-bone IK: the knee turns about its hinge (the thigh's x axis) by the
    angle found numerically (a fine scan of the turns that put the ankle at the reach, then
    the smallest that does not bend the knee backwards), the leg swings at the hip, the
    ankle keeps its world orientation."""
    legs = ((1, 4, 7, 10), (2, 5, 8, 11))
    a = 1.0 - 1.0 / (1.0 + 2.0 * np.pi * lock.speed_cutoff / fps)
    out = np.array(rotations, np.float64)
    planted_all = np.zeros((len(out), 2), bool)
    planted, anchor, offset, filtered = [False, False], np.zeros((2, 3)), np.zeros((2, 3)), None
    for t in range(len(out)):
        joints, world = forward_kinematics(rotations[t], root[t], tpose)
        toes = joints[[10, 11]]
        previous = toes if filtered is None else filtered
        filtered = toes if filtered is None else filtered + a * (toes - filtered)
        speed = np.linalg.norm(filtered - previous, axis=1) * fps
        for side, (hip, knee, ankle, toe) in enumerate(legs):
            low = toes[side, 1] <= toes[1 - side, 1] + lock.height_margin
            if planted[side]:
                planted[side] = low and speed[side] <= lock.lift_speed
            elif t > 0 and low and speed[side] < lock.plant_speed:
                planted[side], anchor[side] = True, toes[side] + offset[side]
            if planted[side]:
                anchor[side] = anchor[side] + lock.anchor_follow * (filtered[side] - anchor[side])
                anchor[side, 1] = toes[side, 1]
                gap = anchor[side] - toes[side]
                if np.linalg.norm(gap) > lock.max_offset:
                    anchor[side] = toes[side] + gap * lock.max_offset / np.linalg.norm(gap)
                offset[side] = anchor[side] - toes[side]
            else:
                offset[side] = lock.release_decay * offset[side]
            planted_all[t, side] = planted[side]
            if np.linalg.norm(offset[side]) <= 1e-5:
                continue
            goal = joints[ankle] + offset[side]
            knee_turn = _hinge_turn(joints[hip], joints[knee], joints[ankle], world[hip][:, 0],
                                    np.linalg.norm(goal - joints[hip]))
            bent = joints[knee] + knee_turn @ (joints[ankle] - joints[knee]) - joints[hip]
            wanted = goal - joints[hip]
            axis = np.cross(bent, wanted)
            hip_turn = (np.eye(3) if np.linalg.norm(axis) < 1e-9 else _turn(
                axis, np.arctan2(np.linalg.norm(axis), bent @ wanted)))
            new_hip, new_knee = hip_turn @ world[hip], hip_turn @ knee_turn @ world[knee]
            for joint, local in ((hip, world[0].T @ new_hip), (knee, new_hip.T @ new_knee),
                                 (ankle, new_knee.T @ world[ankle])):
                out[t, joint] = _matrix_to_quaternion(local)
    return out, planted_all


def _hinge_turn(hip, knee, ankle, hinge, reach):
    """3 x 3 turn of the shank about ``hinge`` (through the knee) that brings the ankle
    nearest to ``reach`` from the hip: scan the circle of turns, refine the best crossing."""
    thigh, shank = knee - hip, ankle - knee
    flexion = np.arctan2(np.cross(thigh, shank) @ hinge, thigh @ shank)

    def miss(angle):
        return np.linalg.norm(thigh + _turn(hinge, angle) @ shank) - reach

    angles = np.linspace(-np.pi, np.pi, 3601)
    misses = np.array([miss(angle) for angle in angles])
    # Candidates: sign changes (refined by bisection), else the least miss.
    candidates = []
    for k in np.nonzero(np.sign(misses[:-1]) != np.sign(misses[1:]))[0]:
        lo, hi = angles[k], angles[k + 1]
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if np.sign(miss(mid)) == np.sign(miss(lo)) else (lo, mid)
        candidates.append(0.5 * (lo + hi))
    if not candidates:
        candidates = [angles[np.argmin(np.abs(misses))]]
    best = min(candidates, key=lambda angle: abs(angle) + (0 if flexion + angle >= 0
                                                           else np.pi))
    return _turn(hinge, best)


def _unit(v):
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def _rotation_between(a, b):
    """Unit a, b (3,) -> 3 x 3 smallest rotation taking a to b (Rodrigues about a x b)."""
    axis = np.cross(a, b)
    angle = np.arctan2(np.linalg.norm(axis), a @ b)
    if np.linalg.norm(axis) < 1e-9:               # parallel, or opposite: any perpendicular
        if a @ b > 0:
            return np.eye(3)
        axis = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
    return _turn(axis, angle)


def analytic_rotations(source, tpose):
    """(T, J, 3) source joints, (J, 3) target T-pose -> (T, J, 3, 3) local rotation matrices:
    each bone turned onto its source bone, Kabsch over several children, leaves keep their
    parent's rotation (minretarget.analytic)."""
    source, tpose = np.asarray(source, np.float64), np.asarray(tpose, np.float64)
    children = [[c for c in range(len(PARENTS)) if PARENTS[c] == j] for j in range(len(PARENTS))]
    out = np.empty(source.shape[:2] + (3, 3))
    for t, frame in enumerate(source):
        world = []
        for j, kids in enumerate(children):
            parent = world[PARENTS[j]] if j else np.eye(3)
            rest = [_unit(parent @ (tpose[c] - tpose[j])) for c in kids]
            posed = [_unit(frame[c] - frame[j]) for c in kids]
            if len(kids) == 1:
                turn = _rotation_between(rest[0], posed[0])
            elif kids:
                u, _, vt = np.linalg.svd(sum(np.outer(b, a) for a, b in zip(rest, posed)))
                turn = u @ np.diag([1, 1, np.sign(np.linalg.det(u @ vt))]) @ vt
            else:
                turn = np.eye(3)
            world.append(turn @ parent)
            out[t, j] = world[j] if j == 0 else world[PARENTS[j]].T @ world[j]
    return out


def rest_pose_reference(directions, tpose, source_lengths):
    """minretarget.rest_pose.prior_reference, written out: predicted rest directions of both
    bodies from their features, each target bone turned by their difference, lengths kept."""
    tpose = np.asarray(tpose, np.float64)
    bones = [tpose[c] - tpose[PARENTS[c]] for c in range(1, len(PARENTS))]
    target_lengths = np.array([np.linalg.norm(b) for b in bones])
    mirror_bone = [MIRROR[c] - 1 for c in range(1, len(PARENTS))]

    def predicted(lengths):
        symmetric = np.array([(lengths[b] + lengths[m]) / 2 for b, m in enumerate(mirror_bone)])
        total = symmetric.sum()
        features = np.concatenate([[1.0], symmetric / total, [total]])
        return np.array([_unit(d) for d in (features @ directions).reshape(-1, 3)])

    turn = predicted(np.asarray(source_lengths, np.float64)) - predicted(target_lengths)
    out = [tpose[0]]
    for c in range(1, len(PARENTS)):
        b = c - 1
        out.append(out[PARENTS[c]] + _unit(bones[b] / target_lengths[b] + turn[b])
                   * target_lengths[b])
    return np.array(out)


def body_model_pose(model, rest, tpose, rotations, joints):
    """The source fit's posed model (minretarget.fit.pose_model) with dense weights:
    points (Q, 3), unit normals (Q, 3), lever (Q, J, 3), reach (Q, J)."""
    weights = np.zeros((len(rest), len(PARENTS)))
    np.add.at(weights, (np.arange(len(rest))[:, None], model.bone_index), model.bone_weight)
    below = np.eye(len(PARENTS))                  # below[k, j]: k is j or a descendant of j
    for k in range(len(PARENTS)):
        j = PARENTS[k]
        while j >= 0:
            below[k, j] = 1.0
            j = PARENTS[j]
    by_bone = np.einsum("kab,qkb->qka", rotations, rest[:, None] - tpose[None]) + joints[None]
    points = np.einsum("qk,qka->qa", weights, by_bone)
    normals = np.einsum("qk,kab,qb->qa", weights, rotations, model.normals)
    reach = weights @ below
    lever = np.einsum("qk,qka,kj->qja", weights, by_bone, below) - reach[:, :, None] * joints
    return points, normals / np.linalg.norm(normals, axis=1, keepdims=True), lever, reach


def lost_legs(model, rest, tpose, rotations, joints, cloud, far, seen=None,
              bones=("knee", "ankle", "foot")):
    """The source fit's lost lower legs (minretarget.fit.lost_legs) by brute force: per leg
    (left, right), the share of the model points whose heaviest bone is its knee, ankle or
    foot (or the side's ``bones``: ("hip",), its thigh) (and that are ``seen`` (Q,) bool, if
    given) that lie farther than ``far`` from every cloud point -> (2,)."""
    from minretarget.conventions import JOINT_INDEX
    points = body_model_pose(model, rest, tpose, rotations, joints)[0]
    seen = np.ones(len(points), bool) if seen is None else seen
    heaviest = model.bone_index[np.arange(len(rest)), model.bone_weight.argmax(axis=1)]
    distance = np.linalg.norm(points[:, None] - cloud[None], axis=-1).min(axis=1)
    shares = []
    for side in ("left", "right"):
        leg = seen & np.isin(heaviest, [JOINT_INDEX[f"{side}_{j}"]
                                        for j in bones])
        shares.append(float((distance[leg] > far).mean()))
    return np.array(shares)


def surface_pairs(posed_points, cloud, robust_width, model_to_cloud, model_stride, truncate,
                  seen=None):
    """The source fit's pairs (minretarget.fit.surface_terms) one by one, before they are
    summed per model point: each cloud point with its nearest model point, each
    ``model_stride``-th model point (of those ``seen`` (Q,) bool, if given) with its nearest
    cloud point (brute force), Geman-McClure weights -> model index (N,), targets (N, 3),
    weights (N,), cost."""
    inward = np.linalg.norm(cloud[:, None] - posed_points[None], axis=-1)          # (P, Q)
    inward_index = inward.argmin(axis=1)
    inward_distance = inward.min(axis=1)
    outward_index = np.arange(0, len(posed_points), model_stride)
    if seen is not None:
        outward_index = outward_index[seen[outward_index]]
    outward = np.linalg.norm(posed_points[outward_index, None] - cloud[None], axis=-1)
    outward_nearest = outward.argmin(axis=1)
    outward_distance = outward.min(axis=1)

    def robust(distances):
        return 1.0 / (1.0 + (distances / robust_width) ** 2) ** 2

    weights = np.concatenate([robust(inward_distance) / len(cloud),
                              model_to_cloud * robust(outward_distance) / len(outward_index)])
    cost = (np.minimum(inward_distance, truncate).mean()
            + model_to_cloud * np.minimum(outward_distance, truncate).mean())
    return (np.concatenate([inward_index, outward_index]),
            np.concatenate([cloud, cloud[outward_nearest]]), weights, cost)


def plane_normal_equations(index, targets, weights, points, normals, lever, reach):
    """Point-to-plane normal equations (minretarget.fit._plane_normal_equations_kernel) with
    dense rows: the row of pair i is sqrt(w) [n, (lever_j x n) for each joint j that moves the
    point], its value sqrt(w) n . (x - y) -> hessian (P, P), gradient (P,)."""
    n = normals[index]
    turns = np.cross(lever[index], n[:, None]) * (reach[index] > 0)[..., None]      # (N, J, 3)
    rows = np.sqrt(weights)[:, None] * np.concatenate([n, turns.reshape(len(index), -1)], 1)
    values = np.sqrt(weights) * np.sum(n * (points[index] - targets), axis=1)
    return rows.T @ rows, rows.T @ values


def joint_pull_rows(joints, goal, weight):
    """The rows and values of the joints' pull towards ``goal`` (minretarget.fit's
    _pull_normal_equations_kernel): joint k moves by t + sum over strict ancestors j of
    d_j x (p_k - p_j); joint k's rows scaled by sqrt(weight_k / J) (``weight`` a number or
    (J,)) -> (J * 3, 3 + 3 J), (J * 3,)."""
    count = len(PARENTS)
    rows = np.zeros((count, 3, 3 + 3 * count))
    for k in range(count):
        rows[k, :, :3] = np.eye(3)
        j = PARENTS[k]
        while j >= 0:
            lever = joints[k] - joints[j]
            rows[k, :, 3 + 3 * j:6 + 3 * j] = -np.cross(np.eye(3), lever)   # d x l, per d
            j = PARENTS[j]
    scale = np.repeat(np.sqrt(np.broadcast_to(weight, (count,)) / count), 3)
    return scale[:, None] * rows.reshape(count * 3, -1), scale * (joints - goal).ravel()


def seen_points(points, normals, viewpoint, hidden_depth, cell):
    """The source fit's model points a camera at ``viewpoint`` sees (minretarget.fit's
    ``_seen_kernel``) by brute force: facing it, past ``near_plane`` in front of it, and no
    such point in the 3 x 3 cells of a perspective image around its own (``cell`` metres at
    the points' centre) more than ``hidden_depth`` nearer along the view -> (Q,) bool."""
    from minretarget.fit import NEAR_PLANE as near_plane
    axis = points.mean(axis=0) - viewpoint
    distance = np.linalg.norm(axis)
    axis = axis / distance
    right = np.cross(axis, np.eye(3)[np.argmin(np.abs(axis))])
    right /= np.linalg.norm(right)
    up = np.cross(axis, right)
    rays = points - viewpoint
    depth = rays @ axis
    front = depth > near_plane
    if not front.any():
        return front
    scale = distance / np.where(front, depth, 1.0)
    across, along = scale * (rays @ right), scale * (rays @ up)
    column = ((across - across[front].min()) / cell).astype(np.int64)
    row = ((along - along[front].min()) / cell).astype(np.int64)
    near = ((np.abs(column[:, None] - column[None]) <= 1)
            & (np.abs(row[:, None] - row[None]) <= 1) & front[None])
    nearest = np.where(near, depth[None], np.inf).min(axis=1)
    facing = np.einsum("qa,qa->q", normals, viewpoint - points) > 0
    return facing & front & ~(nearest < depth - hidden_depth)
