"""Batch jobs on a real server: real FAP files in, valid results out; progress, cancel, failures, restarts."""

from __future__ import annotations

import io
import time
from pathlib import Path

import cluster_support
import httpx
import numpy as np
import pytest
from cluster_support import FACE, add_job, status, wait
from conftest import RunningServer

from facecast.client.jobs import RemoteJobError, render_remote
from facecast.server.harness import spawned_children


@pytest.fixture(scope="module")
def srv(tmp_path_factory) -> RunningServer:
    s = RunningServer(tmp_path_factory.mktemp("jobs"), "--face", FACE, "--job-workers", "1").start()
    yield s
    s.stop()


@pytest.fixture(scope="module")
def n_vertices(srv) -> int:
    return httpx.get(f"{srv.url}/v1/faces/{FACE}", timeout=120).json()["vertices"]


def fap_file(data_dir: Path, name: str = "joy.fap") -> Path:
    return data_dir / "xface" / "faps" / name


def submit(srv: RunningServer, name: str, content: bytes, **options) -> dict:
    resp = cluster_support.submit(srv, name, content, **options)
    assert resp.status_code == 202, resp.text
    assert resp.headers["location"] == f"/v1/jobs/{resp.json()['id']}"
    return resp.json()


def test_fap_job_renders_a_valid_glb(srv, data_dir, n_vertices):
    import pygltflib

    src = fap_file(data_dir)
    job = submit(srv, src.name, src.read_bytes(), format="glb")
    assert (
        job["status"] == "queued"
        and job["input_kind"] == "fap"
        and job["input_bytes"] == src.stat().st_size
    )
    done = wait(srv, job["id"])
    assert done["status"] == "done", done
    assert done["progress"] == 1.0 and done["error"] is None and done["attempts"] == 1
    resp = httpx.get(srv.url + done["result_url"], headers=srv.admin_headers, timeout=60)
    assert resp.status_code == 200 and resp.headers["content-type"] == "model/gltf-binary"
    assert 'filename="joy.glb"' in resp.headers["content-disposition"]
    assert len(resp.content) == done["result_bytes"]
    gltf = pygltflib.GLTF2.load_from_bytes(resp.content)
    position = gltf.meshes[0].primitives[0].attributes.POSITION
    assert gltf.accessors[position].count == n_vertices
    assert gltf.animations, "an animated glTF has at least one animation"


def test_render_remote_reports_progress_and_writes_atomically(srv, data_dir, tmp_path, n_vertices):
    from facecast.protocol.fap_file import read_fap

    calls: list[tuple[int, int]] = []
    out = render_remote(
        srv.url,
        fap_file(data_dir, "anger.fap"),
        tmp_path / "anger.npz",
        options={"face": FACE},
        progress=lambda d, t: calls.append((d, t)),
        admin_key=srv.admin_key,
    )
    assert out == tmp_path / "anger.npz"
    assert calls and calls[-1] == (1000, 1000)
    done = [d for d, _ in calls]
    assert done == sorted(done) and all(t == 1000 for _, t in calls)
    with np.load(out) as npz:
        shapes = [npz[k].shape for k in npz.files]
    assert any(len(s) == 3 and s[1:] == (n_vertices, 3) for s in shapes), shapes
    assert sorted(p.name for p in tmp_path.iterdir()) == ["anger.npz"]  # no partial download left

    fap = render_remote(
        srv.url,
        fap_file(data_dir, "anger.fap"),
        tmp_path / "anger.fap",
        options={"face": FACE},
        admin_key=srv.admin_key,
    )
    reread = read_fap(fap.read_text(), where=str(fap))
    original = read_fap(fap_file(data_dir, "anger.fap").read_text())
    assert len(reread.frames if hasattr(reread, "frames") else reread.values) == len(
        original.frames if hasattr(original, "frames") else original.values
    )


def render_on(srv: RunningServer, src: Path, out: Path, *extra: str, admin_key: str):
    """``facecast render SRC -o OUT --face FACE --server URL *extra`` as a user runs it, with
    ``FACECAST_ADMIN_KEY`` set to ``admin_key``; the finished process."""
    import os
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "facecast.server.cli", "render", str(src), "-o", str(out)]
    return subprocess.run(
        [*cmd, "--face", FACE, "--server", srv.url, *extra],
        env={**os.environ, "FACECAST_ADMIN_KEY": admin_key},
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_render_cli_with_server_option(srv, data_dir, tmp_path):
    out = tmp_path / "joy.fap"
    run = render_on(srv, fap_file(data_dir), out, admin_key=srv.admin_key)
    assert run.returncode == 0, run.stderr
    assert out.read_text().lstrip().startswith(("#", "2.1"))
    run = render_on(srv, fap_file(data_dir), tmp_path / "x.fap", admin_key="wrong")
    last = run.stderr.strip().splitlines()[-1]
    assert run.returncode == 2 and last.startswith("facecast:") and "admin key" in last


def test_speech_upload_recognised_by_content_becomes_a_fap_stream(srv, data_dir):
    from facecast.protocol.fap_file import read_fap

    wav = data_dir / "speech" / "bobby_16bit_16khz.wav"
    job = submit(
        srv, "recording", wav.read_bytes(), format="fap"
    )  # no suffix: sniffed as RIFF/WAVE
    assert job["input_kind"] == "audio"
    done = wait(srv, job["id"])
    assert done["status"] == "done", done
    resp = httpx.get(srv.url + done["result_url"], headers=srv.admin_headers, timeout=60)
    assert resp.headers["content-type"].startswith("text/plain")
    assert 'filename="recording.fap"' in resp.headers["content-disposition"]
    read_fap(resp.text, where="result")  # parses as a FAP file


def test_malformed_file_fails_the_job_with_a_clear_error(srv, tmp_path):
    bad = b"2.1 broken 25 3\nthis line is not a FAP mask\n"
    job = wait(srv, submit(srv, "broken.fap", bad)["id"])
    assert job["status"] == "failed"
    assert "broken.fap" in job["error"] and str(srv.data_dir) not in job["error"]
    resp = httpx.get(f"{srv.url}/v1/jobs/{job['id']}/result", headers=srv.admin_headers)
    assert resp.status_code == 409 and "failed" in resp.json()["error"]
    (tmp_path / "broken.fap").write_bytes(bad)
    # the job's error, then (a wrong key) the server's, reach the client; no file is written
    for key, error in ((srv.admin_key, "broken.fap"), ("wrong", "admin key")):
        with pytest.raises(RemoteJobError, match=error):
            render_remote(
                srv.url,
                tmp_path / "broken.fap",
                tmp_path / "out.glb",
                options={"face": FACE},
                admin_key=key,
            )
        assert not (tmp_path / "out.glb").exists()


def test_cancel_a_running_job(srv, data_dir):
    src = fap_file(data_dir, "disgust.fap")
    job = submit(srv, src.name, src.read_bytes(), format="glb", face="default")
    seen = wait(srv, job["id"], until=("running", "done", "failed"))
    assert seen["status"] == "running", seen
    resp = httpx.delete(f"{srv.url}/v1/jobs/{job['id']}", headers=srv.admin_headers, timeout=30)
    assert resp.status_code == 200 and resp.json()["status"] == "cancelled"
    again = httpx.delete(f"{srv.url}/v1/jobs/{job['id']}", headers=srv.admin_headers, timeout=30)
    assert again.status_code == 200 and again.json()["status"] == "cancelled"
    # The worker is gone: the job never turns done, and the next job gets the (only) worker slot.
    nxt = submit(srv, "joy.fap", fap_file(data_dir).read_bytes(), format="fap")
    assert wait(srv, nxt["id"])["status"] == "done"
    assert status(srv, job["id"])["status"] == "cancelled"
    assert not any((srv.data_dir / "jobs" / job["id"]).glob("result*"))
    finished = httpx.delete(f"{srv.url}/v1/jobs/{nxt['id']}", headers=srv.admin_headers)
    assert finished.status_code == 409 and "already done" in finished.json()["error"]


def test_metrics_count_jobs_by_state(srv):
    from prometheus_client.parser import text_string_to_metric_families

    text = httpx.get(srv.url + "/metrics").text
    jobs = next(f for f in text_string_to_metric_families(text) if f.name == "facecast_jobs")
    by_state = {s.labels["state"]: s.value for s in jobs.samples}
    listed = httpx.get(srv.url + "/v1/jobs?limit=1000", headers=srv.admin_headers).json()["jobs"]
    for state in ("done", "failed", "cancelled"):
        assert by_state[state] == sum(j["status"] == state for j in listed), (state, by_state)


@pytest.mark.slow
def test_queued_job_finishes_after_a_restart(tmp_path, data_dir):
    src = fap_file(data_dir)
    first = RunningServer(tmp_path, "--face", FACE, "--job-workers", "0").start()
    try:
        job = submit(first, src.name, src.read_bytes(), format="npz")
        assert status(first, job["id"])["status"] == "queued"
    finally:
        first.stop()
    second = RunningServer(tmp_path, "--face", FACE, "--job-workers", "1").start()
    try:
        done = wait(second, job["id"])
        assert done["status"] == "done", done
        resp = httpx.get(second.url + done["result_url"], headers=second.admin_headers, timeout=60)
        with np.load(io.BytesIO(resp.content)) as npz:
            assert npz.files
    finally:
        second.stop()


@pytest.mark.slow
def test_running_job_resumes_after_a_restart(tmp_path, data_dir):
    src = fap_file(data_dir, "beg.fap")
    first = RunningServer(tmp_path, "--face", FACE, "--job-workers", "1").start()
    try:
        job = submit(first, src.name, src.read_bytes(), format="glb")
        # A fresh worker spends seconds starting (imports, face, device) while the job is running.
        seen = wait(first, job["id"], until=("running", "done", "failed"))
        assert seen["status"] == "running", seen
    finally:
        first.stop()
    second = RunningServer(tmp_path, "--face", FACE, "--job-workers", "1").start()
    try:
        done = wait(second, job["id"])
        assert done["status"] == "done", done
        assert done["attempts"] == 2  # interrupted once, then finished by the new server's worker
        resp = httpx.get(second.url + done["result_url"], headers=second.admin_headers, timeout=60)
        assert resp.content[:4] == b"glTF"
        assert not [p for p in (tmp_path / "jobs" / job["id"]).iterdir() if p.name.startswith(".")]
    finally:
        second.stop()


def test_worker_records_progress_frame_by_frame(tmp_path, data_dir, monkeypatch):
    """The worker turns render_file's per-frame callback into job progress (in-process, real render)."""
    from collections import OrderedDict

    from facecast.server.jobs import worker
    from facecast.server.jobs.store import JobStore

    class RecordingStore(JobStore):
        def progress(self, job_id, attempt, fraction):
            seen.append(fraction)
            return super().progress(job_id, attempt, fraction)

    seen: list[float] = []
    monkeypatch.setattr(worker, "PROGRESS_INTERVAL", 0.0)
    store = RecordingStore(tmp_path)
    src = fap_file(data_dir, "happy-for.fap")
    opts = {"format": "npz", "face_spec": FACE, "engine": "fp"}
    job_id = add_job(store, src.read_bytes(), name=src.name, result="result.npz", options=opts)
    attempt = store.claim(job_id)
    worker.run_job(store, job_id, attempt, "numpy", None, None, OrderedDict())
    job = store.get(job_id)
    assert job.status == "done" and job.progress == 1.0
    assert (
        len(set(seen)) >= 3 and seen == sorted(seen) and seen[-1] == 1.0 and seen[0] < 0.5
    )  # batches of frames
    assert store.result_path(job).is_file()
    # A cancelled job stops at its next progress report and records nothing more.
    job2 = add_job(store, src.read_bytes(), name=src.name, result="result.npz", options=opts)
    attempt = store.claim(job2)
    store.cancel(job2)
    seen.clear()
    worker.run_job(store, job2, attempt, "numpy", None, None, OrderedDict())
    assert store.get(job2).status == "cancelled"
    assert not store.result_path(store.get(job2)).exists()
    store.close()


def test_store_purges_only_old_finished_jobs(tmp_path):
    from facecast.server.jobs.store import JobStore

    store = JobStore(tmp_path)
    ids = {}
    for state in ("done", "failed", "cancelled", "queued", "running"):
        job_id = add_job(store)
        if state != "queued":
            attempt = store.claim(job_id)
            if state in ("done", "failed"):
                store.finish(job_id, attempt, state)
            elif state == "cancelled":
                store.cancel(job_id)
        ids[state] = job_id
    assert store.purge(time.time() - 3600) == []  # nothing finished an hour ago
    gone = store.purge(time.time() + 1)
    assert sorted(gone) == sorted(ids[s] for s in ("done", "failed", "cancelled"))
    assert store.counts() == {"queued": 1, "running": 1}
    assert sorted(p.name for p in (tmp_path / "jobs").iterdir()) == sorted(
        [ids["queued"], ids["running"]]
    )
    store.close()


# ------------------------------------------------------------------------- layouts travel as content


@pytest.fixture(scope="module")
def mocap_take(tmp_path_factory):
    """A small synthetic TRC take on the jobs server's face, with its layout beside it."""
    import json

    from facecast.protocol.markers_file import write_trc
    from facecast.server.faces import load_face
    from facecast.server.mocap.synthetic import synthetic_take

    syn = synthetic_take(load_face(FACE), n_markers=16, seconds=0.5, fps=60.0, seed=7)
    folder = tmp_path_factory.mktemp("take")
    (folder / "take.trc").write_text(write_trc(syn.take))
    (folder / "take.layout.json").write_text(json.dumps(syn.layout))
    return folder / "take.trc", folder / "take.layout.json", syn


def test_a_mocap_take_renders_with_its_layout_as_content(srv, mocap_take, n_vertices):
    take, layout, syn = mocap_take
    resp = httpx.post(
        srv.url + "/v1/jobs",
        files={
            "file": (take.name, take.read_bytes()),
            "layout": ("take.layout.json", layout.read_bytes()),
        },
        data={"face": FACE, "format": "npz"},
        headers=srv.admin_headers,
        timeout=60,
    )
    assert resp.status_code == 202, resp.text
    assert resp.json()["input_kind"] == "markers" and resp.json()["options"]["layout"] == "uploaded"
    done = wait(srv, resp.json()["id"])
    assert done["status"] == "done", done
    npz = httpx.get(srv.url + done["result_url"], headers=srv.admin_headers, timeout=60).content
    with np.load(io.BytesIO(npz)) as z:
        frames = next(z[k] for k in z.files if z[k].ndim == 3)
    assert frames.shape == (len(syn.take.xyz), n_vertices, 3) and np.isfinite(frames).all()
    assert np.abs(frames - frames[0]).max() > 0  # the markers moved the face
    # The layout inline (a form field holding the JSON) works the same.
    inline = submit(srv, take.name, take.read_bytes(), format="fap", layout=layout.read_text())
    assert wait(srv, inline["id"])["status"] == "done"


def test_render_server_mode_uploads_the_layout_file(srv, mocap_take, tmp_path):
    take, layout, _ = mocap_take
    for extra in (["--layout", str(layout)], []):  # given, or found beside the take as locally
        out = tmp_path / f"take{len(extra)}.fap"
        run = render_on(srv, take, out, *extra, admin_key=srv.admin_key)
        assert run.returncode == 0, run.stderr
        assert out.read_text().lstrip().startswith(("#", "2.1"))
    lone = tmp_path / "lone" / "take.trc"
    lone.parent.mkdir()
    lone.write_bytes(take.read_bytes())
    with pytest.raises(RemoteJobError, match="layout"):
        render_remote(
            srv.url, lone, tmp_path / "x.fap", options={"face": FACE}, admin_key=srv.admin_key
        )


def test_a_layout_naming_a_server_file_is_refused_without_reading_it(srv, mocap_take, tmp_path):
    import json

    take, _, _ = mocap_take
    secret = tmp_path / "secret.json"
    secret.write_text(json.dumps({"zz_secret_key": 1, "markers": {"zz_marker": {}}}))
    for value in (
        str(secret),
        json.dumps(str(secret)),
        "/etc/passwd",
        json.dumps("/etc/passwd"),
        "[1, 2]",
    ):
        resp = httpx.post(
            srv.url + "/v1/jobs",
            files={"file": (take.name, take.read_bytes())},
            data={"face": FACE, "layout": value},
            headers=srv.admin_headers,
            timeout=60,
        )
        assert resp.status_code == 400, (value, resp.text)
        assert resp.json()["error"] and "layout" in resp.json()["error"]
        assert (
            "zz_" not in resp.text and "root:" not in resp.text and str(tmp_path) not in resp.text
        )
    resp = httpx.post(
        srv.url + "/v1/jobs",
        files={"file": (take.name, take.read_bytes())},
        data={"face": FACE},
        headers=srv.admin_headers,
        timeout=60,
    )
    assert resp.status_code == 400 and "layout" in resp.json()["error"]  # a take needs its layout
    leftovers = [p for p in (srv.data_dir / "jobs").iterdir() if not list(p.iterdir())]
    assert leftovers == []


def test_uploads_are_limited_by_kind(srv):
    big_fap = b"2.1 big 25 1\n" + b"0 " * (
        5 * 1024 * 1024
    )  # 10 MiB of FAP text: over the 8 MiB FAP limit
    resp = httpx.post(
        srv.url + "/v1/jobs",
        files={"file": ("big.fap", big_fap)},
        data={"face": FACE},
        headers=srv.admin_headers,
        timeout=60,
    )
    assert resp.status_code == 413, resp.text
    assert "fap input" in resp.json()["error"] and "FACECAST_MAX_FAP_BYTES" in resp.json()["error"]


# ---------------------------------------------------------------------- job timeout, worker lifetime


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.slow
def test_a_job_over_the_time_limit_fails_and_its_worker_is_killed(tmp_path, data_dir):
    s = RunningServer(
        tmp_path, "--face", FACE, "--job-workers", "1", env={"FACECAST_JOB_TIMEOUT_SECONDS": "0.5"}
    ).start()
    try:
        src = fap_file(data_dir, "disgust.fap")
        job = submit(s, src.name, src.read_bytes(), format="glb", face="default")  # seconds of work
        failed = wait(s, job["id"])
        assert failed["status"] == "failed", failed
        assert (
            "longer than" in failed["error"] and "FACECAST_JOB_TIMEOUT_SECONDS" in failed["error"]
        )
        for _ in range(200):  # the killed worker is reaped
            if not [p for p in spawned_children(s.proc.pid) if alive(p)]:
                break
            time.sleep(0.05)
        assert not [p for p in spawned_children(s.proc.pid) if alive(p)]
    finally:
        s.stop()


@pytest.mark.slow
def test_a_worker_dies_with_its_server(tmp_path, data_dir):
    import os
    import signal

    s = RunningServer(tmp_path, "--face", FACE, "--job-workers", "1").start()
    try:
        src = fap_file(data_dir, "disgust.fap")
        job = submit(s, src.name, src.read_bytes(), format="glb", face="default")
        assert wait(s, job["id"], until=("running", "done", "failed"))["status"] == "running"
        workers = [p for p in spawned_children(s.proc.pid) if alive(p)]
        assert workers
        os.kill(s.proc.pid, signal.SIGKILL)
        s.proc.wait(30)
        for _ in range(600):
            if not any(alive(p) for p in workers):
                break
            time.sleep(0.05)
        assert not any(alive(p) for p in workers), "a job worker outlived its server"
    finally:
        s.stop()


def test_die_with_parent_ends_a_busy_process_when_its_parent_is_killed(tmp_path):
    """The mechanism alone: a process busy outside any progress report (a decoder stuck in native
    code) still ends when the process that started it dies by SIGKILL."""
    import os
    import signal
    import subprocess
    import sys

    child = (
        "import os, sys, time; from facecast.server.jobs.worker import die_with_parent; "
        "die_with_parent(int(sys.argv[1])); print(os.getpid(), flush=True); time.sleep(600)"
    )
    parent = (
        "import subprocess, sys, time; "
        f"p = subprocess.Popen([sys.executable, '-c', {child!r}, str(__import__('os').getpid())]); "
        "time.sleep(600)"
    )
    out = tmp_path / "child.pid"
    with open(out, "w") as fh:
        a = subprocess.Popen([sys.executable, "-c", parent], stdout=fh)
    try:
        for _ in range(1200):
            if out.read_text().strip():
                break
            time.sleep(0.05)
        pid = int(out.read_text().split()[0])
        assert alive(pid)
        os.kill(a.pid, signal.SIGKILL)
        a.wait(30)
        for _ in range(600):
            if not alive(pid):
                break
            time.sleep(0.05)
        assert not alive(pid), "the child outlived its parent"
    finally:
        if a.poll() is None:
            a.kill()


def test_a_file_that_crashes_the_decoder_fails_its_job_and_the_server_keeps_serving(
    srv, mocap_take, data_dir
):
    """A 517-byte C3D that made the C3D reader segfault: the worker process may die, the server not."""
    _, layout, _ = mocap_take
    crash = b"\x02\x50" + bytes(510) + b"\x01\x50\x02\x54\xff"
    resp = httpx.post(
        srv.url + "/v1/jobs",
        files={"file": ("segv.c3d", crash), "layout": ("l.json", layout.read_bytes())},
        data={"face": FACE},
        headers=srv.admin_headers,
        timeout=60,
    )
    assert resp.status_code in (202, 400), resp.text
    if resp.status_code == 202:
        failed = wait(srv, resp.json()["id"])
        assert failed["status"] == "failed" and failed["attempts"] == 1, (
            failed
        )  # no retry of a crash
        assert "segv.c3d" in failed["error"] and str(srv.data_dir) not in failed["error"]
    assert httpx.get(srv.url + "/healthz", timeout=30).status_code == 200
    nxt = submit(srv, "joy.fap", fap_file(data_dir).read_bytes(), format="fap")
    assert wait(srv, nxt["id"])["status"] == "done"


def test_a_worker_killed_by_a_fault_fails_the_job_at_once(tmp_path):
    import signal

    from facecast.server.jobs.manager import JobManager

    jobs = JobManager(tmp_path, workers=0)
    ids = []
    for _ in range(2):
        job_id = add_job(jobs.store, name="take.c3d", kind="mocap")
        jobs.store.claim(job_id)
        ids.append(job_id)
    jobs._worker_died(ids[0], -int(signal.SIGSEGV))
    crashed = jobs.store.get(ids[0])
    assert crashed.status == "failed" and "SIGSEGV" in crashed.error and "take.c3d" in crashed.error
    jobs._worker_died(ids[1], -int(signal.SIGTERM))  # killed from outside: tried again
    assert jobs.store.get(ids[1]).status == "queued"
    jobs.store.close()


def test_a_worker_memory_limit_turns_a_huge_allocation_into_a_memory_error():
    import subprocess
    import sys

    code = (
        "from facecast.server.jobs.worker import limit_resources; import resource, numpy as np; "
        "limit_resources(1024); "
        "assert resource.getrlimit(resource.RLIMIT_CORE)[0] == 0\n"
        "try:\n    np.ones(4 * 1024**3, dtype=np.uint8)\nexcept MemoryError:\n    print('memory error')"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and run.stdout.strip() == "memory error", run.stderr


def test_audio_job_with_its_transcript(srv, data_dir):
    """``text`` aligns an audio job's transcript; text that does not match fails the job with a
    clear error; text for other input, or empty text, is refused at submit."""
    import shutil

    if shutil.which("espeak-ng") is None:
        pytest.skip("espeak-ng is not installed (Debian package; CI has it)")
    wav = data_dir / "speech" / "bobby_16bit_16khz.wav"
    job = wait(
        srv,
        submit(srv, wav.name, wav.read_bytes(), format="fap", text="Bobby ripped the ledger.")[
            "id"
        ],
    )
    assert job["status"] == "done" and job["options"]["text"] == "Bobby ripped the ledger.", job
    wrong = "seven of the children said that their shoes were wet through"
    job = wait(srv, submit(srv, wav.name, wav.read_bytes(), format="fap", text=wrong)["id"])
    assert job["status"] == "failed" and "does not match the audio" in job["error"], job
    for name, content, text, message in (
        (fap_file(data_dir).name, fap_file(data_dir).read_bytes(), "hello", "audio input only"),
        (wav.name, wav.read_bytes(), "   ", "empty"),
    ):
        resp = cluster_support.submit(srv, name, content, text=text)
        assert 400 <= resp.status_code < 500 and message in resp.json()["error"], resp.text


def test_the_listing_reports_result_sizes_read_off_the_event_loop(tmp_path, monkeypatch):
    """``GET /v1/jobs`` and ``GET /v1/jobs/{id}`` give each done job's result size; the ``stat``
    (a network away on a shared results folder) runs in a thread, never on the event loop."""
    import asyncio

    from fastapi.testclient import TestClient

    from facecast.server.api.app import create_app
    from facecast.server.api.config import ServerConfig

    cfg = ServerConfig(data_dir=tmp_path, admin_key="k", job_workers=0, backend="numpy")
    app = create_app(cfg)
    store = app.state.jobs.store
    sizes = {}
    for k, n in enumerate((10, 2000, 0)):
        job_id = add_job(store, job_id=f"{k:032x}", options={"format": "glb"})
        store.finish(job_id, store.claim(job_id), "done")
        (store.folder(job_id) / "result.glb").write_bytes(b"x" * n)
        sizes[job_id] = n
    add_job(store, job_id=f"{9:032x}")  # a queued job has no result size
    on_loop: list[bool] = []
    result_path = store.result_path

    def watched(job):
        try:
            asyncio.get_running_loop()
            on_loop.append(True)
        except RuntimeError:
            on_loop.append(False)
        return result_path(job)

    monkeypatch.setattr(store, "result_path", watched)
    client = TestClient(app)
    listed = client.get("/v1/jobs", headers={"Authorization": "Bearer k"}).json()["jobs"]
    assert {j["id"]: j["result_bytes"] for j in listed} == {**sizes, f"{9:032x}": None}
    one = client.get(f"/v1/jobs/{0:032x}", headers={"Authorization": "Bearer k"}).json()
    assert one["result_bytes"] == 10
    assert on_loop and not any(on_loop)
