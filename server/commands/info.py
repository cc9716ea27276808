"""``facecast info``: version, the deformation backend and OpenCL device in use, every device probed;
with ``--url``, a running server's cluster instead: its nodes and the live sessions each owns
(``GET /v1/cluster``, admin key from ``--admin-key`` or ``$FACECAST_ADMIN_KEY``)."""

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
    p.add_argument(
        "--url",
        help="a running server: show its cluster (nodes, the sessions each owns) instead",
    )
    p.add_argument("--admin-key", help="admin key for --url (default: $FACECAST_ADMIN_KEY)")


def cluster(url: str, admin_key: str | None, timeout: float = 10.0) -> dict:
    """``GET /v1/cluster`` of the server at ``url``; ``UpstreamError`` with the server's reason."""
    import httpx

    from ..errors import UpstreamError

    headers = {"Authorization": f"Bearer {admin_key}"} if admin_key else {}
    try:
        r = httpx.get(url.rstrip("/") + "/v1/cluster", headers=headers, timeout=timeout)
    except httpx.HTTPError as e:
        raise UpstreamError(f"cannot reach {url}: {e}", where="--url") from None
    if r.status_code != 200:
        try:
            why = r.json().get("error", r.text)
        except ValueError:
            why = r.text
        hint = " (pass --admin-key or set FACECAST_ADMIN_KEY)" if r.status_code == 401 else ""
        raise UpstreamError(f"{url} answered {r.status_code}: {why}{hint}", where="--url")
    out: dict = r.json()
    return out


def print_cluster(view: dict) -> None:
    """The cluster as text: one line per node (``*`` marks the node that answered)."""
    nodes = view.get("nodes", [])
    print(f"cluster: {len(nodes)} node(s), broker {view.get('broker')}")
    for n in nodes:
        mark = "*" if n.get("self") else " "
        sessions = n.get("sessions") or []
        listed = ", ".join(sessions[:8]) + (" ..." if len(sessions) > 8 else "")
        print(
            f" {mark} {n['id']}  {n['url']}  {n['host']} pid {n['pid']}  "
            f"{len(sessions)} session(s){': ' + listed if sessions else ''}"
        )
    if view.get("orphans"):
        print(f"   sessions being taken over: {', '.join(view['orphans'])}")


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
    if getattr(args, "url", None):
        import os

        view = cluster(args.url, args.admin_key or os.environ.get("FACECAST_ADMIN_KEY"))
        if args.json:
            print(json.dumps(view, indent=2))
        else:
            print_cluster(view)
        return 0
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
