"""Length units, defined once: millimetres per unit for face meshes, marker takes and layouts."""

from __future__ import annotations

__all__ = ["UNIT_MM", "UNIT_SPELLINGS", "unit_name"]

#: Millimetres per unit, by unit name.
UNIT_MM: dict[str, float] = {"mm": 1.0, "cm": 10.0, "dm": 100.0, "m": 1000.0, "in": 25.4}

#: Spellings a file may use for a unit (lower case, no trailing dot) -> its name in ``UNIT_MM``.
UNIT_SPELLINGS: dict[str, str] = {
    **{u: u for u in UNIT_MM},
    **{
        f"{stem}{end}": u
        for u, stem in (("mm", "milli"), ("cm", "centi"), ("dm", "deci"), ("m", ""))
        for end in ("meter", "meters", "metre", "metres")
    },
    "inch": "in",
    "inches": "in",
}


def unit_name(text: str) -> str | None:
    """``"Millimeters"``/``"mm."``/``" MM "`` -> ``"mm"`` etc.; None for an unknown unit."""
    return UNIT_SPELLINGS.get(text.strip().lower().rstrip("."))
