"""Previews of a result: the source and the retargeted target side by side over time.

    render("out/result.npz", "preview.png")   # a strip: a few frames, source above, result below
    render("out/result.npz", "preview.gif")   # an animation: source left, result right

Drawn with matplotlib's Agg canvas (no display, no global pyplot state), orthographic, seen
from the front-left (``AZIMUTH`` about +Y, canonical axes; the body faces +Z), each panel
centred on that frame's pelvis. The source is drawn as its skeleton (the joints SKR found, or
the BVH's), over its point cloud when ``source_points`` are given; the result as its posed
surface, each triangle lit from the viewer's side and drawn far to near (its points shaded by
depth if the target has no faces), under its skeleton, and a reference skeleton (e.g. the
ground truth) over it when ``truth_joints`` are given. Needs the ``cli`` extra (matplotlib,
Pillow).
"""
import io
import math
from pathlib import Path

import numpy as np

from .atomic import atomic_write
from .conventions import NUM_JOINTS, PARENTS
from .extras import require
from .formats.npz import ARCHIVE_ERRORS, NpzFrames, npz_members
from .units import make_space, to_canonical
from .validation import as_float32_array

AZIMUTH = 40.0                 # degrees about +Y from the front view
MAX_POINTS = 4000              # result points drawn per panel (a fixed random subset)
STRIP_FRAMES = 6
MAX_GIF_FRAMES = 150
_SOURCE_COLOR, _RESULT_COLOR, _TRUTH_COLOR = "tab:blue", "tab:orange", "tab:green"
_RESULT_KEYS = ("joints", "source_joints", "vertices", "fps", "units", "up_axis")
# Toward the light: the viewer's side, raised (canonical axes, unit length).
_LIGHT = np.array([math.sin(math.radians(AZIMUTH)), 0.5, math.cos(math.radians(AZIMUTH))]) / \
    math.sqrt(1.25)


def project(points, azimuth=AZIMUTH):
    """(..., 3) canonical points -> (..., 2) screen (right, up) and (...,) depth (toward the
    viewer), for a camera turned ``azimuth`` degrees about +Y from the front (+Z) view."""
    a = math.radians(azimuth)
    x, y, z = np.moveaxis(np.asarray(points, dtype=np.float64), -1, 0)
    right = x * math.cos(a) - z * math.sin(a)
    depth = x * math.sin(a) + z * math.cos(a)
    return np.stack([right, y], axis=-1), depth


def _selected_frames(count, suffix):
    """Indices of the frames to draw: evenly spread for a strip, every k-th for a GIF."""
    if suffix == ".png":
        return np.unique(np.linspace(0, count - 1, min(STRIP_FRAMES, count)).round().astype(int))
    return np.arange(0, count, max(1, math.ceil(count / MAX_GIF_FRAMES)))


def _collect(result, vertices, source_points, keep, truth_joints=None):
    """The drawn frames' arrays, canonical: list of dicts (joints, source_joints, vertices (a
    subset), surface (all of them, if the target has faces, else None), source_points or None,
    truth_joints or None); only these frames' vertices are ever held in memory."""
    space = make_space(str(result["units"]), str(result["up_axis"]))
    joints = to_canonical(result["joints"], space)
    source_joints = to_canonical(result["source_joints"], space)
    subset = np.random.default_rng(0).permutation(vertices.shape[1])[:MAX_POINTS]
    clouds = iter(source_points) if source_points is not None else None
    keep, frames = set(int(k) for k in keep), []
    for index, posed in enumerate(vertices):
        cloud = next(clouds) if clouds is not None else None
        if index in keep:
            posed = to_canonical(np.asarray(posed), space)                     # (V, 3)
            frames.append({"index": index, "joints": joints[index],
                           "source_joints": source_joints[index], "vertices": posed[subset],
                           "surface": None if result["faces"] is None else posed,
                           "source_points": None if cloud is None else np.asarray(cloud),
                           "truth_joints": None if truth_joints is None
                           else np.asarray(truth_joints[index], dtype=np.float64)})
    return frames


def _limits(frames, key, points_key):
    """Half-width about the pelvis and vertical range covering every drawn frame."""
    half, low, high = 0.3, np.inf, -np.inf
    for frame in frames:
        drawn = [frame[key]] + ([frame[points_key]] if frame[points_key] is not None else [])
        if key == "joints" and frame["truth_joints"] is not None:
            drawn.append(frame["truth_joints"])
        screen = np.concatenate([project(p)[0] for p in drawn])
        pelvis = project(frame[key][0])[0]
        half = max(half, np.abs(screen[:, 0] - pelvis[0]).max())
        low, high = min(low, screen[:, 1].min()), max(high, screen[:, 1].max())
    margin = 0.05 * (high - low)
    return half + margin, (low - margin, high + margin)


def _skeleton(axes, joints, color, lw=1.5, size=6):
    screen, _ = project(joints)
    for j, parent in enumerate(PARENTS):
        if parent >= 0:
            axes.plot(screen[[parent, j], 0], screen[[parent, j], 1], color=color, lw=lw)
    axes.scatter(screen[:, 0], screen[:, 1], color=color, s=size, zorder=3)
    return screen


def _surface(axes, vertices, faces):
    """Draw a mesh: (V, 3) canonical vertices, (F, 3) faces; each triangle grey by how
    squarely it faces the light (either side: any winding), far ones first."""
    from matplotlib.collections import PolyCollection

    screen, depth = project(vertices)
    corners = vertices[faces]                                                # (F, 3, 3)
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    lit = np.abs(normals @ _LIGHT) / (np.linalg.norm(normals, axis=1) + 1e-12)   # (F,)
    order = np.argsort(depth[faces].mean(axis=1))
    grey = np.repeat((0.25 + 0.7 * lit[order])[:, None], 3, axis=1)           # (F, 3) RGB
    axes.add_collection(PolyCollection(screen[faces[order]], facecolors=grey,
                                       edgecolors="none", antialiaseds=False))


def _draw(axes, joints, points, color, limits, shaded, truth=None, surface=None, faces=None):
    """One panel: a surface (``surface`` vertices and ``faces``), or points (shaded by depth
    or grey), then the skeleton, centred on the pelvis."""
    half, (low, high) = limits
    if surface is not None:
        _surface(axes, surface, faces)
    elif points is not None:
        screen, depth = project(points)
        order = np.argsort(depth)                          # far points first, near on top
        if shaded:
            # Far points light grey, near ones dark: never white on the white background.
            near, far = depth.max(), depth.min()
            axes.scatter(screen[order, 0], screen[order, 1], c=depth[order], cmap="Greys",
                         vmin=far - 0.5 * (near - far), vmax=near, s=1.5, linewidths=0)
        else:
            axes.scatter(screen[:, 0], screen[:, 1], color="0.65", s=0.8, linewidths=0)
    screen = _skeleton(axes, joints, color)
    if truth is not None:
        _skeleton(axes, truth, _TRUTH_COLOR, lw=1.0, size=3)
    centre = screen[0, 0]
    axes.set_xlim(centre - half, centre + half)
    axes.set_ylim(low, high)
    axes.set_aspect("equal")
    axes.set_xticks([])
    axes.set_yticks([])


def _load_result(path):
    """A ``result.npz``'s arrays that a preview draws, checked: ({joints, source_joints (T, J,
    3) float32, fps float, units, up_axis, faces (F, 3) or None}, its vertices as
    ``NpzFrames`` (T, V, 3)).
    ValueError naming the file and what is wrong."""
    missing = set(_RESULT_KEYS) - set(npz_members(path))
    if missing:
        raise ValueError(f"{path}: not a minretarget result (missing "
                         f"{', '.join(sorted(missing))})")
    try:
        with np.load(path, allow_pickle=False) as data:
            result = {key: data[key] for key in _RESULT_KEYS if key != "vertices"}
            faces = data["target_faces"] if "target_faces" in data.files else None
    except ARCHIVE_ERRORS as error:
        raise ValueError(f"{path}: not a readable .npz ({error})") from None
    vertices = NpzFrames(path, "vertices")
    try:
        for key in ("joints", "source_joints"):
            result[key] = as_float32_array(result[key], key, (None, NUM_JOINTS, 3))
        result["fps"] = float(result["fps"])
        make_space(str(result["units"]), str(result["up_axis"]))
    except (ValueError, TypeError) as error:
        raise ValueError(f"{path}: {error}") from None
    count = len(result["joints"])
    if count == 0:
        raise ValueError(f"{path}: holds no frames")
    if faces is not None and len(faces) and (
            faces.ndim != 2 or faces.shape[1] != 3 or faces.dtype.kind not in "iu"
            or faces.min() < 0 or faces.max() >= vertices.shape[1]):
        raise ValueError(f"{path}: target_faces must be (F, 3) indices of its vertices, got "
                         f"{faces.dtype} {faces.shape}")
    result["faces"] = faces if faces is not None and len(faces) else None
    if not 0 < result["fps"] < math.inf:
        raise ValueError(f"{path}: fps must be positive and finite, got {result['fps']}")
    lengths = {"source_joints": len(result["source_joints"]), "vertices": len(vertices)}
    if (len(vertices.shape) != 3 or vertices.shape[2] != 3 or vertices.dtype.kind not in "fiu"
            or any(length != count for length in lengths.values())):
        raise ValueError(f"{path}: joints {result['joints'].shape}, source_joints "
                         f"{result['source_joints'].shape} and vertices {vertices.dtype} "
                         f"{vertices.shape} must be (T, 22, 3), (T, 22, 3) and (T, V, 3) "
                         "numbers with one T")
    return result, vertices


def render(result_path, out_path, source_points=None, truth_joints=None, title=None):
    """Draw a preview of ``result.npz`` into a ``.png`` strip or a ``.gif`` animation.

    Args:
        result_path: a ``result.npz`` written by ``minretarget retarget``.
        out_path: ``.png`` or ``.gif``; written atomically.
        source_points: optional iterable of the T source clouds (P, 3), canonical metres,
            drawn under the source skeleton.
        truth_joints: optional (T, J, 3) canonical metres, a reference skeleton (the ground
            truth, say) drawn thinner, in green, over the result's skeleton.
        title: optional line written above the strip (PNG only).
    Returns:
        the number of frames drawn.
    """
    out_path = Path(out_path)
    suffix = out_path.suffix.lower()
    if suffix not in (".png", ".gif"):
        raise ValueError(f"{out_path}: the preview must be a .png or a .gif")
    require("matplotlib", "drawing previews")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    result, vertices = _load_result(result_path)
    count = len(result["joints"])
    frames = _collect(result, vertices, source_points, _selected_frames(count, suffix),
                      truth_joints)
    source_limits = _limits(frames, "source_joints", "source_points")
    result_limits = _limits(frames, "joints", "vertices")
    fps = result["fps"]

    def panel(axes, frame, which):
        if which == "source":
            _draw(axes, frame["source_joints"], frame["source_points"], _SOURCE_COLOR,
                  source_limits, shaded=False)
        else:
            _draw(axes, frame["joints"], frame["vertices"], _RESULT_COLOR, result_limits,
                  shaded=True, truth=frame["truth_joints"], surface=frame["surface"],
                  faces=result["faces"])

    # Panel heights follow each row's aspect (vertical range over width), panels 2 inches wide.
    heights = [(limits[1][1] - limits[1][0]) / (2 * limits[0])
               for limits in (source_limits, result_limits)]
    if suffix == ".png":
        figure = Figure(figsize=(2.0 * len(frames), 2.0 * sum(heights) + 0.6), dpi=110)
        grid = figure.subplots(2, len(frames), squeeze=False,
                               gridspec_kw={"height_ratios": heights})
        for column, frame in enumerate(frames):
            panel(grid[0, column], frame, "source")
            panel(grid[1, column], frame, "result")
            grid[0, column].set_title(f"t = {frame['index'] / fps:.2f} s", fontsize=9)
        grid[0, 0].set_ylabel("source")
        grid[1, 0].set_ylabel("retargeted")
        if title:
            figure.suptitle(title, fontsize=9)
        figure.tight_layout()
        buffer = io.BytesIO()
        FigureCanvasAgg(figure).print_png(buffer)
        data = buffer.getvalue()
    else:
        image = require("PIL.Image", "writing GIF previews")
        figure = Figure(figsize=(6.0, 3.0 * max(heights) + 0.6), dpi=80)
        canvas = FigureCanvasAgg(figure)
        images = []
        for frame in frames:
            figure.clear()
            left, right = figure.subplots(1, 2)
            panel(left, frame, "source")
            panel(right, frame, "result")
            left.set_title("source", fontsize=9)
            right.set_title("retargeted", fontsize=9)
            figure.suptitle(f"t = {frame['index'] / fps:.2f} s", fontsize=9)
            canvas.draw()
            rgb = np.asarray(canvas.buffer_rgba())[..., :3]
            images.append(image.fromarray(rgb).quantize(colors=64))
        step = frames[1]["index"] - frames[0]["index"] if len(frames) > 1 else 1
        buffer = io.BytesIO()
        images[0].save(buffer, format="GIF", save_all=True, append_images=images[1:],
                       duration=int(round(1000 * step / fps)), loop=0)
        data = buffer.getvalue()
    with atomic_write(out_path) as file:
        file.write(data)
    return len(frames)
