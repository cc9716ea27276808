"""Where facecast keeps caches and where tests and benchmarks find ../shared/data."""
from __future__ import annotations

import os
from pathlib import Path


def cache_dir(*parts: str) -> Path:
    """The user's cache folder for facecast (``$FACECAST_CACHE`` or ``~/.cache/facecast``), created."""
    root = Path(os.environ.get("FACECAST_CACHE") or Path.home() / ".cache" / "facecast")
    path = root.joinpath(*parts)
    path.mkdir(parents=True, exist_ok=True)
    return path


def shared_data() -> Path | None:
    """``../shared/data`` beside the project checkout (or ``$FACECAST_SHARED_DATA``), if present."""
    env = os.environ.get("FACECAST_SHARED_DATA")
    candidates = [Path(env)] if env else []
    candidates.append(Path(__file__).resolve().parents[2] / "shared" / "data")
    candidates.append(Path.cwd().parent / "shared" / "data")
    for c in candidates:
        if c.is_dir():
            return c
    return None
