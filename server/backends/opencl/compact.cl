// Compact frames on the device (protocol/compact.py's CompactEncoder, bit for bit): for frame j of
// a batch and vertex i, the position in its rigid group's local frame, in grid steps, as NumPy's
// float32 matmul computes it (OpenBLAS: a fused multiply-add chain over x, y, z, then + t); its
// offset from the reference cell; the reference kept where within the tolerance, else the rounded
// offset r; r minus the previous vertex's r per axis, zigzagged; per axis a bitmap of the non-zero
// values and those values' low two bytes (protocol/README.md, compact format 2).
// One work-item per unit of 16 vertices, as float16 vectors (PoCL's vectoriser made slow scalar
// code of one work-item per vertex: 2-3x the NumPy encoder's CPU); it recomputes the previous
// unit's last r (one vertex) instead of a second pass. Rounding by adding 1.5 * 2^23 (ties to
// even, as rint; PoCL's vector rint is several times slower) is exact below 2^22 cells: a
// larger offset is flagged as over 16 bits and the frame goes to the host encoder.
#pragma OPENCL FP_CONTRACT OFF

#define MAX_CELL 8388608.0f

inline int3 cells(__global const float *v, __global const float *m, __global const float *ref,
                  const uint nv, const uint i, const float keep2, int *bad)
{
    const float x = v[3 * i], y = v[3 * i + 1], z = v[3 * i + 2];
    const float l0 = fma(m[2], z, fma(m[1], y, m[0] * x)) + m[3];
    const float l1 = fma(m[6], z, fma(m[5], y, m[4] * x)) + m[7];
    const float l2 = fma(m[10], z, fma(m[9], y, m[8] * x)) + m[11];
    *bad = !(l0 > 1.0f - MAX_CELL && l0 < MAX_CELL - 1.0f && l1 > 1.0f - MAX_CELL &&
             l1 < MAX_CELL - 1.0f && l2 > 1.0f - MAX_CELL && l2 < MAX_CELL - 1.0f);
    const float f0 = l0 - ref[i], f1 = l1 - ref[nv + i], f2 = l2 - ref[2 * nv + i];
    const float p0 = f0 * f0, p1 = f1 * f1, p2 = f2 * f2;
    const float dist = (p0 + p1) + p2;
    if (!(dist > keep2))
        return (int3)(0);
    return (int3)((int)rint(f0), (int)rint(f1), (int)rint(f2));  // scalar: the few odd vertices
}

// The frames of a launch: frame j encodes frame param[j * P] of verts (T, nv, 3); row j of the
// uint words ``param`` (P = 5 + 12 G each): frame index, key flag, keep2 (float bits: squared
// tolerance, cells), flags, the slot of its reference cells in ``refs`` (slots of (3, nv)
// float32, kept across launches), then its groups' (3, 4) float32 matrices (world -> cells).
// Written: ``packed`` from byte (3 NB + 6 nv) j (NB = ceil(nv / 8)): per axis a bitmap of the
// non-zero zigzagged values (bit i % 8 of byte i / 8), then the non-zero values' byte 0 (axis
// after axis, in vertex order), then their byte 1 if bit 2 of the flags is set (none of that if
// bit 0 or 1 is). Staged first: the non-zero values' bytes 0 and 1 in ``out``, byte k
// of axis a's values of work-item l's vertices from byte 6 nv j + k 3 nv + a nv + 16 u0 (u0: the
// work-item's first unit), ``counts[(3 j + a) WG + l]`` of them; for a key frame, its new cells
// ref + r (3, nv) float32 at float ``keys_at + 3 nv j``; flags: bit 0 a bad vertex (not finite,
// or out of the grid), bit 1 a value over 16 bits, bit 2 a value over 8 bits (the frame needs
// both planes) (or-ed in by the work-group's first work-item; the host zeroes them first).

#define MAGIC 12582912.0f
#define ZZ(d) ((as_uint16(d) << 1) ^ as_uint16((d) >> 31))

// Row k of matrix m (3, 4) applied to the unit's x, y, z (as NumPy's matmul: an fma chain).
#define LOCAL(m, k)                                                                              \
    (fma((float16)((m)[k + 2]), z, fma((float16)((m)[k + 1]), y, (float16)((m)[k]) * x)) +       \
     (float16)((m)[k + 3]))

// The bitwise or of the 16 lanes.
inline uint or16(const uint16 b)
{
    const uint8 s8 = b.lo | b.hi;
    const uint4 s4 = s8.lo | s8.hi;
    const uint2 s2 = s4.lo | s4.hi;
    return s2.x | s2.y;
}

// Lane k of the vector 1 where z is non-zero, shifted to bit k + o (min and shift: no masks).
#define NZ(z, o) (min((z), (uint16)(1)) << ((uint16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15) + (o)))
// A float's magnitude as an unsigned int: ordered as the magnitudes, NaN above infinity.
#define MAG(f) (as_uint16(f) & (uint16)(0x7FFFFFFF))

// The lanes of z set in m (in lane order), low 16 bits at st[c], ...: the new count.
// Branch-free: every lane is stored, the count advances on the set ones (the stores past the
// new count stay inside the work-item's run, and are overwritten or never read). With AVX-512,
// one compress to a register (a compress straight to memory is slow on some cores) and one store.
// (-DCOMPACT_PORTABLE=1: the portable code everywhere, as tests check it gives the same bytes)
#if !defined(COMPACT_PORTABLE) && defined(__AVX512F__) &&                                        \
    __has_builtin(__builtin_ia32_compresssi512_mask) && __has_builtin(__builtin_ia32_cmpd512_mask)
typedef int v16si_t __attribute__((__vector_size__(64)));
// Bit k set where lane k of z is not 0 (one test into a mask register).
#define NZ_MASK(z)                                                                               \
    ((uint)__builtin_ia32_cmpd512_mask(__builtin_convertvector(as_int16(z), v16si_t),            \
                                       __builtin_convertvector((int16)(0), v16si_t), 4, 0xFFFF))
inline uint put_nz(const uint16 z, const uint m, __global ushort *st, uint c)
{
    const v16si_t k = __builtin_ia32_compresssi512_mask(
        __builtin_convertvector(as_int16(z), v16si_t), __builtin_convertvector((int16)(0), v16si_t),
        (ushort)m);
    vstore16(convert_ushort16(__builtin_convertvector(k, int16)), 0, st + c);
    return c + popcount(m);
}
#else
inline uint put_nz(const uint16 z, const uint m, __global ushort *st, uint c)
{
    uint t[16];
    vstore16(z, 0, t);
    for (uint k = 0; k < 16; ++k) {
        st[c] = (ushort)t[k];
        c += (m >> k) & 1;
    }
    return c;
}
#endif

// One value of the scalar tail: its bit and, when not 0, its low 16 bits.
inline uint put1(const uint u, const uint i, __global uchar *bm, __global ushort *st, uint c)
{
    if (u) {
        bm[i >> 3] |= (uchar)(1u << (i & 7));
        st[c++] = (ushort)u;
    }
    return c;
}

// n staged values' byte 0 to lo, and byte 1 to hi when hi is not null: 16 at a time (PoCL's
// byte loop was several times slower).
inline void unstage(__global uchar *lo, __global uchar *hi, __global const ushort *st,
                    const uint n)
{
    uint i = 0;
    for (; i + 16 <= n; i += 16) {
        const ushort16 w = vload16(0, st + i);
        vstore16(convert_uchar16(w), 0, lo + i);
        if (hi)
            vstore16(convert_uchar16(w >> (ushort16)(8)), 0, hi + i);
    }
    for (; i < n; ++i) {
        lo[i] = (uchar)st[i];
        if (hi)
            hi[i] = (uchar)(st[i] >> 8);
    }
}

// One work-group of WG work-items per frame; each work-item a contiguous run of units, in a loop
// (as quantize.cl: PoCL's vectoriser widens straight-line code across work-items, which made
// scatters of these vector loads and stores), the tail vertices by the last one.
__kernel __attribute__((reqd_work_group_size(WG, 1, 1)))
void compact_frames(const uint nv, const uint n_groups, __global const float *verts,
                    __global const uchar *groups, __global uint *param,
                    __global const float *refs, __global uchar *out, const uint keys_at,
                    __global uchar *packed, __global uint *counts)
{
    const uint l = get_local_id(0), j = get_group_id(1), units = nv / 16;
    const uint per = (units + WG - 1) / WG, u0 = min(l * per, units), u1 = min(u0 + per, units);
    __global uint *row = param + (size_t)j * (5 + 12 * n_groups);
    __global const float *v = verts + (size_t)row[0] * 3 * nv;
    const int is_key = row[1];
    const float keep2 = as_float(row[2]);
    volatile __global uint *flags = row + 3;
    __global const float *ms = (__global const float *)(row + 5);
    __global const float *ref = refs + (size_t)row[4] * 3 * nv;
    __global uchar *p = out + (size_t)j * 6 * nv;
    __global float *kk = (__global float *)out + keys_at + (size_t)j * 3 * nv;
    const uint nb = (nv + 7) / 8;
    __global uchar *pk = packed + (size_t)j * (3 * nb + 6 * nv);
    __global uchar *bm0 = pk, *bm1 = bm0 + nb, *bm2 = bm1 + nb;
    __global ushort *st0 = (__global ushort *)p + 16 * u0, *st1 = st0 + nv, *st2 = st1 + nv;
    uint c0 = 0, c1 = 0, c2 = 0;
    const float lim = MAX_CELL - 1.0f, big = 4194304.0f;
    int bad;
    int3 prev = (int3)(0);
    if (u0)
        prev = cells(v, ms + 12 * groups[16 * u0 - 1], ref, nv, 16 * u0 - 1, keep2, &bad);
    // the largest local-frame and moved offset magnitudes (MAG): integer max, no compare masks
    uint16 mags = (uint16)(0), moved = (uint16)(0), zs = (uint16)(0);
    for (uint u = u0; u < u1; ++u) {
        const uint i0 = 16 * u;
        __global const float *w = v + 3 * i0;
        const float16 a = vload16(0, w), b = vload16(1, w), c = vload16(2, w);
        const float16 x = __builtin_shufflevector(
            __builtin_shufflevector(a, b, 0, 3, 6, 9, 12, 15, 18, 21, 24, 27, 30, -1, -1, -1, -1, -1), c,
            0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 17, 20, 23, 26, 29);
        const float16 y = __builtin_shufflevector(
            __builtin_shufflevector(a, b, 1, 4, 7, 10, 13, 16, 19, 22, 25, 28, 31, -1, -1, -1, -1, -1), c,
            0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 18, 21, 24, 27, 30);
        const float16 z = __builtin_shufflevector(
            __builtin_shufflevector(a, b, 2, 5, 8, 11, 14, 17, 20, 23, 26, 29, -1, -1, -1, -1, -1, -1), c,
            0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 16, 19, 22, 25, 28, 31);
        const uchar16 g = vload16(0, groups + i0);
        // the local frame by the unit's first group's matrix; the lanes of another group (7
        // units of 1553 on the 25k head) by theirs, selected: a branch of 16 gathered matrices
        // per unit made PoCL's code of the common case ~20% slower
        float16 l0 = LOCAL(ms + 12 * g.s0, 0), l1 = LOCAL(ms + 12 * g.s0, 4),
                l2 = LOCAL(ms + 12 * g.s0, 8);
        if (any(g != (uchar16)(g.s0))) {
            for (uint h = 0; h < n_groups; ++h) {
                const int16 sel = convert_int16(as_char16(g == (uchar16)(h)));
                if (h == g.s0 || !any(sel))
                    continue;
                l0 = select(l0, LOCAL(ms + 12 * h, 0), sel);
                l1 = select(l1, LOCAL(ms + 12 * h, 4), sel);
                l2 = select(l2, LOCAL(ms + 12 * h, 8), sel);
            }
        }
        mags = max(mags, max(max(MAG(l0), MAG(l1)), MAG(l2)));
        const float16 r0 = vload16(0, ref + i0), r1 = vload16(0, ref + nv + i0),
                      r2 = vload16(0, ref + 2 * nv + i0);
        const float16 f0 = l0 - r0, f1 = l1 - r1, f2 = l2 - r2;
        const float16 p0 = f0 * f0, p1 = f1 * f1, p2 = f2 * f2;
        const int16 move = (p0 + p1) + p2 > (float16)(keep2);
        moved = max(moved, max(max(MAG(f0), MAG(f1)), MAG(f2)) & as_uint16(move));
        const int16 q0 = (as_int16(f0 + MAGIC) - 0x4B400000) & move;
        const int16 q1 = (as_int16(f1 + MAGIC) - 0x4B400000) & move;
        const int16 q2 = (as_int16(f2 + MAGIC) - 0x4B400000) & move;
        const int16 d0 = q0 - (int16)(prev.x, q0.s01234567, q0.s89ab, q0.scd, q0.se);
        const int16 d1 = q1 - (int16)(prev.y, q1.s01234567, q1.s89ab, q1.scd, q1.se);
        const int16 d2 = q2 - (int16)(prev.z, q2.s01234567, q2.s89ab, q2.scd, q2.se);
        prev = (int3)(q0.sf, q1.sf, q2.sf);
        const uint16 z0 = ZZ(d0), z1 = ZZ(d1), z2 = ZZ(d2);
        zs |= z0 | z1 | z2;
#ifdef NZ_MASK
        const uint m0 = NZ_MASK(z0), m1 = NZ_MASK(z1), m2 = NZ_MASK(z2);
#else
        const uint m01 = or16(NZ(z0, 0) | NZ(z1, 16)), m2 = or16(NZ(z2, 0));
        const uint m0 = m01 & 0xFFFF, m1 = m01 >> 16;
#endif
        bm0[2 * u] = (uchar)m0;
        bm0[2 * u + 1] = (uchar)(m0 >> 8);
        bm1[2 * u] = (uchar)m1;
        bm1[2 * u + 1] = (uchar)(m1 >> 8);
        bm2[2 * u] = (uchar)m2;
        bm2[2 * u + 1] = (uchar)(m2 >> 8);
        if (m0)
            c0 = put_nz(z0, m0, st0, c0);
        if (m1)
            c1 = put_nz(z1, m1, st1, c1);
        if (m2)
            c2 = put_nz(z2, m2, st2, c2);
        if (is_key) {
            vstore16(r0 + convert_float16(q0), 0, kk + i0);
            vstore16(r1 + convert_float16(q1), 0, kk + nv + i0);
            vstore16(r2 + convert_float16(q2), 0, kk + 2 * nv + i0);
        }
    }
    uint flag = (any(mags >= (uint16)(as_uint(lim))) ? 1u : 0u) |
                (any(moved >= (uint16)(as_uint(big))) || any((zs >> 16) != 0) ? 2u : 0u) |
                (any((zs >> 8) != 0) ? 4u : 0u);
    if (l == WG - 1) {  // the last nv % 16 vertices, one by one
        for (uint b = 2 * units; b < nb; ++b)
            bm0[b] = bm1[b] = bm2[b] = 0;
        for (uint i = 16 * units; i < nv; ++i) {
            const int3 r = cells(v, ms + 12 * groups[i], ref, nv, i, keep2, &bad);
            const int3 d = r - prev;
            const uint3 zz = (as_uint3(d) << 1) ^ as_uint3(d >> 31);
            c0 = put1(zz.x, i, bm0, st0, c0);
            c1 = put1(zz.y, i, bm1, st1, c1);
            c2 = put1(zz.z, i, bm2, st2, c2);
            flag |= (bad ? 1u : 0u) | (((zz.x | zz.y | zz.z) >> 16) ? 2u : 0u) |
                    (((zz.x | zz.y | zz.z) >> 8) ? 4u : 0u);
            if (is_key) {
                kk[i] = ref[i] + (float)r.x;
                kk[nv + i] = ref[nv + i] + (float)r.y;
                kk[2 * nv + i] = ref[2 * nv + i] + (float)r.z;
            }
            prev = r;
        }
    }
    counts[(3 * j) * WG + l] = c0;
    counts[(3 * j + 1) * WG + l] = c1;
    counts[(3 * j + 2) * WG + l] = c2;
    // the runs joined after the bitmaps (lo bytes of axes 0, 1, 2, then their hi bytes if the
    // frame needs them): the payload is one slice for the host (joining ~48 slices in Python
    // cost more than these copies)
    __local uint lc[3 * WG], lf[WG];
    lc[l] = c0;
    lc[WG + l] = c1;
    lc[2 * WG + l] = c2;
    lf[l] = flag;
    barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
    uint all = 0, nnz = 0;
    for (uint k = 0; k < WG; ++k)
        all |= lf[k];
    for (uint k = 0; k < 3 * WG; ++k)
        nnz += lc[k];
    if (l == 0 && all)
        atomic_or(flags, all);
    if (all & 3)  // the host encodes this frame
        return;
    __global uchar *dst = pk + 3 * nb;
    uint pre = 0;
    for (uint a = 0; a < 3; ++a) {
        for (uint k = 0; k < l; ++k)
            pre += lc[a * WG + k];
        unstage(dst + pre, all & 4 ? dst + nnz + pre : 0,
                 (__global const ushort *)p + a * nv + 16 * u0, lc[a * WG + l]);
        for (uint k = l; k < WG; ++k)
            pre += lc[a * WG + k];
    }
}
