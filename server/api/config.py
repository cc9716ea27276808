"""Server settings: embedded defaults, overridable by ``FACECAST_*`` environment variables or CLI flags."""
from __future__ import annotations

from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict


def _default_data_dir() -> Path:
    return Path.home() / ".local" / "share" / "facecast"


class ServerConfig(BaseSettings):
    """Everything ``facecast serve`` needs; every field has a working default."""

    model_config = SettingsConfigDict(env_prefix="FACECAST_", extra="ignore")

    host: str = "127.0.0.1"
    port: int = 8000
    data_dir: Path = Field(default_factory=_default_data_dir)
    admin_key: str | None = None  # FACECAST_ADMIN_KEY; generated and kept in data_dir if unset
    face: str = "default"  # face for sessions and jobs that do not name one
    backend: str = "auto"  # auto | numpy | opencl
    device: str | None = None  # OpenCL device (index or name substring)
    job_workers: int = 1  # worker processes for batch jobs
    max_upload_bytes: int = 64 * 1024 * 1024
    max_sessions: int = 64
    max_viewers_per_session: int = 256
    # close a live session with no viewer and no producer for this long; 0 = never
    session_idle_seconds: float = Field(default=600.0, ge=0)
    max_producer_fps: float = 250.0  # frames per second a producer may send (markers run at 240 Hz)
    allow_remote: bool = False  # must be set to bind to a non-loopback address
    faces: str | None = None  # more faces by name: "ict=/path/mesh.obj,other=/path/x.obj"
    job_retention_hours: float = Field(default=7 * 24.0, ge=0)  # finished jobs kept this long; 0 = forever
