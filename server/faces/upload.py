"""Meshes sent by clients (``POST /v1/faces``): read, checked and annotated in a throw-away process.

A client's bytes are hostile: the mesh parsers (our OBJ reader, trimesh for PLY, GLB/glTF and STL)
and the annotator run in a ``spawn``-ed worker process with an address-space limit and a deadline,
so a parser that crashes, hangs or allocates without bound costs that process (it is replaced),
never the server.
Nothing in an upload ever names a file the server opens: the mesh is read from memory (a glTF
``uri`` must be an embedded ``data:`` URI), and the annotation travels as JSON content.

``MeshWorker().prepare(path, fmt, annotation)`` returns a ``Prepared``: the mesh as read, its complete
annotation (the user's, completed by the automatic one when partial or absent) and what was done.
"""

from __future__ import annotations

import io
import json
import logging
import multiprocessing
import os
import struct
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FacecastError, InputError

log = logging.getLogger(__name__)

#: Mesh formats an upload may be in (file name suffix, else sniffed from the content).
FORMATS = ("obj", "ply", "glb", "gltf", "stl")
#: Largest mesh an upload may hold: vertices and triangles (the annotator's time grows with both).
MAX_VERTICES = 300_000
MAX_TRIANGLES = 600_000
#: Seconds the worker may take to read and annotate a mesh (a 100k-vertex head takes about 6 s).
TIMEOUT_SECONDS = 180.0
#: Address space of the worker process, MiB.
MEMORY_MB = 4096
#: Marker of an annotation that is as complete as it gets: loading it never fills it in again.
FINAL = "final"


class Unprocessable(InputError):
    """The upload is well-formed as a request but its mesh cannot be used."""

    status = 422


class TooLarge(InputError):
    status = 413


@dataclass
class Prepared:
    """An uploaded mesh ready to be stored.

    Attributes:
        vertices: ``(V, 3) float32`` as read; ``triangles``: ``(F, 3) int32``.
        annotation: complete annotation (``loaders`` format, marked ``FINAL``).
        source: ``"user"``, ``"automatic"`` or ``"user+automatic"``.
        report: the annotator's report (seconds, what it left out, warnings), or empty.
        cached: True when the automatic annotation came from the cache.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    annotation: dict[str, Any]
    source: str
    report: dict[str, Any] = field(default_factory=dict)
    cached: bool = False


def sniff_format(filename: str | None, head: bytes) -> str:
    """The mesh format of an upload: its file name's suffix when known, else its first bytes."""
    name = (filename or "").rsplit("/", 1)[-1].rsplit("\\", 1)[-1].lower()
    suffix = name.rsplit(".", 1)[-1] if "." in name else ""
    if suffix in FORMATS:
        return suffix
    if head[:4] == b"glTF":
        return "glb"
    if head[:3] == b"ply":
        return "ply"
    text = head.lstrip()
    if text[:1] == b"{":
        return "gltf"
    if text[:5].lower() == b"solid":
        return "stl"
    if any(line.startswith((b"v ", b"f ")) for line in head.splitlines()):
        return "obj"
    if len(head) >= 84:
        (count,) = struct.unpack_from("<I", head, 80)
        if count and 84 + 50 * count >= len(head):
            return "stl"  # binary STL: 80-byte header, triangle count, 50 bytes a triangle
    raise InputError(
        f"cannot tell what mesh format {name or 'the upload'!r} is; name the file with one of "
        f".{', .'.join(FORMATS)}",
        where="file",
    )


def _gltf_json(data: bytes, fmt: str) -> dict[str, Any]:
    """The JSON part of a glTF (text) or GLB (binary container) file."""
    if fmt == "glb":
        if len(data) < 20:
            raise Unprocessable("the GLB file is shorter than its headers", where="file")
        magic, _version, _length = struct.unpack_from("<4sII", data, 0)
        chunk_len, chunk_type = struct.unpack_from("<II", data, 12)
        if magic != b"glTF" or chunk_type != 0x4E4F534A or 20 + chunk_len > len(data):
            raise Unprocessable("not a GLB file (bad magic or JSON chunk)", where="file")
        text = data[20 : 20 + chunk_len]
    else:
        text = data
    try:
        doc = json.loads(text)
    except (ValueError, RecursionError) as e:
        raise Unprocessable(
            f"the glTF JSON cannot be read ({str(e)[:200]})", where="file"
        ) from None
    if not isinstance(doc, dict):
        raise Unprocessable("the glTF JSON is not an object", where="file")
    return doc


def check_no_external_files(data: bytes, fmt: str) -> None:
    """Refuse a glTF/GLB that refers to other files: the server never opens files a client names."""
    doc = _gltf_json(data, fmt)
    for key in ("buffers", "images"):
        items = doc.get(key) or []
        if not isinstance(items, list):
            raise Unprocessable(f"glTF '{key}' must be an array", where="file")
        for item in items:
            uri = item.get("uri") if isinstance(item, dict) else None
            if uri is not None and not (isinstance(uri, str) and uri.startswith("data:")):
                raise Unprocessable(
                    f"glTF {key} refer to other files ({str(uri)[:60]!r}); the server reads "
                    "only the upload itself: send a .glb or embed buffers as data: URIs",
                    where="file",
                )


def parse_mesh(data: bytes, fmt: str) -> tuple[np.ndarray, np.ndarray]:
    """``(V, 3) float32`` vertices and ``(F, 3) int32`` triangles of mesh bytes; InputError else.

    Reads from memory only; vertices split at UV seams are merged for the trimesh formats (as
    ``loaders.read_mesh`` does for files), OBJ keeps its vertex order.
    """
    if fmt not in FORMATS:
        raise InputError(
            f"unknown mesh format {fmt!r}; use one of {', '.join(FORMATS)}", where="file"
        )
    if fmt == "obj":
        from .obj import read_obj

        v, t = read_obj("upload.obj", text=data.decode("utf-8", "replace"))
    else:
        if fmt in ("glb", "gltf"):
            check_no_external_files(data, fmt)
        import trimesh

        try:  # a file object and no resolver: trimesh can open nothing else
            mesh: Any = trimesh.load(
                file_obj=io.BytesIO(data), file_type=fmt, process=False, force="mesh"
            )
            mesh.merge_vertices(merge_tex=True, merge_norm=True)
            v = np.asarray(mesh.vertices, dtype=np.float32)
            t = np.asarray(mesh.faces, dtype=np.int64)
        except MemoryError:
            raise
        except Exception as e:  # noqa: BLE001  trimesh raises many types for malformed files
            raise Unprocessable(
                f"cannot read the {fmt.upper()} mesh ({type(e).__name__}: {str(e)[:200]})",
                where="file",
            ) from None
    return check_mesh(v, t)


def check_mesh(v: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles a face can be built from (shape, caps, finite, ids in range)."""
    if v.ndim != 2 or v.shape[1] != 3 or len(v) < 3:
        raise Unprocessable("the mesh needs vertices with three coordinates each", where="file")
    if t.ndim != 2 or t.shape[1] != 3 or len(t) == 0:
        raise Unprocessable("the mesh has no triangles", where="file")
    if len(v) > MAX_VERTICES or len(t) > MAX_TRIANGLES:
        raise TooLarge(
            f"the mesh has {len(v)} vertices and {len(t)} triangles; this server takes at most "
            f"{MAX_VERTICES} and {MAX_TRIANGLES}: decimate it first",
            where="file",
        )
    if not np.all(np.isfinite(v)):
        raise Unprocessable(
            "the mesh has non-finite vertex coordinates (NaN or infinity)", where="file"
        )
    if t.min() < 0 or t.max() >= len(v):
        raise Unprocessable(f"a triangle refers to a vertex outside 0..{len(v) - 1}", where="file")
    return np.ascontiguousarray(v, dtype=np.float32), np.ascontiguousarray(t, dtype=np.int32)


def prepare(
    data: bytes, fmt: str, annotation_text: str | None, *, name: str = "upload"
) -> Prepared:
    """Read the mesh, complete its annotation and check that a face can be built from them.

    The user's annotation (complete or partial) always wins; without one, the automatic one (cached
    by mesh hash) is used. Raises InputError (4xx) for anything wrong with the upload.
    """
    from .annotate import cached_annotation, is_partial, merge
    from .annotate import mesh_key as annotation_key
    from .loaders import face_from_annotation, parse_annotation

    v, t = parse_mesh(data, fmt)
    units = "m" if fmt in ("glb", "gltf") else None
    user = (
        parse_annotation(annotation_text, where="annotation")
        if annotation_text is not None
        else None
    )
    report: dict[str, Any] = {}
    cached = False
    if user is not None and not is_partial(user):
        annotation, source = user, "user"
    else:
        from ..paths import cache_dir

        try:
            cached = (cache_dir("annotations") / f"{annotation_key(v, t)}.face.json").is_file()
        except OSError:
            cached = False
        try:
            auto = cached_annotation(v, t, name=name, units=units)
        except InputError as e:
            if user is None:
                raise Unprocessable(
                    f"automatic annotation failed ({e}); send the mesh's .face.json as the "
                    "'annotation' part",
                    where="file",
                ) from None
            annotation, source = user, "user"  # a partial annotation is then all there is
            report = {"failed": str(e)}
        else:
            report = dict(auto.get("automatic", {}))
            annotation, source = (
                (auto, "automatic") if user is None else (merge(auto, user), "user+automatic")
            )
    annotation = {**annotation, FINAL: True}
    face_from_annotation(
        name, v, t, annotation, where="annotation"
    )  # InputError naming the bad field
    return Prepared(v, t, annotation, source, report, cached)


def write_obj(path: Path, vertices: np.ndarray, triangles: np.ndarray) -> None:
    """Write an OBJ that ``obj.read_obj`` reads back to the same float32 vertices, in the same order."""
    v = np.asarray(vertices, dtype=np.float32).astype(np.float64)
    buf = io.StringIO()
    np.savetxt(buf, v, fmt="v %.9g %.9g %.9g")
    np.savetxt(buf, np.asarray(triangles, dtype=np.int64) + 1, fmt="f %d %d %d")
    path.write_text(buf.getvalue())


# -- the worker process --------------------------------------------------------------------------


def _answer(path: str, fmt: str, annotation_text: str | None, name: str) -> tuple[Any, ...]:
    """``("ok", Prepared)`` or ``("error", status, message)`` for one upload (in the worker)."""
    try:
        data = Path(path).read_bytes()
        return ("ok", prepare(data, fmt, annotation_text, name=name))
    except FacecastError as e:
        return ("error", int(getattr(e, "status", 400)), str(e))
    except MemoryError:
        return (
            "error",
            413,
            "the mesh needs more memory to read than this server allows; send a smaller one",
        )
    except RecursionError:
        return ("error", 422, "the mesh is nested too deeply to read")
    except Exception as e:  # a parser's error not turned into ours: still the file's fault
        log.warning("reading an uploaded mesh failed", exc_info=True)
        return ("error", 422, f"cannot read the mesh ({type(e).__name__}: {str(e)[:200]})")


def _serve(conn: Any, memory_mb: int, parent_pid: int) -> None:
    """Worker entry point: answer ``(path, fmt, annotation, name)`` requests until the pipe closes."""
    import signal

    from ..jobs.worker import die_with_parent, limit_resources

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C goes to the server, which ends us
    die_with_parent(parent_pid)
    limit_resources(memory_mb)
    logging.basicConfig(
        level=logging.INFO,
        format=f"%(asctime)s %(levelname)s faces[{os.getpid()}] %(name)s: %(message)s",
    )
    import trimesh  # noqa: F401  imported once, before the first upload's deadline starts

    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):
            break
        if request is None:
            break
        conn.send(_answer(*request))


class MeshWorker:
    """One ``spawn``-ed process that reads and annotates uploaded meshes, one at a time.

    Started on first use and kept (imports are paid once); killed and replaced when it overruns
    ``timeout``, crashes or runs out of memory (``memory_mb`` of address space). Thread-safe.
    """

    def __init__(self, *, timeout: float = TIMEOUT_SECONDS, memory_mb: int = MEMORY_MB) -> None:
        self.timeout = timeout
        self.memory_mb = memory_mb
        self._lock = threading.Lock()
        self._proc: Any = None
        self._conn: Any = None

    def _start(self) -> None:
        ctx = multiprocessing.get_context("spawn")
        parent, child = ctx.Pipe()
        self._proc = ctx.Process(
            target=_serve,
            args=(child, self.memory_mb, os.getpid()),
            name="facecast-mesh-worker",
            daemon=True,
        )
        self._proc.start()
        child.close()
        self._conn = parent

    def stop(self) -> None:
        """End the worker process (if any)."""
        with self._lock:
            self._kill()

    def _kill(self) -> None:
        if self._proc is not None:
            self._proc.kill()
            self._proc.join(5.0)
        if self._conn is not None:
            self._conn.close()
        self._proc = self._conn = None

    def prepare(
        self, path: Path, fmt: str, annotation_text: str | None, *, name: str = "upload"
    ) -> Prepared:
        """``prepare`` of the upload at ``path`` in the worker (blocking: call from a thread).

        Raises InputError (4xx) for a bad upload, including one that makes the worker overrun its
        time, crash or exhaust its memory (the worker is then replaced; the server is unaffected).
        """
        with self._lock:
            if self._proc is None or not self._proc.is_alive():
                self._kill()
                self._start()
            started = time.monotonic()
            try:
                self._conn.send((str(path), fmt, annotation_text, name))
                msg = self._conn.recv() if self._conn.poll(self.timeout) else None
            except (EOFError, OSError):
                msg = None
            if msg is None:
                overran = time.monotonic() - started >= self.timeout
                self._proc.join(0.5)
                code = self._proc.exitcode
                self._kill()
                if overran:
                    raise Unprocessable(
                        f"reading and annotating the mesh took longer than {self.timeout:.0f} s; "
                        "send a smaller mesh or its .face.json as the 'annotation' part",
                        where="file",
                    )
                what = f"signal {-code}" if code is not None and code < 0 else f"exit code {code}"
                log.warning("the mesh worker ended with %s on an upload", what)
                raise Unprocessable(
                    f"the mesh reader failed on this file ({what}); the file is malformed",
                    where="file",
                )
        if msg[0] == "ok":
            prepared: Prepared = msg[1]
            return prepared
        _, status, message = msg
        # The worker's error class, rebuilt by its status (the message names the field at fault already).
        raise {413: TooLarge, 422: Unprocessable}.get(status, InputError)(message)
