"""A picture to check the data by eye: a few bodies walking a CMU walk, side and front views.

Each row is one body. Left: side view, several frames of the walk along its direction of
travel. Right: front view of one frame. The mesh is shaded and coloured by each face's
strongest joint (skinning weights), with the skeleton drawn over it and the floor at y = 0.
"""
import numpy as np

from minretarget.atomic import atomic_write
from minretarget.conventions import JOINT_NAMES, PARENTS

from .bodies import benchmark_bodies, body_from_seed, get_body, pose_body

# Bodies to look at: a child and a heavy body among them.
PREVIEW_PHENOTYPES = {
    "child (about 6 years)": dict(gender=0.3, age=0.2, muscle=0.5, weight=0.5, height=0.5,
                                  proportions=0.5),
    "heavy adult": dict(gender=0.2, age=0.85, muscle=0.3, weight=1.0, height=0.45,
                        proportions=0.5),
}


def preview_bodies(cache_dir=None):
    """[(label, Body)]: the preview phenotypes, two test targets and one sampled body."""
    targets, _ = benchmark_bodies(cache_dir)
    bodies = [(label, get_body(p, label, cache_dir)) for label, p in PREVIEW_PHENOTYPES.items()]
    sampled = body_from_seed(0, cache_dir)
    return bodies + [(t.name, t) for t in (targets[0], targets[3])] + [(sampled.name, sampled)]


def _view_axes(root):
    """Unit horizontal (along, across) axes: the direction of travel and its left normal."""
    travel = root[-1] - root[0]
    travel[1] = 0.0
    along = travel / max(np.linalg.norm(travel), 1e-6)
    return along, np.cross([0.0, 1.0, 0.0], along)


def _draw_mesh(ax, vertices, faces, colours, axis):
    """Shaded mesh projected on (axis, +Y), painted back to front.

    Args:
        vertices: (V, 3) posed vertices; faces: (F, 3); colours: (F, 4) RGBA per face;
        axis: (3,) the screen's horizontal axis (unit, horizontal).
    """
    from matplotlib.collections import PolyCollection
    towards_viewer = np.cross(axis, [0.0, 1.0, 0.0])
    corners = vertices[faces]                                          # (F, 3, 3)
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    light = towards_viewer + np.array([0.0, 0.6, 0.0])
    shade = 0.35 + 0.65 * np.abs(normals @ (light / np.linalg.norm(light)))   # (F,)
    order = np.argsort(corners.mean(axis=1) @ towards_viewer)          # far first
    screen = np.stack([corners @ axis, corners[..., 1]], axis=-1)      # (F, 3, 2)
    shaded = colours.copy()
    shaded[:, :3] *= shade[:, None]
    ax.add_collection(PolyCollection(screen[order], facecolors=shaded[order],
                                     edgecolors="none"))


def render(motion, actor_hip_height, path, frames=5, span=60, cache_dir=None):
    """Draw the preview into ``path`` (png).

    Args:
        motion: a motion (``rotations`` (T, J, 4), ``root`` (T, 3), ``name``) at 30 fps.
        actor_hip_height: the motion's actor hip height, metres (to scale the root path).
        frames: frames drawn in the side view, spread over ``span`` frames mid-motion.
        cache_dir: body cache folder (None: the default).
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bodies = preview_bodies(cache_dir)
    first = max(0, len(motion.rotations) // 2 - span // 2)
    picked = np.linspace(first, min(first + span, len(motion.rotations)) - 1, frames).astype(int)
    figure, axes = plt.subplots(len(bodies), 2, figsize=(15, 3.4 * len(bodies)),
                                gridspec_kw={"width_ratios": [4, 1]}, squeeze=False)
    joint_colours = plt.get_cmap("tab20")(np.arange(len(JOINT_NAMES)) % 20)
    for row, (label, body) in enumerate(bodies):
        root = motion.root[picked] * (body.hip_height / actor_hip_height)
        vertices, joints = pose_body(body, motion.rotations[picked], root)
        along, across = _view_axes(root)
        # Each face takes the colour of its first vertex's strongest joint.
        colours = joint_colours[np.argmax(body.weights[body.faces[:, 0]], axis=1)]
        for column, (axis, frame_ids) in enumerate(((along, range(frames)),
                                                   (across, [frames // 2]))):
            ax = axes[row, column]
            for f in frame_ids:
                _draw_mesh(ax, vertices[f], body.faces, colours, axis)
                for j, p in enumerate(PARENTS[1:], start=1):
                    ax.plot(joints[f, [p, j]] @ axis, joints[f, [p, j], 1], "k-", lw=0.6)
            ax.axhline(0.0, color="0.4", lw=0.8)
            shown = vertices[list(frame_ids)] @ axis
            ax.set_xlim(shown.min() - 0.1, shown.max() + 0.1)
            ax.set_ylim(-0.05, max(2.0, vertices[..., 1].max() + 0.05))
            ax.set_aspect("equal")
            ax.set_title(f"{label}, {body.height:.2f} m: "
                         + ("side view, frames " + ", ".join(map(str, picked)) if column == 0
                            else f"front view, frame {picked[frames // 2]}"), fontsize=9)
    figure.suptitle(f"{motion.name} on anny bodies (colour: strongest joint; black: skeleton; "
                    "grey line: floor)")
    figure.tight_layout()
    with atomic_write(path) as file:
        figure.savefig(file, format="png", dpi=110)
    plt.close(figure)
