"""Old versions of facecast's own modules, from git history, for benchmarks that compare against
them in the same run (``bench/gltf_encode.py``, ``bench/deform_build.py``, ``bench/web_normals.py``)."""

from __future__ import annotations

import subprocess
import sys
import types
from collections.abc import Mapping
from pathlib import Path


def source_at(root: Path, rev: str, path: str) -> str:
    """The text of ``path`` (relative to the repository ``root``) as it was at ``rev``."""
    return subprocess.run(
        ["git", "show", f"{rev}:{path}"], cwd=root, check=True, capture_output=True, text=True
    ).stdout


def module_at(
    root: Path, rev: str, path: str, name: str, replace: Mapping[str, str] | None = None
) -> types.ModuleType:
    """The module ``path`` (relative to the repository ``root``) as it was at ``rev``, loaded as
    ``name`` (e.g. ``facecast.server.output._gltf_baseline``: in the package of the current code,
    so its relative imports resolve) and registered in ``sys.modules``; ``replace`` maps old
    source text to new before it runs (e.g. to import another baseline module)."""
    src = source_at(root, rev, path)
    for old, new in (replace or {}).items():
        src = src.replace(old, new)
    module = types.ModuleType(name)
    module.__package__ = name.rpartition(".")[0]
    sys.modules[name] = module
    exec(compile(src, f"{rev}:{path}", "exec"), module.__dict__)  # noqa: S102 (our own history)
    return module
