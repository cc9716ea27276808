"""``facecast serve``: the HTTP/WebSocket server with embedded defaults.

Built-in face, in-process jobs (spawned worker processes), state in a local data directory.
Binds to loopback unless ``--allow-remote`` is given. Prints the admin key once, when it generates
it (later starts print only where it is kept).
"""

from __future__ import annotations

import argparse
import ipaddress
import logging
import os
import socket
from pathlib import Path

from ..errors import InputError

log = logging.getLogger(__name__)


EPILOG = """\
environment:
  FACECAST_ADMIN_KEY            admin key (else generated, printed once, kept in <data dir>/admin.key, mode 0600)
  FACECAST_FACES                more faces by name: ict=/path/generic_neutral_mesh.obj,other=/path/x.obj
  FACECAST_MAX_UPLOAD_BYTES     largest upload of any kind (default 64 MiB), and per kind:
  FACECAST_MAX_FAP_BYTES        .fap (default 8 MiB)
  FACECAST_MAX_MARKERS_BYTES    .c3d/.trc/.csv (default 32 MiB)
  FACECAST_MAX_AUDIO_BYTES      .wav/.flac/.ogg (default 64 MiB)
  FACECAST_MAX_CONCURRENT_DECODES  uploads /play decodes at once (default 2; more get 503)
  FACECAST_JOB_TIMEOUT_SECONDS  a job running longer fails, its worker killed (default 3600; 0 = none)
  FACECAST_JOB_MEMORY_MB        address space of a job worker process in MiB (default 0 = no limit)
  FACECAST_JOB_RETENTION_HOURS  delete finished jobs after this long (default 168; 0 = never)
  FACECAST_SESSION_IDLE_SECONDS close a live session idle this long (default 600; 0 = never)
  FACECAST_REDIS_URL            make this process a cluster node (--redis; docs/CLUSTER.md)
  every flag also as FACECAST_<NAME> (FACECAST_PORT, FACECAST_JOB_WORKERS, ...); all settings, with their
  defaults: the Configuration table in README.md

routes: /docs (OpenAPI), /healthz, /readyz, /metrics, /v1/faces, /v1/jobs, /v1/sessions, /v1/cluster
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.epilog = EPILOG
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.add_argument("--host", help="address to bind (default 127.0.0.1; others need --allow-remote)")
    p.add_argument("--port", type=int, help="TCP port (default 8000)")
    p.add_argument(
        "--data-dir",
        type=Path,
        help="where jobs, results and the admin key live (default ~/.local/share/facecast)",
    )
    p.add_argument(
        "--face", help="default face: a built-in name (default, default:2k) or a mesh path"
    )
    p.add_argument("--backend", choices=("auto", "numpy", "opencl"), help="deformation backend")
    p.add_argument("--device", help="OpenCL device (index or name substring)")
    p.add_argument(
        "--job-workers",
        type=int,
        dest="job_workers",
        help="batch job worker processes (default 1; 0 = queue only)",
    )
    p.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="node processes on this machine, sharing the port (default: one per CPU core with "
        "--redis, else 1; more than 1 needs --redis)",
    )
    # A node process started by a ``--workers N`` parent: it shares the parent's port and lock.
    p.add_argument("--node-of", type=int, metavar="PID", help=argparse.SUPPRESS)
    p.add_argument(
        "--allow-remote",
        action="store_true",
        default=None,
        help="allow binding to a non-loopback address (anyone who can reach it can use the "
        "public routes; admin routes still need the key)",
    )
    p.add_argument(
        "--session-idle",
        type=float,
        metavar="SECONDS",
        help="close a live session after this long with no viewer and no connected "
        "producer (default 600; 0 = never)",
    )
    p.add_argument(
        "--redis",
        metavar="URL",
        help="make this process a node of a cluster sharing live sessions through Redis at URL "
        "(redis://host:6379/0; FACECAST_REDIS_URL); without it: one process, in memory",
    )
    p.add_argument("--log-level", default=None, help="uvicorn log level (default: warning)")


def is_loopback(host: str) -> bool:
    """True for 127.0.0.0/8, ::1 and names that resolve only to loopback addresses."""
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        pass
    try:
        infos = socket.getaddrinfo(host, None)
    except OSError:
        return False
    return bool(infos) and all(
        ipaddress.ip_address(i[4][0].split("%")[0]).is_loopback for i in infos
    )


def make_config(args: argparse.Namespace):
    """``ServerConfig`` from FACECAST_* environment variables, overridden by the flags given."""
    from ..api.config import load_config

    overrides = {
        k: v
        for k, v in {
            "host": args.host,
            "port": args.port,
            "data_dir": args.data_dir,
            "face": args.face,
            "backend": args.backend,
            "device": args.device,
            "job_workers": getattr(args, "job_workers", None),
            "allow_remote": args.allow_remote,
            "session_idle_seconds": getattr(args, "session_idle", None),
            "redis_url": getattr(args, "redis", None),
        }.items()
        if v is not None
    }
    config = load_config(**overrides)  # one line naming a malformed FACECAST_* variable
    if not is_loopback(config.host) and not config.allow_remote:
        raise InputError(
            f"refusing to bind to {config.host}, which is not a loopback address; pass "
            "--allow-remote (or FACECAST_ALLOW_REMOTE=1) to serve other machines",
            where="--host",
        )
    if config.job_workers < 0:
        raise InputError("must be 0 or more", where="--job-workers")
    return config


def node_processes(args: argparse.Namespace, config) -> int:
    """How many node processes ``--workers`` asks for (checked)."""
    n = getattr(args, "workers", None)
    if n is None:
        return (os.cpu_count() or 1) if config.redis_url else 1
    if n < 1:
        raise InputError("must be 1 or more", where="--workers")
    if n > 1 and not config.redis_url:
        raise InputError(
            f"{n} node processes need a broker to share live sessions: add --redis URL (or "
            "FACECAST_REDIS_URL), or run one process (batch job workers are --job-workers)",
            where="--workers",
        )
    return n


def lock_data_dir(data_dir: Path):
    """Hold an exclusive lock on ``data_dir/server.lock`` for the life of the process.

    Two servers on one data directory would both resume the other's running jobs; the second one
    is refused with a clear error instead. Returns the open lock file (keep a reference).
    """
    import fcntl

    data_dir.mkdir(parents=True, exist_ok=True)
    fh = open(data_dir / "server.lock", "a+")  # noqa: SIM115 - held open (locked) till exit
    try:
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        fh.seek(0)
        holder = fh.read().strip() or "another process"
        fh.close()
        raise InputError(
            f"another facecast server ({holder}) uses this data directory; stop it or pass a "
            "different --data-dir",
            where=str(data_dir),
        ) from None
    fh.seek(0)
    fh.truncate()
    fh.write(f"pid {os.getpid()} on {socket.gethostname()}\n")
    fh.flush()
    return fh


def run(args: argparse.Namespace) -> int:
    import uvicorn

    from ..api.app import create_app
    from ..api.redact import install as mask_secrets_in_logs
    from ..api.security import resolve_admin_key
    from ..live.budget import MAX_WS_MESSAGE

    mask_secrets_in_logs()  # tokens in query strings never reach a log line

    config = make_config(args)
    config.data_dir = config.data_dir.expanduser().resolve()
    parent = getattr(args, "node_of", None)
    workers = 1 if parent else node_processes(args, config)
    if not parent:  # a --workers parent holds the lock for its node processes
        lock = lock_data_dir(config.data_dir)  # noqa: F841  (held until the process exits)
    chosen = bool(config.admin_key)
    key_file = config.data_dir / "admin.key"
    page = f"http://{config.host}:{config.port}/"
    if config.redis_url:  # a cluster node: Redis must answer now; the cluster's admin key
        from ..cluster import bootstrap

        key, source = bootstrap.admin_key(
            bootstrap.connect(config.redis_url), config.admin_key, config.data_dir
        )
        generated = source == "generated"
        if source == "cluster":
            chosen = True
            print("facecast: admin key: the cluster's (kept in its Redis)", flush=True)
    else:
        key, generated = resolve_admin_key(config.admin_key, config.data_dir)
    config.admin_key = key
    if parent:
        from ..cluster.workers import serve_node

        serve_node(create_app(config), config, args.log_level, MAX_WS_MESSAGE)
        return 0
    if generated:  # shown this once; later starts only say where it is
        print(
            f"facecast: generated an admin key, kept in {key_file} (readable by you only); it is shown "
            f"only now:\n  FACECAST_ADMIN_KEY={key}\n"
            f"facecast: web viewer with admin rights: {page}#key={key}",
            flush=True,
        )
    elif not chosen:
        print(
            f"facecast: admin key in {key_file}; web viewer with admin rights: {page}#key=<that key>",
            flush=True,
        )
    if workers > 1:
        from ..cluster.workers import supervise

        print(
            f"facecast: serving on {page} with {workers} node processes (data in "
            f"{config.data_dir}, {config.job_workers} job worker(s), backend {config.backend})",
            flush=True,
        )
        return supervise(config, workers, args.log_level)
    app = create_app(config)
    print(
        f"facecast: serving on {page} (data in {config.data_dir}, "
        f"{config.job_workers} job worker(s), backend {config.backend})",
        flush=True,
    )
    uvicorn.run(
        app,
        host=config.host,
        port=config.port,
        ws_per_message_deflate=False,
        log_level=args.log_level or "warning",
        lifespan="on",
        timeout_graceful_shutdown=5,
        ws_max_size=MAX_WS_MESSAGE,
    )  # the largest message a live input accepts
    return 0
