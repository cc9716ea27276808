"""Choose the rule parameters on development sentences (training voice variants, sentences never
scored): ``python bench/lipsync/tune.py``. Prints the grid, best first; the chosen values are
written into ``visemes.Params`` defaults by hand (so the shipped pipeline does not depend on the
bench)."""
from __future__ import annotations

import itertools
import logging
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

from classes import VISEME_CLASS
from corpus import generated_utterances
from facecast.server.audio.classify import default_net
from facecast.server.audio.io import read_audio
from facecast.server.audio.pipeline import features_of, track_of
from facecast.server.audio.visemes import NN, Params
from run import OUT, fit_len, scores


def main() -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    utts = generated_utterances(OUT / "lipsync_data", 18, dev=True)
    net = default_net()
    pre = []
    for u in utts:
        x, sr = read_audio(u.audio)
        f = features_of(x, sr)
        pre.append((u, f, net.proba(f.k), len(x) / sr))
    grid = {"zcr_fricative": (25.0, 31.0, 40.0), "weak_fricative_db": (20.0, 30.0, 99.0),
            "weak_db": (12.0, 18.0, 24.0, 99.0),
            "min_pause": (0.1, 0.2), "weak_viseme": (NN, None), "median": (3, 5, 7)}
    rows = []
    for values in itertools.product(*grid.values()):
        params = replace(Params(), **dict(zip(grid, values)))
        truth, pred = [], []
        for u, f, proba, dur in pre:
            ls = track_of(f, proba, dur, fps=100.0, params=params)
            truth.append(u.truth)
            pred.append(VISEME_CLASS[fit_len(ls.labels_at(ls.track.t)[0], len(u.truth))])
        s = scores(np.concatenate(truth), np.concatenate(pred))
        rows.append((s["macro_f1"] + s["accuracy"], s["accuracy"], s["macro_f1"], values))
    rows.sort(key=lambda r: -r[0])
    print(f"{len(utts)} dev utterances; grid {list(grid)}")
    for r in rows[:12]:
        print(f"acc {r[1]:.3f} macro-F1 {r[2]:.3f}  {r[3]}")
    print("defaults:", [getattr(Params(), k) for k in grid])
    return 0


if __name__ == "__main__":
    sys.exit(main())
