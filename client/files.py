"""Atomic file output of the client: write to a temporary file beside the target, then rename.

The client's one helper; the server has its own, ``server/output/atomic.py`` (the client may not
import the server, and ``protocol/`` does no I/O, so there is no place both may import).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path (``.<name>.*.part``) in ``path``'s folder; on success rename it to
    ``path``, else delete it: readers never see a half-written file, a failure leaves nothing."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        os.chmod(tmp_path, 0o644)  # mkstemp makes 0600; downloads are ordinary files
        yield tmp_path
        os.replace(tmp_path, path)
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise
