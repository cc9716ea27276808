"""Batch jobs on a real server: real FAP files in, valid results out; progress, cancel, failures, restarts."""
from __future__ import annotations

import io
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from conftest import RunningServer
from facecast.client.jobs import RemoteJobError, render_remote

FACE = "default:2k"


@pytest.fixture(scope="module")
def srv(tmp_path_factory) -> RunningServer:
    s = RunningServer(tmp_path_factory.mktemp("jobs"), "--face", FACE, "--workers", "1").start()
    yield s
    s.stop()


@pytest.fixture(scope="module")
def n_vertices(srv) -> int:
    return httpx.get(f"{srv.url}/v1/faces/{FACE}", timeout=120).json()["vertices"]


def fap_file(data_dir: Path, name: str = "joy.fap") -> Path:
    return data_dir / "xface" / "faps" / name


def submit(srv: RunningServer, name: str, content: bytes, **options) -> dict:
    resp = httpx.post(srv.url + "/v1/jobs", files={"file": (name, content)}, data={"face": FACE, **options},
                      headers=srv.admin_headers, timeout=60)
    assert resp.status_code == 202, resp.text
    assert resp.headers["location"] == f"/v1/jobs/{resp.json()['id']}"
    return resp.json()


def status(srv: RunningServer, job_id: str) -> dict:
    return httpx.get(f"{srv.url}/v1/jobs/{job_id}", headers=srv.admin_headers, timeout=30).json()


def wait(srv: RunningServer, job_id: str, until=("done", "failed", "cancelled"), polls: int = 6000) -> dict:
    for _ in range(polls):
        job = status(srv, job_id)
        if job["status"] in until:
            return job
        time.sleep(0.05)
    raise AssertionError(f"job {job_id} never reached {until}: {job}")


def test_fap_job_renders_a_valid_glb(srv, data_dir, n_vertices):
    import pygltflib

    src = fap_file(data_dir)
    job = submit(srv, src.name, src.read_bytes(), format="glb")
    assert job["status"] == "queued" and job["input_kind"] == "fap" and job["input_bytes"] == src.stat().st_size
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
    out = render_remote(srv.url, fap_file(data_dir, "anger.fap"), tmp_path / "anger.npz",
                        options={"face": FACE}, progress=lambda d, t: calls.append((d, t)),
                        admin_key=srv.admin_key)
    assert out == tmp_path / "anger.npz"
    assert calls and calls[-1] == (1000, 1000)
    done = [d for d, _ in calls]
    assert done == sorted(done) and all(t == 1000 for _, t in calls)
    with np.load(out) as npz:
        shapes = [npz[k].shape for k in npz.files]
    assert any(len(s) == 3 and s[1:] == (n_vertices, 3) for s in shapes), shapes
    assert sorted(p.name for p in tmp_path.iterdir()) == ["anger.npz"]  # no partial download left

    fap = render_remote(srv.url, fap_file(data_dir, "anger.fap"), tmp_path / "anger.fap",
                        options={"face": FACE}, admin_key=srv.admin_key)
    reread = read_fap(fap.read_text(), where=str(fap))
    original = read_fap(fap_file(data_dir, "anger.fap").read_text())
    assert len(reread.frames if hasattr(reread, "frames") else reread.values) == \
        len(original.frames if hasattr(original, "frames") else original.values)


def test_render_cli_with_server_option(srv, data_dir, tmp_path):
    import os
    import subprocess
    import sys

    out = tmp_path / "joy.fap"
    env = {**os.environ, "FACECAST_ADMIN_KEY": srv.admin_key}
    run = subprocess.run([sys.executable, "-m", "facecast.server.cli", "render", str(fap_file(data_dir)), "-o",
                          str(out), "--face", FACE, "--server", srv.url], env=env, capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert out.read_text().lstrip().startswith(("#", "2.1"))
    env["FACECAST_ADMIN_KEY"] = "wrong"
    run = subprocess.run([sys.executable, "-m", "facecast.server.cli", "render", str(fap_file(data_dir)), "-o",
                          str(tmp_path / "x.fap"), "--face", FACE, "--server", srv.url], env=env,
                         capture_output=True, text=True, timeout=300)
    last = run.stderr.strip().splitlines()[-1]
    assert run.returncode == 2 and last.startswith("facecast:") and "admin key" in last


def test_speech_upload_recognised_by_content_becomes_a_fap_stream(srv, data_dir):
    from facecast.protocol.fap_file import read_fap

    wav = data_dir / "speech" / "bobby_16bit_16khz.wav"
    job = submit(srv, "recording", wav.read_bytes(), format="fap")  # no suffix: sniffed as RIFF/WAVE
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
    with pytest.raises(RemoteJobError, match="broken.fap"):
        render_remote(srv.url, tmp_path / "broken.fap", tmp_path / "out.glb", options={"face": FACE},
                      admin_key=srv.admin_key)
    assert not (tmp_path / "out.glb").exists()
    # The worker survives bad input: the next job still runs.
    with pytest.raises(RemoteJobError, match="admin key"):
        render_remote(srv.url, tmp_path / "broken.fap", tmp_path / "out.glb", options={"face": FACE},
                      admin_key="wrong")


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
    first = RunningServer(tmp_path, "--face", FACE, "--workers", "0").start()
    try:
        job = submit(first, src.name, src.read_bytes(), format="npz")
        assert status(first, job["id"])["status"] == "queued"
    finally:
        first.stop()
    second = RunningServer(tmp_path, "--face", FACE, "--workers", "1").start()
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
    first = RunningServer(tmp_path, "--face", FACE, "--workers", "1").start()
    try:
        job = submit(first, src.name, src.read_bytes(), format="glb")
        # A fresh worker spends seconds starting (imports, face, device) while the job is running.
        seen = wait(first, job["id"], until=("running", "done", "failed"))
        assert seen["status"] == "running", seen
    finally:
        first.stop()
    second = RunningServer(tmp_path, "--face", FACE, "--workers", "1").start()
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
    from facecast.server.jobs.store import JobStore, new_job_id

    class RecordingStore(JobStore):
        def progress(self, job_id, attempt, fraction):
            seen.append(fraction)
            return super().progress(job_id, attempt, fraction)

    seen: list[float] = []
    monkeypatch.setattr(worker, "PROGRESS_INTERVAL", 0.0)
    store = RecordingStore(tmp_path)
    job_id = new_job_id()
    store.folder(job_id).mkdir(parents=True)
    src = fap_file(data_dir, "happy-for.fap")
    (store.folder(job_id) / "input.fap").write_bytes(src.read_bytes())
    store.add(job_id, input_name=src.name, input_kind="fap", input_file="input.fap", input_bytes=1,
              result_file="result.npz", options={"format": "npz", "face_spec": FACE, "engine": "fp"})
    attempt = store.claim(job_id)
    worker.run_job(store, job_id, attempt, "numpy", None, None, OrderedDict())
    job = store.get(job_id)
    assert job.status == "done" and job.progress == 1.0
    assert len(set(seen)) >= 3 and seen == sorted(seen) and seen[-1] == 1.0 and seen[0] < 0.5  # batches of frames
    assert store.result_path(job).is_file()
    # A cancelled job stops at its next progress report and records nothing more.
    job2 = new_job_id()
    store.folder(job2).mkdir(parents=True)
    (store.folder(job2) / "input.fap").write_bytes(src.read_bytes())
    store.add(job2, input_name=src.name, input_kind="fap", input_file="input.fap", input_bytes=1,
              result_file="result.npz", options={"format": "npz", "face_spec": FACE, "engine": "fp"})
    attempt = store.claim(job2)
    store.cancel(job2)
    seen.clear()
    worker.run_job(store, job2, attempt, "numpy", None, None, OrderedDict())
    assert store.get(job2).status == "cancelled"
    assert not store.result_path(store.get(job2)).exists()
    store.close()


def test_store_purges_only_old_finished_jobs(tmp_path):
    from facecast.server.jobs.store import JobStore, new_job_id

    store = JobStore(tmp_path)
    ids = {}
    for state in ("done", "failed", "cancelled", "queued", "running"):
        job_id = new_job_id()
        store.folder(job_id).mkdir(parents=True)
        (store.folder(job_id) / "input.fap").write_text("x")
        store.add(job_id, input_name="a.fap", input_kind="fap", input_file="input.fap", input_bytes=1,
                  result_file="result.glb", options={})
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
    assert sorted(p.name for p in (tmp_path / "jobs").iterdir()) == sorted([ids["queued"], ids["running"]])
    store.close()
