"""Test takes with ground truth, made from the ICT FaceKit head and its 45 artist-made expressions.

Markers sit on skin vertices of the ICT neutral plus stable head markers on vertices no expression
moves (the scalp, where a capture's head jig sits). Two placements (``placement``):

- ``"technician"`` (default): a facial-capture layout sheet (``TECHNICIAN_LAYOUT``) written against
  MPEG-4 feature points, as a mocap technician places markers: dense on the lips and around the
  mouth, the nasolabial folds, cheeks, brows, chin and jaw line, one under the jaw, few on rigid
  skin (none on the nose bridge or forehead centre, which the stable markers cover). Each marker
  is a feature point or the skin point between two (the midpoint snapped to the nearest
  front-facing skin vertex). Nothing is tuned to the expressions; beyond the sheet's length the
  rest are spread as in ``"motion"``.
- ``"motion"``: the 29 feature points of ``MARKER_FPS``, then farthest-point sampling over the
  moving skin with distances scaled by √(largest motion over the expressions).

The face is animated by smooth random blends of the expressions, the head moves rigidly, and the
capture adds noise (~0.5 mm), occlusion gaps and a few spikes. Output: ``take.c3d``, ``take.trc``,
``take.layout.json`` and ``take.truth.npz`` (clean per-frame blend weights, head poses, clean
markers) so benchmarks can rebuild ground-truth vertices.

    python -m facecast.server.mocap.generate --out DIR [--markers 60] [--seconds 10] [--fps 120]
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.interpolate import PchipInterpolator
from scipy.spatial import cKDTree

from ...protocol.markers_file import MarkerTake
from ..errors import InputError
from ..faces.face import Face
from ..paths import shared_data
from .io import write_take
from .sampling import farthest_points
from .stabilise import matrix_from_euler

log = logging.getLogger(__name__)

__all__ = [
    "Truth",
    "generate",
    "ict_dir",
    "load_expressions",
    "load_ict",
    "load_truth",
    "truth_vertices",
]

#: Feature points that real marker layouts put a marker on (Kshirsagar's 27 on FPs, thesis fiducials).
MARKER_FPS: tuple[str, ...] = (
    "2.1",
    "2.10",
    "8.1",
    "8.2",
    "8.3",
    "8.4",
    "8.5",
    "8.6",
    "8.7",
    "8.8",
    "4.1",
    "4.2",
    "4.3",
    "4.4",
    "4.5",
    "4.6",
    "5.1",
    "5.2",
    "5.3",
    "5.4",
    "9.1",
    "9.2",
    "9.3",
    "2.13",
    "2.14",
    "3.9",
    "3.10",
    "3.1",
    "3.2",  # upper eyelids (Kshirsagar's layout has eyelid markers)
)

#: Capture space: a Z-up lab, the actor facing -y, the head ~1.6 m above the floor (face axes -> lab).
LAB_R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
LAB_O = np.array([120.0, -300.0, 1600.0])


def ict_dir() -> Path:
    """``../shared/data/ict-facekit`` (InputError when absent)."""
    d = shared_data()
    if d is None or not (d / "ict-facekit" / "generic_neutral_mesh.obj").is_file():
        raise InputError("the ICT FaceKit data (../shared/data/ict-facekit) is not available")
    return d / "ict-facekit"


def face_path() -> Path:
    """The ICT neutral mesh the generated takes are made on (absolute)."""
    return (ict_dir() / "generic_neutral_mesh.obj").resolve()


def load_ict() -> Face:
    """The ICT neutral head as a ``Face`` (centimetres)."""
    from ..faces import load_face

    return load_face(face_path())


def load_expressions(face: Face | None = None) -> tuple[list[str], np.ndarray]:
    """The 45 ICT expressions as ``(names, deltas (E, V, 3) float32)`` from the neutral (cm), cached
    under ``cache_dir("mocap")`` (``prior.load_basis`` of the kit's ``expressions/`` folder)."""
    from .prior import load_basis

    face = face or load_ict()
    basis = load_basis(face, ict_dir() / "expressions")
    assert basis is not None  # a named folder gives a basis or raises
    return basis.names, basis.deltas


#: A facial-capture layout sheet (see the module docstring), in the order a technician would drop
#: markers when fewer are available: ``(name, feature point)`` or ``(name, (fp_a, fp_b))`` for the
#: skin point between two feature points (the face's left = +x = odd MPEG-4 numbers = ``_L``).
TECHNICIAN_LAYOUT: tuple[tuple[str, str | tuple[str, str]], ...] = (
    # lips: the outer contour (corners, peaks, middles and between)
    ("LIP_UP", "8.1"),
    ("LIP_LO", "8.2"),
    ("LIP_CORNER_L", "8.3"),
    ("LIP_CORNER_R", "8.4"),
    ("LIP_UP_L", "8.5"),
    ("LIP_UP_R", "8.6"),
    ("LIP_LO_L", "8.7"),
    ("LIP_LO_R", "8.8"),
    ("LIP_PEAK_R", "8.9"),
    ("LIP_PEAK_L", "8.10"),
    ("LIP_UP_OUT_L", ("8.5", "8.3")),
    ("LIP_UP_OUT_R", ("8.6", "8.4")),
    ("LIP_LO_OUT_L", ("8.7", "8.3")),
    ("LIP_LO_OUT_R", ("8.8", "8.4")),
    # chin and jaw
    ("CHIN", "2.1"),
    ("CHIN_FRONT", "2.10"),
    ("CHIN_L", "2.11"),
    ("CHIN_R", "2.12"),
    ("JAW_L", "2.13"),
    ("JAW_R", "2.14"),
    ("JAW_MID_L", ("2.11", "2.13")),
    ("JAW_MID_R", ("2.12", "2.14")),
    # around the mouth: philtrum, above the upper lip, below the lower lip
    ("PHILTRUM", ("8.1", "9.15")),
    ("MOUTH_UP_L", ("8.5", "9.1")),
    ("MOUTH_UP_R", ("8.6", "9.2")),
    ("LABIOMENTAL", ("8.2", "2.10")),
    ("MOUTH_LO_L", ("8.7", "2.11")),
    ("MOUTH_LO_R", ("8.8", "2.12")),
    # brows
    ("BROW_IN_L", "4.1"),
    ("BROW_IN_R", "4.2"),
    ("BROW_MID_L", "4.3"),
    ("BROW_MID_R", "4.4"),
    ("BROW_OUT_L", "4.5"),
    ("BROW_OUT_R", "4.6"),
    # cheeks and nasolabial folds
    ("CHEEK_L", "5.1"),
    ("CHEEK_R", "5.2"),
    ("CHEEKBONE_L", "5.3"),
    ("CHEEKBONE_R", "5.4"),
    ("NASOLABIAL_UP_L", ("9.1", "5.1")),
    ("NASOLABIAL_UP_R", ("9.2", "5.2")),
    ("NASOLABIAL_LO_L", ("8.3", "5.1")),
    ("NASOLABIAL_LO_R", ("8.4", "5.2")),
    ("CHEEK_LO_L", ("5.1", "2.13")),
    ("CHEEK_LO_R", ("5.2", "2.14")),
    # nose wings, eyes, forehead
    ("NOSTRIL_L", "9.1"),
    ("NOSTRIL_R", "9.2"),
    ("UNDER_EYE_L", "3.9"),
    ("UNDER_EYE_R", "3.10"),
    ("LID_L", "3.1"),
    ("LID_R", "3.2"),
    ("FOREHEAD_L", ("4.3", "11.3")),
    ("FOREHEAD_R", ("4.4", "11.2")),
    ("CHEEK_OUT_L", ("5.3", "2.13")),
    ("CHEEK_OUT_R", ("5.4", "2.14")),
    ("NOSE_TIP", "9.3"),
)

PLACEMENTS: tuple[str, ...] = ("technician", "motion")


def technician_markers(
    face: Face, budget: int, taken: list[int]
) -> tuple[list[str], list[int], dict[str, dict]]:
    """The first ``budget`` markers of ``TECHNICIAN_LAYOUT`` the face can place (needs its feature
    points): ``(names, vertex ids, layout entries)``; vertices in ``taken`` are skipped."""
    import trimesh

    v = face.vertices.astype(np.float64)
    skin = face.part("skin")
    normals = trimesh.Trimesh(face.vertices, face.triangles, process=False).vertex_normals
    front = skin[normals[skin, 2] > 0.2]  # front-facing skin: never the inner lip rolls
    tree = cKDTree(v[front])
    names: list[str] = []
    verts: list[int] = []
    spec: dict[str, dict] = {}
    used = {int(t) for t in taken}
    for name, where in TECHNICIAN_LAYOUT:
        if len(names) >= budget:
            break
        fps = (where,) if isinstance(where, str) else where
        if not all(f in face.feature_points for f in fps):
            continue
        if isinstance(where, str):
            vid, entry = int(face.feature_points[where]), {"fp": where}
        else:
            vid = int(
                front[tree.query((face.fp_position(fps[0]) + face.fp_position(fps[1])) / 2)[1]]
            )
            entry = {"vertex": vid}
        if vid in used:
            continue
        used.add(vid)
        names.append(name), verts.append(vid)
        spec[name] = entry
    return names, verts, spec


def choose_markers(
    face: Face, deltas: np.ndarray, n_markers: int, n_stable: int = 5, placement: str = "technician"
) -> tuple[list[str], np.ndarray, dict[str, dict], list[str]]:
    """Pick marker vertices: ``(names, vertices, layout markers, stable names)`` (see the module
    docstring for ``placement``)."""
    if placement not in PLACEMENTS:
        raise InputError(
            f"placement must be one of {', '.join(PLACEMENTS)}, not {placement!r}",
            where="placement",
        )
    v = face.vertices.astype(np.float64)
    skin = face.part("skin")
    motion = np.linalg.norm(deltas, axis=2).max(axis=0) * face.mm_per_unit  # (V,) mm
    eye_y = (face.fp_position("3.5")[1] + face.fp_position("3.6")[1]) / 2
    nose_z = face.fp_position("9.3")[2]
    mw = abs(face.fp_position("8.3")[0] - face.fp_position("8.4")[0])
    # Stable: skin that no expression moves, on the front and top of the skull (on the ICT head
    # only the scalp above the hairline is that still: where a capture's head jig sits).
    # The technician's is a headband: round the head above the eyes (forehead, temples, back),
    # widely spread so that the pose, pitch included, is well determined at the face.
    front = (
        np.ones(len(v), dtype=bool) if placement == "technician" else v[:, 2] > nose_z - 3.0 * mw
    )
    still = skin[(motion[skin] < 0.01) & front[skin] & (v[skin, 1] > eye_y)]
    if len(still) < n_stable:
        raise InputError(f"only {len(still)} candidate vertices for stable markers on {face.name}")
    st = still[farthest_points(v[still], n_stable)]
    # Face markers: feature points on moving skin first, then evenly spread moving skin.
    names, verts, spec = [], [], {}
    for i, vid in enumerate(st):
        n = f"HEAD{i + 1}"
        names.append(n), verts.append(int(vid))
        spec[n] = {"vertex": int(vid)}
    budget = n_markers - len(st)
    if placement == "technician":
        tn, tv, tspec = technician_markers(face, budget, verts)
        names += tn
        verts += tv
        spec.update(tspec)
        budget -= len(tn)
    for fp in MARKER_FPS if placement == "motion" else ():
        if budget <= 0:
            break
        vid = face.feature_points.get(fp)
        if vid is None or vid in verts:
            continue
        n = "FP" + fp.replace(".", "_")
        names.append(n), verts.append(int(vid))
        spec[n] = {"fp": fp}
        budget -= 1
    face_region = np.zeros(face.n_vertices, dtype=bool)
    face_region[skin] = True
    import trimesh

    normals = trimesh.Trimesh(face.vertices, face.triangles, process=False).vertex_normals
    # front-facing moving skin (not the lip rolls, nostrils or under the chin), off the eyelids
    chin_y = face.fp_position("2.1")[1]
    cand = np.flatnonzero(
        face_region
        & (motion > 0.5)
        & (normals[:, 2] > 0.3)
        & (v[:, 2] > nose_z - 1.6 * mw)
        & (np.abs(v[:, 0]) < 1.5 * mw)
        & (v[:, 1] < eye_y + 1.2 * mw)
        & (v[:, 1] > chin_y - 0.1 * mw)
    )  # the face, not the neck or chest
    lids = np.concatenate(
        [
            np.flatnonzero(np.linalg.norm(v - face.pivot(e), axis=1) < 0.45 * mw)
            for e in ("eye_l", "eye_r")
        ]
    )
    cand = np.setdiff1d(cand, lids)
    # denser where the skin moves more (as real layouts crowd the mouth and brows)
    cand = np.setdiff1d(cand, verts)
    pick = cand[
        farthest_points(v[cand], budget, seed_points=v[verts], weights=np.sqrt(motion[cand]))
    ]
    for j, vid in enumerate(pick):
        n = f"M{j + 1:02d}"
        names.append(n), verts.append(int(vid))
        spec[n] = {"vertex": int(vid)}
    return names, np.asarray(verts, dtype=np.int64), spec, [f"HEAD{i + 1}" for i in range(len(st))]


def _smooth_random(
    rng, n: int, fps: float, lo: float, hi: float, period: tuple[float, float], hold: int
) -> np.ndarray:
    """``(n,)`` smooth random curve in [lo, hi] (PCHIP through random keys), 0 for the first ``hold``."""
    keys_t = [0.0, hold / fps]
    while keys_t[-1] < n / fps + 1:
        keys_t.append(keys_t[-1] + rng.uniform(*period))
    vals = np.r_[0.0, 0.0, rng.uniform(lo, hi, len(keys_t) - 2)]
    return PchipInterpolator(keys_t, vals)(np.arange(n) / fps)


def blend_weights(rng, names: list[str], n: int, fps: float, hold: int) -> np.ndarray:
    """``(n, E)`` sparse, smooth random expression weights in [0, 1]; all 0 for the first ``hold`` frames."""
    e = len(names)
    w = np.zeros((n, e))
    keys = [0, hold]
    while keys[-1] < n + int(fps):
        keys.append(keys[-1] + int(rng.uniform(0.25, 0.7) * fps))
    kv = np.zeros((len(keys), e))
    usable = [i for i, nm in enumerate(names) if not nm.startswith("Pupil")]
    for k in range(2, len(keys)):
        act = rng.choice(usable, size=int(rng.integers(2, 5)), replace=False)
        kv[k, act] = rng.uniform(0.4, 1.0, len(act))
        if rng.random() < 0.1:
            kv[k] = 0.0  # back to rest now and then
    w = PchipInterpolator(np.asarray(keys) / fps, kv, axis=0)(np.arange(n) / fps)
    return np.clip(w, 0.0, 1.0)


@dataclass
class Truth:
    """Ground truth of a generated take (see ``generate``)."""

    fps: float
    names: list[str]
    vertices: np.ndarray  # (M,) marker vertex ids on the ICT head
    stable: list[str]
    expression_names: list[str]
    weights: np.ndarray  # (T, E)
    head_r: np.ndarray  # (T, 3, 3) capture-space head rotation (mm frame), x = R x_neutral + t
    head_t: np.ndarray  # (T, 3) mm
    clean: np.ndarray  # (T, M, 3) mm, capture space, noise-free
    local: np.ndarray  # (T, M, 3) mm, capture space, head motion removed
    lab_r: np.ndarray
    lab_o: np.ndarray


def load_truth(path: str | Path) -> Truth:
    with np.load(path) as z:
        return Truth(
            float(z["fps"]),
            [str(s) for s in z["names"]],
            z["vertices"],
            [str(s) for s in z["stable"]],
            [str(s) for s in z["expression_names"]],
            z["weights"],
            z["head_r"],
            z["head_t"],
            z["clean"],
            z["local"],
            z["lab_r"],
            z["lab_o"],
        )


def truth_vertices(face: Face, deltas: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """``(T, V, 3) float32`` ground-truth meshes (face units, no head motion) for ``(T, E)`` weights."""
    flat = deltas.reshape(len(deltas), -1)
    return (
        face.vertices[None] + (weights.astype(np.float32) @ flat).reshape(len(weights), -1, 3)
    ).astype(np.float32)


def generated_take(
    *,
    n_markers: int,
    seconds: float,
    fps: float,
    seed: int,
    n_stable: int,
    placement: str = "technician",
):
    """Generate a C3D take in a temporary folder and read it back (for benchmarks).

    Returns ``(truth, take, layout)``: the ground truth, the ``MarkerTake`` as a user's reader sees
    it, and the layout as a dict.
    """
    import json
    import tempfile

    from .io import read_take

    with tempfile.TemporaryDirectory() as tmp:
        paths = generate(
            tmp,
            n_markers=n_markers,
            seconds=seconds,
            fps=fps,
            seed=seed,
            formats=("c3d",),
            n_stable=n_stable,
            placement=placement,
        )
        return (
            load_truth(paths["truth"]),
            read_take(paths["c3d"]),
            json.loads(Path(paths["layout"]).read_text()),
        )


def generate(
    out: str | Path,
    *,
    n_markers: int = 60,
    seconds: float = 10.0,
    fps: float = 120.0,
    seed: int = 1,
    noise_mm: float = 0.5,
    gaps: bool = True,
    spikes: bool = True,
    head_motion: bool = True,
    formats: tuple[str, ...] = ("c3d", "trc"),
    name: str = "take",
    n_stable: int = 5,
    placement: str = "technician",
) -> dict[str, Path]:
    """Write a generated take into folder ``out``; returns the written paths by kind. ``n_markers``
    counts the ``n_stable`` head markers too; ``placement``: see the module docstring."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    face = load_ict()
    enames, deltas = load_expressions(face)
    names, verts, spec, stable = choose_markers(face, deltas, n_markers, n_stable, placement)
    n = max(2, round(seconds * fps))
    hold = min(n - 1, int(0.5 * fps))
    w = blend_weights(rng, enames, n, fps, hold)
    mm = face.mm_per_unit
    local_face = (
        face.vertices[verts][None].astype(np.float64)
        + np.einsum("te,emc->tmc", w, deltas[:, verts].astype(np.float64))
    ) * mm  # (T, M, 3) mm, face axes
    if head_motion:
        ang = np.stack(
            [
                _smooth_random(rng, n, fps, -a, a, (0.6, 1.5), hold)
                for a in np.radians([8.0, 12.0, 5.0])
            ],
            -1,
        )
        trans = np.stack(
            [_smooth_random(rng, n, fps, -a, a, (0.8, 2.0), hold) for a in (12.0, 8.0, 10.0)], -1
        )
    else:
        ang, trans = np.zeros((n, 3)), np.zeros((n, 3))
    r_face = matrix_from_euler(ang)  # (T, 3, 3) about the head pivot, face axes
    pivot = face.pivot("head") * mm
    posed = np.einsum("tij,tmj->tmi", r_face, local_face - pivot) + pivot + trans[:, None, :]
    lab = posed @ LAB_R.T + LAB_O
    local_lab = local_face @ LAB_R.T + LAB_O
    # capture-space pose: lab = R lab_neutral + t
    head_r = LAB_R @ r_face @ LAB_R.T
    head_t = (
        LAB_O
        + (pivot - np.einsum("tij,j->ti", r_face, pivot) + trans) @ LAB_R.T
        - np.einsum("tij,j->ti", head_r, LAB_O)
    )
    noisy = lab + rng.normal(0.0, noise_mm, lab.shape)
    m = len(names)
    after_hold = (
        n > hold + 1
    )  # gaps and spikes go after the neutral hold (none in a take that short)
    if gaps and after_hold:
        for j in range(m):
            for _ in range(int(rng.integers(0, 3))):
                if rng.random() < 0.5:
                    continue
                length = int(rng.integers(3, int(0.3 * fps)))
                start = int(rng.integers(hold + 1, max(hold + 2, n - length)))
                if stable[:] and names[j] in stable and j % 2:
                    continue  # keep most stable markers visible
                noisy[start : start + length, j] = np.nan
        for _ in range(2):
            f = int(rng.integers(hold + 1, n))
            noisy[f] = np.nan  # a frame where the capture lost everything
    if spikes and after_hold:
        for _ in range(max(1, n // 300)):
            j, f = int(rng.integers(m)), int(rng.integers(hold + 1, n))
            d = rng.normal(size=3)
            noisy[f : f + int(rng.integers(1, 3)), j] += (
                d / np.linalg.norm(d) * rng.uniform(8.0, 25.0)
            )
    take = MarkerTake(names, noisy, float(fps), "mm")
    paths: dict[str, Path] = {}
    for fmt in formats:
        paths[fmt] = write_take(take, out / f"{name}.{fmt}")
    layout = {"units": "mm", "stable": stable, "neutral_frame": 0, "markers": spec}
    paths["layout"] = out / f"{name}.layout.json"
    # its vertex ids are the ICT head's: say so, so that a render on another face names the right one
    paths["layout"].write_text(json.dumps({**layout, "face": str(face_path())}, indent=1) + "\n")
    # The same markers for any face with MPEG-4 feature points: markers on FPs stay tied, the rest are
    # placed automatically (retargeting the ICT actor onto another head).
    portable = {n: (s if "fp" in s else {}) for n, s in spec.items()}
    paths["layout_fp"] = out / f"{name}.layout-fp.json"
    paths["layout_fp"].write_text(json.dumps({**layout, "markers": portable}, indent=1) + "\n")
    paths["truth"] = out / f"{name}.truth.npz"
    np.savez_compressed(
        paths["truth"],
        fps=fps,
        names=np.array(names),
        vertices=verts,
        stable=np.array(stable),
        expression_names=np.array(enames),
        weights=w.astype(np.float32),
        head_r=head_r,
        head_t=head_t,
        clean=lab,
        local=local_lab,
        lab_r=LAB_R,
        lab_o=LAB_O,
    )
    log.info("wrote %s: %d frames, %d markers (%d stable)", out, n, m, len(stable))
    return paths


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m facecast.server.mocap.generate", description=__doc__.split("\n\n")[0]
    )
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument(
        "--markers", type=int, default=60, help="markers in all, stable ones included (default 60)"
    )
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--fps", type=float, default=120.0)
    p.add_argument(
        "--stable", type=int, default=5, help="stable head markers among them (default 5)"
    )
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--noise", type=float, default=0.5, help="marker noise, mm (default 0.5)")
    p.add_argument("--clean", action="store_true", help="no gaps, no spikes")
    p.add_argument("--no-head-motion", action="store_true")
    p.add_argument("--formats", default="c3d,trc", help="comma-separated: c3d, trc, csv")
    p.add_argument("--name", default="take")
    p.add_argument(
        "--placement",
        choices=PLACEMENTS,
        default="technician",
        help="marker placement: a technician's layout sheet or motion-weighted (default technician)",
    )
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    try:
        paths = generate(
            a.out,
            n_markers=a.markers,
            seconds=a.seconds,
            fps=a.fps,
            seed=a.seed,
            noise_mm=a.noise,
            gaps=not a.clean,
            spikes=not a.clean,
            head_motion=not a.no_head_motion,
            formats=tuple(f.strip() for f in a.formats.split(",") if f.strip()),
            name=a.name,
            n_stable=a.stable,
            placement=a.placement,
        )
    except InputError as e:
        print(f"generate: {e}", file=sys.stderr)
        return 2
    for k, v in paths.items():
        print(f"{k}: {v}")
    take = paths.get("c3d") or next(iter(paths.values()))
    print(
        f"render on the actor's own head: facecast render {take} --face {face_path()} -o take.glb\n"
        f"retarget onto the built-in head: facecast render {take} --layout {paths['layout_fp']} -o take.npz"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
