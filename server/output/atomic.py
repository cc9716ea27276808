"""Atomic file output: write to a temporary file beside the target, fsync it, then rename over it.

The one helper of the server (client code has its own, ``client/files.py``: the client may not
import the server, and ``protocol/`` does no I/O). Temporary files are named ``.<name>.*.part``,
so a folder's leftovers of an interrupted write are its dot files (``jobs/manager.py`` removes them).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def atomic_path(path: str | Path, *, mode: int = 0o644) -> Iterator[Path]:
    """Yield a temporary path in ``path``'s folder; on success rename it to ``path``, else delete it.

    Readers never see a half-written ``path``, and a failure part-way leaves nothing behind. The
    file gets permission bits ``mode`` (``0o600`` for a secret: it is never readable by others,
    not even while it is written).
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        os.chmod(tmp_path, mode)  # mkstemp makes 0600; results are ordinary files
        yield tmp_path
        fsync_path(
            tmp_path
        )  # the bytes are on disk before the name says so (a crash, a shared volume)
        os.replace(tmp_path, path)
        fsync_path(path.parent, directory=True)  # and the new name too
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise


def fsync_path(path: Path, *, directory: bool = False) -> None:
    """Flush ``path`` (a file, or a folder's entries) to its device; best effort for folders
    (some file systems cannot open one)."""
    try:
        fd = os.open(path, os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if directory else 0))
    except OSError:
        if directory:
            return
        raise
    try:
        os.fsync(fd)
    except OSError:
        if not directory:
            raise
    finally:
        os.close(fd)


def write_bytes_atomic(path: str | Path, data: bytes, *, mode: int = 0o644) -> None:
    """Write ``data`` to ``path`` atomically (permission bits ``mode``)."""
    with atomic_path(path, mode=mode) as tmp:
        tmp.write_bytes(data)
