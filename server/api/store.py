"""Faces (and their animators) the server offers, loaded once and shared by requests and sessions.

Clients name faces; they never pass paths. The names are the built-in faces (``default``, also with
a vertex count such as ``default:2k``), the faces configured by the operator in
``FACECAST_FACES`` (``name=/path/mesh.obj`` pairs separated by ``,`` or ``;``) and the faces clients
uploaded (``POST /v1/faces``), by name or id, kept in ``<data dir>/faces/<id>/`` across restarts.
"""

from __future__ import annotations

import hashlib
import json
import logging
import re
import shutil
import tempfile
import threading
from collections import OrderedDict
from pathlib import Path
from typing import Any

from ..errors import Conflict, InputError, NotFound
from ..faces import builtin_faces, load_face, parse_count

log = logging.getLogger(__name__)

_NAME = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
_BUILTIN_SPEC = re.compile(r"^([A-Za-z0-9_-]+)(?::([0-9.]+[kKmM]?))?$")

#: Largest built-in head a client may ask for by name (``default:N``).
MAX_BUILTIN_VERTICES = 600_000
#: Uploaded faces a server keeps at most (each is a folder of a few MB in the data directory).
MAX_UPLOADED_FACES = 32
#: An uploaded face's id: 16 hex digits of the hash of its mesh and annotation.
UPLOAD_ID = re.compile(r"^[0-9a-f]{16}$")
#: File names inside an uploaded face's folder (fixed by the server, never a client's).
UPLOAD_MESH, UPLOAD_ANNOTATION, UPLOAD_META = "mesh.obj", "mesh.face.json", "meta.json"


def upload_id(vertices, triangles, annotation: dict) -> str:
    """Id of an uploaded face: 16 hex digits of the hash of its mesh as read and its annotation."""
    import numpy as np

    h = hashlib.blake2b(digest_size=8)
    h.update(np.ascontiguousarray(vertices, dtype=np.float32).tobytes())
    h.update(np.ascontiguousarray(triangles, dtype=np.int32).tobytes())
    h.update(json.dumps(annotation, sort_keys=True, separators=(",", ":")).encode())
    return h.hexdigest()


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
            raise InputError(
                f"cannot read face entry {item!r}; write name=/path/to/mesh.obj "
                "(name: letters, digits, _ . -)",
                where="FACECAST_FACES",
            )
        out[name] = Path(path).expanduser()
    return out


class FaceStore:
    """Face name -> ``Face`` (and ``(face, engine)`` -> ``Animator``), loaded lazily and cached.

    Thread-safe: loading happens outside the event loop (``run_in_threadpool``) and two requests
    for the same face wait for one load.
    """

    def __init__(
        self,
        *,
        default: str = "default",
        backend: str = "auto",
        device: str | None = None,
        configured: dict[str, Path] | None = None,
        max_faces: int = 8,
        uploads: Path | None = None,
    ):
        """``uploads``: folder of the faces clients upload (None: uploads are refused)."""
        self.configured = dict(configured or {})
        self.uploads = uploads
        self.uploaded: dict[str, Path] = {}  # name -> mesh path
        self.upload_ids: dict[str, str] = {}  # id -> name
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
        if uploads is not None:
            self._scan_uploads()

    # -- names -----------------------------------------------------------------------------------
    def names(self) -> list[str]:
        """Face names a client may use, built-in first."""
        return [
            *builtin_faces(),
            *(n for n in self.configured if n not in builtin_faces()),
            *(n for n in self.uploaded if n not in self.configured),
        ]

    def resolve(self, name: str | None) -> str:
        """The ``load_face`` spec for a client-given face name (``None`` -> the server default).

        Raises NotFound for unknown names; never turns arbitrary client text into a path.
        """
        name = (name or self.default).strip()
        if name in self.configured:
            return str(self.configured[name])
        if name in self.uploaded or name in self.upload_ids:
            return str(self.uploaded[self.upload_ids.get(name, name)])
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
                    raise InputError(
                        f"vertex count {n if n is not None else count[:20] + '...'} out of "
                        f"range 100..{MAX_BUILTIN_VERTICES}; use e.g. default:2k",
                        where=f"face {shown!r}",
                    )
            return name
        raise NotFound(
            f"no face named {shown!r}; GET /v1/faces lists the faces this server offers "
            f"({', '.join(self.names())}; built-in ones also as e.g. default:2k)"
        )

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

    # -- uploaded faces --------------------------------------------------------------------------
    def _scan_uploads(self) -> None:
        """Register the faces uploaded before this start (folders ``<id>/`` with their meta.json)."""
        assert self.uploads is not None
        if not self.uploads.is_dir():
            return
        for folder in sorted(self.uploads.iterdir()):
            if not (folder.is_dir() and UPLOAD_ID.match(folder.name)):
                continue  # a temporary folder of an interrupted upload
            try:
                meta = json.loads((folder / UPLOAD_META).read_text())
                name = meta["name"]
            except (OSError, ValueError, KeyError, TypeError):
                log.warning(
                    "ignoring the uploaded face folder %s (no readable %s)",
                    folder.name,
                    UPLOAD_META,
                )
                continue
            if isinstance(name, str) and _NAME.match(name) and (folder / UPLOAD_MESH).is_file():
                self.uploaded[name] = folder / UPLOAD_MESH
                self.upload_ids[folder.name] = name
                self._seen.add(str(folder / UPLOAD_MESH))

    def upload_info(self, name: str) -> dict | None:
        """The meta data of an uploaded face (id, name, annotation source, report), else None."""
        name = self.upload_ids.get(name, name)
        path = self.uploaded.get(name)
        if path is None:
            return None
        try:
            return json.loads((path.parent / UPLOAD_META).read_text())
        except (OSError, ValueError):
            return None

    @staticmethod
    def check_upload_name(name: str) -> None:
        """InputError unless ``name`` may name an uploaded face."""
        if not _NAME.match(name) or not name[0].isalnum():
            raise InputError(
                "a face name has 1-64 letters, digits, '_', '.' or '-', starting with a "
                "letter or digit",
                where="name",
            )

    def add_upload(
        self, vertices, triangles, annotation: dict, *, name: str | None, meta: dict
    ) -> tuple[str, str, bool]:
        """Keep an uploaded face: ``(name, id, created)``; the same mesh and annotation again is the
        same face (``created`` False). Raises Conflict for a name taken by another face or when the
        server holds ``MAX_UPLOADED_FACES`` already, InputError for a malformed name."""
        from ..faces.upload import write_obj

        if self.uploads is None:
            raise Conflict("this server does not keep uploaded faces", where="face")
        if name is not None:
            self.check_upload_name(name)
        face_id = upload_id(vertices, triangles, annotation)
        with self._guard:
            if face_id in self.upload_ids:
                return self.upload_ids[face_id], face_id, False
        if name is not None and (
            name in builtin_faces()
            or name in self.configured
            or name in self.uploaded
            or UPLOAD_ID.match(name)
        ):
            raise Conflict(
                f"the face name {name!r} is taken; choose another (GET /v1/faces lists them)",
                where="name",
            )
        name = name or f"face-{face_id[:8]}"
        if len(self.uploaded) >= MAX_UPLOADED_FACES:
            raise Conflict(
                f"this server keeps {MAX_UPLOADED_FACES} uploaded faces already; delete one "
                "(DELETE /v1/faces/<name>) first",
                where="face",
            )
        self.uploads.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=".upload-", dir=self.uploads))
        try:
            write_obj(tmp / UPLOAD_MESH, vertices, triangles)
            (tmp / UPLOAD_ANNOTATION).write_text(json.dumps(annotation, separators=(",", ":")))
            (tmp / UPLOAD_META).write_text(
                json.dumps({**meta, "id": face_id, "name": name}, indent=1)
            )
            tmp.chmod(0o755)
            with self._guard:
                if face_id in self.upload_ids:  # the same upload, finished meanwhile
                    return self.upload_ids[face_id], face_id, False
                if name in self.uploaded:
                    raise Conflict(f"the face name {name!r} is taken; choose another", where="name")
                tmp.rename(self.uploads / face_id)
                self.uploaded[name] = self.uploads / face_id / UPLOAD_MESH
                self.upload_ids[face_id] = name
                self._seen.add(str(self.uploaded[name]))
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        log.info("uploaded face %s (id %s) kept in %s", name, face_id, self.uploads / face_id)
        return name, face_id, True

    def remove_upload(self, name: str) -> str:
        """Forget an uploaded face and delete its folder (sessions using it keep their copy); its id."""
        with self._guard:
            name = self.upload_ids.get(name, name)
            if name not in self.uploaded:
                raise NotFound(
                    f"no uploaded face named {name!r}; built-in and configured faces cannot be "
                    "deleted",
                    where="face",
                )
            path = self.uploaded.pop(name)
            face_id = path.parent.name
            self.upload_ids.pop(face_id, None)
            spec = str(path)
            self._faces.pop(spec, None)
            for key in [k for k in self._derived if k[0] == spec]:
                self._derived.pop(key, None)
            for key in [k for k in self._animators if k[0] == spec]:
                self._animators.pop(key, None)
        shutil.rmtree(path.parent, ignore_errors=True)
        return face_id
