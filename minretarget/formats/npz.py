"""NumPy ``.npz`` archives written member by member, and arrays read back frame by frame.

``np.savez`` needs every array in memory at once; a retargeted sequence's vertices (T, V, 3)
need not fit. ``NpzWriter`` streams instead: a member's ``.npy`` header is written for a known
shape, then its frames one at a time. The result is an ordinary ``.npz`` that ``np.load`` reads
(``allow_pickle=False``). Members are stored uncompressed, as ``np.savez`` does, unless
``compress``; timestamps are fixed, so the same arrays always give the same bytes.
``NpzFrames`` reads one (T, ...) member back a frame at a time; ``load_npy`` reads an
``.npy``. Damaged files give ValueErrors naming the file.
"""
import contextlib
import math
import os
import tokenize
import zipfile
import zlib

import numpy as np

# What reading a damaged or hostile .npy/.npz raises besides ValueError (found by fuzzing,
# benchmarks/fuzz_parsers.py): NumPy's header parser raises TokenError, SyntaxError or
# TypeError on a mangled header dict; zipfile raises BadZipFile, zlib.error, EOFError,
# NotImplementedError (unknown compression) and RuntimeError (encrypted member).
ARCHIVE_ERRORS = (ValueError, OSError, EOFError, KeyError, TypeError, OverflowError,
                  SyntaxError, tokenize.TokenError, zipfile.BadZipFile, zlib.error,
                  NotImplementedError, RuntimeError)
_TIMESTAMP = (1980, 1, 1, 0, 0, 0)         # the earliest a zip can hold: reproducible bytes


class NpzWriter:
    """Writes an ``.npz`` into an open, seekable binary file; a context manager that closes
    the archive (not the file) on exit."""

    def __init__(self, file, compress=False):
        self._zip = zipfile.ZipFile(file, "w", allowZip64=True)
        self._method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED

    def _open(self, name):
        info = zipfile.ZipInfo(f"{name}.npy", date_time=_TIMESTAMP)
        info.compress_type = self._method
        return self._zip.open(info, "w", force_zip64=True)

    def add(self, name, array):
        """Write a whole array (no object dtypes: the archive must load without pickle)."""
        with self._open(name) as member:
            np.lib.format.write_array(member, np.asarray(array), allow_pickle=False)

    @contextlib.contextmanager
    def frames(self, name, shape, dtype):
        """Write the member ``name`` of ``shape`` (T, ...) one frame at a time.

        Yields ``write(frame)``, to be called exactly T times with arrays of shape ``shape[1:]``.
        Raises ValueError for a frame of another shape or a frame count other than T.
        """
        dtype = np.dtype(dtype)
        header = {"descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": False,
                  "shape": tuple(int(s) for s in shape)}
        written = 0
        with self._open(name) as member:
            np.lib.format.write_array_header_2_0(member, header)

            def write(frame):
                nonlocal written
                frame = np.asarray(frame)
                if frame.shape != header["shape"][1:] or written == header["shape"][0]:
                    raise ValueError(f"{name}: frame {written} of shape {frame.shape} does not "
                                     f"fit an array of shape {header['shape']}")
                member.write(np.ascontiguousarray(frame, dtype=dtype).tobytes())
                written += 1

            yield write
            if written != header["shape"][0]:
                raise ValueError(f"{name}: {written} frames written of {header['shape'][0]}")

    def close(self):
        self._zip.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc_info):
        self.close()


def load_npy(path, mmap_mode=None):
    """``np.load`` of an ``.npy`` file without pickle; any damage is a ValueError naming it.

    The header's shape is checked against the file's size first: NumPy would allocate
    whatever a damaged header claims (found by fuzzing: 21.8 TiB) before reading.
    """
    try:
        with open(path, "rb") as file:
            shape, _, dtype = _read_header(file)
            available = os.fstat(file.fileno()).st_size - file.tell()
        needed = math.prod(shape) * dtype.itemsize
        if needed > available:
            raise ValueError(f"truncated: its header says {dtype} {shape} ({needed} bytes of "
                             f"data), the file holds {available}")
        array = np.load(path, mmap_mode=mmap_mode, allow_pickle=False)
    except ARCHIVE_ERRORS as error:
        raise ValueError(f"{path}: not a readable .npy array: {error}") from None
    if not isinstance(array, np.ndarray):
        raise ValueError(f"{path}: not an .npy file (it holds several arrays)")
    return array


def load_npz(file, name=None, keys=None):
    """Every array of an ``.npz`` (a path or a binary file), or those named in ``keys``,
    without pickle: {key: array}.

    Each member's header is checked against the member's size before NumPy allocates what
    it claims. Any damage is a ValueError naming the file (``name``, default ``file``).
    """
    name = file if name is None else name
    try:
        with zipfile.ZipFile(file) as archive:
            for info in archive.infolist():
                if info.filename.endswith(".npy"):
                    with archive.open(info) as member:
                        shape, _, dtype = _read_header(member)
                        available = info.file_size - member.tell()
                    if math.prod(shape) * dtype.itemsize > available:
                        raise ValueError(f"member {info.filename} is truncated: its header "
                                         f"says {dtype} {shape}, it holds {available} bytes")
        if hasattr(file, "seek"):
            file.seek(0)
        with np.load(file, allow_pickle=False) as data:
            return {key: data[key] for key in (data.files if keys is None else keys)}
    except ARCHIVE_ERRORS as error:
        raise ValueError(f"{name}: not a readable .npz ({error})") from None


def npz_members(path):
    """The names of the arrays in an ``.npz``, from its zip directory alone (nothing is
    decoded); ValueError naming the file if it is not a zip archive."""
    try:
        with zipfile.ZipFile(path) as archive:
            return [name[:-len(".npy")] for name in archive.namelist() if name.endswith(".npy")]
    except ARCHIVE_ERRORS as error:
        raise ValueError(f"{path}: not a readable .npz ({error})") from None


class NpzFrames:
    """One (T, ...) array of an ``.npz`` file, read lazily: ``len``, ``shape``, iteration.

    Only one frame is in memory at a time (a Fortran-ordered member is loaded whole).
    Errors, damaged archives included, are ValueErrors naming the file.
    """

    def __init__(self, path, key):
        self.path, self.key = path, key
        try:
            with zipfile.ZipFile(path) as archive, archive.open(f"{key}.npy") as member:
                self.shape, self.fortran_order, self.dtype = _read_header(member)
        except ARCHIVE_ERRORS as error:
            raise ValueError(f"{path}: cannot read array {key!r}: {error}") from None
        if not self.shape:
            raise ValueError(f"{path}: array {key!r} is a scalar, not a sequence of frames")

    def __len__(self):
        return self.shape[0]

    def __iter__(self):
        return self.frames()

    def frames(self, start=0):
        """Yield frames ``start``, ``start + 1``, ... (the ones before are decoded, not kept)."""
        try:
            yield from self._frames(start)
        except ARCHIVE_ERRORS as error:
            raise ValueError(f"{self.path}: array {self.key!r}: {error}") from None

    def _frames(self, start):
        if self.fortran_order:
            with np.load(self.path, allow_pickle=False) as data:
                yield from data[self.key][start:]
            return
        frame_shape = self.shape[1:]
        size = self.dtype.itemsize * int(np.prod(frame_shape, dtype=np.int64))
        with zipfile.ZipFile(self.path) as archive, archive.open(f"{self.key}.npy") as member:
            _read_header(member)
            for index in range(self.shape[0]):
                data = member.read(size)
                if len(data) != size:
                    raise ValueError(f"ends at frame {index} of {self.shape[0]}")
                if index >= start:
                    yield np.frombuffer(data, dtype=self.dtype).reshape(frame_shape)


def _read_header(member):
    """(shape, fortran_order, dtype) of an ``.npy`` stream, which is left at its data."""
    version = np.lib.format.read_magic(member)
    readers = {(1, 0): np.lib.format.read_array_header_1_0,
               (2, 0): np.lib.format.read_array_header_2_0}
    if version not in readers:
        raise ValueError(f".npy format version {version} is not supported")
    shape, fortran_order, dtype = readers[version](member)
    if dtype.hasobject:
        raise ValueError("object arrays are refused (they would need pickle)")
    return shape, fortran_order, dtype
