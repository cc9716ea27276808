"""Batch lip-sync speed and output check: ``python bench/lipsync/batch_speed.py [--save F | --compare F]``.

Runs ``pipeline.lipsync`` (the ``facecast lipsync`` path, shipped network) over real recordings
from ``../shared/data/real-speech`` and reports process-time × real time (1 core, best of
``--repeat``) with the load average. ``--save`` writes every recording's class probabilities and
visemes to an ``.npz``; ``--compare`` checks this code's output against such a file (max abs
difference of the probabilities, visemes identical or not). To time two versions in one run,
export the old code and run this script under both (``PYTHONPATH``), alternating; results go to
``bench/out/lipsync_batch_speed.json``.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):  # one core
    os.environ.setdefault(_v, "1")

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from facecast.server.audio.classify import FrameNet
from facecast.server.audio.io import read_audio
from facecast.server.audio.pipeline import lipsync
from facecast.server.paths import shared_data

#: Recordings timed (four speakers, about 48 s in all).
FILES = (
    "mfa-tests/acoustic_corpus.wav",
    "sphinx4-digits/10001-90210-01803.wav",
    "pocketsphinx-librivox/sense_and_sensibility_01_austen_64kb-0870.wav",
    "coqui-ljspeech/LJ001-0001.wav",
)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--save", type=Path)
    ap.add_argument("--compare", type=Path)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--label", default="current")
    ap.add_argument("--net", type=Path, help="frame network file (default: the shipped one)")
    a = ap.parse_args()
    net = FrameNet.load(a.net) if a.net else None
    data = shared_data()
    root = data / "real-speech" if data else Path("/nonexistent")
    clips = [(f, *read_audio(root / f)) for f in FILES if (root / f).is_file()]
    if not clips:
        print(f"no recordings under {root}", file=sys.stderr)
        return 2
    dur = sum(len(x) / sr for _, x, sr in clips)
    for _, x, sr in clips[:1]:
        lipsync(x, sr, net=net)  # load the network, warm caches
    best, outs = np.inf, {}
    for _ in range(a.repeat):
        c = time.process_time()
        for name, x, sr in clips:
            ls = lipsync(x, sr, net=net)
            outs[name + ":proba"], outs[name + ":visemes"] = ls.proba, ls.visemes
        best = min(best, time.process_time() - c)
    res = {
        "label": a.label,
        "net": str(a.net or "shipped"),
        "audio_s": dur,
        "cpu_s": best,
        "x_realtime": dur / best,
        "load": os.getloadavg()[0],
    }
    if a.save:
        np.savez(a.save, **outs)
    if a.compare:
        with np.load(a.compare) as ref:
            res["max_abs_diff_proba"] = max(
                float(np.max(np.abs(ref[k] - outs[k]), initial=0.0))
                for k in ref.files
                if k.endswith(":proba")
            )
            res["visemes_identical"] = all(
                np.array_equal(ref[k], outs[k]) for k in ref.files if k.endswith(":visemes")
            )
    print(json.dumps(res))
    out = Path(__file__).resolve().parents[1] / "out" / "lipsync_batch_speed.json"
    out.parent.mkdir(exist_ok=True)
    with out.open("a") as fh:
        fh.write(json.dumps(res) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
