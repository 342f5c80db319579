"""Atomic file writes: a reader sees the old file or the complete new one, never a part."""
import contextlib
import os
import secrets
from pathlib import Path


def _create_beside(path):
    """A new, empty file beside ``path`` with a random name -> (descriptor, its path). Made
    with mode 0o666, so the kernel applies the process's umask (tempfile.mkstemp makes 0600,
    and reading the umask means setting it, for every thread of an embedding program)."""
    while True:
        temporary = path.with_name(f".{path.name}.{secrets.token_hex(6)}.tmp")
        try:
            return os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666), temporary
        except FileExistsError:
            continue


@contextlib.contextmanager
def atomic_write(path):
    """Open a temporary binary file beside ``path``; on success rename it over ``path``.

    On any error (or Ctrl-C) the temporary file is removed and ``path`` is left as it was.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = _create_beside(path)
    try:
        with os.fdopen(handle, "wb") as file:
            yield file
            file.flush()
            os.fsync(file.fileno())
        os.replace(temporary, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(temporary)
        raise
