"""BML performances: where the text's sync marks land on real speech, and what each step costs.

    python bench/bml_perform.py [--repeat 200] [--fps 25]

On the real recording ``speech/bobby_16bit_16khz.wav`` ("Bobby ripped the ledger", word times in
``bobby_words.TextGrid``), a BML speech with a ``<sync>`` mark before every word is timed by the
transcript's forced alignment (``server/bml/speech.py``) and by the fallback spread by characters;
the error of each mark against the TextGrid's word onset is reported (target: within one frame,
40 ms at 25 fps). Costs: parsing a BML document (the fuzz seed of ``bench/fuzz_parsers.py``),
scheduling it, lip-sync with the transcript, and mixing the performance's layers per frame
(``render_performance``: speech, expression, gaze with head, nod). Writes ``bench/out/bml_perform.json``
and prints a table, with the machine's load.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent
OUT = ROOT / "out" / "bml_perform.json"
WORDS = ("BOBBY", "RIPPED", "THE", "LEDGER")


def word_onsets(textgrid: Path) -> dict[str, float]:
    text = textgrid.read_text()
    out = {}
    for w in WORDS:
        i = text.index(f'text = "{w}"')
        out[w] = float(text[:i].rsplit("xmin =", 1)[1].split()[0])
    return out


def per_call(fn, repeat: int) -> float:
    """Mean seconds per call of ``fn`` over ``repeat`` calls (after one warm-up)."""
    fn()
    t0 = time.perf_counter()
    for _ in range(repeat):
        fn()
    return (time.perf_counter() - t0) / repeat


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeat", type=int, default=200)
    p.add_argument("--fps", type=float, default=25.0)
    a = p.parse_args(argv)

    from facecast.protocol.bml import parse_bml
    from facecast.server.audio.driver import track_states
    from facecast.server.bml.perform import render_performance
    from facecast.server.bml.schedule import schedule
    from facecast.server.bml.speech import char_marks, lipsync_speech
    from facecast.server.paths import shared_data

    sys.path.insert(0, str(ROOT))
    from fuzz_parsers import BML_SEED

    data = shared_data()
    if data is None:
        print("../shared/data is missing", file=sys.stderr)
        return 2
    wav = data / "speech" / "bobby_16bit_16khz.wav"
    truth = word_onsets(data / "speech" / "bobby_words.TextGrid")
    load_before = os.getloadavg()

    doc = (
        '<bml id="b"><speech id="s1" audio="bobby.wav"><text>'
        + " ".join(f'<sync id="m{i}"/>{w.lower()}' for i, w in enumerate(WORDS))
        + '</text></speech><faceLexeme id="f1" lexeme="JOY" start="s1:m2" end="s1:end"/>'
        '<gaze id="g1" target="camera" influence="HEAD" offsetAngle="15" start="0" end="s1:m3"/>'
        '<head id="h1" lexeme="NOD" start="g1:end"/></bml>'
    )
    block = parse_bml(doc)
    speech = block.behaviours[0]
    t0 = time.perf_counter()
    spoken = lipsync_speech(speech, wav, a.fps)  # type: ignore[arg-type]
    lipsync_s = time.perf_counter() - t0
    aligned = spoken.timing.marks
    chars = char_marks(speech, spoken.lipsync)  # type: ignore[arg-type]
    rows = {}
    for how, marks in (("aligned", aligned), ("characters", chars)):
        err = [abs(marks[f"m{i}"] - truth[w]) * 1000 for i, w in enumerate(WORDS)]
        rows[how] = {"mean_ms": float(np.mean(err)), "max_ms": float(np.max(err))}

    seed_block = parse_bml(BML_SEED)
    parse_s = per_call(lambda: parse_bml(BML_SEED), a.repeat)
    from facecast.server.bml.schedule import SpeechTiming

    timing = {"s1": SpeechTiming(2.0, {"tm1": 0.5, "tm2": 1.2})}
    schedule_s = per_call(lambda: schedule(seed_block, timing), a.repeat)
    perf = schedule(block, {"s1": spoken.timing})
    states = {"s1": track_states(spoken.lipsync)}
    n_frames = int(perf.duration * a.fps) + 1
    mix_s = per_call(lambda: render_performance(perf, states, a.fps), max(1, a.repeat // 20))
    result = {
        "recording": wav.name,
        "fps": a.fps,
        "mark_error_vs_textgrid": rows,
        "frame_ms": 1000 / a.fps,
        "parse_us": parse_s * 1e6,
        "bml_bytes": len(BML_SEED),
        "schedule_us": schedule_s * 1e6,
        "lipsync_with_transcript_ms": lipsync_s * 1000,
        "audio_seconds": spoken.timing.duration,
        "mix_us_per_frame": mix_s / n_frames * 1e6,
        "layers": 4,
        "load_before": load_before,
        "load_after": os.getloadavg(),
        "cpus": os.cpu_count(),
    }
    OUT.parent.mkdir(exist_ok=True)
    OUT.write_text(json.dumps(result, indent=2))
    print(
        f"load average before {load_before}, after {result['load_after']} ({os.cpu_count()} CPUs)\n"
    )
    print(
        "| marks timed by | mean error (ms) | max error (ms) | one frame (ms) |\n|---|---:|---:|---:|"
    )
    for how, r in rows.items():
        print(f"| {how} | {r['mean_ms']:.1f} | {r['max_ms']:.1f} | {1000 / a.fps:.0f} |")
    print(
        f"\nparse {result['parse_us']:.0f} µs ({len(BML_SEED)} B, 8 behaviours), schedule "
        f"{result['schedule_us']:.0f} µs, lip-sync with transcript {lipsync_s * 1000:.0f} ms for "
        f"{spoken.timing.duration:.2f} s, mixing {result['mix_us_per_frame']:.0f} µs/frame (4 layers)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
