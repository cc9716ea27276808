"""The annotated template fitted to a user's mesh: the built-in head at a modest resolution (or the
ICT FaceKit neutral, when ``../shared/data`` has it), in mm.

The template supplies everything an annotation needs — feature points, parts and pivots — in MPEG-4
axes (y up, z forward, x the face's left) and millimetres; ``fit`` warps it onto the user's mesh.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

#: Vertices of the built-in head used as the template (its feature points sit at fixed surface
#: parameters, so the resolution only sets how finely the warp is sampled).
TEMPLATE_VERTICES = 8000
#: Skin subsets that are inside the head (never matched to the user's outer surface).
INNER_SKIN = ("mouth_socket", "eye_socket_l", "eye_socket_r")
#: Rigid or interior parts a user's mesh may carry as separate pieces.
PIECE_PARTS = ("eye_l", "eye_r", "teeth_upper", "teeth_lower", "gums_upper", "gums_lower", "tongue")
#: Template label of each vertex: 0 outer skin, 1 inner skin (mouth and eye sockets), then PIECE_PARTS.
OUTER, INNER = 0, 1


@dataclass(frozen=True)
class Template:
    """The template head.

    Attributes:
        name: ``default`` (the built-in head) or ``ict`` (the ICT FaceKit neutral).
        vertices: ``(N, 3) float64`` mm, MPEG-4 axes.
        triangles: ``(F, 3) int32``.
        label: ``(N,) int8``: ``OUTER``, ``INNER`` or ``2 + PIECE_PARTS.index(part)``.
        outer: ids of the outer skin (the surface matched to the user's mesh).
        feature_points: MPEG-4 id -> template vertex id.
        pivots: ``head``, ``jaw``, ``eye_l``, ``eye_r`` -> ``(3,)`` mm.
        face_region: ids of outer-skin vertices on the face (forehead to chin, cheek to cheek).
        normals: ``(N, 3)`` unit vertex normals.
        mouth_socket: ids of the mouth cavity behind the lips (part of the inner skin).
        profile: the midline landmarks ``detect.profile_landmarks`` finds on the template.
        mouth_corners: where ``detect.mouth_corners`` ends the mouth slit on the template (for
            reference: the template's own 8.3/8.4 lie about 6 mm farther out; on a mesh the
            detected ends are taken as the corners).
        skull_centre: ``(3,)`` mm: centre of the sphere fitted to the skin above the brows.
        cranial: feature points on the smooth skull, off the face (crown, hairline, back of the
            head, nape): nothing on the surface says where along it they are, so they are
            carried over by direction from ``skull_centre``, not by the warp's closest point.
        skin_pieces: ids of each outer-skin piece apart from the head's own surface (the built-in
            head's ears; none for ICT, whose ears are part of its skin).
    """

    name: str
    vertices: np.ndarray
    triangles: np.ndarray
    label: np.ndarray
    outer: np.ndarray
    feature_points: dict[str, int]
    pivots: dict[str, np.ndarray]
    face_region: np.ndarray
    normals: np.ndarray
    mouth_socket: np.ndarray
    profile: dict[str, np.ndarray]
    mouth_corners: dict[str, np.ndarray]
    skull_centre: np.ndarray
    cranial: frozenset[str]
    skin_pieces: tuple[np.ndarray, ...] = ()

    @property
    def profile_heights(self) -> dict[str, float]:
        return {k: float(p[1]) for k, p in self.profile.items()}

    def part_of(self, fp: str) -> str:
        """``"skin"`` or the piece part name carrying feature point ``fp``."""
        lab = int(self.label[self.feature_points[fp]])
        return "skin" if lab < 2 else PIECE_PARTS[lab - 2]

    def fp_position(self, fp: str) -> np.ndarray:
        return self.vertices[self.feature_points[fp]]


@lru_cache(maxsize=1)
def default_template() -> Template:
    """The built-in head as a template (memoised)."""
    from ..procedural import build_default_head

    return template_from_face(build_default_head(TEMPLATE_VERTICES), "default")


#: ICT FaceKit parts that are not part of a head's surface or its pieces (dropped from the template).
ICT_DROPPED = ("eye_extras", "eyelashes")


@lru_cache(maxsize=1)
def ict_template() -> Template:
    """The ICT FaceKit neutral (its shipped annotation) as a template, from ``../shared/data``
    (memoised). Raises InputError when the ICT FaceKit is not there."""
    from ...errors import InputError
    from ...paths import shared_data
    from .. import load_face

    data = shared_data()
    path = data / "ict-facekit" / "generic_neutral_mesh.obj" if data is not None else None
    if path is None or not path.is_file():
        raise InputError(
            "the ICT FaceKit template needs ../shared/data/ict-facekit/generic_neutral_mesh.obj; "
            "use --template default",
            where="template",
        )
    return template_from_face(load_face(path), "ict", drop=ICT_DROPPED)


def ict_available() -> bool:
    """True when the ICT FaceKit template can be built here."""
    from ...paths import shared_data

    data = shared_data()
    return data is not None and (data / "ict-facekit" / "generic_neutral_mesh.obj").is_file()


TEMPLATES = {"default": default_template, "ict": ict_template}


def template_from_face(face, name: str, *, drop: tuple[str, ...] = ()) -> Template:
    """An annotated face (MPEG-4 axes) as a template: in mm, without the parts ``drop``."""
    from ...deform.mesh_graph import components, edge_graph
    from ...deform.normals import vertex_normals
    from .detect import mouth_corners, profile_landmarks, sphere_centre

    keep = np.ones(face.n_vertices, bool)
    for part in drop:
        keep[face.part(part)] = False
    new_id = np.cumsum(keep) - 1
    tri = face.triangles[keep[face.triangles].all(axis=1)]
    tri = new_id[tri].astype(np.int32)
    mm = float(face.mm_per_unit)
    v = face.vertices[keep].astype(np.float64) * mm
    label = np.full(len(v), OUTER, dtype=np.int8)
    for part in (*INNER_SKIN, "eye_socket"):
        ids = face.part(part)
        label[new_id[ids[keep[ids]]]] = INNER
    for i, part in enumerate(PIECE_PARTS):
        ids = face.part(part)
        label[new_id[ids[keep[ids]]]] = 2 + i
    outer = np.nonzero(label == OUTER)[0]
    fps = {k: int(new_id[i]) for k, i in face.feature_points.items() if keep[i]}
    pivots = {k: face.pivot(k).astype(np.float64) * mm for k in ("head", "jaw", "eye_l", "eye_r")}
    nose_base = v[fps["9.15"]]
    chin, brow = v[fps["2.1"]], v[fps["4.3"]]
    p = v[outer]
    front = (
        (p[:, 2] > nose_base[2] - 45)
        & (p[:, 1] > chin[1] - 5)
        & (p[:, 1] < brow[1] + 25)
        & (np.abs(p[:, 0]) < 62)
    )
    outer_tri = tri[(label[tri] == OUTER).all(axis=1)]
    profile = profile_landmarks(v, outer_tri)
    corners = mouth_corners(v, outer_tri, profile["slit"], abs(float(v[fps["8.3"], 0])))
    socket = face.part("mouth_socket")
    normals = vertex_normals(v, tri)
    skull = p[p[:, 1] > brow[1] + 10.0]
    piece = components(edge_graph(v, outer_tri))
    sizes = np.bincount(piece[outer], minlength=piece.max() + 1)
    pieces = tuple(
        np.nonzero(piece == c)[0]
        for c in np.nonzero(sizes)[0]
        if c != np.argmax(sizes) and sizes[c] >= 20
    )
    return Template(
        name=name,
        vertices=v,
        triangles=tri,
        label=label,
        outer=outer,
        feature_points=fps,
        pivots=pivots,
        face_region=outer[front],
        normals=normals,
        mouth_socket=new_id[socket[keep[socket]]],
        profile=profile,
        mouth_corners=corners,
        skull_centre=sphere_centre(skull),
        cranial=_cranial(v, normals, outer, set(outer[front].tolist()), fps),
        skin_pieces=pieces,
    )


#: Mean ``1 - cos`` between a point's normal and the skin's normals within ``SMOOTH_MM`` under
#: which the skin around the point is smooth (a sphere of the head's size gives about 0.01; an ear
#: 0.5 or more).
SMOOTH_COS, SMOOTH_MM = 0.05, 15.0


def _cranial(
    v: np.ndarray, normals: np.ndarray, outer: np.ndarray, face: set[int], fps: dict[str, int]
) -> frozenset[str]:
    """Feature points of the outer skin off the face region whose surroundings are smooth, but not
    the jaw's (MPEG-4 group 2: the jaw angle is placed by the jaw's shape, which the warp fits)."""
    from scipy.spatial import cKDTree

    tree = cKDTree(v[outer])
    on_outer = set(outer.tolist())
    out = set()
    for k, i in fps.items():
        if i in face or i not in on_outer or k.startswith("2."):
            continue
        near = outer[tree.query_ball_point(v[i], SMOOTH_MM)]
        if float(np.mean(1.0 - normals[near] @ normals[i])) < SMOOTH_COS:
            out.add(k)
    return frozenset(out)
