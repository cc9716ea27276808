"""Server settings: embedded defaults, overridable by ``FACECAST_*`` environment variables or CLI flags.

Every ``FACECAST_*`` setting the server reads is a field here (those the library reads outside a
server too, ``cache``, ``shared_data`` and ``max_audio_seconds``, come from ``settings.LocalSettings``);
README.md's configuration table lists them. ``load_config`` refuses a malformed one in one line.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from ..live.settings import LiveSettings
from ..settings import LocalSettings, load


def _default_data_dir() -> Path:
    return Path.home() / ".local" / "share" / "facecast"


class ServerConfig(LocalSettings):
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
    # Cluster (issue 15): a Redis URL makes this process a node; unset = one process, in memory.
    redis_url: str | None = None  # FACECAST_REDIS_URL, e.g. redis://127.0.0.1:6379/0
    results_dir: Path | None = None  # job folders all nodes share; unset: <data_dir>/jobs
    # a node's job that goes this long unrenewed (its node died) is taken by another node
    job_claim_seconds: float = Field(default=30.0, ge=1.0, allow_inf_nan=False)
    # Uploads (jobs and /play): a file may not exceed its kind's limit nor max_upload_bytes.
    max_upload_bytes: int = Field(default=64 * 1024 * 1024, gt=0)
    max_fap_bytes: int = Field(default=8 * 1024 * 1024, gt=0)  # FAP text: about 18 min at 25 fps
    max_markers_bytes: int = Field(default=32 * 1024 * 1024, gt=0)  # C3D/TRC/CSV mocap takes
    max_audio_bytes: int = Field(default=64 * 1024 * 1024, gt=0)  # WAV/FLAC/OGG speech
    max_concurrent_decodes: int = Field(default=2, ge=1)  # /play decodes at once; more get 503
    job_timeout_seconds: float = Field(
        default=3600.0, ge=0
    )  # a job running longer fails; 0 = no limit
    job_memory_mb: int = Field(
        default=0, ge=0
    )  # address space of a job worker process (MiB); 0 = no limit
    max_sessions: int = 64
    max_viewers_per_session: int = 256
    # close a live session with no viewer and no producer for this long; 0 = never
    session_idle_seconds: float = Field(default=600.0, ge=0)
    max_producer_fps: float = 250.0  # frames per second a producer may send (markers run at 240 Hz)
    allow_remote: bool = False  # must be set to bind to a non-loopback address
    faces: str | None = None  # more faces by name: "ict=/path/mesh.obj,other=/path/x.obj"
    job_retention_hours: float = Field(
        default=7 * 24.0, ge=0
    )  # finished jobs kept this long; 0 = forever
    # Live path tuning (FACECAST_LIVE_*; ``live.settings.LiveSettings`` says what each does).
    live_threads: int | None = Field(
        default=None, ge=1
    )  # driver/animator threads; unset: CPUs, <= 8
    live_batches: int = Field(default=1, ge=1)  # batches of one animator worked on at once
    live_coalesce_ms: float = Field(
        default=0.0, ge=0, allow_inf_nan=False
    )  # batch wait for more frames
    live_coalesce_frames: int = Field(default=8, ge=1, le=32)  # ... until this many wait
    live_compact_threads: int | None = Field(default=None, ge=1)  # compact encoders; unset: CPUs
    live_device_quantize: bool = True  # int16 quantisation on a host-memory OpenCL device
    live_direct: bool = True  # vertex frames straight to viewers' transports (0: through ASGI)

    def live_settings(self) -> LiveSettings:
        """The ``live_*`` fields, for ``SessionRegistry``."""
        return LiveSettings(
            threads=self.live_threads,
            batches=self.live_batches,
            coalesce_ms=self.live_coalesce_ms,
            coalesce_frames=self.live_coalesce_frames,
            compact_threads=self.live_compact_threads,
            device_quantize=self.live_device_quantize,
            direct=self.live_direct,
        )

    def upload_limit(self, kind: str) -> tuple[int, str]:
        """``(bytes, variable)``: the largest upload of an input kind (fap | audio | markers) and the
        ``FACECAST_*`` variable that raises it."""
        own = {
            "fap": ("max_fap_bytes", self.max_fap_bytes),
            "audio": ("max_audio_bytes", self.max_audio_bytes),
            "markers": ("max_markers_bytes", self.max_markers_bytes),
        }.get(kind)
        if own is None or own[1] >= self.max_upload_bytes:
            return self.max_upload_bytes, "FACECAST_MAX_UPLOAD_BYTES"
        return own[1], f"FACECAST_{own[0].upper()}"


def load_config(**overrides: Any) -> ServerConfig:
    """``ServerConfig`` from the ``FACECAST_*`` variables and ``overrides`` (flags); a malformed
    variable raises one ``InputError`` line naming it (``settings.load``)."""
    return load(ServerConfig, **overrides)
