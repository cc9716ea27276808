"""The OpenCL backend (PyOpenCL): the NumPy reference's results, near the memory-bandwidth limit.

Per frame the device reads the resident operator, rest positions and rigid groups, and writes the
vertices; only the frame's parameters (transforms and ``D``, a few hundred bytes) go up. On a CPU
device (PoCL) device memory is host memory, so kernels read the parameters from, and write the
vertices straight into, NumPy arrays (``CL_MEM_USE_HOST_PTR``): no upload or read-back copies. On
other devices the vertices are copied back from a resident buffer.

One work-item deforms a *slice* of 16 consecutive vertices as float16 vectors: ``u = B·D``, plus
the rest position, then its rigid transform (jaw, eyes, head), all in one kernel; batches loop
over frames inside the kernel, so a slice's operator stays in L1 from frame to frame. The slice
goes out as (V, 3) rows through a fixed 3x8 shuffle network; launches whose data outgrow half the
last-level cache write with non-temporal stores (``STREAM_FRACTION``). Per frame the host sets only
the launch's buffers (the other kernel arguments are set once). PoCL's worker threads are pinned
one per CPU (``select.pin_pocl_workers``).

Device format of a sparse operator (``pack_operator``): per slice, columns of 16 weights (one per
vertex; three planes when the operator's axis columns differ, else one). A *shared* slice stores
one control id per column: neighbouring vertices are moved by the same feature points, so the
union of the 16 rows is rarely wider than the longest row (100% of the slices of the built-in
500k head, with 1.12 stored weights per non-zero), and each column costs one ``D`` load for 16
vertices. Other slices are ELL (16 ids per column). Ids are ``uchar`` for ``K < 256`` (else ``ushort``/``uint``); ELL padding points at an
extra all-zero control ``K``; shared columns hold zero weights for vertices that do not use the
control. A dense operator (RBF, linear shell) is K shared columns per slice. Weights stay float32,
so results equal NumPy's to float32 rounding (different summation order and FMA).
"""
from __future__ import annotations

import functools
import logging
import threading
import warnings
from dataclasses import dataclass

import numpy as np

from ...protocol.quantize import dequantize_int16  # noqa: F401  (re-exported for symmetry)
from ..deform.operator import Operator
from .select import context_label, default_context, probe_devices  # noqa: F401  (re-exported)

log = logging.getLogger(__name__)

#: Vertices per slice: one work-item deforms one slice as float16 vectors (two AVX2 registers,
#: two independent chains). 8 (float8) also works; 16 measured 10-20% less CPU per frame here.
SLICE = 16
#: Work-group size (in slices) of the deform kernel; in vertices for the others.
LOCAL_SLICES = 64
LOCAL_SIZE = 128
#: Work-items for the min/max pass of the int16 quantisation.
MINMAX_ITEMS = 64
#: Floats per rigid transform on the device (4 float4 columns of the 3x4 matrix).
T_FLOATS = 16
#: Write the vertices with non-temporal (streaming) stores when a launch's data -- resident operator
#: and rest positions plus the frames it writes -- exceed this fraction of the device's last-level
#: cache (CPU devices; ``deform``/``deform_batch``): allocating the output in the cache would evict
#: the operator the next frame reads again, and costs a read of every output line first (memcpy
#: streams large copies for the same reasons). 500k vertices: 23 MB per frame, 32 MB L3 here:
#: 12% less CPU per frame. Smaller faces keep ordinary stores (their output stays in cache for the
#: consumer).
STREAM_FRACTION = 0.5


def _aos_store8(x: str, y: str, z: str, o: str, stream: bool = False) -> str:
    """OpenCL C storing float8 ``x``, ``y``, ``z`` (8 vertices, SoA) as 24 AoS floats at ``o``: six
    in-lane shuffles and three 128-bit lane moves, 12 instructions with the stores (LLVM's lowering
    of the generic ``(float16)(ox.s0, oy.s0, ...)`` took ~75 per 16 vertices: 15% of the frame's CPU).
    ``stream``: non-temporal stores (``o`` must be 32-byte aligned)."""
    sh = "__builtin_shufflevector"
    if stream:
        def store(v: str, i: int) -> str:
            return f"__builtin_nontemporal_store({v}, (__global float8 *)({o}) + {i});"
    else:
        def store(v: str, i: int) -> str:
            return f"vstore8({v}, {i}, {o});"
    return f"""{{
            const float8 xy = {sh}({x}, {y}, 0, 2, 8, 10, 4, 6, 12, 14);  // x0 x2 y0 y2 | x4 x6 y4 y6
            const float8 yz = {sh}({y}, {z}, 1, 3, 9, 11, 5, 7, 13, 15);  // y1 y3 z1 z3 | y5 y7 z5 z7
            const float8 zx = {sh}({z}, {x}, 0, 2, 9, 11, 4, 6, 13, 15);  // z0 z2 x1 x3 | z4 z6 x5 x7
            const float8 a = {sh}(xy, zx, 0, 2, 8, 10, 4, 6, 12, 14);     // x0 y0 z0 x1 | x4 y4 z4 x5
            const float8 b = {sh}(yz, xy, 0, 2, 9, 11, 4, 6, 13, 15);     // y1 z1 x2 y2 | y5 z5 x6 y6
            const float8 c = {sh}(zx, yz, 1, 3, 9, 11, 5, 7, 13, 15);     // z2 x3 y3 z3 | z6 x7 y7 z7
            {store(f"{sh}(a, b, 0, 1, 2, 3, 8, 9, 10, 11)", 0)}
            {store(f"{sh}(c, a, 0, 1, 2, 3, 12, 13, 14, 15)", 1)}
            {store(f"{sh}(b, c, 4, 5, 6, 7, 12, 13, 14, 15)", 2)}
        }}"""


def _deform_source(S: int) -> str:
    """OpenCL C of the ``deform`` and ``deform_stream`` kernels for slices of ``S`` (8 or 16)
    vertices; ``deform_stream`` writes the vertices with non-temporal stores (see ``STREAM_FRACTION``)."""
    return _deform_kernel(S, "deform", False) + _deform_kernel(S, "deform_stream", True)


def _deform_kernel(S: int, name: str, stream: bool) -> str:
    hx = "0123456789abcdef"
    lanes = range(S)

    def vec(parts: list[str]) -> str:
        return f"(VF)({', '.join(parts)})"

    inter = [f"o{c}.s{hx[v]}" for v in lanes for c in "xyz"]  # AoS order of the slice's output
    stores = "\n        ".join(_aos_store8(f"ox{h}", f"oy{h}", f"oz{h}", f"o + {24 * i}", stream)
                                 for i, h in enumerate((".lo", ".hi") if S == 16 else ("",)))
    tail = "\n        ".join(f"if ({i} < n) o[{i}] = {x};" for i, x in enumerate(inter))
    gathers = "\n            ".join(f"const float4 d{l} = D[id[{l}]];" for l in lanes)
    # Non-temporal stores are weakly ordered: drain them before the work-group ends (on CPU
    # devices, the only ones that stream, a work-group's items run in order on one thread).
    fence = ("\n    if (get_local_id(0) + 1 == get_local_size(0)) STREAM_FENCE();" if stream else "")
    dx, dy, dz = (vec([f"d{l}.{c}" for l in lanes]) for c in "xyz")
    return f"""
#ifndef SN
#define SN {S}
#define VF float{S}
#define VI int{S}
#define VLOAD vload{S}
#define VSTORE vstore{S}
#define CONVERT_VI convert_int{S}
#if defined(__x86_64__) || defined(__i386__)
#define STREAM_FENCE() __builtin_ia32_sfence()
#else
#define STREAM_FENCE() mem_fence(CLK_GLOBAL_MEM_FENCE)
#endif

// (ox, oy, oz) = the 3x4 transform at T (4 float4 columns) applied to (px, py, pz).
#define TRANSFORM(T, ox, oy, oz) do {{ \\
        const float4 c0 = (T)[0], c1 = (T)[1], c2 = (T)[2], c3 = (T)[3]; \\
        ox = fma((VF)(c0.x), px, fma((VF)(c1.x), py, fma((VF)(c2.x), pz, (VF)(c3.x)))); \\
        oy = fma((VF)(c0.y), px, fma((VF)(c1.y), py, fma((VF)(c2.y), pz, (VF)(c3.y)))); \\
        oz = fma((VF)(c0.z), px, fma((VF)(c1.z), py, fma((VF)(c2.z), pz, (VF)(c3.z)))); \\
    }} while (0)
#endif

// One work-item deforms one slice of SN consecutive vertices, as SN-wide vectors, in frames
// 0..n_frames-1 (the slice's operator stays in L1 from one frame to the next):
// out[f, v] = T[f, g[v]] . (rest[v] + sum_j w[v, j] * D[f, id[v, j]]).
// params per frame (pstride4 float4): n_groups transforms as 4 float4 columns, then D as float4
// rows ((K + 1) rows, the last one zero). rest is SoA per slice (x[SN] y[SN] z[SN]); sgroup[s] is
// the slice's rigid group, or 255 when its vertices differ (then group[v] is read per vertex).
__kernel void {name}(const uint n_vertices,
                     const uint n_controls,
                     __global const uint *col_ptr,
                     __global const uint *id_ptr,
                     __global const IDX_T *ids,
                     __global const float *w,
                     __global const float *rest,
                     __global const uchar *sgroup,
                     __global const uchar *group,
                     __global const float4 *params,
                     const uint pstride4,
                     const uint n_groups,
                     const uint n_frames,
                     __global float *out)
{{
    const uint s = get_global_id(0);
    const uint v0 = s * SN;
    for (uint f = 0; v0 < n_vertices && f < n_frames; ++f) {{
    __global const float4 *P = params + (size_t)f * pstride4;
    __global const float4 *D = P + 4 * n_groups;
    VF sx = (VF)(0.0f), sy = (VF)(0.0f), sz = (VF)(0.0f);  // u = B.D of the slice
#if DENSE
    for (uint j = 0; j < n_controls; ++j) {{
        const float4 d = D[j];
        const VF wj = VLOAD(0, w + ((size_t)s * n_controls + j) * SN);
        sx = fma(wj, (VF)(d.x), sx);
        sy = fma(wj, (VF)(d.y), sy);
        sz = fma(wj, (VF)(d.z), sz);
    }}
#else
    const uint c0 = col_ptr[s], width = col_ptr[s + 1] - c0;
    const uint i0 = id_ptr[s];
    __global const float *wc = w + (size_t)c0 * (SN * AXES);
    if (id_ptr[s + 1] - i0 == width) {{
        // Shared columns: column j is one control for all SN vertices (zero weight where unused).
        for (uint j = 0; j < width; ++j) {{
            const float4 d = D[ids[i0 + j]];
            __global const float *wj = wc + j * (SN * AXES);
#if AXES == 3
            sx = fma(VLOAD(0, wj), (VF)(d.x), sx);
            sy = fma(VLOAD(1, wj), (VF)(d.y), sy);
            sz = fma(VLOAD(2, wj), (VF)(d.z), sz);
#else
            const VF wv = VLOAD(0, wj);
            sx = fma(wv, (VF)(d.x), sx);
            sy = fma(wv, (VF)(d.y), sy);
            sz = fma(wv, (VF)(d.z), sz);
#endif
        }}
    }} else {{
        // ELL columns: entry j of each vertex, each with its own control.
        for (uint j = 0; j < width; ++j) {{
            __global const IDX_T *id = ids + i0 + j * SN;
            {gathers}
            __global const float *wj = wc + j * (SN * AXES);
#if AXES == 3
            sx = fma(VLOAD(0, wj), {dx}, sx);
            sy = fma(VLOAD(1, wj), {dy}, sy);
            sz = fma(VLOAD(2, wj), {dz}, sz);
#else
            const VF wv = VLOAD(0, wj);
            sx = fma(wv, {dx}, sx);
            sy = fma(wv, {dy}, sy);
            sz = fma(wv, {dz}, sz);
#endif
        }}
    }}
#endif
    __global const float *r = rest + (size_t)s * (3 * SN);
    const VF px = VLOAD(0, r) + sx, py = VLOAD(1, r) + sy, pz = VLOAD(2, r) + sz;
    VF ox, oy, oz;
    const uchar g = sgroup[s];
    if (g != 255) {{
        TRANSFORM(P + 4 * g, ox, oy, oz);
    }} else {{
        // Vertices of several rigid groups: every group's transform, each lane keeps its own.
        const VI gv = CONVERT_VI(VLOAD(0, group + v0));
        ox = oy = oz = (VF)(0.0f);
        for (uint k = 0; k < n_groups; ++k) {{
            VF ax, ay, az;
            TRANSFORM(P + 4 * k, ax, ay, az);
            const VI m = gv == (VI)((int)k);
            ox = select(ox, ax, m);
            oy = select(oy, ay, m);
            oz = select(oz, az, m);
        }}
    }}
    __global float *o = out + ((size_t)f * n_vertices + v0) * 3;
    if (v0 + SN <= n_vertices) {{
        {stores}
    }} else {{  // the last, partial slice: 3 * (n_vertices - v0) floats
        const uint n = 3 * (n_vertices - v0);
        {tail}
    }}
    }}{fence}
}}
"""


KERNEL_SOURCE = r"""
// Build defines: AXES (1|3), IDX_T (uchar|ushort|uint), DENSE (0|1); the deform kernel comes
// from _deform_source(SLICE).

// Cross product per triangle (length = 2 * area), for the area-weighted vertex normals.
__kernel void face_normals(const uint n_faces, __global const int *tri,
                           __global const float *verts, __global float *fn)
{
    const uint t = get_global_id(0);
    if (t >= n_faces) return;
    const int a = tri[3 * t], b = tri[3 * t + 1], c = tri[3 * t + 2];
    const float3 p0 = vload3(a, verts), p1 = vload3(b, verts), p2 = vload3(c, verts);
    vstore3(cross(p1 - p0, p2 - p0), t, fn);
}

// Sum of the incident triangles' cross products, normalised; (0, 0, 0) when it vanishes.
__kernel void vertex_normals(const uint n_vertices, __global const uint *adj_ptr,
                             __global const uint *adj, __global const float *fn,
                             __global float *out)
{
    const uint v = get_global_id(0);
    if (v >= n_vertices) return;
    float3 n = (float3)(0.0f);
    for (uint e = adj_ptr[v]; e < adj_ptr[v + 1]; ++e) n += vload3(adj[e], fn);
    const float len = sqrt(n.x * n.x + n.y * n.y + n.z * n.z);
    vstore3(len > 0.0f ? n / len : (float3)(0.0f), v, out);
}

// Per-axis min and max over contiguous chunks of the vertices: partial[i] = (min xyz, max xyz).
__kernel void minmax_partial(const uint n_vertices, __global const float *verts,
                             __global float *partial)
{
    const uint i = get_global_id(0), n = get_global_size(0);
    const uint chunk = (n_vertices + n - 1) / n;
    const uint lo = min(i * chunk, n_vertices), hi = min(lo + chunk, n_vertices);
    float3 mn = (float3)(INFINITY), mx = (float3)(-INFINITY);
    for (uint v = lo; v < hi; ++v) {
        const float3 p = vload3(v, verts);
        mn = fmin(mn, p);
        mx = fmax(mx, p);
    }
    vstore3(mn, 2 * i, partial);
    vstore3(mx, 2 * i + 1, partial);
}

// q = clip(rint((v - offset) / scale), -32767, 32767), as protocol/quantize.py.
__kernel void quantize(const uint n_vertices, __global const float *verts,
                       const float ox, const float oy, const float oz,
                       const float sx, const float sy, const float sz,
                       __global short *q)
{
    const uint v = get_global_id(0);
    if (v >= n_vertices) return;
    const float3 p = vload3(v, verts);
    const float3 r = rint((p - (float3)(ox, oy, oz)) / (float3)(sx, sy, sz));
    vstore3(convert_short3(clamp(r, -32767.0f, 32767.0f)), v, q);
}
"""


@dataclass
class PackedOperator:
    """An ``Operator`` in the device's format (see the module docstring).

    Slice ``s`` (vertices ``S*s .. S*s+S-1``, ``S = slice``) owns columns ``col_ptr[s] ..
    col_ptr[s+1]`` of ``weights`` (``S * axes`` floats per column: lane-major, one plane per axis
    when ``axes == 3``) and ids ``id_ptr[s] .. id_ptr[s+1]``: one per column for a *shared* slice
    (each column is one control for all S vertices), or S per column for an *ELL* slice (column j
    is entry j of each vertex;
    padding points at the all-zero control ``K``). A dense operator is K shared columns per slice
    with implicit ids (``col_ptr``/``id_ptr``/``ids`` unused).
    """

    n_vertices: int
    n_controls: int
    n_padded: int
    slice: int
    dense: bool
    axes: int
    col_ptr: np.ndarray
    id_ptr: np.ndarray
    ids: np.ndarray
    weights: np.ndarray

    @property
    def idx_ctype(self) -> str:
        return {1: "uchar", 2: "ushort", 4: "uint"}[self.ids.dtype.itemsize]

    @property
    def n_columns(self) -> int:
        return int(self.weights.size // (self.slice * self.axes))

    @property
    def shared_fraction(self) -> float:
        """Fraction of the non-empty slices stored as shared columns."""
        if self.dense:
            return 1.0
        ncol = np.diff(self.col_ptr.astype(np.int64))
        nid = np.diff(self.id_ptr.astype(np.int64))
        busy = ncol > 0
        return float(np.mean(nid[busy] == ncol[busy])) if busy.any() else 1.0

    @property
    def nbytes(self) -> int:
        """Bytes of operator data one frame reads."""
        meta = 0 if self.dense else self.ids.nbytes + self.col_ptr.nbytes + self.id_ptr.nbytes
        return int(self.weights.nbytes + meta)

    def to_dense(self) -> np.ndarray:
        """``(V, K, 3) float32`` dense weights read back from the packed layout (for checks)."""
        K, A, S = self.n_controls, self.axes, self.slice
        out = np.zeros((self.n_padded, K + 1, 3), np.float32)
        w = self.weights.reshape(-1, A, S)
        for s in range(self.n_padded // S):
            lanes = np.arange(S) + S * s
            if self.dense:
                cols, ids = s * K + np.arange(K), np.arange(K)[:, None].repeat(S, 1)
            else:
                c0, c1 = int(self.col_ptr[s]), int(self.col_ptr[s + 1])
                i0, i1 = int(self.id_ptr[s]), int(self.id_ptr[s + 1])
                cols = np.arange(c0, c1)
                ids = self.ids[i0:i1].astype(np.int64)
                ids = ids[:, None].repeat(S, 1) if i1 - i0 == c1 - c0 else ids.reshape(-1, S)
            for j, c in enumerate(cols):
                for a in range(3):
                    np.add.at(out, (lanes, ids[j], a), w[c, min(a, A - 1)])
        return out[:self.n_vertices, :K]


def _id_dtype(n_ids: int) -> np.dtype:
    for dt in (np.uint8, np.uint16, np.uint32):
        if n_ids <= np.iinfo(dt).max + 1:
            return np.dtype(dt)
    raise ValueError("too many controls")


#: A slice is stored as shared columns when that needs at most this many times the columns of
#: ELL (neighbouring vertices mostly share their controls: on the built-in 500k head every slice
#: qualifies). Shared columns cost one D load per column instead of one per vertex.
SHARED_MAX_RATIO = 1.5


def pack_operator(op: Operator, slice_size: int = SLICE) -> PackedOperator:
    """Convert ``op`` to the device format for slices of ``slice_size`` (pure NumPy, vectorised)."""
    V, K, S = op.n_vertices, op.n_controls, slice_size
    n_slices = max(1, -(-V // S))
    Vp = n_slices * S
    id_dtype = _id_dtype(K + 1)
    if not op.is_sparse:
        # weights[s, k, lane] = dense[s * S + lane, k]
        B = np.zeros((Vp, K), dtype=np.float32)
        B[:V] = op.dense
        w = np.ascontiguousarray(B.reshape(n_slices, S, K).transpose(0, 2, 1)).ravel()
        z = np.zeros(1, np.uint32)
        return PackedOperator(V, K, Vp, S, True, 1, z, z, np.zeros(1, id_dtype), w)
    W = op.weights
    same = bool(np.array_equal(W[:, 0], W[:, 1]) and np.array_equal(W[:, 0], W[:, 2]))
    A = 1 if same else 3
    indptr = op.indptr.astype(np.int64)
    rows = np.repeat(np.arange(V, dtype=np.int64), np.diff(indptr))
    pos = np.arange(indptr[-1], dtype=np.int64) - indptr[rows]      # entry's position in its row
    s, lane = rows // S, rows % S
    k = op.indices.astype(np.int64)
    lengths = np.zeros(Vp, dtype=np.int64)
    lengths[:V] = np.diff(indptr)
    ell_width = lengths.reshape(n_slices, S).max(axis=1)
    # Shared columns: the sorted distinct controls of each slice.
    pairs, rank_of = np.unique(s * (K + 1) + k, return_inverse=True)
    pair_slice = pairs // (K + 1)
    union = np.bincount(pair_slice, minlength=n_slices)
    first = np.zeros(n_slices + 1, dtype=np.int64)
    np.cumsum(union, out=first[1:])
    rank = rank_of.reshape(-1) - first[s]                               # column of each entry
    shared = union <= SHARED_MAX_RATIO * ell_width
    ncol = np.where(shared, union, ell_width)
    nid = np.where(shared, union, S * ell_width)
    col_ptr = np.zeros(n_slices + 1, dtype=np.int64)
    np.cumsum(ncol, out=col_ptr[1:])
    id_ptr = np.zeros(n_slices + 1, dtype=np.int64)
    np.cumsum(nid, out=id_ptr[1:])
    if max(col_ptr[-1] * S * A, id_ptr[-1]) >= 2**32:
        raise ValueError("operator too large for 32-bit offsets")
    ids = np.full(int(id_ptr[-1]), K, dtype=id_dtype)                 # ELL padding -> zero control K
    w = np.zeros(int(col_ptr[-1]) * S * A, dtype=np.float32)
    # shared slices
    ps = shared[pair_slice]
    ids[id_ptr[pair_slice[ps]] + (np.arange(len(pairs)) - first[pair_slice])[ps]] = (pairs % (K + 1))[ps]
    es = shared[s]
    col = np.where(es, col_ptr[s] + rank, col_ptr[s] + pos)
    base = col * (S * A) + lane
    eg = ~es
    ids[id_ptr[s[eg]] + pos[eg] * S + lane[eg]] = k[eg]
    for a in range(A):
        np.add.at(w, base + a * S, W[:, a])
    return PackedOperator(V, K, Vp, S, False, A, col_ptr.astype(np.uint32), id_ptr.astype(np.uint32), ids, w)


def aligned_empty(shape: tuple[int, ...], dtype, align: int = 128) -> np.ndarray:
    """``np.empty`` whose data pointer is ``align``-byte aligned (what zero-copy buffers want)."""
    dtype = np.dtype(dtype)
    n = int(np.prod(shape)) * dtype.itemsize
    raw = np.empty(n + align, dtype=np.uint8)
    off = (-raw.ctypes.data) % align
    return raw[off:off + n].view(dtype).reshape(shape)


def _serialised(method):
    """Run ``method`` under the deformer's lock: one queue and one parameter block per deformer,
    so calls from several threads (server sessions) take turns."""
    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        with self._lock:
            return method(self, *args, **kwargs)

    return wrapper


_programs: dict[tuple, object] = {}
_programs_lock = threading.Lock()


def _program(ctx, defines: dict[str, object]):
    """The kernel program for ``ctx`` with ``defines``, built once per process."""
    import pyopencl as cl

    key = (id(ctx), tuple(sorted(defines.items())))
    with _programs_lock:
        hit = _programs.get(key)
        if hit is None:
            opts = [f"-D{k}={v}" for k, v in sorted(defines.items())]
            # -w: clang's notes that float16 arguments change the ABI without AVX-512 are harmless
            opts += ["-cl-fp32-correctly-rounded-divide-sqrt", "-w"]
            source = _deform_source(int(defines["SLICE"])) + KERNEL_SOURCE
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", cl.CompilerWarning)
                hit = (ctx, cl.Program(ctx, source).build(options=opts))
            _programs[key] = hit  # holding ctx keeps id(ctx) unique
        return hit[1]


class OpenCLDeformer:
    """Per-frame deformation on an OpenCL device; the interface of ``NumpyDeformer``.

    ``out[v] = T[g[v]] · [rest[v] + (B·D)[v]; 1]``. Operator, rest positions, rigid groups and
    triangle adjacency are uploaded once and stay on the device; kernels are built and run once at
    construction (PoCL caches the compiled code under ``cache_dir("pocl")``).

    Args:
        rest: ``(V, 3) float32`` neutral vertices.
        triangles: ``(F, 3) int32``.
        rigid_group: ``(V,) uint8`` group index per vertex.
        operator: the compiled ``Operator`` (K controls).
        context: a ``pyopencl.Context`` (default: ``default_context()``).
        zero_copy: let kernels read parameters from and write results into host arrays directly
            (default, and only possible, on CPU devices; False forces the copying path).
        slice_size: vertices per work-item (8 or 16; see ``SLICE``).
    """

    def __init__(self, rest: np.ndarray, triangles: np.ndarray, rigid_group: np.ndarray,
                 operator: Operator, context=None, *, zero_copy: bool | None = None,
                 slice_size: int = SLICE):
        import pyopencl as cl

        self._cl = cl
        self._lock = threading.RLock()
        ctx = context if context is not None else default_context()
        if ctx is None:
            from ..errors import FacecastError

            raise FacecastError("no working OpenCL device; install pocl-opencl-icd or use --backend numpy")
        self.context = ctx
        self.device = ctx.devices[0]
        self.name = f"opencl:{context_label(ctx)}"
        self.queue = cl.CommandQueue(ctx)
        self.rest = np.ascontiguousarray(rest, dtype=np.float32)
        self.triangles = np.ascontiguousarray(triangles, dtype=np.int32)
        self.operator = operator
        self.n_vertices = int(self.rest.shape[0])
        self.n_controls = int(operator.n_controls)
        self.n_faces = int(self.triangles.shape[0])
        if operator.n_vertices != self.n_vertices:
            raise ValueError(f"operator has {operator.n_vertices} vertices, the mesh {self.n_vertices}")
        group = np.ascontiguousarray(rigid_group, dtype=np.uint8)
        self.n_groups = int(group.max(initial=0)) + 1
        cpu = bool(self.device.type & cl.device_type.CPU)
        # Zero-copy only where device memory is host memory (PoCL and other CPU drivers).
        self.zero_copy = cpu if zero_copy is None else bool(zero_copy and cpu)

        if slice_size not in (8, 16):
            raise ValueError("slice_size must be 8 or 16")
        self.packed = pack_operator(operator, slice_size)
        p = self.packed
        S = p.slice
        self._program = _program(ctx, {"AXES": p.axes, "IDX_T": p.idx_ctype, "DENSE": int(p.dense), "SLICE": S})
        self._k_deform = cl.Kernel(self._program, "deform")
        self._k_deform_stream = cl.Kernel(self._program, "deform_stream")
        self._cache_bytes = int(self.device.global_mem_cache_size) if cpu else 0
        self._resident_bytes = self.packed.nbytes + 12 * self.packed.n_padded  # operator and rest positions
        self._k_face_normals = cl.Kernel(self._program, "face_normals")
        self._k_vertex_normals = cl.Kernel(self._program, "vertex_normals")
        self._k_minmax = cl.Kernel(self._program, "minmax_partial")
        self._k_quantize = cl.Kernel(self._program, "quantize")

        ro = cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR

        def nonempty(a: np.ndarray) -> np.ndarray:  # OpenCL buffers cannot be empty
            return a if a.size else np.zeros(1, a.dtype)

        self._col_ptr = cl.Buffer(ctx, ro, hostbuf=nonempty(p.col_ptr))
        self._id_ptr = cl.Buffer(ctx, ro, hostbuf=nonempty(p.id_ptr))
        self._ids = cl.Buffer(ctx, ro, hostbuf=nonempty(p.ids))
        self._w = cl.Buffer(ctx, ro, hostbuf=nonempty(p.weights))
        n_slices = p.n_padded // S
        rest_p = np.zeros((p.n_padded, 3), np.float32)
        rest_p[:self.n_vertices] = self.rest
        group_p = np.zeros(p.n_padded, np.uint8)
        group_p[:self.n_vertices] = group
        group_p[self.n_vertices:] = group_p[max(0, self.n_vertices - 1)]
        gs = group_p.reshape(n_slices, S)
        sgroup = np.where((gs == gs[:, :1]).all(axis=1), gs[:, 0], 255).astype(np.uint8)
        self._rest = cl.Buffer(ctx, ro, hostbuf=np.ascontiguousarray(
            rest_p.reshape(n_slices, S, 3).transpose(0, 2, 1)))
        self._sgroup = cl.Buffer(ctx, ro, hostbuf=sgroup)
        self._sgroup_host = sgroup
        self._group = cl.Buffer(ctx, ro, hostbuf=group_p)
        self._n_slices = n_slices
        self._global_slices = -(-n_slices // LOCAL_SLICES) * LOCAL_SLICES
        # Per-frame parameters: transforms, then D as float4 rows with an all-zero control K at the end.
        self._pstride = -(-(self.n_groups * T_FLOATS + 4 * (self.n_controls + 1)) // 16) * 16
        self._params_host = aligned_empty((self._pstride,), np.float32)
        self._params_host[:] = 0
        if self.zero_copy:  # the kernel reads the host array itself: no upload command per frame
            self._params_single = self._host_buffer(self._params_host, cl.mem_flags.READ_ONLY)
        else:
            self._params_single = cl.Buffer(ctx, cl.mem_flags.READ_ONLY, self._params_host.nbytes)
        self._params = self._params_single
        self._verts = cl.Buffer(ctx, cl.mem_flags.READ_WRITE, max(12, 12 * self.n_vertices))
        self._minmax_host = np.empty((MINMAX_ITEMS, 2, 3), dtype=np.float32)
        self._minmax = cl.Buffer(ctx, cl.mem_flags.WRITE_ONLY, self._minmax_host.nbytes)
        self._global = (-(-max(1, self.n_vertices) // LOCAL_SIZE) * LOCAL_SIZE,)
        self._set_deform_args()
        self._warm_up()

    # ----------------------------------------------------------------------------------- helpers
    def _prepare_normals(self) -> None:
        """Upload triangles and the vertex -> triangle adjacency (CSR) once."""
        cl = self._cl
        F, V = self.n_faces, self.n_vertices
        flat = self.triangles.ravel().astype(np.int64)
        order = np.argsort(flat, kind="stable")
        adj = (order // 3).astype(np.uint32)
        adj_ptr = np.zeros(V + 1, dtype=np.uint32)
        np.cumsum(np.bincount(flat, minlength=V), out=adj_ptr[1:])
        ro = cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR
        self._tri = cl.Buffer(self.context, ro, hostbuf=self.triangles if F else np.zeros(3, np.int32))
        self._adj = cl.Buffer(self.context, ro, hostbuf=adj if adj.size else np.zeros(1, np.uint32))
        self._adj_ptr = cl.Buffer(self.context, ro, hostbuf=adj_ptr)
        self._fn = cl.Buffer(self.context, cl.mem_flags.READ_WRITE, max(12, 12 * F))

    def _warm_up(self) -> None:
        """Run every kernel once so that the first real frame pays no compilation."""
        self._prepare_normals()
        D = np.zeros((self.n_controls, 3), np.float32)
        T = np.tile(np.eye(3, 4, dtype=np.float32), (self.n_groups, 1, 1))
        v = self.deform(D, T)
        self.normals(v)
        self.deform_quantized(D, T)

    def _check(self, D: np.ndarray, transforms: np.ndarray, batch: bool) -> tuple[np.ndarray, np.ndarray]:
        D = np.asarray(D, dtype=np.float32)
        T = np.asarray(transforms, dtype=np.float32)
        lead = D.shape[:1] if batch else ()
        D = D.reshape(lead + (self.n_controls, 3))
        if T.ndim != len(lead) + 3 or T.shape[-2:] != (3, 4) or T.shape[:len(lead)] != lead:
            raise ValueError(f"transforms must be {lead + ('G', 3, 4)}, not {T.shape}")
        if T.shape[-3] < self.n_groups:
            raise ValueError(f"the mesh has {self.n_groups} rigid groups; transforms has {T.shape[-3]}")
        if not (np.isfinite(D).all() and np.isfinite(T).all()):
            # (zero weights would otherwise spread a NaN to vertices that do not use the control)
            from ..errors import InputError

            raise InputError("control displacements and transforms must be finite (fill mocap gaps first)",
                             where="D" if not np.isfinite(D).all() else "transforms")
        return D, T[..., :self.n_groups, :, :]

    def _fill_params(self, D: np.ndarray, T: np.ndarray) -> np.ndarray:
        """``(n, pstride) float32`` parameter block for frames ``D (n, K, 3)``, ``T (n, G, 3, 4)``."""
        n = D.shape[0]
        if n == 1:
            P = self._params_host
        else:
            P = aligned_empty((n, self._pstride), np.float32)
            P[:] = 0
        P = P.reshape(n, self._pstride)
        gt = self.n_groups * T_FLOATS
        cols = P[:, :gt].reshape(n, self.n_groups, 4, 4)
        cols[..., :3] = T.transpose(0, 1, 3, 2)  # column c of each 3x4 transform as a float4
        Dv = P[:, gt:gt + 4 * (self.n_controls + 1)].reshape(n, self.n_controls + 1, 4)
        Dv[:, :self.n_controls, :3] = D
        return P

    def _upload_params(self, P: np.ndarray) -> None:
        """Make ``P`` (from ``_fill_params``) the parameters of the next launch."""
        cl = self._cl
        single = P.base is self._params_host or P is self._params_host
        if self.zero_copy:
            self._params = self._params_single if single else self._host_buffer(P, cl.mem_flags.READ_ONLY)
            return
        self._params = self._params_single if single else cl.Buffer(self.context, cl.mem_flags.READ_ONLY, P.nbytes)
        cl.enqueue_copy(self.queue, self._params, P, is_blocking=False)

    def _set_deform_args(self) -> None:
        """Set the deform kernels' resident arguments once (see ``_launch_deform``)."""
        self._arg_frames = {}
        for k in (self._k_deform, self._k_deform_stream):
            k.set_args(np.uint32(self.n_vertices), np.uint32(self.n_controls), self._col_ptr,
                       self._id_ptr, self._ids, self._w, self._rest, self._sgroup, self._group,
                       self._params, np.uint32(self._pstride // 4), np.uint32(self.n_groups),
                       np.uint32(1), self._verts)
            self._arg_frames[k] = 1

    def _streams(self, n_frames: int, out: np.ndarray | None = None) -> bool:
        """Whether a launch writing ``n_frames`` frames (into ``out``, else the resident vertex
        buffer) uses non-temporal stores (see ``STREAM_FRACTION``; they need 32-byte aligned frames)."""
        big = self._resident_bytes + n_frames * 12 * self.n_vertices > STREAM_FRACTION * self._cache_bytes
        if not (big and self._cache_bytes) or self.n_vertices < self.packed.slice:
            return False
        return not ((n_frames > 1 and (12 * self.n_vertices) % 32) or (out is not None and out.ctypes.data % 32))

    def _launch_deform(self, n_frames: int, out_buf, stream: bool = False):
        """Enqueue the deform kernel (``deform_stream`` if ``stream``), setting only the per-launch
        arguments: buffers cost 0.2 us to set, a scalar ~20 us through PyOpenCL (``Kernel.__call__``
        setting all fourteen cost ~60 us a frame, a third of a 25k-vertex frame), so the frame
        count is set only when it changes."""
        k = self._k_deform_stream if stream else self._k_deform
        k.set_arg(9, self._params)
        if n_frames != self._arg_frames[k]:
            k.set_arg(12, np.uint32(n_frames))
            self._arg_frames[k] = n_frames
        k.set_arg(13, out_buf)
        return self._cl.enqueue_nd_range_kernel(self.queue, k, (self._global_slices,), (LOCAL_SLICES,))

    def _host_buffer(self, arr: np.ndarray, flags=None):
        """A buffer whose storage is host array ``arr`` (``CL_MEM_USE_HOST_PTR``): on a CPU device
        the kernels read and write ``arr`` itself."""
        cl = self._cl
        flags = cl.mem_flags.READ_WRITE if flags is None else flags
        return cl.Buffer(self.context, flags | cl.mem_flags.USE_HOST_PTR, hostbuf=arr)

    def _host_out(self, arr: np.ndarray):
        return self._host_buffer(arr, self._cl.mem_flags.WRITE_ONLY)

    def _sync_host(self, buf, arr: np.ndarray, event) -> None:
        """Wait for ``event`` (the kernel writing ``buf``) and make ``arr``, the host storage of
        ``buf``, hold its results: on a host-memory device it already does."""
        if self.zero_copy:
            event.wait()
            return
        cl = self._cl
        mapped, _ = cl.enqueue_map_buffer(self.queue, buf, cl.map_flags.READ, 0, arr.shape, arr.dtype,
                                          is_blocking=True)
        mapped.base.release(self.queue)

    # ------------------------------------------------------------------------------- interface
    def displacements(self, D: np.ndarray) -> np.ndarray:
        """``u = B·D``: ``D (K, 3)`` -> ``(V, 3) float32``."""
        T = np.zeros((self.n_groups, 3, 4), np.float32)
        T[:, :, :3] = np.eye(3, dtype=np.float32)
        return self.deform(D, T) - self.rest

    @_serialised
    def deform(self, D: np.ndarray, transforms: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """One frame: ``D (K, 3)``, ``transforms (G, 3, 4)`` -> vertices ``(V, 3) float32``.

        ``out`` (a C-contiguous ``(V, 3) float32`` array) receives the result if given.
        """
        D, T = self._check(D, transforms, batch=False)
        self._upload_params(self._fill_params(D[None], T[None]))
        if out is None:
            out = aligned_empty((self.n_vertices, 3), np.float32)
        elif out.shape != (self.n_vertices, 3) or out.dtype != np.float32 or not out.flags.c_contiguous:
            raise ValueError("out must be a C-contiguous (V, 3) float32 array")
        if self.n_vertices == 0:
            return out
        if self.zero_copy:  # the kernel writes straight into ``out``
            buf = self._host_out(out)
            self._sync_host(buf, out, self._launch_deform(1, buf, self._streams(1, out)))
        else:
            self._launch_deform(1, self._verts, self._streams(1))
            self._cl.enqueue_copy(self.queue, out, self._verts, is_blocking=True)
        return out

    @_serialised
    def deform_batch(self, D: np.ndarray, transforms: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Many frames in one launch: ``D (T, K, 3)``, ``transforms (T, G, 3, 4)`` -> ``(T, V, 3)``.

        ``out`` (a C-contiguous ``(T, V, 3) float32`` array) receives the frames if given.
        """
        D, T = self._check(D, transforms, batch=True)
        n = D.shape[0]
        if out is None:
            out = aligned_empty((n, self.n_vertices, 3), np.float32)
        elif out.shape != (n, self.n_vertices, 3) or out.dtype != np.float32 or not out.flags.c_contiguous:
            raise ValueError("out must be a C-contiguous (T, V, 3) float32 array")
        if n == 0 or self.n_vertices == 0:
            return out
        frame_bytes = 12 * self.n_vertices
        max_alloc = int(self.device.max_mem_alloc_size)
        chunk = max(1, min(n, max_alloc // frame_bytes, 65535))
        for a in range(0, n, chunk):
            b = min(n, a + chunk)
            self._upload_params(self._fill_params(D[a:b], T[a:b]))
            if self.zero_copy:
                buf = self._host_out(out[a:b])
                self._sync_host(buf, out[a:b], self._launch_deform(b - a, buf, self._streams(b - a, out[a:b])))
            else:
                buf = self._cl.Buffer(self.context, self._cl.mem_flags.WRITE_ONLY, (b - a) * frame_bytes)
                self._launch_deform(b - a, buf, self._streams(b - a))
                self._cl.enqueue_copy(self.queue, out[a:b], buf, is_blocking=True)
        return out

    @_serialised
    def normals(self, vertices: np.ndarray) -> np.ndarray:
        """Area-weighted unit vertex normals ``(V, 3) float32`` of deformed ``vertices (V, 3)``."""
        cl = self._cl
        v = np.ascontiguousarray(vertices, dtype=np.float32).reshape(self.n_vertices, 3)
        out = aligned_empty((self.n_vertices, 3), np.float32)
        if self.n_vertices == 0:
            return out
        cl.enqueue_copy(self.queue, self._verts, v, is_blocking=False)
        self._launch_normals()
        cl.enqueue_copy(self.queue, out, self._nbuf(), is_blocking=True)
        return out

    def _nbuf(self):
        if not hasattr(self, "_normals_out"):
            self._normals_out = self._cl.Buffer(self.context, self._cl.mem_flags.READ_WRITE,
                                                max(12, 12 * self.n_vertices))
        return self._normals_out

    def _launch_normals(self) -> None:
        F = self.n_faces
        if F:
            self._k_face_normals(self.queue, (-(-F // LOCAL_SIZE) * LOCAL_SIZE,), (LOCAL_SIZE,),
                                 np.uint32(F), self._tri, self._verts, self._fn)
        self._k_vertex_normals(self.queue, self._global, (LOCAL_SIZE,), np.uint32(self.n_vertices),
                               self._adj_ptr, self._adj, self._fn, self._nbuf())

    @_serialised
    def deform_with_normals(self, D: np.ndarray, transforms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``deform`` and ``normals`` of the result, without sending the vertices back up."""
        cl = self._cl
        D, T = self._check(D, transforms, batch=False)
        self._upload_params(self._fill_params(D[None], T[None]))
        verts = aligned_empty((self.n_vertices, 3), np.float32)
        nrm = aligned_empty((self.n_vertices, 3), np.float32)
        if self.n_vertices == 0:
            return verts, nrm
        self._launch_deform(1, self._verts)
        self._launch_normals()
        cl.enqueue_copy(self.queue, verts, self._verts, is_blocking=False)
        cl.enqueue_copy(self.queue, nrm, self._nbuf(), is_blocking=True)
        return verts, nrm

    @_serialised
    def deform_quantized(self, D: np.ndarray, transforms: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One frame as int16 for the wire: ``(q (V, 3) int16, offset (3,), scale (3,) float32)``.

        The same numbers as ``protocol.quantize.quantize_int16`` of ``deform(D, transforms)``:
        ``vertices ~= offset + q * scale`` with an error of at most ``scale / 2`` per axis.
        """
        cl = self._cl
        D, T = self._check(D, transforms, batch=False)
        self._upload_params(self._fill_params(D[None], T[None]))
        q = aligned_empty((self.n_vertices, 3), np.int16)
        if self.n_vertices == 0:
            return q, np.zeros(3, np.float32), np.full(3, 1e-12, np.float32)
        self._launch_deform(1, self._verts)
        self._k_minmax(self.queue, (MINMAX_ITEMS,), None, np.uint32(self.n_vertices), self._verts,
                       self._minmax)
        cl.enqueue_copy(self.queue, self._minmax_host, self._minmax, is_blocking=True)
        lo = self._minmax_host[:, 0].min(axis=0)
        hi = self._minmax_host[:, 1].max(axis=0)
        # The formula of protocol.quantize.quantize_int16, on the same float32 values.
        offset = ((lo + hi) / 2).astype(np.float32)
        scale = np.maximum((hi - lo) / np.float32(65534.0), np.float32(1e-12)).astype(np.float32)
        self._k_quantize(self.queue, self._global, (LOCAL_SIZE,), np.uint32(self.n_vertices), self._verts,
                         *(np.float32(x) for x in offset), *(np.float32(x) for x in scale),
                         self._qbuf())
        cl.enqueue_copy(self.queue, q, self._qbuf(), is_blocking=True)
        return q, offset, scale

    # ------------------------------------------------------------------------ measuring aids
    def bytes_per_frame(self) -> int:
        """Bytes one ``deform`` frame moves at least: the operator as stored, rest positions, slice
        groups (and per-vertex groups of mixed slices), the frame's parameters and the output."""
        p = self.packed
        mixed = int(np.count_nonzero(self._sgroup_host == 255)) * p.slice
        return int(p.nbytes + 12 * p.n_padded + len(self._sgroup_host) + mixed + 4 * self._pstride
                   + 12 * self.n_vertices)

    def format_description(self) -> str:
        """The operator's device format, in words."""
        p = self.packed
        if p.dense:
            return "dense, slice-major float32"
        return (f"slices of {p.slice}: {100 * p.shared_fraction:.0f}% shared columns, others ELL; "
                f"{p.idx_ctype} ids; {p.axes} float32 weight plane{'s' if p.axes > 1 else ''}; "
                f"{p.slice * p.n_columns / max(1, self.operator.nnz):.2f} stored weights per non-zero")

    @_serialised
    def upload_frame(self, D: np.ndarray, transforms: np.ndarray, wait: bool = False) -> None:
        """Send one frame's ``D`` and transforms (for ``run_kernel_resident``)."""
        D, T = self._check(D, transforms, batch=False)
        self._upload_params(self._fill_params(D[None], T[None]))
        if wait:
            self.queue.finish()

    @_serialised
    def run_kernel_resident(self, wait: bool = False) -> None:
        """Deform the uploaded frame into the resident vertex buffer (with ``deform``'s stores)."""
        self._launch_deform(1, self._verts, self._streams(1))
        if wait:
            self.queue.finish()

    @_serialised
    def read_resident(self) -> np.ndarray:
        """Copy the resident vertex buffer to a new host array (the non-zero-copy read-back)."""
        out = aligned_empty((self.n_vertices, 3), np.float32)
        self._cl.enqueue_copy(self.queue, out, self._verts, is_blocking=True)
        return out

    def _qbuf(self):
        if not hasattr(self, "_q"):
            self._q = self._cl.Buffer(self.context, self._cl.mem_flags.READ_WRITE, max(6, 6 * self.n_vertices))
        return self._q
