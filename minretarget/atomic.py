"""Atomic file writes: a reader sees the old file or the complete new one, never a part."""
import contextlib
import os
import tempfile
from pathlib import Path


def process_umask():
    """The process's file-creation mask, read without changing it (Linux: /proc; elsewhere
    the usual 0o022): setting and restoring it, the only portable way, would briefly give
    every other thread of an embedding program a mask of 0."""
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    return 0o022


@contextlib.contextmanager
def atomic_write(path):
    """Open a temporary binary file beside ``path``; on success rename it over ``path``.

    On any error (or Ctrl-C) the temporary file is removed and ``path`` is left as it was.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(handle, "wb") as file:
            yield file
            file.flush()
            os.fsync(file.fileno())
        os.chmod(temporary, 0o666 & ~process_umask())   # mkstemp makes 0600: the usual mode
        os.replace(temporary, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(temporary)
        raise
