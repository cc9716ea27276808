"""Viseme tracks as cue segments: facecast's named segments and Rhubarb Lip Sync's mouth cues.

Rhubarb's nine mouth shapes (Hanna-Barbera style, as Rhubarb documents them): A closed (P B M),
B slightly open with clenched teeth (most consonants, EE), C open (EH AE), D wide open (AA),
E slightly rounded (AO ER), F puckered (UW OW W), G upper teeth on the lower lip (F V), H tongue
raised (L), X idle (rest, silence). Its output formats: JSON ``{"metadata": {"soundFile",
"duration"}, "mouthCues": [{"start", "end", "value"}]}`` and TSV lines ``start<TAB>shape`` whose
last line is the end time with X. Times in seconds, two decimals.
"""

from __future__ import annotations

import json

import numpy as np

from ..mpeg4.highlevel import VISEME_NAMES

#: MPEG-4 viseme id (0 sil, 1 PP, 2 FF, 3 TH, 4 DD, 5 kk, 6 CH, 7 SS, 8 nn, 9 RR, 10 aa, 11 E,
#: 12 ih, 13 oh, 14 ou) → Rhubarb mouth shape.
RHUBARB_SHAPES = ("X", "A", "G", "B", "B", "B", "B", "B", "B", "B", "D", "C", "B", "E", "F")


def segments(vis: np.ndarray, fps: float) -> list[tuple[float, float, int]]:
    """Runs of equal visemes in a track sampled at ``i / fps`` s: ``[(start s, end s, viseme)]``;
    each frame lasts ``1 / fps``."""
    vis = np.asarray(vis)
    out: list[tuple[float, float, int]] = []
    if len(vis) == 0:
        return out
    cuts = np.nonzero(np.diff(vis))[0] + 1
    starts = np.concatenate([[0], cuts])
    ends = np.concatenate([cuts, [len(vis)]])
    return [(float(s) / fps, float(e) / fps, int(vis[s])) for s, e in zip(starts, ends)]


def named_segments(vis: np.ndarray, fps: float) -> list[dict]:
    """``[{"start", "end", "viseme", "name"}]`` (seconds rounded to 1 µs; MPEG-4 viseme names)."""
    return [
        {"start": round(s, 6), "end": round(e, 6), "viseme": v, "name": VISEME_NAMES[v]}
        for s, e, v in segments(vis, fps)
    ]


def rhubarb_cues(vis: np.ndarray, fps: float, duration: float) -> list[tuple[float, float, str]]:
    """Rhubarb mouth cues ``[(start, end, shape)]`` covering ``[0, duration]`` (times rounded to
    10 ms as Rhubarb writes them; adjacent equal shapes merged, empty cues dropped)."""
    cues: list[tuple[float, float, str]] = []
    for s, e, v in segments(vis, fps):
        shape = RHUBARB_SHAPES[v]
        s, e = round(min(s, duration), 2), round(min(e, duration), 2)
        if cues and cues[-1][2] == shape:
            cues[-1] = (cues[-1][0], e, shape)
        elif e > s:
            cues.append((s, e, shape))
    if cues:
        cues[-1] = (cues[-1][0], round(duration, 2), cues[-1][2])
    return cues


def rhubarb_json(cues: list[tuple[float, float, str]], sound_file: str, duration: float) -> str:
    """Rhubarb's JSON export format."""
    return (
        json.dumps(
            {
                "metadata": {"soundFile": sound_file, "duration": round(duration, 2)},
                "mouthCues": [{"start": s, "end": e, "value": v} for s, e, v in cues],
            },
            indent=2,
        )
        + "\n"
    )


def rhubarb_tsv(cues: list[tuple[float, float, str]]) -> str:
    """Rhubarb's TSV export format: ``start<TAB>shape`` per cue, then ``end<TAB>X``."""
    lines = [f"{s:.2f}\t{v}" for s, _, v in cues]
    if cues:
        lines.append(f"{cues[-1][1]:.2f}\tX")
    return "\n".join(lines) + "\n"
