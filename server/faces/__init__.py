"""Faces: the built-in procedural head, user meshes with a ``.face.json`` annotation, and ICT FaceKit.

``load_face(spec)`` takes ``default`` (the built-in head at its default resolution), ``default:N``
(about N vertices, e.g. ``default:2k``, ``default:500k``), or a mesh path.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import InputError
from .face import JAW_PARTS, KNOWN_PARTS, RIGID_GROUPS, Face

__all__ = ["JAW_PARTS", "KNOWN_PARTS", "RIGID_GROUPS", "Face", "builtin_faces", "load_face"]

#: Built-in faces: name -> approximate vertex count.
BUILTIN: dict[str, int] = {"default": 25_000}


def builtin_faces() -> dict[str, int]:
    """Names of the built-in faces and their default vertex counts."""
    return dict(BUILTIN)


def parse_count(text: str) -> int:
    """``"2k"`` -> 2000, ``"1.5M"`` -> 1500000, ``"30000"`` -> 30000."""
    t = text.strip().lower()
    mult = {"k": 1_000, "m": 1_000_000}.get(t[-1:], 1)
    try:
        return int(float(t[:-1] if mult > 1 else t) * mult)
    except ValueError:
        raise InputError(
            f"cannot read a vertex count from {text!r}; use e.g. 2k, 25000 or 0.5M"
        ) from None


def load_face(spec: str | Path) -> Face:
    """The face named by ``spec`` (see module docstring)."""
    text = str(spec)
    name, _, count = text.partition(":")
    if name in BUILTIN and not Path(text).exists():
        from .procedural import build_default_head

        return build_default_head(parse_count(count) if count else BUILTIN[name])
    path = Path(text)
    if not path.exists():
        raise InputError(
            f"no built-in face or mesh file named {text!r}; built-in faces: "
            f"{', '.join(BUILTIN)} (optionally with ':<vertices>', e.g. default:100k)"
        )
    from .loaders import load_mesh_face

    return load_mesh_face(path)
