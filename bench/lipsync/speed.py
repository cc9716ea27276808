"""What the lip-sync speed benches (``batch_speed.py``, ``live_speed.py``) share: their options,
the real recordings they time, their result line and where it is appended."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

from facecast.server.audio.io import read_audio
from facecast.server.paths import shared_data


def arguments(doc: str | None, repeat: int) -> argparse.Namespace:
    """The benches' options: ``--save``/``--compare`` an outputs ``.npz``, ``--repeat`` (best of),
    ``--label``, ``--net`` (a frame network file; default the shipped one)."""
    ap = argparse.ArgumentParser(description=doc)
    ap.add_argument("--save", type=Path)
    ap.add_argument("--compare", type=Path)
    ap.add_argument("--repeat", type=int, default=repeat)
    ap.add_argument("--label", default="current")
    ap.add_argument("--net", type=Path, help="frame network file (default: the shipped one)")
    return ap.parse_args()


def clips(files: tuple[str, ...]) -> list[tuple[str, np.ndarray, int]] | None:
    """``(name, samples, rate)`` of each of ``files`` under ``../shared/data/real-speech`` that
    exists; None (said on stderr) when none does."""
    data = shared_data()
    root = data / "real-speech" if data else Path("/nonexistent")
    out = [(f, *read_audio(root / f)) for f in files if (root / f).is_file()]
    if not out:
        print(f"no recordings under {root}", file=sys.stderr)
        return None
    return out


def result(a: argparse.Namespace, audio_s: float, cpu_s: float) -> dict:
    """The result line: label, network, seconds of audio, best CPU seconds, × real time, load."""
    return {
        "label": a.label,
        "net": str(a.net or "shipped"),
        "audio_s": audio_s,
        "cpu_s": cpu_s,
        "x_realtime": audio_s / cpu_s,
        "load": os.getloadavg()[0],
    }


def write(res: dict, name: str) -> None:
    """Print ``res`` and append it to ``bench/out/<name>``."""
    print(json.dumps(res))
    out = Path(__file__).resolve().parents[1] / "out" / name
    out.parent.mkdir(exist_ok=True)
    with out.open("a") as fh:
        fh.write(json.dumps(res) + "\n")
