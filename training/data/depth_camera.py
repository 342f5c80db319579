"""What one depth camera sees of a body: the visible surface as a depth sensor gives it.

A pinhole camera (``Camera``) renders a triangle mesh into a z-buffer (``render``): every
triangle that faces the camera and lies wholly in front of its near plane is rasterised by its
bounding box and a barycentric test at the pixel centres; the nearest hit of each pixel wins,
and the pixel's ray is carried to that depth, so each returned point lies exactly on the mesh
(on the triangle seen through that pixel's centre). ``visible_points`` then keeps a seeded
random subset of a fixed size, as the benchmark feeds the runtime. ``view_cameras`` places the
front, side and back cameras of the single-view benchmark (``benchmarks/single_view.py``).

Camera frame: x right, y down (image rows), z forward (the optical axis); pixel (row r,
column c) has its centre at image coordinates (c + 0.5, r + 0.5). World units are metres,
+Y up (``minretarget.conventions``). Triangles are wound outward (counter-clockwise seen from
outside, as the anny bodies are: positive signed volume): a triangle faces the camera when its
normal points towards it. Back faces are culled, and a closed mesh's front faces hide them in
any case.

NumPy only: each candidate (triangle, pixel) pair is one array element, so the cost grows with
the pixels the triangles' bounding boxes cover (about 20,000 for a body 2.5 m away at 320 x 240,
a few milliseconds).
"""
import math
from typing import NamedTuple

import numpy as np

from minretarget.conventions import FORWARD_AXIS, JOINT_INDEX, LEFT_AXIS, UP_AXIS
from minretarget.kinematics import quaternion_to_matrix

# The default sensor: 320 x 240 pixels, 60 degrees vertical field of view (75 horizontal),
# close to a Kinect v2's or an Azure Kinect's narrow mode (70-75 x 60-65 degrees); depth from
# 0.25 m to 6 m. At 2.5 m a pixel spans about 12 mm, and a standing adult fills the frame's
# height with room to spare.
WIDTH, HEIGHT, FOV_Y_DEGREES = 320, 240, 60.0
NEAR, FAR = 0.25, 6.0
VIEW_DISTANCE = 2.5        # metres from the body's root at frame 0
CHEST_JOINT = JOINT_INDEX["spine3"]
VIEWS = ("front", "side", "back")


class Camera(NamedTuple):
    """A pinhole depth camera.

    position: (3,) float64 world position, metres.
    rotation: (3, 3) float64 world -> camera rotation; its rows are the camera's right, down
        and forward axes in world coordinates.
    width, height: image size, pixels.
    focal: focal length, pixels (square pixels; the principal point is the image centre).
    near, far: the depth range seen, metres along the optical axis.
    """
    position: np.ndarray
    rotation: np.ndarray
    width: int
    height: int
    focal: float
    near: float
    far: float


def look_at(position, target, width=WIDTH, height=HEIGHT, fov_y_degrees=FOV_Y_DEGREES,
            near=NEAR, far=FAR):
    """A ``Camera`` at ``position`` looking at ``target`` (world points, metres), its image
    upright (+Y up). The view direction must not be vertical."""
    position = np.asarray(position, np.float64)
    forward = np.asarray(target, np.float64) - position
    forward /= np.linalg.norm(forward)
    up = np.zeros(3)
    up[UP_AXIS] = 1.0
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-6:
        raise ValueError("look_at: the camera cannot look straight up or down")
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    focal = 0.5 * height / math.tan(math.radians(fov_y_degrees) / 2)
    return Camera(position, np.stack([right, down, forward]), int(width), int(height),
                  float(focal), float(near), float(far))


def render(vertices, faces, camera):
    """The mesh's visible surface, one point per pixel it covers (a z-buffer render).

    Args:
        vertices: (V, 3) mesh vertices, world, metres.
        faces: (F, 3) integer triangles, wound outward.
        camera: a ``Camera``.
    Returns:
        pixels: (N,) int64 row-major pixel indices (row * width + column), ascending.
        points: (N, 3) float64 world points, metres: for each pixel, the point of the nearest
            front-facing triangle hit by the ray through its centre.
        depth: (N,) float64 their depth along the optical axis, metres.
    """
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    local = (vertices - camera.position) @ camera.rotation.T                   # (V, 3)
    tri = local[faces]                                                          # (F, 3, 3)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    normal = np.cross(b - a, c - a)
    facing = np.einsum("fi,fi->f", normal, a) < 0          # the normal points at the camera
    in_front = tri[:, :, 2].min(axis=1) > camera.near
    keep = np.flatnonzero(facing & in_front)
    tri = tri[keep]
    cx, cy = camera.width / 2, camera.height / 2
    inverse_z = 1.0 / tri[:, :, 2]                                              # (K, 3)
    u = camera.focal * tri[:, :, 0] * inverse_z + cx                            # (K, 3)
    v = camera.focal * tri[:, :, 1] * inverse_z + cy
    # Pixel centres inside each triangle's bounding box, clipped to the image.
    col0 = np.maximum(np.ceil(u.min(axis=1) - 0.5), 0).astype(np.int64)
    col1 = np.minimum(np.floor(u.max(axis=1) - 0.5), camera.width - 1).astype(np.int64)
    row0 = np.maximum(np.ceil(v.min(axis=1) - 0.5), 0).astype(np.int64)
    row1 = np.minimum(np.floor(v.max(axis=1) - 0.5), camera.height - 1).astype(np.int64)
    cols, rows = col1 - col0 + 1, row1 - row0 + 1
    area = (u[:, 1] - u[:, 0]) * (v[:, 2] - v[:, 0]) - (u[:, 2] - u[:, 0]) * (v[:, 1] - v[:, 0])
    live = np.flatnonzero((cols > 0) & (rows > 0) & (area != 0))
    counts = cols[live] * rows[live]
    empty = (np.empty(0, np.int64), np.empty((0, 3)), np.empty(0))
    if counts.sum() == 0:
        return empty
    which = np.repeat(live, counts)                                             # (C,)
    offset = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    col = col0[which] + offset % cols[which]
    row = row0[which] + offset // cols[which]
    px, py = col + 0.5, row + 0.5
    u0, v0 = u[which, 0], v[which, 0]
    du1, dv1 = u[which, 1] - u0, v[which, 1] - v0
    du2, dv2 = u[which, 2] - u0, v[which, 2] - v0
    # Screen-space barycentric weights of vertices 1 and 2 (and 0: the rest).
    w1 = ((px - u0) * dv2 - du2 * (py - v0)) / area[which]
    w2 = (du1 * (py - v0) - (px - u0) * dv1) / area[which]
    w0 = 1.0 - w1 - w2
    inside = (w0 >= 0) & (w1 >= 0) & (w2 >= 0)
    which, col, row = which[inside], col[inside], row[inside]
    # 1/z is linear in screen space on a plane: the exact depth of the ray's hit.
    depth = 1.0 / (w0[inside] * inverse_z[which, 0] + w1[inside] * inverse_z[which, 1]
                   + w2[inside] * inverse_z[which, 2])
    seen = depth < camera.far
    which, col, row, depth = which[seen], col[seen], row[seen], depth[seen]
    pixel = row * camera.width + col
    order = np.lexsort((depth, pixel))               # by pixel, the nearest first
    pixel, depth, col, row = pixel[order], depth[order], col[order], row[order]
    first = np.ones(len(pixel), bool)
    first[1:] = pixel[1:] != pixel[:-1]
    pixel, depth, col, row = pixel[first], depth[first], col[first], row[first]
    ray = np.stack([(col + 0.5 - cx) / camera.focal, (row + 0.5 - cy) / camera.focal,
                    np.ones(len(col))], axis=1)                                 # (N, 3)
    points = (ray * depth[:, None]) @ camera.rotation + camera.position
    return pixel, points, depth


def visible_points(vertices, faces, camera, count, rng):
    """What the camera gives the runtime: ``render``'s points, ``count`` of them drawn at
    random without replacement when more are seen, all of them (in a random order) otherwise.

    Args: as ``render``, plus count (points kept at most) and a seeded numpy Generator.
    Returns:
        (N, 3) float32 world points, metres, N = min(count, pixels seen); N may be below
        ``conventions.MIN_POINTS`` (the body out of view): the caller decides what such a
        frame is.
    """
    _, points, _ = render(vertices, faces, camera)
    chosen = rng.permutation(len(points))[:count]
    return np.ascontiguousarray(points[chosen], dtype=np.float32)


# A structured-light sensor's noise (Nguyen, Izadi and Lovell 2012, "Modeling Kinect sensor
# noise for improved 3D reconstruction and tracking": Kinect v1, surfaces 10-60 degrees from
# facing the camera): along the optical axis a standard deviation of 1.2 mm + 1.9 mm per m^2
# of (depth - 0.4 m)^2 (10 mm at 2.5 m), across it 0.8 pixels. Time-of-flight sensors (Kinect
# v2, Azure Kinect) are quieter: this is the noisy end.
AXIAL_NOISE = (0.0012, 0.0019, 0.4)       # metres, metres per m^2, metres
LATERAL_NOISE_PIXELS = 0.8


def sensor_noise(points, camera, rng):
    """``points`` (N, 3) world metres that ``camera`` sees, as a noisy depth sensor gives them:
    each moved along its own ray by the axial noise of its depth (so it stays on its pixel)
    and across the image by the lateral noise, independently -> (N, 3) float32."""
    local = (np.asarray(points, np.float64) - camera.position) @ camera.rotation.T  # x, y, z
    depth = local[:, 2]
    base, growth, offset = AXIAL_NOISE
    noisy_depth = depth + rng.normal(size=len(depth)) * (base + growth * (depth - offset) ** 2)
    local *= (noisy_depth / depth)[:, None]
    local[:, :2] += (rng.normal(size=(len(depth), 2))
                     * (LATERAL_NOISE_PIXELS * noisy_depth / camera.focal)[:, None])
    return np.ascontiguousarray(local @ camera.rotation + camera.position, dtype=np.float32)


def body_axes(root_rotation):
    """The body's forward (+Z) and left (+X) axes at a frame, turned by its root rotation
    (w, x, y, z) and laid flat (horizontal unit vectors)."""
    matrix = quaternion_to_matrix(np.asarray(root_rotation, np.float32)).astype(np.float64)
    out = []
    for axis in (FORWARD_AXIS, LEFT_AXIS):
        direction = matrix[:, axis].copy()
        direction[UP_AXIS] = 0.0
        length = np.linalg.norm(direction)
        if length < 1e-6:
            raise ValueError("the body's root lies flat: its horizontal axes are undefined")
        out.append(direction / length)
    return tuple(out)


def view_cameras(root_rotation, root, chest_height, distance=VIEW_DISTANCE, **camera):
    """The single-view benchmark's cameras, fixed in the world: ``distance`` metres from the
    body's root at frame 0 in front of it (its +Z then), at its side (its left, +X) and behind
    it (-Z), at chest height, each looking horizontally at the root.

    Args:
        root_rotation: (4,) the root's rotation at frame 0 (w, x, y, z).
        root: (3,) the root's world position at frame 0, metres.
        chest_height: the camera height, metres (the chest joint's at frame 0).
        distance: metres, horizontally.
        camera: ``look_at`` options (image size, field of view, depth range).
    Returns:
        {"front": Camera, "side": Camera, "back": Camera}.
    """
    forward, left = body_axes(root_rotation)
    centre = np.asarray(root, np.float64).copy()
    centre[UP_AXIS] = chest_height
    return {name: look_at(centre + distance * direction, centre, **camera)
            for name, direction in zip(VIEWS, (forward, left, -forward))}


def following(camera, shift):
    """``camera`` moved by ``shift`` (3,) metres, its orientation kept (a camera that travels
    with the body)."""
    return camera._replace(position=camera.position + np.asarray(shift, np.float64))

