"""``/v1/faces``: the faces this server offers, their description, and their topology for thin clients.

Reading is public (no key): viewers need the topology to draw the vertex frames they receive.
``POST /v1/faces`` (admin key) adds a face from an uploaded mesh (OBJ, PLY, GLB/glTF, STL) and its
optional ``.face.json``; without one (or with a partial one) the server annotates it automatically.
The mesh is read and annotated in a throw-away process with a deadline and a memory limit
(``faces.upload``); the face is then kept in ``<data dir>/faces/`` and usable by name or id in
sessions, jobs and playback. ``DELETE /v1/faces/{name}`` (admin key) removes an uploaded face.
"""

from __future__ import annotations

import logging
import tempfile
import threading
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from fastapi import APIRouter, Depends, Request, status
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, Field

from ...protocol.rest import TOPOLOGY_MEDIA_TYPE, ErrorBody, FaceInfo, FaceList, FaceSummary
from ...protocol.topology import Topology, encode_topology, part_ids_from_parts
from ..errors import Forbidden, InputError, Unavailable
from ..faces import KNOWN_PARTS, RIGID_GROUPS, builtin_faces
from ..faces import upload as mesh_upload
from ..jobs.upload import (
    FIELD_LIMITS,
    UploadParser,
    boundary_of,
    drain,
    multipart_doc,
    receive,
    refuse_declared_oversize,
    safe_display_name,
    upload_dir,
)
from ..mpeg4 import measure_fapu
from .security import bearer, require_admin, same

log = logging.getLogger(__name__)

router = APIRouter(prefix="/v1/faces", tags=["faces"])

_ERRORS = {
    404: {"model": ErrorBody, "description": "no such face"},
    403: {
        "model": ErrorBody,
        "description": "a new resolution of a built-in face needs the admin key",
    },
}


def part_order(face) -> list[str]:
    """Part names in topology order: the known parts the face has, then the others alphabetically."""
    known = [p for p in KNOWN_PARTS if p in face.parts]
    return known + sorted(p for p in face.parts if p not in KNOWN_PARTS)


def face_topology(face) -> Topology:
    """The ``Topology`` of a face: rest vertices, triangles, part per vertex, rigid group per vertex."""
    order = part_order(face)
    return Topology(
        vertices=face.vertices,
        triangles=face.triangles,
        part_ids=part_ids_from_parts(face.n_vertices, face.parts, order),
        part_names=order,
        rigid_group=face.rigid_group,
        group_names=list(RIGID_GROUPS),
        mm_per_unit=face.mm_per_unit,
    )


def face_fapu(face) -> dict[str, float] | None:
    """The face's FAPU in mesh units, or None when its feature points cannot give them."""
    try:
        return measure_fapu(face)
    except InputError as e:  # the description still works without FAPU
        log.info("no FAPU for %s: %s", face.name, e)
        return None


def check_public_load(request: Request, name: str) -> None:
    """Public routes may describe any offered face, but only an admin may make the server build a
    new resolution of a built-in face (``default:300k``); sessions and jobs do that with the key."""
    store = request.app.state.store
    if store.needs_admin(name) and not same(bearer(request), request.app.state.admin_key):
        raise Forbidden(
            f"face {name!r} is not loaded on this server; building a new resolution of a built-in "
            "face needs the admin key (Authorization: Bearer <key>), or use one of GET /v1/faces",
            where="face",
        )


#: Largest uploaded mesh file and annotation (bytes); the request's limit is also max_upload_bytes.
MAX_MESH_BYTES = 64 * 1024 * 1024
MAX_ANNOTATION_BYTES = 16 * 1024 * 1024
#: Meshes read and annotated at once (each in its own process); more get 503.
MAX_CONCURRENT_UPLOADS = 1
#: Room for the multipart framing and form fields around the file.
FORM_OVERHEAD = 64 * 1024 + MAX_ANNOTATION_BYTES


class Busy(Unavailable):
    """Every mesh-reading slot is taken: the client should retry after ``Retry-After`` seconds."""

    headers: ClassVar[dict[str, str]] = {"Retry-After": "5"}


class FaceUploaded(BaseModel):
    """Answer of ``POST /v1/faces``."""

    id: str = Field(
        description="the face's id (hash of its mesh and annotation); usable as its name"
    )
    name: str
    created: bool = Field(
        description="false when the same mesh and annotation were uploaded before"
    )
    annotation: str = Field(
        description="user | automatic | user+automatic: where the annotation came from"
    )
    cached: bool = Field(False, description="the automatic annotation came from the server's cache")
    left_out: dict[str, str] = Field(
        default_factory=dict, description="feature points the annotator left out, with the reason"
    )
    warnings: list[str] = Field(default_factory=list)
    annotate_seconds: float | None = None
    face: FaceInfo


class _MeshUpload(UploadParser):
    """The mesh upload: a ``file`` part and an optional ``annotation`` (JSON content) and ``name``."""

    field_limits: ClassVar[dict[str, int]] = {**FIELD_LIMITS, "annotation": MAX_ANNOTATION_BYTES}

    def _check_kind(
        self,
    ) -> None:  # a mesh, whatever its first bytes (the child tells formats apart)
        self.kind = "mesh"


def _upload_slots(app) -> threading.BoundedSemaphore:
    slots = getattr(app.state, "face_upload_slots", None)
    if slots is None:
        slots = app.state.face_upload_slots = threading.BoundedSemaphore(MAX_CONCURRENT_UPLOADS)
    return slots


def mesh_worker(app) -> mesh_upload.MeshWorker:
    """The app's mesh-reading worker (its process starts on the first upload)."""
    worker = getattr(app.state, "mesh_worker", None)
    if worker is None:
        worker = app.state.mesh_worker = mesh_upload.MeshWorker()
    return worker


_UPLOAD_DOC = multipart_doc(
    file={
        "type": "string",
        "format": "binary",
        "description": "the head mesh: .obj, .ply, .glb/.gltf (buffers embedded) or .stl",
    },
    annotation={
        "type": "string",
        "format": "binary",
        "description": "optional .face.json content (complete or partial; it always wins over the "
        "automatic annotation); never a path",
    },
    name={
        "type": "string",
        "description": "optional name (letters, digits, _ . -); default face-<id>",
    },
)


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=FaceUploaded,
    openapi_extra=_UPLOAD_DOC,
    dependencies=[Depends(require_admin)],
    responses={
        200: {"model": FaceUploaded, "description": "the same face was uploaded before"},
        401: {"model": ErrorBody, "description": "admin key missing or wrong"},
        409: {"model": ErrorBody, "description": "name taken, or too many uploaded faces"},
        413: {"model": ErrorBody, "description": "file or mesh larger than the server's limits"},
        415: {"model": ErrorBody, "description": "not multipart"},
        422: {"model": ErrorBody, "description": "the mesh cannot be read or annotated"},
        503: {"model": ErrorBody, "description": "another mesh is being read; retry"},
    },
)
async def upload_face(request: Request) -> Any:
    """Add a face from a mesh (multipart ``file``), with an optional ``annotation`` and ``name``.

    Without an annotation the server fits its template to the mesh (a few seconds; cached by the
    mesh's hash). Answers 201 with the new face, 200 when the same face exists already.
    """
    app = request.app
    cfg = app.state.config
    limit = min(int(cfg.max_upload_bytes), MAX_MESH_BYTES)
    boundary = boundary_of(request.headers.get("content-type", ""))
    await refuse_declared_oversize(request, limit, FORM_OVERHEAD, "a mesh; decimate the mesh")
    slots = _upload_slots(app)
    if not slots.acquire(blocking=False):
        await drain(request, 0)
        raise Busy("the server is reading another mesh; retry in a few seconds", where="file")
    try:
        with tempfile.TemporaryDirectory(
            prefix="facecast-face-", dir=upload_dir(cfg.data_dir)
        ) as tmp:
            path = Path(tmp) / "upload"
            parser = _MeshUpload(boundary, path, limit)
            parser.limit_variable = "FACECAST_MAX_UPLOAD_BYTES"
            await receive(request, parser)
            unknown = sorted(set(parser.fields) - {"annotation", "name"})
            if unknown:
                raise InputError(
                    f"unknown form field(s) {', '.join(unknown)[:200]}; known: file, annotation, "
                    "name",
                    where="form",
                )
            if parser.size == 0:
                raise InputError("the uploaded file is empty", where="file")
            fmt = mesh_upload.sniff_format(parser.filename, parser.head)
            display = safe_display_name(parser.filename, f"upload.{fmt}")
            name = parser.fields.get("name") or None
            if name is not None:
                app.state.store.check_upload_name(name)
            prepared = await run_in_threadpool(
                mesh_worker(app).prepare, path, fmt, parser.fields.get("annotation"), name=display
            )
    finally:
        slots.release()
    report = prepared.report
    meta = {"source": prepared.source, "file": display, "format": fmt, "report": report}
    store = app.state.store
    name, face_id, created = await run_in_threadpool(
        store.add_upload,
        prepared.vertices,
        prepared.triangles,
        prepared.annotation,
        name=name,
        meta=meta,
    )
    if created and prepared.source != "user":
        log.info(
            "face %s (%s): annotated automatically%s",
            name,
            display,
            " (from the cache)" if prepared.cached else f" in {report.get('seconds', 0):.1f} s",
        )
    info = await describe_face(name, request)
    body = FaceUploaded(
        id=face_id,
        name=name,
        created=created,
        annotation=prepared.source,
        cached=prepared.cached,
        left_out={str(k): str(v) for k, v in (report.get("left_out") or {}).items()},
        warnings=[str(w) for w in report.get("warnings") or []],
        annotate_seconds=report.get("seconds"),
        face=info,
    )
    return JSONResponse(
        body.model_dump(),
        status_code=201 if created else 200,
        headers={"Location": f"/v1/faces/{name}"},
    )


@router.delete(
    "/{name}",
    status_code=status.HTTP_204_NO_CONTENT,
    dependencies=[Depends(require_admin)],
    responses={
        401: {"model": ErrorBody},
        404: {"model": ErrorBody, "description": "no uploaded face"},
    },
)
async def delete_face(name: str, request: Request) -> Response:
    """Delete an uploaded face (by name or id); built-in and configured faces stay."""
    await run_in_threadpool(request.app.state.store.remove_upload, name)
    return Response(status_code=204)


@router.get("", response_model=FaceList)
async def list_faces(request: Request) -> FaceList:
    """Faces a client may name: built-in ones (also as ``default:<vertices>``) and configured meshes."""
    store = request.app.state.store
    builtin = builtin_faces()
    faces = []
    for name in store.names():
        face = store.loaded_face(name)
        faces.append(
            FaceSummary(
                name=name,
                builtin=name in builtin,
                default=name == store.default,
                vertices=face.n_vertices if face is not None else builtin.get(name),
            )
        )
    return FaceList(faces=faces, default=store.default)


@router.get("/{name}", response_model=FaceInfo, responses=_ERRORS)
async def describe_face(name: str, request: Request) -> FaceInfo:
    """Vertices, triangles, parts, feature points, FAPU and bounds of a face (loads it if needed)."""
    store = request.app.state.store
    check_public_load(request, name)
    face = await run_in_threadpool(store.face, name)
    fapu = await run_in_threadpool(store.derived, name, "fapu", face_fapu)
    groups = np.bincount(face.rigid_group, minlength=len(RIGID_GROUPS))
    return FaceInfo(
        name=name,
        vertices=face.n_vertices,
        triangles=int(face.triangles.shape[0]),
        units=face.units,
        mm_per_unit=face.mm_per_unit,
        mesh_hash=face.mesh_hash,
        parts={p: int(len(face.parts[p])) for p in part_order(face)},
        rigid_groups={g: int(groups[i]) for i, g in enumerate(RIGID_GROUPS)},
        feature_points=len(face.feature_points),
        feature_point_ids=sorted(
            face.feature_points, key=lambda s: tuple(int(x) for x in s.split(".") if x.isdigit())
        ),
        fapu=fapu,
        bounds=[face.vertices.min(axis=0).tolist(), face.vertices.max(axis=0).tolist()],
        topology_url=f"/v1/faces/{name}/topology",
    )


@router.get(
    "/{name}/topology",
    response_class=Response,
    responses={
        200: {
            "content": {TOPOLOGY_MEDIA_TYPE: {}},
            "description": "binary topology (protocol/TOPOLOGY.md): rest vertices, triangles, parts, rigid groups",
        },
        **_ERRORS,
    },
)
async def face_topology_route(name: str, request: Request) -> Response:
    """Rest vertices, triangles, per-vertex part ids and rigid groups as one little-endian blob."""
    store = request.app.state.store
    check_public_load(request, name)  # 404 / 403 before any work
    blob = await run_in_threadpool(
        store.derived, name, "topology", lambda face: encode_topology(face_topology(face))
    )
    return Response(
        blob,
        media_type=TOPOLOGY_MEDIA_TYPE,
        headers={
            "Cache-Control": "no-cache",
            "Content-Disposition": f'inline; filename="{name}.topology"',
        },
    )
