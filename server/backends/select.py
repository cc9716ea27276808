"""OpenCL device probing and selection.

Every OpenCL device is probed by building and running a small kernel (a device whose compiler fails,
such as the old PoCL in the PyOpenCL wheel on some CPUs -- "unknown target CPU 'generic'" -- is
skipped). ``default_context(device)`` returns a context on the first device that works, or on the
one named by ``device``; the choice is logged once and probe failures are remembered for the life of
the process.

Before PoCL starts, ``probe_devices`` points its kernel cache at facecast's cache directory and
has it pin its worker threads to the cores (``pin_pocl_workers``); both leave settings in the
environment alone.

``device`` is ``"N"`` (the N-th device over all platforms, as ``facecast info`` lists them),
``"P:D"`` (platform and device index) or a case-insensitive part of ``"<platform name> <device
name>"`` (``"pthread"``, ``"NVIDIA"``).
"""

from __future__ import annotations

import logging
import os
import threading
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)

_PROBE_SOURCE = """
__kernel void probe(__global float *x, const float a) {
    size_t i = get_global_id(0);
    x[i] = a * x[i] + (float)i;
}
"""


@dataclass
class DeviceProbe:
    """What probing one device found."""

    platform_index: int
    device_index: int
    platform: str
    name: str
    kind: str  # "cpu" | "gpu" | "accelerator" | "other"
    ok: bool
    error: str = ""

    @property
    def key(self) -> str:
        return f"{self.platform_index}:{self.device_index}"

    @property
    def label(self) -> str:
        return f"{self.platform} / {self.name}"


_lock = threading.RLock()
_probes: list[DeviceProbe] | None = None
_contexts: dict[str, object] = {}  # probe key -> pyopencl.Context
_logged: set[str] = set()


def set_pocl_cache_dir() -> str:
    """Point PoCL's kernel cache at ``cache_dir("pocl")`` unless ``POCL_CACHE_DIR`` is set; returns it.

    Must run before the first OpenCL call in the process (PoCL reads it when it starts).
    """
    if not os.environ.get("POCL_CACHE_DIR"):
        from ..paths import cache_dir

        os.environ["POCL_CACHE_DIR"] = str(cache_dir("pocl"))
    return os.environ["POCL_CACHE_DIR"]


def pin_pocl_workers() -> bool:
    """Have PoCL pin its worker threads, thread i to CPU i (``POCL_AFFINITY=1``); returns whether
    pinning is on. Left alone when ``POCL_AFFINITY`` is already set, or when this process may not
    run on every CPU (PoCL would pin to CPUs outside its set).

    Unpinned on this 2-vCPU machine, Linux ran both workers on one CPU in 600 of 600 500k-vertex
    frames sampled under load (the kernel then gets one core): pinned, the OpenCL frame's median
    dropped from 1.47 to 1.15 ms and its ratio to the copy bound from 1.6 to 1.3 (6 paired runs).
    Must run before PoCL starts (it reads the variable when it creates its threads).
    """
    if "POCL_AFFINITY" in os.environ:
        return os.environ["POCL_AFFINITY"].strip() not in ("", "0")
    try:
        if os.sched_getaffinity(0) != set(range(os.cpu_count() or 0)):
            return False
    except (AttributeError, OSError):  # no sched_getaffinity (not Linux)
        return False
    os.environ["POCL_AFFINITY"] = "1"
    return True


def _kind(dev) -> str:
    import pyopencl as cl

    t = dev.type
    if t & cl.device_type.GPU:
        return "gpu"
    if t & cl.device_type.CPU:
        return "cpu"
    if t & cl.device_type.ACCELERATOR:
        return "accelerator"
    return "other"


def _probe_one(dev) -> tuple[object | None, str]:
    """Build and run the probe kernel on ``dev``; returns ``(context, "")`` or ``(None, error)``."""
    import pyopencl as cl

    try:
        ctx = cl.Context([dev])
        queue = cl.CommandQueue(ctx)
        prg = cl.Program(ctx, _PROBE_SOURCE).build()
        x = np.arange(64, dtype=np.float32)
        buf = cl.Buffer(ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=x)
        cl.Kernel(prg, "probe")(queue, (64,), None, buf, np.float32(2.0))
        y = np.empty_like(x)
        cl.enqueue_copy(queue, y, buf)
        queue.finish()
        if not np.allclose(y, 3 * np.arange(64, dtype=np.float32)):
            return None, "probe kernel gave wrong results"
        return ctx, ""
    except Exception as e:  # noqa: BLE001 - any driver or compiler failure: the device is unusable
        msg = str(e).strip().splitlines()
        return None, (msg[0] if msg else type(e).__name__)[:300]


def probe_devices(refresh: bool = False) -> list[DeviceProbe]:
    """Probe every OpenCL device once per process (``refresh`` re-probes); empty without PyOpenCL."""
    global _probes
    with _lock:
        if _probes is not None and not refresh:
            return _probes
        set_pocl_cache_dir()
        pin_pocl_workers()
        probes: list[DeviceProbe] = []
        try:
            import pyopencl as cl

            platforms = cl.get_platforms()
        except Exception as e:  # noqa: BLE001 - no PyOpenCL, no ICD loader, or no platform at all
            log.debug("no OpenCL platforms: %s", e)
            _probes = probes
            return probes
        for pi, plat in enumerate(platforms):
            try:
                devices = plat.get_devices()
            except Exception as e:  # noqa: BLE001 - a broken platform is skipped, not fatal
                log.debug("platform %s lists no devices: %s", plat.name, e)
                continue
            for di, dev in enumerate(devices):
                ctx, err = _probe_one(dev)
                p = DeviceProbe(
                    pi, di, plat.name.strip(), dev.name.strip(), _kind(dev), ctx is not None, err
                )
                probes.append(p)
                if ctx is not None:
                    _contexts[p.key] = ctx
                else:
                    log.debug("OpenCL device %s (%s) failed its probe: %s", p.key, p.label, err)
        _probes = probes
        return probes


def _matches(p: DeviceProbe, device: str, position: int) -> bool:
    d = device.strip().lower()
    if d.isdigit():  # "N": the N-th device of all platforms, in probe order
        return int(d) == position
    return d == p.key or d in f"{p.platform} {p.name}".lower()


def default_context(device: str | None = None):
    """A ``pyopencl.Context`` on the first working device (or the one ``device`` names), else None.

    Logs the choice (or that facecast falls back to NumPy) once per process and device.
    """
    with _lock:
        probes = probe_devices()
        candidates = [p for i, p in enumerate(probes) if device is None or _matches(p, device, i)]
        chosen = next((p for p in candidates if p.ok), None)
        note = f"{device or 'auto'}->{chosen.key if chosen else None}"
        if note not in _logged:
            _logged.add(note)
            if chosen is not None:
                log.info("OpenCL device %s: %s", chosen.key, chosen.label)
            elif device is not None and not candidates:
                log.warning(
                    "no OpenCL device matches %r (have: %s); using NumPy",
                    device,
                    ", ".join(f"{p.key} {p.label}" for p in probes) or "none",
                )
            else:
                why = (
                    "; ".join(f"{p.label}: {p.error}" for p in candidates)
                    or "no OpenCL devices found"
                )
                log.warning("no working OpenCL device (%s); using NumPy", why)
        return _contexts.get(chosen.key) if chosen is not None else None


def context_label(ctx) -> str:
    """``"<device name>"`` of the context's first device."""
    return ctx.devices[0].name.strip()
