"""A real ``facecast serve`` in a child process on loopback, for tests and benchmarks.

``LocalServer(data_dir, "--face", "default:2k").start()`` starts it on a free port, waits until
``/healthz`` answers (``start(ready=True)``: until the default face is loaded), and knows its URL,
admin key (given, or the one the server generated in ``<data dir>/admin.key``), log file, CPU time
and memory; ``stop()`` ends it. ``RedisServer()`` does the same for a real ``redis-server`` (the
broker of a cluster). One harness for tests/conftest.py and the scripts in bench/.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path
from types import TracebackType
from typing import IO, TYPE_CHECKING, Any

import httpx

if TYPE_CHECKING:
    from typing_extensions import Self

#: Seconds between two health probes while a server starts.
POLL_SECONDS = 0.2


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def process_cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` so far (Linux /proc), or NaN."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return float("nan")


def parent_pids() -> dict[int, int]:
    """``pid -> parent pid`` of every process now (Linux /proc); empty elsewhere."""
    out = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            out[int(stat.parent.name)] = int(stat.read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
    return out


def spawned_children(pid: int) -> list[int]:
    """Pids of the ``multiprocessing`` spawn children of process ``pid`` (a server's job workers;
    not its resource tracker), from Linux /proc; empty elsewhere."""
    out = []
    for child, parent in parent_pids().items():
        if parent != pid:
            continue
        try:
            cmd = Path(f"/proc/{child}/cmdline").read_bytes()
        except OSError:
            continue
        if b"spawn_main" in cmd and b"resource_tracker" not in cmd:
            out.append(child)
    return out


def descendants(pid: int) -> list[int]:
    """Pids of the children of process ``pid``, their children and so on (Linux /proc; empty
    elsewhere)."""
    children: dict[int, list[int]] = {}
    for child, parent in parent_pids().items():
        children.setdefault(parent, []).append(child)
    out, stack = [], list(children.get(pid, []))
    while stack:
        p = stack.pop()
        out.append(p)
        stack.extend(children.get(p, []))
    return out


class LocalServer:
    """``facecast serve --port P --data-dir D *args`` as a child process of this one.

    ``data_dir`` None: a temporary folder, deleted by ``stop()``. ``env``: variables added to this
    process's environment (they win over ``admin_key``). No admin key in the end (None or empty):
    the server generates one, read from the data dir once it runs.
    ``python``: the interpreter to run (another checkout's venv, to compare two versions).
    """

    def __init__(
        self,
        data_dir: Path | None = None,
        *args: str,
        env: Mapping[str, str] | None = None,
        admin_key: str | None = None,
        python: str = sys.executable,
    ) -> None:
        self._tmp = None
        if data_dir is None:
            self._tmp = tempfile.TemporaryDirectory(prefix="facecast-serve-")
            data_dir = Path(self._tmp.name)
        self.data_dir = Path(data_dir)
        self.args, self.python = args, python
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        key = {"FACECAST_ADMIN_KEY": admin_key} if admin_key is not None else {}
        self.env = {**os.environ, **key, **(env or {})}
        self.admin_key = self.env.get("FACECAST_ADMIN_KEY") or ""  # else read once the server runs
        self.proc: subprocess.Popen[bytes] | None = None
        self.health: dict[str, Any] = {}
        self._logf: IO[bytes] | None = None

    @property
    def log(self) -> Path:
        """The server's stdout and stderr (appended to across restarts)."""
        return self.data_dir / f"server-{self.port}.log"

    @property
    def admin_headers(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.admin_key}"}

    def start(self, timeout: float = 120.0, *, ready: bool = False) -> Self:
        """Start the process and wait until ``/healthz`` answers 200 (and says ready, if ``ready``).

        Raises ``RuntimeError`` with the end of the server's log when it exits or times out.
        """
        self.data_dir.mkdir(parents=True, exist_ok=True)
        cmd = [
            self.python,
            "-m",
            "facecast.server.cli",
            "serve",
            "--port",
            str(self.port),
            "--data-dir",
            str(self.data_dir),
            *self.args,
        ]
        self._logf = open(self.log, "ab")  # noqa: SIM115 (closed by stop)
        self.proc = subprocess.Popen(cmd, env=self.env, stdout=self._logf, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(
                    f"facecast serve exited with {self.proc.returncode}:\n{self.tail()}"
                )
            try:
                r = httpx.get(self.url + "/healthz", timeout=2.0)
                if r.status_code == 200 and (not ready or r.json().get("ready", True)):
                    self.health = r.json()
                    if not self.admin_key:
                        self.admin_key = (self.data_dir / "admin.key").read_text().strip()
                    return self
            except httpx.HTTPError:
                pass
            time.sleep(POLL_SECONDS)
        self.stop()
        raise RuntimeError(
            f"facecast serve did not become {'ready' if ready else 'healthy'} in {timeout:g} s:\n"
            f"{self.tail()}"
        )

    def tail(self, chars: int = 4000) -> str:
        """The end of the server's log."""
        try:
            return self.log.read_text(errors="replace")[-chars:]
        except OSError:
            return ""

    def healthy(self, timeout: float = 10.0) -> bool:
        """True when the process runs and ``/healthz`` answers 200."""
        try:
            return (
                self.proc is not None
                and self.proc.poll() is None
                and httpx.get(self.url + "/healthz", timeout=timeout).status_code == 200
            )
        except httpx.HTTPError:
            return False

    def cpu_seconds(self) -> float:
        """User + system CPU seconds of the server process so far (NaN when unknown)."""
        return process_cpu_seconds(self.proc.pid) if self.proc is not None else float("nan")

    def rss(self) -> int:
        """Resident memory of the server process, bytes (0 when unknown)."""
        try:
            for line in (
                Path(f"/proc/{self.proc.pid if self.proc else 0}/status").read_text().splitlines()
            ):
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
        except OSError:
            pass
        return 0

    def kill(self) -> None:
        """End the process at once (SIGKILL), as a crash would; ``start()`` brings it back."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)
        self._close_log()

    def stop(self) -> None:
        """Terminate the process (SIGTERM, then SIGKILL after 10 s); delete a temporary data dir."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self._close_log()
        if self._tmp is not None:
            self._tmp.cleanup()

    def _close_log(self) -> None:
        if self._logf is not None:
            self._logf.close()
            self._logf = None

    def __enter__(self) -> Self:
        return self if self.proc is not None else self.start()

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()


class RedisServer:
    """A real ``redis-server`` on a free loopback port, in memory only (no RDB, no AOF).

    ``start()`` waits until it answers PING; ``kill()`` ends it at once (SIGKILL), ``start()``
    again brings it back on the same port (empty: nothing is persisted), ``stop()`` ends it.
    ``available()`` says whether the binary is installed (``.ci/setup`` installs it).
    """

    def __init__(self, port: int | None = None) -> None:
        self.port = port or free_port()
        self.url = f"redis://127.0.0.1:{self.port}/0"
        self.proc: subprocess.Popen[bytes] | None = None
        self._tmp = tempfile.TemporaryDirectory(prefix="facecast-redis-")

    @staticmethod
    def available() -> bool:
        return shutil.which("redis-server") is not None

    def start(self, timeout: float = 20.0) -> Self:
        """Start the process; raise ``RuntimeError`` with its output when it does not answer."""
        log = Path(self._tmp.name) / "redis.log"
        cmd = ["redis-server", "--port", str(self.port), "--bind", "127.0.0.1", "--save", ""]
        cmd += ["--appendonly", "no", "--dir", self._tmp.name, "--logfile", str(log)]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                break
            if self.ping():
                return self
            time.sleep(0.05)
        self.kill()
        text = log.read_text(errors="replace")[-2000:] if log.exists() else ""
        raise RuntimeError(f"redis-server on port {self.port} did not answer PING:\n{text}")

    def ping(self) -> bool:
        """True when the server answers PING (a raw RESP exchange: no client library needed)."""
        try:
            with socket.create_connection(("127.0.0.1", self.port), timeout=1.0) as s:
                s.sendall(b"PING\r\n")
                return s.recv(64).startswith(b"+PONG")
        except OSError:
            return False

    def kill(self) -> None:
        """End the process at once (SIGKILL), as a crash would."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)

    def stop(self) -> None:
        """End the process and delete its folder."""
        self.kill()
        self._tmp.cleanup()

    def __enter__(self) -> Self:
        return self if self.proc is not None else self.start()

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()
