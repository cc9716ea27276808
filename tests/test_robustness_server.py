"""Hostile files against a real server (issue 12): the crash and hang files go through ``/play`` and
as batch jobs; each must get a 4xx JSON answer (a job: a clear failure), while ``/healthz`` answers
throughout and another live session keeps streaming.

Timing is checked with wide margins only (a quarter of the frames, no silence over 5 s), so the test
holds on a loaded machine; what it catches is a crashed server, a frozen event loop or a 500.
"""

from __future__ import annotations

import asyncio
import io
import json
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING

import httpx
import numpy as np
import pytest
import soundfile as sf
from conftest import RunningServer

from facecast.client.api import watch

if TYPE_CHECKING:
    from typing_extensions import Self

#: Seconds a request may take before the server counts as hung (generous: the machine may be loaded).
REQUEST_TIMEOUT = 60.0
#: Longest silence of the watched session, and longest /healthz answer, before it counts as frozen.
MAX_GAP = 5.0
#: Seconds the other session and /healthz are watched at least.
MIN_SPAN = 3.0
#: Seconds a failing job may take to be reported failed.
JOB_TIMEOUT = 180.0


# ---- the files ----


def c3d_segv() -> bytes:
    """517 bytes that made ezc3d segfault (issue 12)."""
    return b"\x02\x50" + bytes(510) + b"\x01\x50\x02\x54\xff"


def c3d_spin() -> bytes:
    """The same with the last byte 0x80: ezc3d spun at 100 % CPU holding the GIL."""
    return c3d_segv()[:-1] + b"\x80"


def valid_take() -> tuple[bytes, str]:
    """A valid C3D take (ezc3d's writer) and its marker layout as JSON (30 markers: cut to 900 or
    1092 bytes, ezc3d 1.7.2 spins on it)."""
    import tempfile

    from facecast.server.faces import load_face
    from facecast.server.mocap.io import write_take
    from facecast.server.mocap.synthetic import synthetic_take

    syn = synthetic_take(load_face("default"), n_markers=30, seconds=1.0, fps=60.0, seed=3)
    with tempfile.TemporaryDirectory() as tmp:
        path = write_take(syn.take, Path(tmp) / "take.c3d")
        return path.read_bytes(), json.dumps(syn.layout)


def flac_huge_length() -> bytes:
    """A short FLAC whose header declares 2^36 samples (decoding it whole raised MemoryError)."""
    t = np.arange(8000) / 16000
    buf = io.BytesIO()
    sf.write(buf, 0.3 * np.sin(2 * np.pi * 220 * t), 16000, format="FLAC")
    b = bytearray(buf.getvalue())
    total = 2**36 - 1
    b[21] = (b[21] & 0xF0) | (total >> 32)
    b[22:26] = (total & 0xFFFFFFFF).to_bytes(4, "big")
    return bytes(b)


def fap_long_integer() -> bytes:
    """A FAP file with a 4,301-digit integer (past Python's int-from-string limit: a 500)."""
    mask = b" ".join([b"0", b"0", b"1"] + [b"0"] * 65)
    return b"2.1 digits 25 1\n" + mask + b"\n0 " + b"9" * 4301 + b"\n"


@pytest.fixture(scope="module")
def take() -> tuple[bytes, str]:
    return valid_take()


def hostile(name: str, take: tuple[bytes, str]) -> tuple[str, bytes, str | None]:
    """``(filename, content, layout JSON or None)`` for a case name."""
    c3d, layout = take
    if name.startswith("c3d-cut-"):
        return "take.c3d", c3d[: int(name.rsplit("-", 1)[1])], layout
    return {
        "c3d-segv": ("segv.c3d", c3d_segv(), layout),
        "c3d-spin": ("spin.c3d", c3d_spin(), layout),
        "flac-huge-length": ("huge.flac", flac_huge_length(), None),
        "fap-4301-digits": ("digits.fap", fap_long_integer(), None),
    }[name]


CASES = [
    "c3d-segv",
    "c3d-spin",
    "c3d-cut-900",
    "c3d-cut-964",
    "c3d-cut-1092",
    "flac-huge-length",
    "fap-4301-digits",
]


# ---- a server that is restarted if a case killed or froze it ----


@pytest.fixture(scope="module")
def server_box(tmp_path_factory):
    box = {"server": RunningServer(tmp_path_factory.mktemp("robust")).start()}
    yield box
    box["server"].stop()


def healthy(server: RunningServer) -> bool:
    if server.proc is None or server.proc.poll() is not None:
        return False
    try:
        return httpx.get(server.url + "/healthz", timeout=10).status_code == 200
    except httpx.HTTPError:
        return False


@pytest.fixture
def srv(server_box) -> RunningServer:
    """The module's server, restarted (killed first if it hangs) when a previous case broke it."""
    s = server_box["server"]
    if not healthy(s):
        if s.proc is not None and s.proc.poll() is None:
            s.proc.kill()
            s.proc.wait(10)
        s.stop()
        s = server_box["server"] = RunningServer(s.data_dir).start()
    return s


def create_session(server: RunningServer, fps: float = 30.0) -> dict:
    r = httpx.post(
        server.url + "/v1/sessions",
        json={"input": "fap", "fps": fps},
        headers=server.admin_headers,
        timeout=REQUEST_TIMEOUT,
    )
    r.raise_for_status()
    return r.json()


def close_session(server: RunningServer, session: dict) -> None:
    try:
        httpx.delete(
            f"{server.url}/v1/sessions/{session['id']}", headers=server.admin_headers, timeout=10
        )
    except httpx.HTTPError:
        pass


class Monitor:
    """Another live session (the demo at ``fps``, watched by a real viewer) and a ``/healthz`` poller,
    both in background threads, recording what they see while hostile files go in."""

    def __init__(self, server: RunningServer, fps: float = 30.0) -> None:
        self.server, self.fps = server, fps
        self.session = create_session(server, fps)
        r = httpx.post(
            f"{server.url}/v1/sessions/{self.session['id']}/demo",
            headers=server.admin_headers,
            timeout=REQUEST_TIMEOUT,
        )
        assert r.status_code == 202, r.text
        self.frames: list[float] = []  # monotonic arrival times
        self.health: list[tuple[float, str]] = []  # (monotonic time, "200" or the failure)
        self.watch_error: str | None = None
        self._stop = threading.Event()
        self._threads = [
            threading.Thread(target=lambda: asyncio.run(self._watch()), daemon=True),
            threading.Thread(target=self._poll, daemon=True),
        ]

    async def _watch(self) -> None:
        try:
            async with watch(
                self.server.url, self.session["id"], self.session["viewer_token"]
            ) as w:
                async for _ in w:
                    self.frames.append(time.monotonic())
                    if self._stop.is_set():
                        return
        except Exception as e:  # noqa: BLE001 - recorded; the assertions say what it means
            self.watch_error = repr(e)

    def _poll(self) -> None:
        while True:
            t = time.monotonic()
            try:
                r = httpx.get(self.server.url + "/healthz", timeout=MAX_GAP)
                self.health.append((t, str(r.status_code)))
            except httpx.HTTPError as e:
                self.health.append((t, repr(e)))
            if self._stop.wait(0.5):
                return

    def __enter__(self) -> Self:
        for th in self._threads:
            th.start()
        deadline = time.monotonic() + 30
        while not self.frames and time.monotonic() < deadline and self.watch_error is None:
            time.sleep(0.05)
        assert self.frames, f"the watched session never streamed ({self.watch_error})"
        self.t0 = time.monotonic()
        return self

    def __exit__(self, *exc) -> None:
        time.sleep(max(0.0, self.t0 + MIN_SPAN - time.monotonic()))
        self.t1 = time.monotonic()
        self._stop.set()
        self._threads[1].join(MAX_GAP + 5)
        self._threads[0].join(MAX_GAP)  # a frozen server leaves the viewer waiting: it is a daemon
        close_session(self.server, self.session)

    def problems(self) -> list[str]:
        """What went wrong between entering and leaving (empty: the server kept serving)."""
        out = [
            f"/healthz at +{t - self.t0:.1f} s: {what}" for t, what in self.health if what != "200"
        ]
        if not self.health:
            out.append("/healthz was never asked")
        seen = [t for t in self.frames if self.t0 <= t <= self.t1]
        span = self.t1 - self.t0
        gaps = np.diff([self.t0, *seen, self.t1])
        if gaps.max() > MAX_GAP:
            out.append(f"the watched session was silent for {gaps.max():.1f} s")
        if len(seen) < 0.25 * self.fps * span - 2:
            out.append(
                f"the watched session sent {len(seen)} frames in {span:.1f} s at {self.fps:g} fps"
            )
        return out


def four_xx_json(r: httpx.Response) -> str | None:
    """None when ``r`` is a 4xx with a JSON error body, else what is wrong with it."""
    try:
        body = r.json()
    except ValueError:
        body = None
    if not (400 <= r.status_code < 500) or not isinstance(body, dict) or not body.get("error"):
        return f"HTTP {r.status_code}: {r.text[:300]}"
    return None


# ---- the tests ----


@pytest.mark.parametrize("case", CASES)
def test_hostile_file_through_play_gets_a_4xx_while_the_server_keeps_serving(srv, take, case):
    name, content, layout = hostile(case, take)
    target = create_session(srv)
    with Monitor(srv) as mon:
        try:
            r = httpx.post(
                f"{srv.url}/v1/sessions/{target['id']}/play?token={target['producer_token']}",
                files={"file": (name, content)},
                data={"layout": layout} if layout else {},
                timeout=REQUEST_TIMEOUT,
            )
            answer = four_xx_json(r)
        except httpx.HTTPError as e:
            answer = f"no answer: {e!r}"
    close_session(srv, target)
    alive = srv.proc.poll() is None
    problems = (
        ([answer] if answer else [])
        + mon.problems()
        + ([] if alive else [f"the server died (exit {srv.proc.returncode})"])
    )
    assert not problems, f"{case}: " + "; ".join(problems)


def wait_job(server: RunningServer, job_id: str, deadline: float) -> dict:
    while True:
        job = httpx.get(
            f"{server.url}/v1/jobs/{job_id}", headers=server.admin_headers, timeout=REQUEST_TIMEOUT
        ).json()
        if job["status"] in ("done", "failed", "cancelled") or time.monotonic() > deadline:
            return job
        time.sleep(0.5)


@pytest.mark.parametrize("case", CASES)
def test_hostile_file_as_a_job_fails_clearly_while_the_server_keeps_serving(srv, take, case):
    name, content, layout = hostile(case, take)
    answer, job = None, None
    with Monitor(srv) as mon:
        try:
            data = {"format": "fap", **({"layout": layout} if layout else {})}
            r = httpx.post(
                srv.url + "/v1/jobs",
                files={"file": (name, content)},
                data=data,
                headers=srv.admin_headers,
                timeout=REQUEST_TIMEOUT,
            )
            if r.status_code == 202:
                job = wait_job(srv, r.json()["id"], time.monotonic() + JOB_TIMEOUT)
                if job["status"] != "failed" or not job.get("error"):
                    answer = f"the job ended {job['status']!r} (error {job.get('error')!r})"
                else:
                    res = httpx.get(
                        f"{srv.url}/v1/jobs/{job['id']}/result",
                        headers=srv.admin_headers,
                        timeout=REQUEST_TIMEOUT,
                    )
                    answer = four_xx_json(res)
            else:
                answer = four_xx_json(r)
        except httpx.HTTPError as e:
            answer = f"no answer: {e!r}"
    if job is not None and job["status"] in (
        "queued",
        "running",
    ):  # free the worker for the next case
        httpx.delete(
            f"{srv.url}/v1/jobs/{job['id']}", headers=srv.admin_headers, timeout=REQUEST_TIMEOUT
        )
    alive = srv.proc.poll() is None
    problems = (
        ([answer] if answer else [])
        + mon.problems()
        + ([] if alive else [f"the server died (exit {srv.proc.returncode})"])
    )
    assert not problems, f"{case} as a job: " + "; ".join(problems)
