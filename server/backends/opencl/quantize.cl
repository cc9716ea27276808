// Frames are (V, 3) float32 rows; a unit of 16 vertices is 48 floats = three float16 a, b, c
// whose lanes j hold axis j % 3, (j + 1) % 3 and (j + 2) % 3.
#define PAT0(x, y, z) (float16)(x, y, z, x, y, z, x, y, z, x, y, z, x, y, z, x)
#define PAT1(x, y, z) (float16)(y, z, x, y, z, x, y, z, x, y, z, x, y, z, x, y)
// clip(rint(x), -32767, 32767) as short16: clipping first gives the same, and adding 1.5 * 2^23
// to |x| <= 32767 rounds it to the nearest integer, ties to even (as rint), into the low mantissa
// bits (PoCL's vector rint is several times slower).
#define RINT_SHORT16(x) convert_short16(as_int16(clamp((x), -32767.0f, 32767.0f) + 12582912.0f) - 0x4B400000)
#define PAT2(x, y, z) (float16)(z, x, y, z, x, y, z, x, y, z, x, y, z, x, y, z)

// One work-group (WG work-items) per frame: the frame's bounds (each work-item a contiguous run
// of 16-vertex units, then a reduction through local memory), then the quantisation of the same
// run while the frame is still in this core's cache. params[f] = (offset xyz, pad, scale xyz, pad).
__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void quantize_frames(const uint n_vertices, __global const float *verts, __global float *params,
                     __global short *q, const uint q_start, const uint q_stride)
{
    const uint f = get_group_id(0), l = get_local_id(0);
    __global const float *v = verts + (size_t)f * 3 * n_vertices;
    __global short *out = q + q_start + (size_t)f * q_stride;
    const uint units = n_vertices / 16, per = (units + WG - 1) / WG;
    const uint u0 = min(l * per, units), u1 = min(u0 + per, units);
    float16 mna = (float16)(INFINITY), mnb = mna, mnc = mna, mxa = -mna, mxb = mxa, mxc = mxa;
    for (uint k = u0; k < u1; ++k) {
        __global const float *w = v + 48 * k;
        const float16 a = vload16(0, w), b = vload16(1, w), c = vload16(2, w);
        mna = fmin(mna, a); mnb = fmin(mnb, b); mnc = fmin(mnc, c);
        mxa = fmax(mxa, a); mxb = fmax(mxb, b); mxc = fmax(mxc, c);
    }
    // fold lanes to axes: a holds axes 012012..., b 120120..., c 201201...
    float3 mn = (float3)(INFINITY), mx = (float3)(-INFINITY);
    for (uint j = 0; j < 16; ++j) {
        const uint ax = j % 3;
        mn = fmin(mn, ax == 0 ? (float3)(mna[j], mnb[j], mnc[j]) : ax == 1 ? (float3)(mnc[j], mna[j], mnb[j])
                                                                  : (float3)(mnb[j], mnc[j], mna[j]));
        mx = fmax(mx, ax == 0 ? (float3)(mxa[j], mxb[j], mxc[j]) : ax == 1 ? (float3)(mxc[j], mxa[j], mxb[j])
                                                                  : (float3)(mxb[j], mxc[j], mxa[j]));
    }
    if (l == WG - 1) {
        for (uint i = 16 * units; i < n_vertices; ++i) {
            const float3 x = vload3(i, v);
            mn = fmin(mn, x);
            mx = fmax(mx, x);
        }
    }
    __local float lmn[3 * WG], lmx[3 * WG];
    vstore3(mn, l, lmn);
    vstore3(mx, l, lmx);
    barrier(CLK_LOCAL_MEM_FENCE);
    float3 lo = vload3(0, lmn), hi = vload3(0, lmx);
    for (uint i = 1; i < WG; ++i) {
        lo = fmin(lo, vload3(i, lmn));
        hi = fmax(hi, vload3(i, lmx));
    }
    // the formula of protocol.quantize.quantize_int16, in float32
    const float3 o = (lo + hi) / 2.0f;
    const float3 sc = fmax((hi - lo) / 65534.0f, (float3)(1e-12f));
    if (l == 0) {
        vstore3(o, 0, params + 8 * f);
        vstore3(sc, 0, params + 8 * f + 4);
    }
    const float16 o0 = PAT0(o.x, o.y, o.z), o1 = PAT1(o.x, o.y, o.z), o2 = PAT2(o.x, o.y, o.z);
    const float16 s0 = PAT0(sc.x, sc.y, sc.z), s1 = PAT1(sc.x, sc.y, sc.z), s2 = PAT2(sc.x, sc.y, sc.z);
    for (uint k = u0; k < u1; ++k) {
        __global const float *w = v + 48 * k;
        __global short *z = out + 48 * k;
        vstore16(RINT_SHORT16((vload16(0, w) - o0) / s0), 0, z);
        vstore16(RINT_SHORT16((vload16(1, w) - o1) / s1), 1, z);
        vstore16(RINT_SHORT16((vload16(2, w) - o2) / s2), 2, z);
    }
    if (l == WG - 1) {
        for (uint i = 16 * units; i < n_vertices; ++i) {
            const float3 r = rint((vload3(i, v) - o) / sc);
            vstore3(convert_short3(clamp(r, -32767.0f, 32767.0f)), i, out);
        }
    }
}
