"""``facecast info``: version, the deformation backend and OpenCL device in use, every device probed."""

from __future__ import annotations

import argparse
import json
import platform
import sys


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--backend",
        choices=("auto", "numpy", "opencl"),
        default="auto",
        help="backend to report on (default: auto, as the server would choose)",
    )
    p.add_argument(
        "--device",
        default=None,
        help="OpenCL device: 'P:D' index or part of its name (default: first that works)",
    )
    p.add_argument("--json", action="store_true", help="print JSON instead of text")


def gather(backend: str = "auto", device: str | None = None) -> dict:
    """What ``facecast info`` reports, as a dict."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        fc_version = version("facecast")
    except PackageNotFoundError:
        fc_version = "unknown"
    info: dict = {
        "facecast": fc_version,
        "python": platform.python_version(),
        "numpy": _version("numpy"),
        "scipy": _version("scipy"),
        "pyopencl": _version("pyopencl"),
    }
    from ..backends.select import default_context, probe_devices, set_pocl_cache_dir

    info["pocl_cache_dir"] = set_pocl_cache_dir()
    probes = probe_devices() if backend != "numpy" else []
    info["devices"] = [
        {
            "id": p.key,
            "platform": p.platform,
            "name": p.name,
            "type": p.kind,
            "ok": p.ok,
            **({"error": p.error} if not p.ok else {}),
        }
        for p in probes
    ]
    ctx = default_context(device) if backend != "numpy" else None
    if ctx is not None:
        dev = ctx.devices[0]
        info["backend"] = "opencl"
        info["device"] = {
            "name": dev.name.strip(),
            "platform": dev.platform.name.strip(),
            "version": dev.version.strip(),
            "driver": dev.driver_version.strip(),
            "compute_units": int(dev.max_compute_units),
            "global_memory_mb": int(dev.global_mem_size) // 2**20,
        }
    else:
        info["backend"] = "numpy"
        info["device"] = None
        if backend == "opencl":
            info["error"] = "no working OpenCL device" + (f" matches {device!r}" if device else "")
    return info


def _version(module: str) -> str | None:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(module)
    except PackageNotFoundError:
        return None


def run(args: argparse.Namespace) -> int:
    info = gather(args.backend, args.device)
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        print(
            f"facecast {info['facecast']} (Python {info['python']}, NumPy {info['numpy']}, "
            f"SciPy {info['scipy']}, PyOpenCL {info['pyopencl'] or 'not installed'})"
        )
        if info["device"]:
            d = info["device"]
            print(
                f"backend: opencl on {d['name']} ({d['platform']}; {d['version']}; "
                f"{d['compute_units']} compute units)"
            )
        else:
            why = (
                ""
                if args.backend == "numpy"
                else (
                    f" (no working OpenCL device matches {args.device!r})"
                    if args.device
                    else " (no working OpenCL device)"
                )
            )
            print("backend: numpy" + why)
        for p in info["devices"]:
            state = "ok" if p["ok"] else f"FAILED: {p['error']}"
            print(f"  device {p['id']}: {p['platform']} / {p['name']} [{p['type']}] {state}")
        if not info["devices"] and args.backend != "numpy":
            print("  no OpenCL devices found (install pocl-opencl-icd for CPUs)")
        print(f"PoCL kernel cache: {info['pocl_cache_dir']}")
    if "error" in info:
        print(f"facecast: {info['error']}", file=sys.stderr)
        return 2
    return 0
