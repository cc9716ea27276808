"""``facecast bench deform``: per-frame deformation time against the machine's memory bandwidth.

For each vertex count and backend it measures the time of one frame including the upload of D
and the read-back of the vertices, counts the bytes that frame must move with the backend's own
data layout (operator, rest positions, rigid groups, output), and times a plain array copy that
moves the same number of bytes in the same run: that copy time is the bandwidth bound, and
``ms_per_frame / bandwidth_bound_ms`` says how close a backend comes to it. Backends: ``opencl``
(the fused kernel), ``numpy`` (the reference ``NumpyDeformer.deform``) and ``scipy`` (SciPy's CSR
product u = B·D alone). Batch records (``*-batch``) deform many frames of a 25 fps take at once
(at the smallest size measured; at most ``BATCH_MAX_BYTES`` of output).

Timing: every backend and its two copies alternate in blocks of ``BLOCK`` calls (each block after
an untimed call), ``--rounds`` times with all backends interleaved, so that load which comes and
goes on a shared machine falls on a backend and its bound alike; the records give medians (and
bests). ``copy bound`` = the faster of the two copies' medians.

The face is ``load_face("default:N")`` and the operator the feature-point engine's
(``deform.build.get_operator``) when those are available; otherwise a synthetic ellipsoid head
and/or a synthetic operator with the feature-point operator's row structure (each record says which
in ``face`` and ``operator``).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import time

import numpy as np

from ...protocol.quantize import quantize_int16  # noqa: F401
from ..deform.operator import Operator
from ..faces.face import Face

log = logging.getLogger(__name__)

DEFAULT_SIZES = (25_000, 100_000, 500_000)
#: Timed calls per block: a backend and its bandwidth-bound copies alternate in blocks this long.
BLOCK = 5
#: Largest output of the batch test (bytes); fewer frames beyond it (recorded in ``frames``).
BATCH_MAX_BYTES = 256 << 20


# ------------------------------------------------------------------------------- test subjects
def ellipsoid_face(n_vertices: int) -> Face:
    """A closed ellipsoid "head" of about ``n_vertices`` vertices (mm) with jaw and eye groups.

    Used when the procedural head is unavailable; its vertex order is row by row, like a scan.
    """
    rows = max(8, int(round(np.sqrt(n_vertices / 2))))
    cols = max(8, int(round(n_vertices / rows)))
    th = np.linspace(0.05, np.pi - 0.05, rows)
    ph = np.linspace(0, 2 * np.pi, cols, endpoint=False)
    T, P = np.meshgrid(th, ph, indexing="ij")
    v = np.stack([75 * np.sin(T) * np.sin(P), 110 * np.cos(T), 95 * np.sin(T) * np.cos(P)], -1)
    v = v.reshape(-1, 3).astype(np.float32)
    i, j = np.meshgrid(np.arange(rows - 1), np.arange(cols), indexing="ij")
    a, b = i * cols + j, i * cols + (j + 1) % cols
    c, d = a + cols, b + cols
    tri = np.concatenate(
        [np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)]
    )
    front = v[:, 2] > 40
    parts = {
        "tongue": np.flatnonzero(front & (v[:, 1] < -60) & (np.abs(v[:, 0]) < 30)),
        "eye_l": np.flatnonzero((np.hypot(v[:, 0] - 30, v[:, 1] - 25) < 12) & front),
        "eye_r": np.flatnonzero((np.hypot(v[:, 0] + 30, v[:, 1] - 25) < 12) & front),
    }
    return Face(f"ellipsoid:{len(v)}", v, tri.astype(np.int32), "mm", parts)


def synthetic_fp_operator(face: Face, n_controls: int = 78, seed: int = 0) -> Operator:
    """A sparse operator shaped like the feature-point engine's on a real head: controls on the
    front of the face, each constrained on a random subset of axes (as MPEG-4 FPs are); each vertex
    weighted by the (up to 8) controls within a sine falloff radius, normalised per axis; the back
    of the head has empty rows (about 3 entries per row on average, as on the ICT head)."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    v = face.vertices.astype(np.float64)
    front = np.flatnonzero(v[:, 2] > np.percentile(v[:, 2], 60))
    ctrl = rng.choice(front, size=min(n_controls, len(front)), replace=False)
    K = len(ctrl)
    constrained = rng.random((K, 3)) < np.array([0.7, 0.9, 0.55])
    constrained[~constrained.any(axis=1), 1] = True
    radius = 0.16 * float(np.ptp(v[:, 1]))
    dist, nb = cKDTree(v[ctrl]).query(v, k=min(8, K), distance_upper_bound=radius)
    nb = np.where(np.isfinite(dist), nb, 0)
    w = np.where(np.isfinite(dist), np.sin(np.pi / 2 * (1 - np.minimum(dist / radius, 1))), 0.0)
    wa = w[:, :, None] * constrained[nb]  # (V, k, 3) per axis
    wa = wa / np.maximum(wa.sum(axis=1, keepdims=True), 1e-12)
    keep = (wa > 1e-3).any(axis=2)
    order = np.argsort(np.where(keep, nb, K), axis=1, kind="stable")  # ids ascending per row
    nb_s = np.take_along_axis(nb, order, axis=1)
    keep_s = np.take_along_axis(keep, order, axis=1)
    wa_s = np.take_along_axis(wa, order[:, :, None], axis=1)
    indptr = np.zeros(len(v) + 1, dtype=np.int64)
    np.cumsum(keep_s.sum(axis=1), out=indptr[1:])
    return Operator(
        len(v),
        K,
        indptr=indptr,
        indices=nb_s[keep_s],
        weights=wa_s[keep_s].astype(np.float32),
        meta={"engine": "synthetic-fp"},
    )


def load_subject(n_vertices: int, engine: str = "fp") -> tuple[Face, Operator, str, str]:
    """``(face, operator, face_kind, operator_kind)`` for a benchmark of ``n_vertices``."""
    try:
        from ..faces import load_face

        face = load_face(f"default:{n_vertices}")
        face_kind = "default"
        if not np.isfinite(face.vertices).all():
            raise ValueError("the built-in head has non-finite vertices")
    except Exception as e:  # noqa: BLE001 - the bench falls back, logs why and records the kind
        log.warning("built-in head unavailable (%s: %s); using an ellipsoid", type(e).__name__, e)
        face, face_kind = ellipsoid_face(n_vertices), "ellipsoid (procedural head unavailable)"
    operator, operator_kind = _operator_for(face, engine)
    return face, operator, face_kind, operator_kind


# --------------------------------------------------------------------------------- measuring
#: Process CPU seconds (all threads, PoCL's included) of the timed calls, by label: on a loaded
#: machine the wall time mostly measures waiting for a core; CPU time shows the work done.
CPU: dict[str, float] = {}


def _times(fn, n: int, label: str | None = None) -> list[float]:
    """Seconds of ``n`` calls of ``fn`` (after one untimed call)."""
    fn()
    out = []
    c0 = time.process_time()
    for _ in range(n):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    if label:
        CPU[label] = CPU.get(label, 0.0) + time.process_time() - c0
    return out


class CopyMeter:
    """Times a plain array copy that moves ``n_bytes`` (half read, half written): NumPy's copy on
    one core, and PyOpenCL's ``enqueue_copy`` on the OpenCL device (PoCL: both cores); the faster
    one is the bandwidth bound."""

    def __init__(self, n_bytes: int, context=None):
        n = max(1, n_bytes // 8)  # float32 elements per array
        self.n_bytes = 8 * n
        self.src = np.ones(n, dtype=np.float32)
        self.dst = np.empty_like(self.src)
        self.cl = None
        if context is not None:
            import pyopencl as cl

            q = cl.CommandQueue(context)
            a = cl.Buffer(context, cl.mem_flags.READ_WRITE, self.src.nbytes)
            b = cl.Buffer(context, cl.mem_flags.READ_WRITE, self.src.nbytes)
            cl.enqueue_copy(q, a, self.src)
            q.finish()
            self.cl = (cl, q, a, b)

    def numpy_copy(self) -> None:
        np.copyto(self.dst, self.src)

    def device_copy(self) -> None:
        cl, q, a, b = self.cl
        cl.enqueue_copy(q, b, a)
        q.finish()


def bytes_numpy(op: Operator, n_vertices: int, axes_equal: bool) -> tuple[int, int]:
    """``(scipy, numpy)`` bytes per frame: SciPy's CSR product reads indptr, indices and data of
    one matrix (three when the axis columns differ) and writes u; the reference deformer also
    reads the rest positions and writes the vertices."""
    V = n_vertices
    if op.is_sparse:
        one = 4 * (V + 1) + 8 * op.nnz
        csr = one if axes_equal else 3 * one
    else:
        csr = 4 * V * op.n_controls
    scipy_bytes = csr + 12 * op.n_controls + 12 * V
    numpy_bytes = (
        (3 * (4 * (V + 1) + 8 * op.nnz) if op.is_sparse else csr) + 12 * op.n_controls + 36 * V
    )
    return scipy_bytes, numpy_bytes


def measure_size(
    n_vertices: int,
    *,
    backends: tuple[str, ...],
    engine: str,
    frames: int,
    rounds: int,
    batch_frames: int,
    device: str | None,
    face_spec: str | None = None,
) -> list[dict]:
    """Records for one face size (see the module docstring)."""
    import scipy.sparse as sp

    from ..backends import NumpyDeformer

    if face_spec:
        from ..faces import load_face

        face = load_face(face_spec)
        face_kind = face_spec
        op, op_kind = _operator_for(face, engine)
    else:
        face, op, face_kind, op_kind = load_subject(n_vertices, engine)
    V, K = face.n_vertices, op.n_controls
    rng = np.random.default_rng(7)
    Ds = [(rng.standard_normal((K, 3)) * 2.0).astype(np.float32) for _ in range(8)]
    Ts = []
    for i in range(8):
        T = np.tile(np.eye(3, 4, dtype=np.float32), (4, 1, 1))
        c, s_ = np.cos(0.01 * i), np.sin(0.01 * i)
        T[1, :, :3] = np.array([[1, 0, 0], [0, c, -s_], [0, s_, c]], np.float32)
        T[:, :, 3] = rng.standard_normal((4, 3)).astype(np.float32)
        Ts.append(T)
    W = op.weights if op.is_sparse else None
    axes_equal = bool(
        W is None or (np.array_equal(W[:, 0], W[:, 1]) and np.array_equal(W[:, 0], W[:, 2]))
    )
    scipy_bytes, numpy_bytes = bytes_numpy(op, V, axes_equal)

    runners: dict[str, tuple] = {}  # backend -> (callable per frame, bytes per frame, extra)
    ctx = None
    cl_def = None
    if "opencl" in backends:
        from ..backends.opencl import OpenCLDeformer, default_context

        ctx = default_context(device)
        if ctx is None:
            log.warning("no working OpenCL device: skipping the opencl backend")
        else:
            t0 = time.perf_counter()
            cl_def = OpenCLDeformer(
                face.vertices, face.triangles, face.rigid_group, op, context=ctx
            )
            setup_s = time.perf_counter() - t0
            cl_bytes = cl_def.bytes_per_frame()
            k = [0]

            def cl_frame():
                k[0] += 1
                cl_def.deform(Ds[k[0] % 8], Ts[k[0] % 8])

            runners["opencl"] = (
                cl_frame,
                cl_bytes,
                {
                    "device": cl_def.name,
                    "setup_s": round(setup_s, 3),
                    "readback": "zero-copy" if cl_def.zero_copy else "copy",
                    "operator_format": cl_def.format_description(),
                },
            )
    if "numpy" in backends:
        nd = NumpyDeformer(face.vertices, face.triangles, face.rigid_group, op)
        kn = [0]

        def np_frame():
            kn[0] += 1
            nd.deform(Ds[kn[0] % 8], Ts[kn[0] % 8])

        runners["numpy"] = (np_frame, numpy_bytes, {})
    if "scipy" in backends:
        if op.is_sparse:
            if axes_equal:
                B = sp.csr_matrix((W[:, 0], op.indices, op.indptr), shape=(V, K))
                ks = [0]

                def sp_frame():
                    ks[0] += 1
                    B @ Ds[ks[0] % 8]
            else:
                Bs = [
                    sp.csr_matrix((W[:, a], op.indices, op.indptr), shape=(V, K)) for a in range(3)
                ]
                ks = [0]

                def sp_frame():
                    ks[0] += 1
                    d = Ds[ks[0] % 8]
                    for a in range(3):
                        Bs[a] @ d[:, a]
        else:

            def sp_frame():
                op.dense @ Ds[0]

        runners["scipy"] = (
            sp_frame,
            scipy_bytes,
            {
                "what": "u = B·D only"
                + ("" if axes_equal or not op.is_sparse else ", one CSR matrix per axis")
            },
        )

    meters = {name: CopyMeter(b, ctx) for name, (_, b, _) in runners.items()}
    times: dict[str, list[float]] = {n: [] for n in runners}
    copies: dict[str, list[float]] = {n: [] for n in runners}
    dev_copies: dict[str, list[float]] = {n: [] for n in runners}
    for _ in range(rounds):  # interleave backends and copies so that all see the same load
        for name, (fn, _, _) in runners.items():
            reps = frames if name != "numpy" or V <= 100_000 else max(3, frames // 4)
            # A backend and its copies alternate in blocks of BLOCK calls, each block after one
            # untimed call: load that comes and goes (the machine is shared) falls on both alike.
            for done in range(0, reps, BLOCK):
                n = min(BLOCK, reps - done)
                times[name] += _times(fn, n, f"{V}:{name}")
                copies[name] += _times(meters[name].numpy_copy, n, f"{V}:{name}:copy")
                if meters[name].cl is not None:
                    dev_copies[name] += _times(meters[name].device_copy, n)

    records = []
    base = {
        "vertices": V,
        "controls": K,
        "nnz": op.nnz,
        "face": face_kind,
        "operator": op_kind,
        "loadavg_1min": _loadavg(),
    }  # the machine may be shared: how busy it was
    scipy_ms = 1e3 * float(np.median(times["scipy"])) if "scipy" in times else None
    for name, (_, nbytes, extra) in runners.items():
        ms = 1e3 * float(np.median(times[name]))
        np_copy_ms = 1e3 * float(np.median(copies[name]))
        dev_copy_ms = 1e3 * float(np.median(dev_copies[name])) if dev_copies[name] else None
        bound_ms = min(x for x in (np_copy_ms, dev_copy_ms) if x is not None)
        rec = {
            "backend": name,
            "vertices": V,
            "ms_per_frame": round(ms, 4),
            "bytes_per_frame": int(nbytes),
            "bandwidth_bound_ms": round(bound_ms, 4),
            **base,
            "ms_per_frame_min": round(1e3 * min(times[name]), 4),
            "cpu_ms_per_frame": round(1e3 * CPU[f"{V}:{name}"] / len(times[name]), 4),
            "copy_cpu_ms": round(1e3 * CPU[f"{V}:{name}:copy"] / len(copies[name]), 4),
            "bandwidth_bound_ms_min": round(1e3 * min(copies[name] + dev_copies[name]), 4),
            "x_bound": round(ms / bound_ms, 2),
            "copy_gbps": round(nbytes / bound_ms / 1e6, 2),
            "copy_gbps_numpy": round(meters[name].n_bytes / np_copy_ms / 1e6, 2),
            **(
                {"copy_gbps_device": round(meters[name].n_bytes / dev_copy_ms / 1e6, 2)}
                if dev_copy_ms
                else {}
            ),
            "effective_gbps": round(nbytes / ms / 1e6, 2),
            **extra,
        }
        if scipy_ms is not None:
            rec["speedup_vs_scipy"] = round(scipy_ms / ms, 2)
        records.append(rec)
    if cl_def is not None:
        records[[r["backend"] for r in records].index("opencl")].update(
            _breakdown(cl_def, Ds[0], Ts[0], frames)
        )
    if batch_frames > 0:
        n_batch = max(1, min(batch_frames, BATCH_MAX_BYTES // (12 * V)))
        records += _batch_records(face, op, runners, cl_def, Ds, Ts, n_batch, base, records)
    return records


def _loadavg() -> float | None:
    """The 1-minute load average (None where the OS has none)."""
    try:
        return round(os.getloadavg()[0], 2)
    except (AttributeError, OSError):
        return None


def _breakdown(cl_def, D: np.ndarray, T: np.ndarray, frames: int) -> dict:
    """Where an OpenCL frame's time goes: parameter upload, kernel (into a resident buffer), and
    what a copying read-back would cost (the zero-copy path skips it)."""
    up, kern, back = [], [], []
    for _ in range(3):  # interleaved, like the main rounds
        up += _times(lambda: cl_def.upload_frame(D, T, wait=True), frames)
        kern += _times(lambda: cl_def.run_kernel_resident(wait=True), frames)
        back += _times(lambda: cl_def.read_resident(), frames)
    out = {}
    for key, ts in (("upload_ms", up), ("kernel_ms", kern), ("copy_readback_ms", back)):
        out[key] = round(1e3 * float(np.median(ts)), 4)
        out[key.replace("_ms", "_ms_min")] = round(1e3 * min(ts), 4)
    return out


def _batch_records(face, op, runners, cl_def, Ds, Ts, n_frames, base, records) -> list[dict]:
    """Deform ``n_frames`` frames of a 25 fps take in one call; real-time factor = duration / time."""
    from ..backends import NumpyDeformer

    D = np.stack([Ds[i % 8] for i in range(n_frames)])
    T = np.stack([Ts[i % 8] for i in range(n_frames)])
    out = []
    by_name = {r["backend"]: r for r in records}
    deformers = []
    if cl_def is not None:
        deformers.append(("opencl-batch", cl_def, by_name["opencl"]))
    if "numpy" in runners:
        deformers.append(
            (
                "numpy-batch",
                NumpyDeformer(face.vertices, face.triangles, face.rigid_group, op),
                by_name["numpy"],
            )
        )
    for name, d, single in deformers:
        reps = 3 if name.startswith("opencl") else 1
        ts = _times(lambda: d.deform_batch(D, T), reps, f"{name}:{base['vertices']}")
        secs = float(np.median(ts))
        ms = 1e3 * secs / n_frames
        extra = {}
        if name.startswith("opencl"):
            # Into a buffer the caller reuses: no page faults on fresh memory (about half the CPU).
            buf = np.empty((n_frames, base["vertices"], 3), np.float32)
            ts2 = _times(
                lambda: d.deform_batch(D, T, out=buf), reps, f"{name}:{base['vertices']}:out"
            )
            extra = {
                "realtime_factor_into_buffer": round(n_frames / 25 / float(np.median(ts2)), 1),
                "cpu_ms_per_frame_into_buffer": round(
                    1e3 * CPU[f"{name}:{base['vertices']}:out"] / reps / n_frames, 4
                ),
            }
        out.append(
            {
                "backend": name,
                "vertices": base["vertices"],
                "ms_per_frame": round(ms, 4),
                "bytes_per_frame": single["bytes_per_frame"],
                "bandwidth_bound_ms": single["bandwidth_bound_ms"],
                **base,
                "frames": n_frames,
                "fps": 25,
                "realtime_factor": round(n_frames / 25 / secs, 1),
                "realtime_factor_best": round(n_frames / 25 / min(ts), 1),
                "cpu_ms_per_frame": round(
                    1e3 * CPU[f"{name}:{base['vertices']}"] / reps / n_frames, 4
                ),
                "x_bound": round(ms / single["bandwidth_bound_ms"], 2),
                **extra,
            }
        )
    return out


def _operator_for(face: Face, engine: str) -> tuple[Operator, str]:
    if engine == "fp":
        try:
            from ..deform.build import get_operator
            from ..mpeg4 import fap_controls

            _, vertex_ids, constrained = fap_controls(face)
            return get_operator(face, vertex_ids, engine="fp", constrained=constrained), "fp"
        except Exception as e:  # noqa: BLE001 - e.g. the face lacks feature points; logged, recorded
            log.info("feature-point operator unavailable (%s); using a synthetic one", e)
            return synthetic_fp_operator(face), "synthetic-fp"
    rng = np.random.default_rng(1)
    dense = rng.random((face.n_vertices, 84), dtype=np.float32) / 84
    return Operator(
        face.n_vertices, 84, dense=dense, meta={"engine": "synthetic-dense"}
    ), "synthetic-dense"


# --------------------------------------------------------------------------------------- CLI
def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--vertices",
        nargs="+",
        default=[str(n) for n in DEFAULT_SIZES],
        help="face sizes (e.g. 25k 100k 500k; default: %(default)s)",
    )
    p.add_argument(
        "--face", default=None, help="benchmark this face (a mesh path) instead of default:N"
    )
    p.add_argument(
        "--engine",
        choices=("fp", "dense"),
        default="fp",
        help="fp: the sparse feature-point operator; dense: an RBF-like dense one (K=84)",
    )
    p.add_argument(
        "--backends", default="opencl,numpy,scipy", help="comma-separated (default: %(default)s)"
    )
    p.add_argument("--device", default=None, help="OpenCL device ('P:D' or part of its name)")
    p.add_argument(
        "--frames", type=int, default=20, help="timed frames per round (default: %(default)s)"
    )
    p.add_argument(
        "--rounds", type=int, default=5, help="rounds, backends interleaved (default: %(default)s)"
    )
    p.add_argument(
        "--batch-frames",
        type=int,
        default=250,
        help="frames of the batch test at the smallest size (fewer if they would exceed "
        f"{BATCH_MAX_BYTES >> 20} MB), 0 to skip (default: %(default)s)",
    )
    p.add_argument("--json", action="store_true", help="print the records as JSON")


def run(args: argparse.Namespace) -> int:
    from ..faces import parse_count

    backends = tuple(b.strip() for b in args.backends.split(",") if b.strip())
    sizes = [args.vertices[0]] if args.face else args.vertices
    records: list[dict] = []
    counts = [parse_count(size) for size in sizes]
    smallest = counts.index(min(counts))
    for i, n in enumerate(counts):
        records += measure_size(
            n,
            backends=backends,
            engine=args.engine,
            frames=args.frames,
            rounds=args.rounds,
            batch_frames=args.batch_frames if i == smallest else 0,
            device=args.device,
            face_spec=args.face,
        )
    if args.json:
        print(json.dumps(records, indent=1))
    else:
        print(markdown_table(records))
        load = _loadavg()
        if load is not None:
            print(
                f"\nLoad average (1 min) after: {load} on {os.cpu_count()} CPUs (work by other "
                "processes raises the medians; each record has loadavg_1min)."
            )
    return 0


def markdown_table(records: list[dict]) -> str:
    """A short markdown table of benchmark records."""
    lines = [
        (
            "| backend | vertices | ms/frame (median / best) | CPU ms/frame | MB/frame | copy bound ms "
            "(median / best) | × bound | vs scipy | notes |"
        ),
        "|---|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in records:
        notes = []
        if "realtime_factor" in r:
            notes.append(
                f"{r['frames']} frames at 25 fps: {r['realtime_factor']}× real time "
                f"(best run {r['realtime_factor_best']}×"
                + (
                    f"; into a reused buffer {r['realtime_factor_into_buffer']}×, "
                    f"{r['cpu_ms_per_frame_into_buffer']} CPU ms/frame"
                    if "realtime_factor_into_buffer" in r
                    else ""
                )
                + ")"
            )
        if "kernel_ms" in r:
            notes.append(
                f"median (best): upload {r['upload_ms']} ({r['upload_ms_min']}) ms, kernel "
                f"{r['kernel_ms']} ({r['kernel_ms_min']}) ms, a copying read-back would add "
                f"{r['copy_readback_ms']} ({r['copy_readback_ms_min']}) ms; read-back: {r.get('readback')}"
            )
        notes.append(f"{r['operator']} on {r['face']}")
        best = r.get("ms_per_frame_min")
        bound_best = r.get("bandwidth_bound_ms_min")
        lines.append(
            f"| {r['backend']} | {r['vertices']} | {r['ms_per_frame']:.3f}"
            f"{f' / {best:.3f}' if best is not None else ''} | {r.get('cpu_ms_per_frame', '')} "
            f"| {r['bytes_per_frame'] / 1e6:.1f} | {r['bandwidth_bound_ms']:.3f}"
            f"{f' / {bound_best:.3f}' if bound_best is not None else ''} | {r['x_bound']:.2f} "
            f"| {r.get('speedup_vs_scipy', '')} | {'; '.join(notes)} |"
        )
    return "\n".join(lines)
