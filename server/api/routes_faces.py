"""``/v1/faces``: the faces this server offers, their description, and their topology for thin clients.

Public (no key): viewers need the topology to draw the vertex frames they receive.
"""
from __future__ import annotations

import logging

import numpy as np
from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import Response

from ...protocol.rest import TOPOLOGY_MEDIA_TYPE, ErrorBody, FaceInfo, FaceList, FaceSummary
from ...protocol.topology import Topology, encode_topology, part_ids_from_parts
from ..errors import Forbidden, InputError
from ..faces import KNOWN_PARTS, RIGID_GROUPS, builtin_faces
from ..mpeg4 import measure_fapu
from .security import bearer, same

log = logging.getLogger(__name__)

router = APIRouter(prefix="/v1/faces", tags=["faces"])

_ERRORS = {404: {"model": ErrorBody, "description": "no such face"},
           403: {"model": ErrorBody, "description": "a new resolution of a built-in face needs the admin key"}}


def part_order(face) -> list[str]:
    """Part names in topology order: the known parts the face has, then the others alphabetically."""
    known = [p for p in KNOWN_PARTS if p in face.parts]
    return known + sorted(p for p in face.parts if p not in KNOWN_PARTS)


def face_topology(face) -> Topology:
    """The ``Topology`` of a face: rest vertices, triangles, part per vertex, rigid group per vertex."""
    order = part_order(face)
    return Topology(
        vertices=face.vertices, triangles=face.triangles,
        part_ids=part_ids_from_parts(face.n_vertices, face.parts, order), part_names=order,
        rigid_group=face.rigid_group, group_names=list(RIGID_GROUPS), mm_per_unit=face.mm_per_unit)


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
        raise Forbidden(f"face {name!r} is not loaded on this server; building a new resolution of a built-in "
                        "face needs the admin key (Authorization: Bearer <key>), or use one of GET /v1/faces",
                        where="face")


@router.get("", response_model=FaceList)
async def list_faces(request: Request) -> FaceList:
    """Faces a client may name: built-in ones (also as ``default:<vertices>``) and configured meshes."""
    store = request.app.state.store
    builtin = builtin_faces()
    faces = []
    for name in store.names():
        face = store.loaded_face(name)
        faces.append(FaceSummary(name=name, builtin=name in builtin, default=name == store.default,
                                 vertices=face.n_vertices if face is not None else builtin.get(name)))
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
        name=name, vertices=face.n_vertices, triangles=int(face.triangles.shape[0]), units=face.units,
        mm_per_unit=face.mm_per_unit, mesh_hash=face.mesh_hash,
        parts={p: int(len(face.parts[p])) for p in part_order(face)},
        rigid_groups={g: int(groups[i]) for i, g in enumerate(RIGID_GROUPS)},
        feature_points=len(face.feature_points),
        feature_point_ids=sorted(face.feature_points, key=lambda s: tuple(int(x) for x in s.split(".")
                                                                          if x.isdigit())),
        fapu=fapu,
        bounds=[face.vertices.min(axis=0).tolist(), face.vertices.max(axis=0).tolist()],
        topology_url=f"/v1/faces/{name}/topology",
    )


@router.get("/{name}/topology", response_class=Response, responses={
    200: {"content": {TOPOLOGY_MEDIA_TYPE: {}},
          "description": "binary topology (protocol/TOPOLOGY.md): rest vertices, triangles, parts, rigid groups"},
    **_ERRORS})
async def face_topology_route(name: str, request: Request) -> Response:
    """Rest vertices, triangles, per-vertex part ids and rigid groups as one little-endian blob."""
    store = request.app.state.store
    check_public_load(request, name)  # 404 / 403 before any work
    blob = await run_in_threadpool(store.derived, name, "topology",
                                   lambda face: encode_topology(face_topology(face)))
    return Response(blob, media_type=TOPOLOGY_MEDIA_TYPE,
                    headers={"Cache-Control": "no-cache",
                             "Content-Disposition": f'inline; filename="{name}.topology"'})
