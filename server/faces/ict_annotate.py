"""How facecast determined its ICT FaceKit annotation (feature points and parts) from the neutral mesh.

Run ``python -m facecast.server.faces.ict_annotate generic_neutral_mesh.obj vertex_indices.json -o
server/faces/data/ict_facekit.face.json`` to regenerate the shipped file. Inputs are facts published
with the model: the part vertex ranges of its README and its 68 Multi-PIE landmark vertices; the
remaining MPEG-4 points are picked geometrically here (front-most surface point at a given x/y, extremes
of a part). Units are centimetres; axes already match MPEG-4 (y up, +z forward, +x = the face's left).
"""

from __future__ import annotations

import argparse
import hashlib
import json
from pathlib import Path

import numpy as np

#: Inclusive vertex ranges of the ICT FaceKit parts (its README).
ICT_RANGES: dict[str, tuple[int, int]] = {
    "face": (0, 9408),
    "head_neck": (9409, 11247),
    "mouth_socket": (11248, 13293),
    "eye_socket_l": (13294, 13677),
    "eye_socket_r": (13678, 14061),
    "gums_tongue": (14062, 17038),
    "teeth_upper": (17039, 19246),
    "teeth_lower": (19247, 21450),
    "eye_l": (21451, 23020),
    "eye_r": (23021, 24590),
    "eye_extras": (24591, 25350),
    "eyelashes": (25351, 26718),
}
#: Each ICT eyeball is two concentric spheres: an outer transparent shell (the cornea and the eye's
#: wet surface) and an inner opaque one whose front carries the iris texture.
CORNEA_L, CORNEA_R = (21451, 22220), (23021, 23790)
INNER_EYE_L, INNER_EYE_R = (22221, 23020), (23791, 24590)
#: Iris radius over eyeball radius (an 11-12 mm iris on a 24 mm eyeball), as the built-in head.
IRIS_RATIO = 0.475
UPPER_CENTRAL_INCISORS, LOWER_CENTRAL_INCISORS = (18067, 18218), (20263, 20434)

#: MPEG-4 feature point -> index into the 68 Multi-PIE landmarks (0 = the subject's right jaw end).
FROM_LANDMARK: dict[str, int] = {
    "2.1": 8,
    "2.2": 62,
    "2.3": 66,
    "2.4": 64,
    "2.5": 60,
    "2.6": 63,
    "2.7": 61,
    "2.8": 65,
    "2.9": 67,
    "2.11": 10,
    "2.12": 6,
    "2.13": 13,
    "2.14": 3,
    "3.7": 45,
    "3.8": 39,
    "3.11": 42,
    "3.12": 36,
    "4.1": 22,
    "4.2": 21,
    "4.3": 24,
    "4.4": 19,
    "4.5": 26,
    "4.6": 17,
    "8.1": 51,
    "8.2": 57,
    "8.3": 54,
    "8.4": 48,
    "8.5": 53,
    "8.6": 49,
    "8.7": 55,
    "8.8": 59,
    "8.9": 50,
    "8.10": 52,
    "9.3": 30,
    "9.4": 31,
    "9.5": 35,
    "9.12": 29,
    "9.15": 33,
}


def topology_hash(triangles: np.ndarray) -> str:
    """Hash of the triangle index array (the topology, whatever the vertex positions)."""
    return hashlib.blake2b(
        np.ascontiguousarray(triangles, dtype=np.int32).tobytes(), digest_size=8
    ).hexdigest()


def _ids(name: str) -> np.ndarray:
    a, b = ICT_RANGES[name]
    return np.arange(a, b + 1)


def annotate(v: np.ndarray, triangles: np.ndarray, landmarks: list[int]) -> dict:
    """The annotation dict for an ICT FaceKit neutral ``v (26719, 3)`` given its 68 landmark vertices."""
    v = np.asarray(v, dtype=np.float64)
    face = _ids("face")
    skin = np.r_[face, _ids("head_neck")]
    fp: dict[str, int] = {k: int(landmarks[i]) for k, i in FROM_LANDMARK.items()}
    P = lambda k: v[fp[k]]  # noqa: E731

    def front(x: float, y: float, among: np.ndarray = face, r: float = 0.3) -> int:
        """The front-most (max z) vertex of ``among`` within ``r`` cm of (x, y) in the image plane."""
        d = np.hypot(v[among, 0] - x, v[among, 1] - y)
        near = among[d < r] if np.any(d < r) else among[np.argsort(d)[:5]]
        return int(near[np.argmax(v[near, 2])])

    def nearest(p: np.ndarray, among: np.ndarray) -> int:
        return int(among[np.argmin(np.linalg.norm(v[among] - p, axis=1))])

    lm = lambda i: v[landmarks[i]]  # noqa: E731
    # Chin boss: the midline, a third of the way from the chin bottom up to the lower lip.
    fp["2.10"] = front(0.0, P("2.1")[1] + 0.4 * (P("8.2")[1] - P("2.1")[1]))
    # Eyelids: the lid-margin vertex nearest the middle of the two margin landmarks.
    lids = {"3.1": (43, 44), "3.2": (37, 38), "3.3": (46, 47), "3.4": (40, 41)}
    for k, (a, b) in lids.items():
        fp[k] = nearest((lm(a) + lm(b)) / 2, face)
    # Outer edges of the lids: 0.45 cm above the upper / below the lower lid centre.
    for k, base, dy in (
        ("3.13", "3.1", 0.45),
        ("3.14", "3.2", 0.45),
        ("3.9", "3.3", -0.45),
        ("3.10", "3.4", -0.45),
    ):
        fp[k] = front(P(base)[0], P(base)[1] + dy)
    # Pupils: the front-most vertex of the inner eyeball.
    for k, (a, b) in (("3.5", INNER_EYE_L), ("3.6", INNER_EYE_R)):
        inner = np.arange(a, b + 1)
        fp[k] = int(inner[np.argmax(v[inner, 2])])
    # Cheeks: below the outer eye corner at nostril height; cheekbones 1.3 cm under the lower lid.
    for side, sign in (("l", 1.0), ("r", -1.0)):
        corner = P("3.7" if side == "l" else "3.12")
        lower_lid = P("3.3" if side == "l" else "3.4")
        fp["5.1" if side == "l" else "5.2"] = front(0.85 * corner[0], P("9.15")[1] - 0.3)
        fp["5.3" if side == "l" else "5.4"] = front(0.95 * corner[0], lower_lid[1] - 1.3)
        # Nose wing: just outside the nostril's lower edge; nose-bone edges beside the bridge.
        nostril = P("9.5" if side == "l" else "9.4")
        fp["9.1" if side == "l" else "9.2"] = front(nostril[0] + sign * 0.45, nostril[1] + 0.45)
        fp["9.7" if side == "l" else "9.6"] = front(sign * 0.55, lm(27)[1])
        fp["9.13" if side == "l" else "9.14"] = front(sign * 0.6, lm(29)[1])
    # Teeth: biting edges and roots of the central incisors near the midline.
    for (a, b), top, bottom in (
        (UPPER_CENTRAL_INCISORS, "9.8", "9.10"),
        (LOWER_CENTRAL_INCISORS, "9.11", "9.9"),
    ):
        inc = np.arange(a, b + 1)
        inc = inc[np.abs(v[inc, 0]) < 0.25] if np.any(np.abs(v[inc, 0]) < 0.25) else inc
        fp[top], fp[bottom] = int(inc[np.argmax(v[inc, 1])]), int(inc[np.argmin(v[inc, 1])])
    # Tongue: the gums/tongue vertices farther than 0.35 cm from every tooth and below the upper teeth.
    parts = _split_mouth(v)
    tongue = parts["tongue"]
    fp["6.1"] = int(tongue[np.argmax(v[tongue, 2])])
    zmid = v[tongue, 2].min() + 0.6 * np.ptp(v[tongue, 2])
    band = tongue[np.abs(v[tongue, 2] - zmid) < 0.3]
    mid = band[np.abs(v[band, 0]) < 0.3]
    fp["6.2"] = int(mid[np.argmax(v[mid, 1])])
    fp["6.3"], fp["6.4"] = int(band[np.argmax(v[band, 0])]), int(band[np.argmin(v[band, 0])])
    # Head: top of the skull, back of the skull, top of the spine (back of the neck at mouth height).
    mid_skin = skin[np.abs(v[skin, 0]) < 0.4]
    fp["11.4"] = int(mid_skin[np.argmax(v[mid_skin, 1])])
    behind_top = mid_skin[(v[mid_skin, 1] > v[fp["11.4"], 1] - 0.6) & (mid_skin != fp["11.4"])]
    fp["11.5"] = int(behind_top[np.argmin(v[behind_top, 2])])  # no hair: just behind the top
    eye_y = (P("3.7")[1] + P("3.12")[1]) / 2
    row = mid_skin[np.abs(v[mid_skin, 1] - eye_y) < 0.5]
    fp["11.6"] = int(row[np.argmin(v[row, 2])])
    row = mid_skin[np.abs(v[mid_skin, 1] - P("8.4")[1]) < 0.5]
    fp["7.1"] = int(row[np.argmin(v[row, 2])])
    # Hairline: a brow-to-nose-bottom distance above the brows (facial thirds).
    brow_y = (P("4.3")[1] + P("4.4")[1]) / 2
    hair_y = brow_y + 0.9 * (brow_y - P("9.15")[1])
    fp["11.1"] = front(0.0, hair_y)
    for k, sign in (("11.3", 1.0), ("11.2", -1.0)):
        fp[k] = front(sign * 0.9 * abs(P("3.7")[0]), hair_y - 1.2, among=skin)
    # Ears: the part of the head beside the skull between brow and mouth height.
    for side, sign in (("l", 1.0), ("r", -1.0)):
        hn = _ids("head_neck")
        # ICT's ear is low-poly: its rim is what reaches past 8 cm from the midline (top, back), and
        # the lobe the lowest point past 7.3 cm behind the jaw angle.
        rim = hn[(sign * v[hn, 0] > 8.0) & (v[hn, 1] > P("2.1")[1]) & (v[hn, 1] < brow_y)]
        lobe_zone = hn[(sign * v[hn, 0] > 7.3) & (v[hn, 1] > P("8.4")[1] + 1.5) & (v[hn, 2] < 0.5)]
        top, back = rim[np.argmax(v[rim, 1])], rim[np.argmin(v[rim, 2])]
        low = lobe_zone[np.argmin(v[lobe_zone, 1])]
        k = {
            "l": ("10.1", "10.3", "10.5", "10.7", "10.9"),
            "r": ("10.2", "10.4", "10.6", "10.8", "10.10"),
        }[side]
        fp[k[0]], fp[k[1]], fp[k[2]] = int(top), int(back), int(low)
        # Contact points: the most medial head vertex in front of the ear, level with its top and lobe.
        front_of_ear = hn[
            (sign * v[hn, 0] > 6.0) & (v[hn, 2] > v[top, 2]) & (v[hn, 2] < v[top, 2] + 1.5)
        ]
        for key, y in ((k[3], v[low, 1]), (k[4], v[top, 1])):
            band = front_of_ear[np.abs(v[front_of_ear, 1] - y) < 0.4]
            fp[key] = int(band[np.argmin(sign * v[band, 0])])
    dup = len(fp) - len(set(fp.values()))
    assert dup == 0, f"{dup} feature points share a vertex"

    r = lambda name: [list(ICT_RANGES[name])]  # noqa: E731
    hinge = np.array(
        [0.0, (P("10.7")[1] + P("10.9")[1]) / 2 - 0.3, (P("10.7")[2] + P("10.9")[2]) / 2 + 1.2]
    )
    return {
        "units": "cm",
        "axes": {"up": "+y", "forward": "+z"},
        "topology": {
            "vertices": int(len(v)),
            "triangles": int(len(triangles)),
            "hash": topology_hash(triangles),
        },
        "feature_points": dict(
            sorted(fp.items(), key=lambda kv: tuple(int(p) for p in kv[0].split(".")))
        ),
        "parts": {
            "skin": r("face") + r("head_neck"),
            "mouth_socket": r("mouth_socket"),
            "eye_socket": r("eye_socket_l") + r("eye_socket_r"),
            "eye_l": r("eye_l"),
            "eye_r": r("eye_r"),
            "iris_l": _iris(v, INNER_EYE_L, fp["3.5"]).tolist(),
            "iris_r": _iris(v, INNER_EYE_R, fp["3.6"]).tolist(),
            "cornea_l": [list(CORNEA_L)],
            "cornea_r": [list(CORNEA_R)],
            "eye_extras": r("eye_extras"),
            "eyelashes": r("eyelashes"),
            "teeth_upper": r("teeth_upper"),
            "teeth_lower": r("teeth_lower"),
            "gums_upper": parts["gums_upper"].tolist(),
            "gums_lower": parts["gums_lower"].tolist(),
            "tongue": tongue.tolist(),
        },
        "pivots": {"jaw": [round(float(x), 4) for x in hinge]},
    }


def _iris(v: np.ndarray, inner: tuple[int, int], pupil: int) -> np.ndarray:
    """Vertex ids of the inner eyeball's front disc around ``pupil`` (``IRIS_RATIO`` of its radius)."""
    ids = np.arange(inner[0], inner[1] + 1)
    centre = v[ids].mean(axis=0)
    p = v[ids] - centre
    axis = (v[pupil] - centre) / np.linalg.norm(v[pupil] - centre)
    along = p @ axis
    lateral = np.linalg.norm(p - along[:, None] * axis, axis=1)
    return ids[(along > 0) & (lateral < IRIS_RATIO * np.linalg.norm(v[pupil] - centre))]


def _split_mouth(v: np.ndarray) -> dict[str, np.ndarray]:
    """Split ICT's single gums-and-tongue part into upper gums, lower gums and tongue."""
    from scipy.spatial import cKDTree

    gt = _ids("gums_tongue")
    upper_teeth, lower_teeth = _ids("teeth_upper"), _ids("teeth_lower")
    occlusal = (v[upper_teeth, 1].min() + v[lower_teeth, 1].max()) / 2
    d_up = cKDTree(v[upper_teeth]).query(v[gt])[0]
    d_lo = cKDTree(v[lower_teeth]).query(v[gt])[0]
    upper = gt[(v[gt, 1] > occlusal) & (d_up <= d_lo + 0.1)]
    rest = np.setdiff1d(gt, upper)
    d_lo_rest = cKDTree(v[lower_teeth]).query(v[rest])[0]
    lower = rest[d_lo_rest < 0.35]
    tongue = np.setdiff1d(rest, lower)
    return {"gums_upper": upper, "gums_lower": lower, "tongue": tongue}


def main(argv: list[str] | None = None) -> int:
    from .obj import read_obj

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mesh", type=Path)
    ap.add_argument("indices", type=Path, help="vertex_indices.json of ICT FaceKit")
    ap.add_argument("-o", "--out", type=Path, required=True)
    args = ap.parse_args(argv)
    v, tri = read_obj(args.mesh)
    landmarks = json.loads(args.indices.read_text())["idx_to_landmark_verts"]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(annotate(v, tri, landmarks), separators=(",", ":")) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
