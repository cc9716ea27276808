"""Where facecast keeps caches and where tests and benchmarks find ../shared/data."""

from __future__ import annotations

from pathlib import Path

from .settings import settings


def cache_dir(*parts: str) -> Path:
    """The user's cache folder for facecast (``$FACECAST_CACHE`` or ``~/.cache/facecast``), created."""
    path = settings().cache.joinpath(*parts)
    path.mkdir(parents=True, exist_ok=True)
    return path


def shared_data() -> Path | None:
    """``../shared/data`` beside the project checkout (or ``$FACECAST_SHARED_DATA``), if present."""
    env = settings().shared_data
    candidates = [env] if env else []
    candidates.append(Path(__file__).resolve().parents[2] / "shared" / "data")
    candidates.append(Path.cwd().parent / "shared" / "data")
    for c in candidates:
        if c.is_dir():
            return c
    return None
