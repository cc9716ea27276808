"""``get_operator``: build a face's deformation operator, or load it from the on-disk cache.

Operators are cached under ``cache_dir("operators")`` as ``<mesh_hash>-<key>.npz``; the key hashes
everything the result depends on: the mesh (``face.mesh_hash``), the deformable mask and rigid
groups (from the face's parts), the control vertices, the constraints, the engine, its parameters
(after defaults are filled in) and ``ALGORITHM_VERSION``. Files are written atomically; a file
that cannot be read back, or does not match, is rebuilt and replaced.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..paths import cache_dir
from .feature_point import feature_point_operator
from .operator import Operator
from .rbf import rbf_operator
from .shell import shell_operator

log = logging.getLogger(__name__)

#: Bump when a change to an engine changes its output, to invalidate cached operators.
ALGORITHM_VERSION = 5

#: Default parameters per engine, chosen with ``bench/fidelity.py`` (45 ICT expressions rebuilt from
#: their control displacements; mean skin error in mm, no deformation: 0.598):
#:
#: ==========================  =========  ==========  ======
#: fp variant                  78 FPs     68 landm.   both
#: ==========================  =========  ==========  ======
#: paper eq. 5, literal        0.2166     0.2518      0.1934
#: slides ΣW·D/ΣW, literal     0.2174     0.2471      0.1908
#: slides + rim cap + blend    0.2137     0.2434      0.1870
#: clamped, rim cap, no blend  0.2045     0.2223      0.1904
#: clamped + rim cap + blend   0.2010     0.2200      0.1875   <- default
#: ==========================  =========  ==========  ======
#:
#: Of the paper's two normalisations "slides" wins 5 of the 6 mean/p95 numbers. The rim rule
#: (``no_neighbour="cap"``) and ``own_blend`` also make the skin less torn (see
#: ``feature_point``). Un-normalised ΣW·D ("none") is far behind (0.41). ``neighbour_ratio`` 3 beat
#: 2 and 4.
#: rbf: IMQ over surface distance without the affine part (0.242 with the 78 FPs) beat Euclidean
#: distance (0.271) and the affine part (0.321, 0.353 Euclidean); shape 1 beat 0.5 and 2.
#:
#: Version 5 adds smoothness (``bench/deform_quality.py``: creases = change of the dihedral angle
#: of skin edges, p99 per frame; the built-in head's demo and the five Xface FAP files on it and
#: on ICT). ``smooth`` diffuses the fp weight field (strength s: s·(FP spacing / edge)² Jacobi
#: steps, 12 on ``default``, 8 on ICT, capped at 60 on ``default:500k``); ``smooth_hold`` holds
#: the rows within that fraction of each FP's spacing, so a control is not a cone in a smoothed
#: surrounding; ``inner="membrane"`` makes the mouth socket and floating strips (eyelashes) move
#: with the skin they hang from. ICT, 78 FPs, mean / mean p95 skin error mm:
#:
#: ===============================  ===============  ======  ========  ======================
#: fp                               78 FPs           landm.  both      demo creases (default)
#: ===============================  ===============  ======  ========  ======================
#: v4 default (no smoothing)        0.2010 / 1.050   0.2200  0.1875    7.6° mean, 40 flips
#: s 0.3 / 0.5 / 0.7 / 1.5          0.1984 / 0.1985 / 0.1991 / 0.2025 (p95 1.027-1.029)
#: s 0.5, hold 0.15                 0.1979 / 1.024   0.2125  0.1835    4.0°, 6 flips
#: s 0.5, hold 0.3  <- default      0.1970 / 1.022   0.2110  0.1819    4.6°, 4 flips
#: sin² fall-off (+ s 0.5)          0.208 (0.203): worse, ``falloff="sine"`` stays
#: ===============================  ===============  ======  ========  ======================
#:
#: Smoothing more (s 1.5) lowers creases little more and starts to blur the expressions. With
#: ``inner="membrane"`` no socket vertex shows through the skin in the demo (17 before, fp; 12
#: before, rbf: 2). fp stays the default engine: lower error than rbf (0.197 vs 0.242 mm, p95 alike),
#: fewer creases and flips on the built-in head, and sparse (about 6 weights per vertex vs 78 dense).
#:
#: shell (Bickel et al.'s linear shell, ``shell.py``): ``stretch`` = k_s/k_b x (control spacing)².
#: Mean skin error, mm, ICT: ``bench/fidelity.py`` (78 FPs / 68 landmarks / both) and
#: ``bench/mocap_fidelity.py`` (60 markers of the technician layout + 130 anchors, seed 1, every 8th
#: frame: exact displacements / the take through the batch driver):
#:
#: =======  =====  =====  =====  ===============
#: stretch  78 FP  lm68   both   mocap
#: =======  =====  =====  =====  ===============
#: 0        0.370  0.715  0.333  -                (a thin plate: extrapolates over scalp and neck)
#: 1        0.219  0.345  0.200  0.184 / 0.280
#: 3        0.232  0.354  0.211  0.178 / 0.273
#: 10       0.257  0.377  0.230  0.175 / 0.264    <- default (the shell is the mocap engine)
#: 30       0.282  0.401  0.251  0.186 / 0.265
#: =======  =====  =====  =====  ===============
DEFAULTS: dict[str, dict] = {
    "fp": {
        "normalisation": "clamped",
        "no_neighbour": "cap",
        "own_blend": 0.5,
        "neighbour_ratio": 3.0,
        "attach_distance": None,
        "smooth": 0.5,
        "smooth_hold": 0.3,
        "inner": "membrane",
        "falloff": "sine",
    },
    "rbf": {
        "kernel": "imq",
        "shape": 1.0,
        "affine": False,
        "distance": "surface",
        "attach_distance": None,
        "inner": "membrane",
    },
    "shell": {"stretch": 10.0, "attach_distance": None, "inner": "membrane"},
}

ENGINES = {"fp": feature_point_operator, "rbf": rbf_operator, "shell": shell_operator}


def engine_params(engine: str, params: dict) -> dict:
    """The engine's full parameter set: ``params`` over ``DEFAULTS`` (InputError on unknown names)."""
    if engine not in ENGINES:
        raise InputError(
            f"unknown deformation engine {engine!r}; choose one of {', '.join(ENGINES)}",
            where="engine",
        )
    unknown = sorted(set(params) - set(DEFAULTS[engine]))
    if unknown:
        raise InputError(
            f"unknown parameter(s) {', '.join(unknown)} for engine {engine!r}; known: "
            f"{', '.join(DEFAULTS[engine])}",
            where="engine_params",
        )
    return {**DEFAULTS[engine], **params}


def cache_key(
    face, control_vertices: np.ndarray, constrained: np.ndarray, engine: str, params: dict
) -> str:
    """Hex digest naming the cached operator (see module docstring)."""
    h = hashlib.sha256()
    h.update(
        json.dumps(
            {
                "v": ALGORITHM_VERSION,
                "mesh": face.mesh_hash,
                "engine": engine,
                "params": {k: params[k] for k in sorted(params)},
            },
            default=str,
        ).encode()
    )
    arrays = [
        np.asarray(control_vertices, np.int64),
        np.asarray(constrained, bool),
        inner_vertices(face),
        np.asarray(face.deformable, bool),
        np.asarray(face.rigid_group, np.uint8),
    ]
    if engine == "shell":
        arrays.append(
            np.asarray(skin_vertices(face) if skin_vertices(face) is not None else [], np.int64)
        )
    for arr in arrays:
        h.update(str(arr.shape).encode())
        h.update(np.ascontiguousarray(arr).tobytes())
    return h.hexdigest()[:24]


def build_operator(
    face, control_vertices, *, engine: str = "fp", constrained=None, **params
) -> Operator:
    """Build (never cached) the operator of ``engine`` for ``face`` and ``control_vertices (K,)``."""
    full = engine_params(engine, params)
    if engine == "shell":  # the shell covers the skin only
        full["surface"] = skin_vertices(face)
    return ENGINES[engine](
        face.vertices,
        face.triangles,
        control_vertices,
        constrained=constrained,
        deformable=face.deformable,
        rigid_group=face.rigid_group,
        inner_vertices=inner_vertices(face),
        **full,
    )


def skin_vertices(face) -> np.ndarray | None:
    """``(n,)`` vertex ids of the face's ``skin`` part, or None when it has none."""
    skin = face.parts.get("skin")
    return None if skin is None or not len(skin) else np.asarray(skin, dtype=np.int64)


def inner_vertices(face) -> np.ndarray:
    """``(n,)`` vertex ids of the face's inner surfaces hanging from the skin: the mouth socket."""
    return np.asarray(face.parts.get("mouth_socket", np.zeros(0, np.int64)), dtype=np.int64)


def get_operator(
    face, control_vertices, *, engine: str = "fp", constrained=None, cache: bool = True, **params
) -> Operator:
    """The operator mapping ``D (K, 3)`` of ``control_vertices (K,)`` to ``u (V, 3)`` on ``face``.

    Args:
        face: a ``Face``.
        control_vertices: ``(K,)`` vertex ids.
        engine: ``"fp"`` (feature points, sparse), ``"rbf"`` (dense) or ``"shell"`` (linear shell, dense).
        constrained: ``(K, 3) bool`` axes on which each control is driven (default all).
        cache: read and write the on-disk cache.
        **params: engine parameters (see ``DEFAULTS``).
    """
    controls = np.asarray(control_vertices, dtype=np.int64).reshape(-1)
    if constrained is None:
        constrained = np.ones((len(controls), 3), dtype=bool)
    constrained = np.asarray(constrained, dtype=bool)
    full = engine_params(engine, params)
    if not cache:
        return build_operator(face, controls, engine=engine, constrained=constrained, **full)
    key = cache_key(face, controls, constrained, engine, full)
    try:
        path = cache_dir("operators") / f"{face.mesh_hash}-{key}.npz"
    except OSError as e:  # an unwritable cache folder costs a rebuild, not a failure
        log.warning("operator cache unavailable (%s); building without it", e)
        return build_operator(face, controls, engine=engine, constrained=constrained, **full)
    if path.exists():
        try:
            op = Operator.load(path)
            if (op.n_vertices, op.n_controls) == (face.n_vertices, len(controls)) and op.meta.get(
                "key"
            ) == key:
                log.debug("operator cache hit %s", path.name)
                return op
            log.warning("cached operator %s does not match; rebuilding", path)
        except Exception as e:  # noqa: BLE001 - any unreadable file is rebuilt
            log.warning("cached operator %s is unreadable (%s); rebuilding", path, e)
    t0 = time.perf_counter()
    op = build_operator(face, controls, engine=engine, constrained=constrained, **full)
    op.meta["key"] = key
    log.info(
        "built %s operator for %s (%d vertices, %d controls) in %.2f s",
        engine,
        face.name,
        face.n_vertices,
        len(controls),
        time.perf_counter() - t0,
    )
    _save_atomic(op, path)
    return op


def _save_atomic(op: Operator, path: Path) -> None:
    """Write ``op`` to ``path`` atomically (``Operator.save``); a failure only logs a warning."""
    try:
        op.save(path)
    except OSError as e:
        log.warning("could not write operator cache %s: %s", path, e)
