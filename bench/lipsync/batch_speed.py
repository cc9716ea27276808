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

import sys
import time

import numpy as np
import speed  # (bench/lipsync, beside this script)

from facecast.server.audio.classify import FrameNet
from facecast.server.audio.pipeline import lipsync

#: Recordings timed (four speakers, about 48 s in all).
FILES = (
    "mfa-tests/acoustic_corpus.wav",
    "sphinx4-digits/10001-90210-01803.wav",
    "pocketsphinx-librivox/sense_and_sensibility_01_austen_64kb-0870.wav",
    "coqui-ljspeech/LJ001-0001.wav",
)


def main() -> int:
    a = speed.arguments(__doc__, repeat=5)
    net = FrameNet.load(a.net) if a.net else None
    clips = speed.clips(FILES)
    if clips is None:
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
    res = speed.result(a, dur, best)
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
    speed.write(res, "lipsync_batch_speed.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
