"""Minimal Praat TextGrid reader (long and short text formats) for the lip-sync benchmark."""

from __future__ import annotations

import re
from pathlib import Path

_TOKEN = re.compile(r'"((?:[^"]|"")*)"|(-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?)')


def _tokens(text: str) -> list[str | float]:
    text = re.sub(r"\[\s*\d+\s*\]", " ", text)  # long format: "item [1]:", "intervals [3]:"
    out: list[str | float] = []
    for m in _TOKEN.finditer(text):
        out.append(m.group(1).replace('""', '"') if m.group(1) is not None else float(m.group(2)))
    return out


def read_tiers(path: str | Path) -> dict[str, list[tuple[float, float, str]]]:
    """Interval tiers of a TextGrid: name → [(start s, end s, label), ...]."""
    raw = Path(path).read_bytes()
    text = raw.decode("utf-16") if raw[:2] in (b"\xff\xfe", b"\xfe\xff") else raw.decode("utf-8")
    tok = _tokens(text)
    if tok[:2] != ["ooTextFile", "TextGrid"]:
        raise ValueError(f"{path}: not a TextGrid")
    i = 4  # file type, object class, xmin, xmax
    n_tiers = int(tok[i])
    i += 1
    tiers: dict[str, list[tuple[float, float, str]]] = {}
    for _ in range(n_tiers):
        kind, name = tok[i], tok[i + 1]
        n = int(tok[i + 4])
        i += 5
        if kind == "IntervalTier":
            tiers[str(name)] = [
                (float(tok[i + 3 * j]), float(tok[i + 3 * j + 1]), str(tok[i + 3 * j + 2]).strip())
                for j in range(n)
            ]
            i += 3 * n
        else:  # TextTier: (time, mark) points
            i += 2 * n
    return tiers
