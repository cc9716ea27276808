"""Tuning of the live path, read once at start-up (``ServerConfig``'s ``live_*`` fields, i.e. the
``FACECAST_LIVE_*`` variables) and passed down: nothing under ``server.live`` reads the environment.
"""

from __future__ import annotations

import os
from dataclasses import dataclass


def _cpus() -> int:
    return max(1, os.cpu_count() or 1)


@dataclass(frozen=True, slots=True)
class LiveSettings:
    """Args (each ``None`` picks the default shown):
    threads: threads running producer drivers and building animators (``FACECAST_LIVE_THREADS``;
        the CPU count, at most 8).
    batches: batches of one animator worked on at once (``FACECAST_LIVE_BATCHES``; 1). Measured
        on 2 cores with PoCL (20 sessions): a second concurrent batch splits the frames into
        smaller launches and adds GIL contention; it cost more CPU per frame than it saved.
    coalesce_ms: longest wait of a batch for more frames (``FACECAST_LIVE_COALESCE_MS``; 0, no
        wait). On the shared 2-core machine (load 5-9) batches of 20 sessions held 6-13 frames
        by themselves and a 3 ms wait changed nothing measurable.
    coalesce_frames: ... until this many frames wait (``FACECAST_LIVE_COALESCE_FRAMES``; 8, at
        most a batch's 32). A cluster node holding half the sessions of a machine fills a batch
        half as fast: measured with two nodes on 2 cores (50 sessions), 12 ms / 32 frames cost
        353-364 µs per session-frame against 416-468 at 4 ms / 8 (``docs/SCALING.md``); one
        process gained nothing from it (its batches grow by themselves) and its p95 grew.
    compact_threads: threads encoding ``compact`` frames at once on the host
        (``FACECAST_LIVE_COMPACT_THREADS``; the CPU count). Batches encoded on the device are
        deflated in the batcher's own thread.
    device_quantize: quantise int16 frames on the OpenCL device when it shares host memory
        (``FACECAST_LIVE_DEVICE_QUANTIZE``; true).
    direct: write vertex frames straight to viewers' transports and take producers' binary
        frames in their connections' callbacks (``FACECAST_LIVE_DIRECT``; true; false sends and
        receives them through ASGI, the baseline of ``bench serve --compare-asgi``).
    """

    threads: int | None = None
    batches: int = 1
    coalesce_ms: float = 0.0
    coalesce_frames: int = 8
    compact_threads: int | None = None
    device_quantize: bool = True
    direct: bool = True

    @property
    def deform_threads(self) -> int:
        return max(1, self.threads) if self.threads else min(8, _cpus())

    @property
    def batch_threads(self) -> int:
        return max(1, self.batches)

    @property
    def coalesce_seconds(self) -> float:
        return max(0.0, self.coalesce_ms) / 1000

    @property
    def compact_pool_threads(self) -> int:
        return max(1, self.compact_threads) if self.compact_threads else _cpus()
