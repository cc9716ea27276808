"""OpenCL C of the backend's kernels, and building them once per context and options.

The deform kernel is generated for a slice width (``deform_source``: its 16 lanes are unrolled
into the gathers and stores); the others are plain sources beside this module (``*.cl``):
``normals.cl`` (area-weighted vertex normals) and ``quantize.cl`` (int16 wire frames, see
``quantize.DeviceQuantizer``).
"""

from __future__ import annotations

import threading
import warnings
from pathlib import Path
from typing import Any

#: Options every program is built with: correctly rounded division (the int16 quantiser must match
#: NumPy bit for bit) and ``-w`` (clang's notes that float16 arguments change the ABI without
#: AVX-512 are harmless).
BUILD_OPTIONS = ("-cl-fp32-correctly-rounded-divide-sqrt", "-w")


def cl_source(name: str) -> str:
    """The OpenCL C of ``name`` (``"normals"``, ``"quantize"``), a ``.cl`` file of this package."""
    return (Path(__file__).parent / f"{name}.cl").read_text(encoding="utf-8")


def aos_store8(x: str, y: str, z: str, o: str, stream: bool = False) -> str:
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


def deform_source(S: int) -> str:
    """OpenCL C of the ``deform`` and ``deform_stream`` kernels for slices of ``S`` (8 or 16)
    vertices; ``deform_stream`` writes the vertices with non-temporal stores (see ``STREAM_FRACTION``)."""
    return deform_kernel(S, "deform", False) + deform_kernel(S, "deform_stream", True)


def deform_kernel(S: int, name: str, stream: bool) -> str:
    hx = "0123456789abcdef"
    lanes = range(S)

    def vec(parts: list[str]) -> str:
        return f"(VF)({', '.join(parts)})"

    inter = [f"o{c}.s{hx[v]}" for v in lanes for c in "xyz"]  # AoS order of the slice's output
    stores = "\n        ".join(
        aos_store8(f"ox{h}", f"oy{h}", f"oz{h}", f"o + {24 * i}", stream)
        for i, h in enumerate((".lo", ".hi") if S == 16 else ("",))
    )
    tail = "\n        ".join(f"if ({i} < n) o[{i}] = {x};" for i, x in enumerate(inter))
    gathers = "\n            ".join(f"const float4 d{ln} = D[id[{ln}]];" for ln in lanes)
    # Non-temporal stores are weakly ordered: drain them before the work-group ends (on CPU
    # devices, the only ones that stream, a work-group's items run in order on one thread).
    fence = "\n    if (get_local_id(0) + 1 == get_local_size(0)) STREAM_FENCE();" if stream else ""
    dx, dy, dz = (vec([f"d{ln}.{c}" for ln in lanes]) for c in "xyz")
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


_programs: dict[tuple[int, str, tuple[str, ...]], tuple[Any, Any]] = {}
_programs_lock = threading.Lock()


def build(ctx: Any, source: str, defines: dict[str, object]) -> Any:
    """``source`` built for ``ctx`` with ``-Dk=v`` for each of ``defines`` and ``BUILD_OPTIONS``,
    once per process (a ``pyopencl.Program``)."""
    import pyopencl as cl

    opts = tuple(f"-D{k}={v}" for k, v in sorted(defines.items())) + BUILD_OPTIONS
    key = (id(ctx), source, opts)
    with _programs_lock:
        hit = _programs.get(key)
        if hit is None:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", cl.CompilerWarning)
                hit = (ctx, cl.Program(ctx, source).build(options=list(opts)))
            _programs[key] = hit  # holding ctx keeps id(ctx) unique
        return hit[1]


def deform_program(ctx: Any, defines: dict[str, object]) -> Any:
    """The deform and normals kernels for ``ctx``; ``defines``: ``AXES`` (1|3), ``IDX_T``
    (uchar|ushort|uint), ``DENSE`` (0|1) and ``SLICE`` (8|16, the deform kernel's width)."""
    return build(ctx, deform_source(int(str(defines["SLICE"]))) + cl_source("normals"), defines)
