"""Robustness against hostile input (issue 12): fuzzed parsers, 5xx from a real server, a flooding
producer, peak server memory on the largest uploads, and large .glb files checked.

    python bench/robustness.py [--fuzz N] [--http N] [--jobs N] [--memory [KIND ...]]
                               [--flood] [--glb] [--all] [--seed S]

Each part runs only when asked (``--all``: every part); nothing is estimated or filled in: a part
that cannot run says why.

- ``--fuzz N``: N mutated inputs per parser. Audio (WAV/FLAC/OGG made with soundfile from the
  speech in ``../shared/data``, or a tone without it) goes through ``decode_audio`` in a child
  process so a crash (signal) or a hang (no progress for ``HANG_S``) is counted, not fatal. The
  other parsers come from ``bench/fuzz_parsers.py``'s ``fuzz_counts(parser, n, seed)`` when that
  file exists.
- ``--http N``: N mutated files (audio, FAP, C3D and TRC with a layout) through ``/play`` of a real
  ``facecast serve`` on a free loopback port, and ``--jobs N`` as batch jobs; counts the answers by
  class, and the crashes and hangs of the server (it is restarted after each).
- ``--memory``: peak RSS of the server process (sampled every 20 ms from ``/proc``) while it decodes
  the largest allowed upload of each kind through ``/play`` (``wav``, ``flac``, ``fap``, ``trc``;
  ``wav60x4``: four 60 MiB WAVs at once, the case in the issue).
- ``--flood``: ``bench/flood.py``'s ``run_flood`` (another session's fps and p95 while a producer
  floods), when that file exists.
- ``--glb``: ``bench/gltf_encode.py``'s ``glb_check`` for ``default:200k`` and ``default:500k``,
  when it exists.

Writes ``bench/out/robustness.json`` and ``bench/out/robustness.md`` (the table it prints), with
the load average.
"""

from __future__ import annotations

import argparse
import inspect
import io
import json
import os
import select
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from facecast.server.harness import LocalServer

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "bench" / "out" / "robustness.json"
sys.path.insert(0, str(ROOT / "bench"))  # sibling benches: fuzz_parsers, flood, gltf_encode

#: Parsers fuzzed by ``bench/fuzz_parsers.py`` (the audio decoder is fuzzed here).
PARSERS = ("c3d", "trc", "csv", "fap", "annotation", "bml")
#: Seconds without progress after which a fuzzed decode or a request counts as a hang.
HANG_S = 20.0
REQUEST_TIMEOUT = 60.0
ADMIN_KEY = "bench-robustness-key"


def optional(module: str, attr: str):
    """``module.attr`` from a sibling bench, or None when the file or the function is absent."""
    try:
        return getattr(__import__(module), attr, None)
    except ImportError:
        return None


def call_with(fn, **available):
    """Call ``fn`` with the keyword arguments its signature names (others are its defaults)."""
    names = inspect.signature(fn).parameters
    return fn(**{k: v for k, v in available.items() if k in names})


# ---- inputs ----


def speech() -> tuple[np.ndarray, int, str]:
    """Real speech (``../shared/data/speech``) or, without the data, a voiced synthetic tone."""
    import soundfile as sf

    from facecast.server.paths import shared_data

    d = shared_data()
    if d is not None and (d / "speech" / "bobby_16bit_16khz.wav").is_file():
        x, sr = sf.read(str(d / "speech" / "bobby_16bit_16khz.wav"))
        return x, sr, "speech/bobby_16bit_16khz.wav"
    t = np.arange(19000) / 16000
    return (
        0.3 * np.sin(2 * np.pi * 140 * t) * (1 + np.sin(2 * np.pi * 3 * t)) / 2,
        16000,
        "synthetic tone",
    )


def audio_seeds(x: np.ndarray, sr: int) -> list[tuple[str, bytes]]:
    """Small real files to mutate: WAV (16-bit, float, 8-bit stereo), FLAC (16, 24-bit stereo), OGG."""
    import soundfile as sf

    x = x[:3000]
    out = []
    for name, data, fmt, subtype in (
        ("a.wav", x, "WAV", "PCM_16"),
        ("b.wav", x, "WAV", "FLOAT"),
        ("c.wav", np.stack([x, x], 1), "WAV", "PCM_U8"),
        ("d.flac", x, "FLAC", "PCM_16"),
        ("e.flac", np.stack([x, -x], 1), "FLAC", "PCM_24"),
        ("f.ogg", x, "OGG", "VORBIS"),
    ):
        buf = io.BytesIO()
        sf.write(buf, data, sr, format=fmt, subtype=subtype)
        out.append((name, buf.getvalue()))
    return out


def mutate(data: bytes, rng: np.random.Generator) -> bytes:
    """1-8 random edits: byte changes (often in the header), 32-bit field overwrites, inserts, a cut."""
    b = bytearray(data)
    for _ in range(int(rng.integers(1, 9))):
        op = rng.random()
        if not b:
            b = bytearray(rng.integers(0, 256, 16, dtype=np.uint8).tobytes())
        if op < 0.45:
            i = (
                int(rng.integers(0, min(len(b), 128)))
                if rng.random() < 0.6
                else int(rng.integers(0, len(b)))
            )
            b[i] = int(rng.integers(0, 256))
        elif op < 0.65:
            i = int(rng.integers(0, max(1, len(b) - 4)))
            word = [0, 1, 0xFFFF, 0x7FFFFFFF, 0xFFFFFFFF, 0x80000000][int(rng.integers(0, 6))]
            b[i : i + 4] = word.to_bytes(4, "little")
        elif op < 0.8:
            i = int(rng.integers(0, len(b) + 1))
            b[i:i] = rng.integers(0, 256, int(rng.integers(1, 9)), dtype=np.uint8).tobytes()
        else:
            b = b[: int(rng.integers(0, len(b) + 1))]
    return bytes(b)


def take_seeds() -> tuple[dict[str, bytes], str]:
    """A small valid marker take as C3D (ezc3d's writer) and TRC, and its layout as JSON."""
    from facecast.server.faces import load_face
    from facecast.server.mocap.io import write_take
    from facecast.server.mocap.synthetic import synthetic_take

    syn = synthetic_take(load_face("default"), n_markers=16, seconds=1.0, fps=60.0, seed=3)
    files = {}
    with tempfile.TemporaryDirectory() as tmp:
        for suffix in (".c3d", ".trc"):
            files["take" + suffix] = write_take(
                syn.take, Path(tmp) / ("take" + suffix)
            ).read_bytes()
    return files, json.dumps(syn.layout)


def fap_seed() -> bytes:
    """A real FAP file (XFace's joy.fap) or, without the data, a generated two-frame one."""
    from facecast.server.paths import shared_data

    d = shared_data()
    if d is not None and (d / "xface" / "faps" / "joy.fap").is_file():
        return (d / "xface" / "faps" / "joy.fap").read_bytes()
    mask = b" ".join([b"0", b"0", b"1"] + [b"0"] * 65)
    return b"2.1 gen 25 2\n" + mask + b"\n0 300\n" + mask + b"\n1 -200\n"


# ---- audio fuzz in a child process ----


def _audio_child(seed: int, start: int, n: int) -> None:
    """Decode mutated inputs ``start..n-1``; print ``i outcome`` for each before and after."""
    import logging

    logging.disable(logging.WARNING)  # clipping warnings of mutated files are expected
    from facecast.server.audio.io import decode_audio
    from facecast.server.errors import FacecastError

    x, sr, _ = speech()
    seeds = audio_seeds(x, sr)
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(start, n):
            rng = np.random.default_rng([seed, i])
            name, data = seeds[int(rng.integers(0, len(seeds)))]
            path = Path(tmp) / name
            path.write_bytes(mutate(data, rng))
            print(i, "start", flush=True)
            try:
                decode_audio(path, 10000, max_seconds=600)
                outcome = "parsed"
            except FacecastError:
                outcome = "project_errors"
            except Exception as e:  # noqa: BLE001 - counted: any other exception is a bug
                outcome = "other_errors:" + type(e).__name__
            print(i, outcome, flush=True)


def audio_fuzz(n: int, seed: int) -> dict:
    """Counts over ``n`` mutated audio files, keyed as ``fuzz_parsers.fuzz_counts``: parsed,
    project_errors, other_errors (any other exception), crashes (the child died by a signal) and
    hangs (no progress for ``HANG_S``)."""
    counts = {
        "parser": "audio",
        "inputs": 0,
        "crashes": 0,
        "hangs": 0,
        "project_errors": 0,
        "parsed": 0,
        "other_errors": 0,
    }
    others: dict[str, int] = {}
    t0 = time.monotonic()
    start = 0
    while start < n:
        p = subprocess.Popen(
            [sys.executable, __file__, "--_audio-child", str(seed), str(start), str(n)],
            stdout=subprocess.PIPE,
            text=True,
        )
        current, last, hung = start, time.monotonic(), False
        while True:
            ready, _, _ = select.select([p.stdout], [], [], 1.0)
            if ready:
                line = p.stdout.readline()
                if not line:
                    break
                i, outcome = line.split()
                current, last = int(i), time.monotonic()
                if outcome == "start":
                    continue
                counts["inputs"] += 1
                kind, _, detail = outcome.partition(":")
                counts[kind] += 1
                if detail:
                    others[detail] = others.get(detail, 0) + 1
                current += 1
            elif time.monotonic() - last > HANG_S:
                p.kill()
                counts["hangs"] += 1
                counts["inputs"] += 1
                current, hung = current + 1, True
                break
        code = p.wait()
        if code != 0 and not hung and current < n:  # died during input `current`
            counts["crashes"] += 1
            counts["inputs"] += 1
            current += 1
        start = current
    counts["other_types"] = others
    counts["seconds"] = round(time.monotonic() - t0, 1)
    return counts


# ---- a real server ----


class Server(LocalServer):
    """``facecast serve`` in a subprocess on a free loopback port (the shared harness), restartable."""

    def __init__(self, data_dir: Path, env: dict | None = None) -> None:
        super().__init__(data_dir, env=env, admin_key=ADMIN_KEY)
        self.restarts = 0

    @property
    def headers(self) -> dict:
        return self.admin_headers

    def start(self, timeout: float = 180.0, *, ready: bool = False) -> Server:
        super().start(timeout, ready=ready)
        return self

    def restart(self) -> None:
        self.kill()
        self.restarts += 1
        self.start()

    def session(self) -> dict:
        import httpx

        r = httpx.post(
            self.url + "/v1/sessions",
            json={"input": "fap", "fps": 30},
            headers=self.headers,
            timeout=REQUEST_TIMEOUT,
        )
        r.raise_for_status()
        return r.json()


def http_inputs(seed: int):
    """Endless ``(kind, filename, content, layout or None)`` mutated inputs, cycling over the kinds."""
    x, sr, _ = speech()
    audio = audio_seeds(x, sr)
    takes, layout = take_seeds()
    kinds = (
        [(n, d, None) for n, d in audio[:1] + audio[3:4]]
        + [("joy.fap", fap_seed(), None)]
        + [(n, d, layout) for n, d in takes.items()]
    )
    i = 0
    while True:
        rng = np.random.default_rng([seed, i])
        name, data, lay = kinds[i % len(kinds)]
        yield name.rsplit(".", 1)[1], name, mutate(data, rng), lay
        i += 1


def _classify(server: Server, send) -> str:
    """``2xx`` / ``4xx`` / ``5xx`` for the answer of ``send()``, else ``crash`` or ``hang`` (the server
    is restarted)."""
    import httpx

    try:
        code = send().status_code
        return f"{code // 100}xx"
    except httpx.HTTPError:
        outcome = (
            "crash"
            if server.proc.poll() is not None
            else ("hang" if not server.healthy() else "timeout")
        )
        if outcome != "timeout":
            server.restart()
        return outcome


def http_fuzz(n_play: int, n_jobs: int, seed: int) -> dict:
    """Mutated files through ``/play`` and as jobs on a real server; answers by class per kind."""
    import httpx

    out: dict = {"play": {}, "jobs": {}}
    with tempfile.TemporaryDirectory() as tmp:
        server = Server(Path(tmp)).start()
        try:
            inputs = http_inputs(seed)
            target = server.session()
            for _ in range(n_play):
                kind, name, content, layout = next(inputs)
                url = f"{server.url}/v1/sessions/{target['id']}/play"

                def send():
                    return httpx.post(
                        url,
                        files={"file": (name, content)},
                        data={"layout": layout} if layout else {},
                        headers=server.headers,
                        timeout=REQUEST_TIMEOUT,
                    )

                outcome = _classify(server, send)
                if outcome in ("crash", "hang"):
                    target = server.session()
                row = out["play"].setdefault(kind, {})
                row[outcome] = row.get(outcome, 0) + 1
            for _ in range(n_jobs):
                kind, name, content, layout = next(inputs)
                job: dict = {}

                def submit():
                    r = httpx.post(
                        server.url + "/v1/jobs",
                        files={"file": (name, content)},
                        data={"format": "fap", **({"layout": layout} if layout else {})},
                        headers=server.headers,
                        timeout=REQUEST_TIMEOUT,
                    )
                    job.update(r.json() if r.status_code == 202 else {})
                    return r

                outcome = _classify(server, submit)
                if outcome == "2xx" and job.get("id"):
                    deadline = time.monotonic() + 180
                    while True:
                        st = httpx.get(
                            f"{server.url}/v1/jobs/{job['id']}",
                            headers=server.headers,
                            timeout=REQUEST_TIMEOUT,
                        )
                        if st.status_code >= 500:
                            outcome = "5xx"
                            break
                        status = st.json().get("status")
                        if status in ("done", "failed", "cancelled"):
                            outcome = f"job {status}"
                            break
                        if time.monotonic() > deadline:
                            outcome = "job stuck"
                            httpx.delete(
                                f"{server.url}/v1/jobs/{job['id']}",
                                headers=server.headers,
                                timeout=30,
                            )
                            break
                        time.sleep(0.3)
                row = out["jobs"].setdefault(kind, {})
                row[outcome] = row.get(outcome, 0) + 1
            out["server_restarts"] = server.restarts
        finally:
            server.stop()
    return out


# ---- peak server memory on the largest uploads ----


def big_file(kind: str, size: int, max_seconds: float, tmp: Path) -> Path:
    """A valid upload of about ``size`` bytes of ``kind``, built from the real inputs."""
    import soundfile as sf

    if kind in ("wav", "wav60x4"):
        x, sr, _ = speech()
        n = min((size - 1024) // 2, int(max_seconds * sr))
        path = tmp / f"{kind}.wav"
        sf.write(path, np.resize(x, n), sr, subtype="PCM_16")
    elif kind == "flac":
        x, sr, _ = speech()
        path = tmp / "big.flac"
        rng = np.random.default_rng(0)
        with sf.SoundFile(path, "w", sr, 1, format="FLAC", subtype="PCM_16") as f:
            written, block = 0, sr * 60
            while written < max_seconds * sr and (
                written == 0 or path.stat().st_size < size - 2**20
            ):
                k = int(min(block, max_seconds * sr - written))
                f.write(np.resize(x, k) * (0.5 + rng.random()))  # vary the level so blocks differ
                written += k
    elif kind == "fap":
        head, *lines = fap_seed().decode().splitlines()
        parts = head.split()
        body, used, i = [], 200, 0
        while True:  # the clip's frames again and again, renumbered into one long clip
            mask, frame = lines[2 * (i % (len(lines) // 2))], lines[2 * (i % (len(lines) // 2)) + 1]
            text = f"{mask}\n{i} {frame.split(maxsplit=1)[1]}\n"
            if used + len(text) > size:
                break
            body.append(text)
            used += len(text)
            i += 1
        path = tmp / "big.fap"
        path.write_text(" ".join(parts[:3] + [str(i)]) + "\n" + "".join(body))
    elif kind == "trc":
        from facecast.protocol.markers_file import MarkerTake, write_trc

        take = _trc_take().take
        row_bytes = len(write_trc(take).encode()) / len(take.xyz)
        t = int(size / row_bytes * 0.95)
        big = MarkerTake(
            take.names, np.resize(take.xyz, (t, *take.xyz.shape[1:])), take.fps, take.units, 0.0
        )
        path = tmp / "big.trc"
        path.write_text(write_trc(big))
    else:
        raise ValueError(kind)
    return path


def _trc_take():
    from facecast.server.faces import load_face
    from facecast.server.mocap.synthetic import synthetic_take

    return synthetic_take(load_face("default"), n_markers=16, seconds=2.0, fps=60.0, seed=3)


def warm_up(server: Server, kind: str) -> None:
    """Play a small valid file of ``kind`` once, so the peak that follows is the big upload's."""
    import httpx

    x, sr, _ = speech()
    if kind in ("wav", "flac", "wav60x4"):
        name, data, layout = audio_seeds(x, sr)[0 if kind != "flac" else 3] + (None,)
    elif kind == "fap":
        name, data, layout = "joy.fap", fap_seed(), None
    else:
        syn = _trc_take()
        from facecast.protocol.markers_file import write_trc

        name, data, layout = "take.trc", write_trc(syn.take).encode(), json.dumps(syn.layout)
    s = server.session()
    r = httpx.post(
        f"{server.url}/v1/sessions/{s['id']}/play",
        headers=server.headers,
        files={"file": (name, data)},
        data={"layout": layout} if layout else {},
        timeout=REQUEST_TIMEOUT,
    )
    r.raise_for_status()
    time.sleep(2.0)


def peak_memory(kinds: list[str], timeout: float) -> list[dict]:
    """Peak RSS of a fresh server while it decodes each kind's largest allowed upload via ``/play``."""
    import httpx

    from facecast.server.api.config import ServerConfig
    from facecast.server.audio.io import max_audio_seconds

    cfg = ServerConfig()
    rows = []
    for kind in kinds:
        input_kind = {"fap": "fap", "trc": "markers"}.get(kind, "audio")
        # the limit of this kind of upload where the server has one, else the general one
        limit = (
            cfg.upload_limit(input_kind)[0]
            if hasattr(cfg, "upload_limit")
            else cfg.max_upload_bytes
        )
        with tempfile.TemporaryDirectory() as tmp:
            tmp = Path(tmp)
            size = 60 * 2**20 if kind == "wav60x4" else int(limit) - 4096
            path = big_file(kind, size, max_audio_seconds(), tmp)
            layout = json.dumps(_trc_take().layout) if kind == "trc" else None
            server = Server(tmp).start()
            try:
                start_rss = server.rss()
                warm_up(
                    server, kind
                )  # imports, the face and the lip-sync net: not the upload's cost
                base = server.rss()
                peak, stop = [base], threading.Event()

                def sample():
                    while not stop.wait(0.02):
                        try:
                            peak[0] = max(peak[0], server.rss())
                        except OSError:
                            return

                th = threading.Thread(target=sample, daemon=True)
                th.start()
                copies = 4 if kind == "wav60x4" else 1
                answers: list = []

                def play():
                    s = server.session()
                    try:
                        with open(path, "rb") as fh:
                            r = httpx.post(
                                f"{server.url}/v1/sessions/{s['id']}/play",
                                headers=server.headers,
                                files={"file": (path.name, fh)},
                                data={"layout": layout} if layout else {},
                                timeout=timeout,
                            )
                        answers.append(r.status_code)
                    except httpx.HTTPError as e:
                        answers.append(type(e).__name__)

                t0 = time.monotonic()
                workers = [threading.Thread(target=play) for _ in range(copies)]
                for w in workers:
                    w.start()
                for w in workers:
                    w.join()
                seconds = time.monotonic() - t0
                stop.set()
                th.join()
                rows.append(
                    {
                        "kind": kind,
                        "file_mib": round(path.stat().st_size / 2**20, 1),
                        "concurrent": copies,
                        "start_mb": round(start_rss / 2**20),
                        "base_mb": round(base / 2**20),
                        "peak_mb": round(peak[0] / 2**20),
                        "answers": answers,
                        "seconds": round(seconds, 1),
                        "load_avg": os.getloadavg(),
                    }
                )
                print(rows[-1], flush=True)
            finally:
                server.stop()
    return rows


# ---- report ----


def table(rec: dict) -> str:
    lines = [
        f"robustness — load average {rec['load_avg'][0]:.1f} (start) / {os.getloadavg()[0]:.1f} (end)",
        "",
    ]
    if "fuzz" in rec:
        lines += [
            "| parser | inputs | parsed | project errors | other exceptions | crashes | hangs |",
            "|---|---|---|---|---|---|---|",
        ]
        for name, c in rec["fuzz"].items():
            if not isinstance(c, dict) or "inputs" not in c:
                lines.append(f"| {name} | {c} | | | | | |")
                continue
            lines.append(
                f"| {name} | {c['inputs']} | {c.get('parsed')} | {c.get('project_errors')} "
                f"| {c.get('other_errors')} | {c.get('crashes')} | {c.get('hangs')} |"
            )
        lines.append("")
    if "http" in rec:
        lines += ["| endpoint | kind | answers |", "|---|---|---|"]
        for ep in ("play", "jobs"):
            for kind, row in rec["http"][ep].items():
                lines.append(
                    f"| {ep} | {kind} | {', '.join(f'{k}: {v}' for k, v in sorted(row.items()))} |"
                )
        lines += [f"\nserver restarts (crash or hang): {rec['http'].get('server_restarts')}", ""]
    if "memory" in rec:
        lines += [
            "| upload | MiB | concurrent | server RSS at start | warmed up | peak | answers | s |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for r in rec["memory"]:
            lines.append(
                f"| {r['kind']} | {r['file_mib']} | {r['concurrent']} | {r['start_mb']} MB | {r['base_mb']} MB "
                f"| {r['peak_mb']} MB "
                f"| {r['answers']} | {r['seconds']} |"
            )
        lines.append("")
    for part in ("flood", "glb"):
        if part in rec:
            lines.append(f"{part}: {json.dumps(rec[part])}")
    return "\n".join(lines)


def parse(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--fuzz", type=int, default=0, metavar="N", help="mutated inputs per parser")
    p.add_argument("--http", type=int, default=0, metavar="N", help="mutated files through /play")
    p.add_argument("--jobs", type=int, default=0, metavar="N", help="mutated files as batch jobs")
    p.add_argument(
        "--memory",
        nargs="*",
        default=None,
        metavar="KIND",
        help="peak server RSS on the largest upload of each kind (default: wav flac fap wav60x4)",
    )
    p.add_argument("--memory-timeout", type=float, default=600.0, help="seconds per upload")
    p.add_argument("--flood", action="store_true", help="bench/flood.py's run_flood")
    p.add_argument(
        "--glb", action="store_true", help="bench/gltf_encode.py's glb_check at 200k and 500k"
    )
    p.add_argument("--all", action="store_true", help="every part (fuzz 2000, http 300, jobs 30)")
    p.add_argument("--seed", type=int, default=12)
    p.add_argument("--out", type=Path, default=OUT)
    a = p.parse_args(argv)
    if a.all:
        a.fuzz, a.http, a.jobs = a.fuzz or 2000, a.http or 300, a.jobs or 30
        a.memory = a.memory if a.memory is not None else []
        a.flood = a.glb = True
    if a.memory == []:
        a.memory = ["wav", "flac", "fap", "wav60x4"]
    return a


def main(argv: list[str]) -> int:
    if argv[:1] == ["--_audio-child"]:
        _audio_child(*map(int, argv[1:4]))
        return 0
    args = parse(argv)
    rec: dict = {"load_avg": os.getloadavg(), "seed": args.seed, "cpus": os.cpu_count()}
    if args.fuzz:
        rec["fuzz"] = {"audio": audio_fuzz(args.fuzz, args.seed)}
        rec["fuzz"]["audio"]["source"] = speech()[2]
        fuzz_counts = optional("fuzz_parsers", "fuzz_counts")
        for name in optional("fuzz_parsers", "PARSERS") or PARSERS:
            rec["fuzz"][name] = (
                fuzz_counts(name, args.fuzz, args.seed)
                if fuzz_counts
                else "not run: bench/fuzz_parsers.py (fuzz_counts) is not here"
            )
    if args.http or args.jobs:
        rec["http"] = http_fuzz(args.http, args.jobs, args.seed)
    if args.memory:
        rec["memory"] = peak_memory(args.memory, args.memory_timeout)
    if args.flood:
        run_flood = optional("flood", "run_flood")
        rec["flood"] = (
            {
                "binary FAP": call_with(run_flood, json_frames=False),
                "JSON FAP": call_with(run_flood, json_frames=True),
            }
            if run_flood
            else "not run: bench/flood.py (run_flood) is not here"
        )
    if args.glb:
        glb_check = optional("gltf_encode", "glb_check")
        rec["glb"] = (
            {spec: glb_check(spec) for spec in ("default:200k", "default:500k")}
            if glb_check
            else "not run: bench/gltf_encode.py has no glb_check"
        )
    rec["load_avg_end"] = os.getloadavg()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(rec, indent=1, default=str) + "\n")
    text = table(rec)
    args.out.with_suffix(".md").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
