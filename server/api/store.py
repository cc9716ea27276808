"""Faces (and their animators) the server offers, loaded once and shared by requests and sessions.

Clients name faces; they never pass paths. The names are the built-in faces (``default``, also with
a vertex count such as ``default:2k``) and the faces configured by the operator in
``FACECAST_FACES`` (``name=/path/mesh.obj`` pairs separated by ``,`` or ``;``).
"""
from __future__ import annotations

import logging
import re
import threading
from collections import OrderedDict
from pathlib import Path
from typing import Any

from ..errors import InputError, NotFound
from ..faces import builtin_faces, load_face, parse_count

log = logging.getLogger(__name__)

_NAME = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
_BUILTIN_SPEC = re.compile(r"^([A-Za-z0-9_-]+)(?::([0-9.]+[kKmM]?))?$")

#: Largest built-in head a client may ask for by name (``default:N``).
MAX_BUILTIN_VERTICES = 600_000


def parse_faces_env(text: str | None) -> dict[str, Path]:
    """``"ict=/p/a.obj, x=/p/b.obj"`` -> ``{"ict": Path("/p/a.obj"), ...}``; InputError when malformed."""
    out: dict[str, Path] = {}
    for item in re.split(r"[,;]", text or ""):
        item = item.strip()
        if not item:
            continue
        name, sep, path = item.partition("=")
        name, path = name.strip(), path.strip()
        if not sep or not _NAME.match(name) or not path:
            raise InputError(f"cannot read face entry {item!r}; write name=/path/to/mesh.obj "
                             "(name: letters, digits, _ . -)", where="FACECAST_FACES")
        out[name] = Path(path).expanduser()
    return out


class FaceStore:
    """Face name -> ``Face`` (and ``(face, engine)`` -> ``Animator``), loaded lazily and cached.

    Thread-safe: loading happens outside the event loop (``run_in_threadpool``) and two requests
    for the same face wait for one load.
    """

    def __init__(self, *, default: str = "default", backend: str = "auto", device: str | None = None,
                 configured: dict[str, Path] | None = None, max_faces: int = 8):
        self.configured = dict(configured or {})
        self.default = default
        self.backend = backend
        self.device = device
        self.max_faces = max_faces
        self._faces: OrderedDict[str, Any] = OrderedDict()
        self._animators: OrderedDict[tuple, Any] = OrderedDict()
        self._derived: dict[tuple, Any] = {}
        self._seen: set[str] = set()  # specs loaded at least once
        self._locks: dict[Any, threading.Lock] = {}
        self._guard = threading.Lock()
        if default not in self.configured and not _BUILTIN_SPEC.match(default):
            # The operator gave a mesh path with --face: offer it under its file stem.
            path = Path(default).expanduser()
            self.configured.setdefault(path.stem, path)
            self.default = path.stem
        self._seen.add(self.default)  # the operator chose it: public even before it is loaded

    # -- names -----------------------------------------------------------------------------------
    def names(self) -> list[str]:
        """Face names a client may use, built-in first."""
        return [*builtin_faces(), *(n for n in self.configured if n not in builtin_faces())]

    def resolve(self, name: str | None) -> str:
        """The ``load_face`` spec for a client-given face name (``None`` -> the server default).

        Raises NotFound for unknown names; never turns arbitrary client text into a path.
        """
        name = (name or self.default).strip()
        if name in self.configured:
            return str(self.configured[name])
        m = _BUILTIN_SPEC.match(name)
        shown = name if len(name) <= 80 else name[:80] + "..."
        if m and m.group(1) in builtin_faces():
            if m.group(2):
                count = m.group(2)
                try:  # a count of hundreds of digits overflows: out of range like any other
                    n = parse_count(count) if len(count) <= 12 else None
                except (ValueError, OverflowError):
                    n = None
                if n is None or not 100 <= n <= MAX_BUILTIN_VERTICES:
                    raise InputError(f"vertex count {n if n is not None else count[:20] + '...'} out of "
                                     f"range 100..{MAX_BUILTIN_VERTICES}; use e.g. default:2k",
                                     where=f"face {shown!r}")
            return name
        raise NotFound(f"no face named {shown!r}; GET /v1/faces lists the faces this server offers "
                       f"({', '.join(self.names())}; built-in ones also as e.g. default:2k)")

    def needs_admin(self, name: str | None) -> bool:
        """True if loading ``name`` is a new resolution of a built-in face (``default:300k``) that this
        server has not loaded yet: public routes may not make the server build arbitrary meshes."""
        spec = self.resolve(name)
        m = _BUILTIN_SPEC.match(spec)
        return bool(m and m.group(2)) and spec not in self._seen

    # -- cached loads ----------------------------------------------------------------------------
    def _lock(self, key: Any) -> threading.Lock:
        with self._guard:
            return self._locks.setdefault(key, threading.Lock())

    def face(self, name: str | None = None):
        """The ``Face`` for a face name (blocking; call from a worker thread in async code)."""
        spec = self.resolve(name)
        with self._lock(("face", spec)):
            if spec in self._faces:
                self._faces.move_to_end(spec)
                return self._faces[spec]
            log.info("loading face %s", spec)
            face = load_face(spec)
            with self._guard:
                self._seen.add(spec)
                self._faces[spec] = face
                while len(self._faces) > self.max_faces:
                    self._faces.popitem(last=False)
            return face

    def loaded(self) -> list[str]:
        """Specs of the faces in memory."""
        return list(self._faces)

    def loaded_face(self, name: str):
        """The ``Face`` for a name if it is already in memory, else None (never loads)."""
        try:
            return self._faces.get(self.resolve(name))
        except Exception:
            return None

    def derived(self, name: str | None, kind: str, fn):
        """``fn(face)`` for a face, computed once per face and ``kind`` (e.g. its encoded topology)."""
        key = (self.resolve(name), kind)
        with self._lock(("derived", key)):
            if key in self._derived:
                return self._derived[key]
            value = fn(self.face(name))
            with self._guard:
                self._derived[key] = value
                while len(self._derived) > 4 * self.max_faces:
                    self._derived.pop(next(iter(self._derived)))
            return value

    def animator(self, name: str | None = None, engine: str = "fp", **params):
        """A shared ``Animator`` for a face and engine (blocking; built once, then cached)."""
        spec = self.resolve(name)
        key = (spec, engine, tuple(sorted(params.items())))
        face = self.face(name)
        with self._lock(("animator", key)):
            if key in self._animators:
                return self._animators[key]
            from ..pipeline import Animator

            anim = Animator(face, engine=engine, backend=self.backend, device=self.device, **params)
            with self._guard:
                self._animators[key] = anim
                while len(self._animators) > self.max_faces:
                    self._animators.popitem(last=False)
            return anim
