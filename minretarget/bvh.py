"""Reading and writing BVH (Biovision Hierarchy) motion capture files. NumPy only.

File model
    HIERARCHY: one ROOT and nested JOINTs; each has an OFFSET (its translation from its parent
    in the zero pose, in the parent's frame) and CHANNELS (any mix of ``X/Y/Zposition`` and
    ``X/Y/Zrotation``, in any order); a leaf may carry an ``End Site`` with an OFFSET only.
    MOTION: ``Frames: T``, ``Frame Time: seconds``, then one line of C channel values per frame,
    joints in file order, each joint's channels in its listed order.

Conventions (the usual reading of BVH)
    - The zero pose (every channel zero) has every joint frame aligned with the world axes, so
      a joint's rotation is local to its parent in world-aligned frames, as in
      ``minretarget.conventions``; in the zero pose all world rotations are the identity.
    - Rotation channels are Euler angles in degrees, composed intrinsically in the listed order:
      ``Zrotation Xrotation Yrotation`` means ``R = Rz(z) @ Rx(x) @ Ry(y)`` (column vectors).
    - A position channel sets that coordinate of the joint's translation from its parent,
      replacing the OFFSET coordinate (the root's OFFSET is normally zero, where this and the
      "offset + position" reading agree).
    - Forward kinematics: ``G[j] = G[parent] @ R[j]``, ``p[j] = p[parent] + G[parent] @ t[j]``.
    - Lengths stay in the file's units unless ``scale`` converts them (the CMU files are about
      centimetres: ``scale=0.01`` gives metres). Axes stay the file's unless ``axes`` maps them.
    - Arrays are float64: channel values keep the file's precision for a writer to round-trip,
      and the long FK chains lose nothing; cast to float32 at the runtime boundary.
    - Shape letters: T frames, J joints of the file, C channels of a frame.

Errors: any malformed input raises ``BVHError`` (a ``ValueError``) whose message starts with
``<file>:<line>:``.

Writing is the reader's inverse: ``parse_bvh(format_bvh(motion))`` gives ``motion`` back, every
number bit for bit.
"""
import gzip
import math
import os
import zlib
from dataclasses import dataclass, replace

import numpy as np

from .atomic import atomic_write
from .kinematics import matrix_to_quaternion, quaternion_slerp, quaternion_to_matrix

CHANNEL_NAMES = ("Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation")
_CHANNEL_BY_LOWER = {name.lower(): name for name in CHANNEL_NAMES}
_AXIS_INDEX = {"X": 0, "Y": 1, "Z": 2}
MAX_UPSAMPLING = 10          # resample: at most this many output frames per source frame


class BVHError(ValueError):
    """Malformed BVH input; the message starts with ``<file>:<line>:``."""


@dataclass(frozen=True, eq=False)
class BVHMotion:
    """Everything a BVH file holds, enough for a writer to reproduce it (up to number format).

    Attributes:
        names: (J,) joint names in file order; parents come before their children.
        parents: (J,) int64 parent index of each joint, -1 for the root.
        offsets: (J, 3) float64 OFFSET of each joint from its parent, file units.
        channels: (J,) tuple per joint of its channel names in file order, e.g.
            ``("Zrotation", "Xrotation", "Yrotation")``; names as in ``CHANNEL_NAMES``.
        end_sites: {joint index: (3,) float64 OFFSET of that joint's End Site}.
        values: (T, C) float64 channel values per frame, in file order.
        frame_time: seconds per frame, as the header says.
    """
    names: tuple
    parents: np.ndarray
    offsets: np.ndarray
    channels: tuple
    end_sites: dict
    values: np.ndarray
    frame_time: float

    @property
    def num_frames(self):
        return self.values.shape[0]

    @property
    def channel_starts(self):
        """(J,) int64 column of ``values`` holding each joint's first channel."""
        counts = [len(c) for c in self.channels]
        return np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)

    @property
    def fps(self):
        """Frame rate from the header's Frame Time, snapped to an integer within 0.01 %
        (headers print ~6 digits: 0.00833333 s is 120 fps, not 120.00005)."""
        fps = 1.0 / self.frame_time
        return float(round(fps)) if abs(fps - round(fps)) < 1e-4 * fps else fps


# ----------------------------------------------------------------------------- reading

def read_bvh(path, scale=1.0):
    """Read a ``.bvh`` or gzip-compressed ``.bvh.gz`` file (any of LF, CRLF line ends).

    Args:
        path: file path; gzip is recognised by its magic bytes, whatever the name.
        scale: factor applied to every length (OFFSETs and position channels).
    Returns:
        BVHMotion.
    Raises:
        BVHError naming the file and line; OSError if the file cannot be opened.
    """
    source = os.fspath(path)
    with open(source, "rb") as f:
        data = f.read()
    if data[:2] == b"\x1f\x8b":
        try:
            data = gzip.decompress(data)
        except (OSError, EOFError, zlib.error) as error:    # truncated or corrupt gzip
            raise BVHError(f"{source}:0: cannot decompress: {error}") from None
    # latin-1 decodes any byte, so stray bytes surface as parse errors with a line number.
    return parse_bvh(data.decode("latin-1"), source=source, scale=scale)


def parse_bvh(text, source="<string>", scale=1.0):
    """Parse the text of a BVH file. See ``read_bvh``; ``source`` names it in error messages."""
    # Only \n, \r\n and \r end lines (str.splitlines would also split on \x85 and others).
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    if lines[-1] == "":
        lines.pop()                                # the last line's own line end
    motion_line = next((i for i, line in enumerate(lines) if line.strip() == "MOTION"), None)
    if motion_line is None:
        raise BVHError(f"{source}:{len(lines)}: no MOTION section (truncated file?)")
    tokens = _Tokens(lines[:motion_line], source)
    names, parents, offsets, channels, end_sites = _parse_hierarchy(tokens)
    num_channels = sum(len(c) for c in channels)
    frame_count, frame_time, first_frame_line = _parse_motion_header(
        lines, motion_line + 1, source)
    values = _parse_frames(lines, first_frame_line, frame_count, num_channels, source)
    motion = BVHMotion(names=tuple(names), parents=np.array(parents, dtype=np.int64),
                       offsets=np.array(offsets, dtype=np.float64).reshape(-1, 3),
                       channels=tuple(channels), end_sites=end_sites, values=values,
                       frame_time=frame_time)
    return motion if scale == 1.0 else scale_motion(motion, scale)


class _Tokens:
    """Whitespace-separated tokens of the HIERARCHY lines, each with its 1-based line number."""

    def __init__(self, lines, source):
        self.items = [(word, number) for number, line in enumerate(lines, start=1)
                      for word in line.split()]
        self.position = 0
        self.source = source
        self.last_line = len(lines)

    def error(self, message, line=None):
        return BVHError(f"{self.source}:{self.last_line if line is None else line}: {message}")

    def next(self, what):
        """The next (token, line); ``what`` says what was expected if the input ends."""
        if self.position == len(self.items):
            raise self.error(f"unexpected end of HIERARCHY, expected {what}")
        self.position += 1
        return self.items[self.position - 1]

    def expect(self, word):
        token, line = self.next(repr(word))
        if token != word:
            raise self.error(f"expected {word!r}, got {token!r}", line)
        return line

    def number(self, what):
        token, line = self.next(what)
        try:
            value = float(token)
        except ValueError:
            raise self.error(f"bad number {token!r} for {what}", line) from None
        if not math.isfinite(value):
            raise self.error(f"non-finite number {token!r} for {what}", line)
        return value


def _parse_hierarchy(tokens):
    """Returns names, parents, offsets (flat list), channels and end sites, in file order."""
    tokens.expect("HIERARCHY")
    tokens.expect("ROOT")
    names, parents, offsets, channels, end_sites = [], [], [], [], {}
    # Explicit stack instead of recursion: entries are joint indices whose '}' is pending.
    name, _ = tokens.next("the root's name")
    stack = [_parse_joint_head(tokens, name, -1, names, parents, offsets, channels)]
    while stack:
        token, line = tokens.next("JOINT, End Site or '}'")
        if token == "JOINT":
            name, _ = tokens.next("a joint name")
            stack.append(_parse_joint_head(tokens, name, stack[-1], names, parents, offsets,
                                           channels))
        elif token == "End":
            tokens.expect("Site")
            if stack[-1] in end_sites:
                raise tokens.error(f"joint {names[stack[-1]]!r} has two End Sites", line)
            tokens.expect("{")
            tokens.expect("OFFSET")
            end_sites[stack[-1]] = np.array([tokens.number("End Site OFFSET")
                                             for _ in range(3)])
            tokens.expect("}")
        elif token == "}":
            stack.pop()
        else:
            raise tokens.error(f"expected JOINT, End Site or '}}', got {token!r}", line)
    if tokens.position != len(tokens.items):
        token, line = tokens.items[tokens.position]
        raise tokens.error(f"unexpected {token!r} after the ROOT's closing '}}' "
                           "(only one ROOT is supported)", line)
    return names, parents, offsets, channels, end_sites


def _parse_joint_head(tokens, name, parent, names, parents, offsets, channels):
    """Parses ``{ OFFSET x y z CHANNELS n ...`` of one joint, appends it, returns its index."""
    tokens.expect("{")
    tokens.expect("OFFSET")
    offset = [tokens.number(f"OFFSET of {name!r}") for _ in range(3)]
    tokens.expect("CHANNELS")
    count_token, line = tokens.next("the channel count")
    if not _is_count(count_token):
        raise tokens.error(f"bad channel count {count_token!r} for {name!r}", line)
    joint_channels = []
    for _ in range(int(count_token)):
        token, line = tokens.next(f"a channel name of {name!r}")
        channel = _CHANNEL_BY_LOWER.get(token.lower())
        if channel is None:
            raise tokens.error(f"unknown channel {token!r} of {name!r}", line)
        if channel in joint_channels:
            raise tokens.error(f"channel {channel!r} repeated in {name!r}", line)
        joint_channels.append(channel)
    names.append(name)
    parents.append(parent)
    offsets.extend(offset)
    channels.append(tuple(joint_channels))
    return len(names) - 1


def _is_count(word):
    return word.isascii() and word.isdigit()      # ASCII only: int() refuses some digits


def _parse_motion_header(lines, start, source):
    """Reads ``Frames: T`` and ``Frame Time: dt``; returns T, dt and the first frame's index."""
    def header_line(index, label):
        # Skip blank lines; return (index, words) of the next line or fail at the file's end.
        while index < len(lines) and not lines[index].strip():
            index += 1
        if index == len(lines):
            raise BVHError(f"{source}:{len(lines)}: file ends before {label!r}")
        return index, lines[index].split()

    index, words = header_line(start, "Frames:")
    if len(words) != 2 or words[0] != "Frames:" or not _is_count(words[1]):
        raise BVHError(f"{source}:{index + 1}: expected 'Frames: <count>', "
                       f"got {lines[index].strip()!r}")
    frame_count = int(words[1])
    index, words = header_line(index + 1, "Frame Time:")
    if len(words) != 3 or words[:2] != ["Frame", "Time:"]:
        raise BVHError(f"{source}:{index + 1}: expected 'Frame Time: <seconds>', "
                       f"got {lines[index].strip()!r}")
    try:
        frame_time = float(words[2])
    except ValueError:
        frame_time = math.nan
    if not frame_time > 0 or not math.isfinite(frame_time):
        raise BVHError(f"{source}:{index + 1}: bad frame time {words[2]!r}")
    return frame_count, frame_time, index + 1


def _parse_frames(lines, start, frame_count, num_channels, source):
    """(T, C) float64 values of the frame lines ``lines[start:]``; trailing blank lines are ok."""
    end = len(lines)
    while end > start and not lines[end - 1].strip():
        end -= 1
    if end - start < frame_count:
        raise BVHError(f"{source}:{len(lines)}: file ends after {end - start} of "
                       f"{frame_count} frames (truncated file?)")
    if end - start > frame_count:
        raise BVHError(f"{source}:{start + frame_count + 1}: more frame lines than "
                       f"'Frames: {frame_count}'")
    rows = [line.split() for line in lines[start:end]]
    for number, row in enumerate(rows, start=start + 1):
        if len(row) != num_channels:
            raise BVHError(f"{source}:{number}: expected {num_channels} values, got {len(row)}")
    try:                                           # fast path: NumPy parses every value at once
        values = np.array(rows, dtype=np.float64).reshape(frame_count, num_channels)
        if np.isfinite(values).all():
            return values
    except ValueError:
        pass
    # Slow path, value by value, to name the offending line.
    values = np.empty((frame_count, num_channels))
    for i, row in enumerate(rows):
        for k, word in enumerate(row):
            try:
                values[i, k] = float(word)
            except ValueError:
                values[i, k] = math.nan
            if not math.isfinite(values[i, k]):
                raise BVHError(f"{source}:{start + i + 1}: bad number {word!r}")
    return values


def scale_motion(motion, factor):
    """A copy of ``motion`` with every length (OFFSETs, End Sites, position channels) times
    ``factor``, e.g. 0.01 for centimetres -> metres."""
    position_columns = [i for i, name in enumerate(c for cs in motion.channels for c in cs)
                        if name.endswith("position")]
    values = motion.values.copy()
    values[:, position_columns] *= factor
    return replace(motion, offsets=motion.offsets * factor, values=values,
                   end_sites={j: o * factor for j, o in motion.end_sites.items()})


# ----------------------------------------------------------------------------- writing

def write_bvh(path, motion):
    """Write ``motion`` to ``path`` as a BVH file, atomically (see ``format_bvh``)."""
    text = format_bvh(motion)
    with atomic_write(path) as file:
        file.write(text.encode("ascii"))


def format_bvh(motion):
    """The text of a BVH file holding ``motion``; ``parse_bvh`` gives it back exactly.

    Numbers are written in Python's shortest round-trip form (``repr``), so every OFFSET and
    channel value reads back bit for bit. Line ends are LF; indentation is one tab per level.

    Args:
        motion: BVHMotion whose joints are in depth-first order (each joint's subtree right
            after it), the order a hierarchy lists them and the reader returns them in.
    Raises:
        ValueError naming the joint or the array at fault: a name with whitespace, joints not
        in depth-first order, unknown or repeated channels, ``values`` not (T, C) for the
        channels' count C, non-finite numbers.
    """
    _check_writable(motion)
    lines = ["HIERARCHY"]
    open_joints = []                                   # the current joint's ancestors, and it

    def close(joint):
        depth = len(open_joints)                       # joint is already popped: its depth
        if joint in motion.end_sites:
            lines.extend(["\t" * (depth + 1) + "End Site", "\t" * (depth + 1) + "{",
                          "\t" * (depth + 2) + "OFFSET " + _numbers(motion.end_sites[joint]),
                          "\t" * (depth + 1) + "}"])
        lines.append("\t" * depth + "}")

    for joint, name in enumerate(motion.names):
        while open_joints and open_joints[-1] != motion.parents[joint]:
            close(open_joints.pop())
        indent = "\t" * len(open_joints)
        channels = motion.channels[joint]
        lines.extend([indent + ("ROOT " if joint == 0 else "JOINT ") + name, indent + "{",
                      indent + "\tOFFSET " + _numbers(motion.offsets[joint]),
                      indent + f"\tCHANNELS {len(channels)}" + "".join(" " + c for c in channels)])
        open_joints.append(joint)
    while open_joints:
        close(open_joints.pop())
    lines.extend(["MOTION", f"Frames: {motion.num_frames}",
                  f"Frame Time: {float(motion.frame_time)!r}"])
    lines.extend(_numbers(row) for row in motion.values)
    return "\n".join(lines) + "\n"


def _numbers(values):
    return " ".join(repr(float(v)) for v in values)


def _check_writable(motion):
    """Raise ValueError if ``format_bvh`` cannot write ``motion`` so that it reads back."""
    count = len(motion.names)
    if count == 0 or len(motion.parents) != count or len(motion.channels) != count or \
            np.shape(motion.offsets) != (count, 3):
        raise ValueError(f"BVH motion: names, parents, channels and offsets must describe the "
                         f"same joints; got {count} names, {len(motion.parents)} parents, "
                         f"{len(motion.channels)} channel lists, "
                         f"offsets {np.shape(motion.offsets)}")
    ancestors = []
    for joint, (name, parent) in enumerate(zip(motion.names, motion.parents)):
        if not name or any(c.isspace() for c in name) or not name.isascii():
            raise ValueError(f"BVH motion: joint {joint} name {name!r} must be non-empty ASCII "
                             "without whitespace")
        while ancestors and ancestors[-1] != parent:
            ancestors.pop()
        if (joint == 0) != (parent == -1) or (joint > 0 and not ancestors):
            raise ValueError(f"BVH motion: joint {name!r} (parent {parent}) breaks depth-first "
                             "order with one root first")
        ancestors.append(joint)
        channels = motion.channels[joint]
        if any(c not in CHANNEL_NAMES for c in channels) or len(set(channels)) != len(channels):
            raise ValueError(f"BVH motion: joint {name!r} has bad channels {channels}; each of "
                             f"{', '.join(CHANNEL_NAMES)} at most once")
    if any(j not in range(count) or np.shape(o) != (3,) for j, o in motion.end_sites.items()):
        raise ValueError("BVH motion: end_sites must map joint indices to (3,) offsets")
    width = sum(len(c) for c in motion.channels)
    if np.ndim(motion.values) != 2 or np.shape(motion.values)[1] != width:
        raise ValueError(f"BVH motion: values must have shape (T, {width}), got "
                         f"{np.shape(motion.values)}")
    numbers = [np.asarray(motion.offsets), np.asarray(motion.values),
               np.asarray([motion.frame_time]), *map(np.asarray, motion.end_sites.values())]
    if not all(np.isfinite(a).all() for a in numbers) or not motion.frame_time > 0:
        raise ValueError("BVH motion: offsets, values and end sites must be finite and the "
                         f"frame time positive (frame time {motion.frame_time!r})")


# ----------------------------------------------------------------------------- rotations

def axis_rotation(axis, degrees):
    """(...,) angles in degrees about axis 'X', 'Y' or 'Z' -> (..., 3, 3) float64 matrices."""
    radians = np.radians(np.asarray(degrees, dtype=np.float64))
    c, s = np.cos(radians), np.sin(radians)
    one, zero = np.ones_like(c), np.zeros_like(c)
    rows = {"X": ((one, zero, zero), (zero, c, -s), (zero, s, c)),
            "Y": ((c, zero, s), (zero, one, zero), (-s, zero, c)),
            "Z": ((c, -s, zero), (s, c, zero), (zero, zero, one))}[axis]
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


def euler_to_matrix(degrees, order):
    """Intrinsic Euler angles -> rotation matrices, BVH style.

    Args:
        degrees: (..., K) float angles in degrees, one per letter of ``order``.
        order: K axis letters, e.g. "ZXY"; the result is R_Z @ R_X @ R_Y for "ZXY".
    Returns:
        (..., 3, 3) float64 rotation matrices (the identity for K = 0).
    """
    degrees = np.asarray(degrees, dtype=np.float64)
    if degrees.shape[-1:] != (len(order),):
        raise ValueError(f"degrees must have shape (..., {len(order)}) for order {order!r}, "
                         f"got {degrees.shape}")
    result = np.broadcast_to(np.eye(3), degrees.shape[:-1] + (3, 3))
    for k, axis in enumerate(order):
        result = result @ axis_rotation(axis, degrees[..., k])
    return np.array(result)                        # own the memory even when K = 0


def matrix_to_euler(matrices, order):
    """Rotation matrices -> intrinsic Euler angles, the inverse of ``euler_to_matrix``.

    Args:
        matrices: (..., 3, 3) rotation matrices.
        order: three distinct axis letters, e.g. "ZXY".
    Returns:
        (..., 3) float64 degrees; the middle angle lies in [-90, 90], the others in
        [-180, 180]. At gimbal lock (middle angle +-90) the last angle is set to 0.
    """
    m = np.asarray(matrices, dtype=np.float64)
    if len(order) != 3 or len(set(order)) != 3:
        raise ValueError(f"order must be three distinct axes, got {order!r}")
    i, j, k = (_AXIS_INDEX[a] for a in order)
    # s = +1 for cyclic orders (XYZ, YZX, ZXY), -1 for the others; then for R = Ri Rj Rk:
    # R[i,k] = s sin(b), R[j,k] = -s sin(a) cos(b), R[k,k] = cos(a) cos(b),
    # R[i,j] = -s cos(b) sin(c), R[i,i] = cos(b) cos(c).
    s = 1.0 if (j - i) % 3 == 1 else -1.0
    middle = np.arcsin(np.clip(s * m[..., i, k], -1.0, 1.0))
    locked = np.abs(m[..., i, k]) > 1 - 1e-12
    # At gimbal lock only a +- c is determined: put it all in a, with c = 0.
    first = np.where(locked, np.arctan2(s * m[..., k, j], m[..., j, j]),
                     np.arctan2(-s * m[..., j, k], m[..., k, k]))
    last = np.where(locked, 0.0, np.arctan2(-s * m[..., i, j], m[..., i, i]))
    return np.degrees(np.stack([first, middle, last], axis=-1))


def local_rotations(motion):
    """(T, J, 3, 3) float64 rotation of each joint relative to its parent, per frame.

    Each joint's rotation channels are composed in its own listed order; a joint without
    rotation channels gets the identity.
    """
    starts = motion.channel_starts
    out = np.empty((motion.num_frames, len(motion.names), 3, 3))
    for joint, channels in enumerate(motion.channels):
        columns = [starts[joint] + c for c, name in enumerate(channels)
                   if name.endswith("rotation")]
        order = "".join(channels[c - starts[joint]][0] for c in columns)
        out[:, joint] = euler_to_matrix(motion.values[:, columns], order)    # (T, 3, 3)
    return out


def local_translations(motion):
    """(T, J, 3) float64 translation of each joint from its parent (OFFSET, with any position
    channel replacing its coordinate), per frame."""
    starts = motion.channel_starts
    out = np.repeat(motion.offsets[None], motion.num_frames, axis=0)          # (T, J, 3)
    for joint, channels in enumerate(motion.channels):
        for c, name in enumerate(channels):
            if name.endswith("position"):
                out[:, joint, _AXIS_INDEX[name[0]]] = motion.values[:, starts[joint] + c]
    return out


def world_transforms(motion, axes=None):
    """Forward kinematics of every frame at once (a loop over joints, not frames).

    Args:
        motion: BVHMotion.
        axes: optional (3, 3) rotation matrix A taking file axes to output axes; positions
            become ``A p`` and rotations ``A G A^T`` (so the zero pose keeps identity rotations).
    Returns:
        positions: (T, J, 3) float64 world joint positions, motion's units.
        rotations: (T, J, 3, 3) float64 world joint rotations (identity in the zero pose).
    """
    local_r = local_rotations(motion)
    local_t = local_translations(motion)
    positions = np.empty_like(local_t)
    rotations = np.empty_like(local_r)
    for joint, parent in enumerate(motion.parents):
        if parent < 0:
            positions[:, joint] = local_t[:, joint]
            rotations[:, joint] = local_r[:, joint]
        else:
            positions[:, joint] = positions[:, parent] + np.einsum(
                "tab,tb->ta", rotations[:, parent], local_t[:, joint])
            rotations[:, joint] = rotations[:, parent] @ local_r[:, joint]
    if axes is not None:
        a = np.asarray(axes, dtype=np.float64)
        if a.shape != (3, 3) or not np.allclose(a @ a.T, np.eye(3), atol=1e-6) or \
                np.linalg.det(a) < 0:
            raise ValueError("axes must be a (3, 3) rotation matrix (orthonormal, det +1)")
        positions = positions @ a.T
        rotations = a @ rotations @ a.T
    return positions, rotations


# ----------------------------------------------------------------------------- resampling

def resample(motion, fps=30, source_fps=None):
    """Resample a motion in time; returns a BVHMotion at ``fps``.

    Output frame k is at time k / fps, from 0 up to the last source frame. Position channels
    are interpolated linearly; each joint's rotation is interpolated by quaternion slerp
    (shortest path) and written back as Euler angles in the joint's channel order. An output
    frame that lands exactly on a source frame (e.g. every one for 120 -> 30 fps) copies its
    values verbatim; interpolated rotations pass through float32 quaternions (about 1e-5
    degree). Joints with fewer than three rotation channels interpolate their angles linearly
    (for a single axis that is slerp, for steps under 180 degrees).

    Args:
        motion: BVHMotion.
        fps: target frame rate.
        source_fps: the true source frame rate, overriding the header's Frame Time (some
            files' headers are wrong); None trusts the header (``motion.fps``).
    """
    source_fps = motion.fps if source_fps is None else float(source_fps)
    if not (fps > 0 and source_fps > 0):
        raise ValueError(f"frame rates must be positive, got fps={fps}, source_fps={source_fps}")
    if fps > MAX_UPSAMPLING * source_fps:
        # A frame time of minutes is a damaged header, and would make the motion huge.
        raise ValueError(f"a source at {source_fps:g} fps (frame time {1 / source_fps:g} s) "
                         f"is too slow to resample to {fps:g} fps: at most "
                         f"{MAX_UPSAMPLING}x more frames")
    count = motion.num_frames
    out_count = 0 if count == 0 else int(math.floor((count - 1) * fps / source_fps + 1e-9)) + 1
    u = np.arange(out_count) * (source_fps / fps)          # (T',) fractional source index
    lower = np.minimum(np.floor(u + 1e-9).astype(np.int64), max(count - 1, 0))
    weight = u - lower
    weight[weight < 1e-9] = 0.0                            # exact hits copy, not round-trip
    upper = np.minimum(lower + 1, max(count - 1, 0))
    v0, v1 = motion.values[lower], motion.values[upper]    # (T', C) each
    values = v0 + weight[:, None] * (v1 - v0)              # linear: positions, 1-2 axis joints
    starts = motion.channel_starts
    moving = weight > 0
    for joint, channels in enumerate(motion.channels):
        columns = [starts[joint] + c for c, name in enumerate(channels)
                   if name.endswith("rotation")]
        if len(columns) != 3 or not moving.any():
            continue
        order = "".join(channels[c - starts[joint]][0] for c in columns)
        q0 = matrix_to_quaternion(euler_to_matrix(v0[moving][:, columns], order))
        q1 = matrix_to_quaternion(euler_to_matrix(v1[moving][:, columns], order))
        q = quaternion_slerp(q0, q1, weight[moving])
        values[np.ix_(moving, columns)] = matrix_to_euler(quaternion_to_matrix(q), order)
    return replace(motion, values=values, frame_time=1.0 / fps)
