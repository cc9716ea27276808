// VERTICES_COMPACT frames (kind 7), written from protocol/README.md section 3. A decoder holds the
// face's topology (rest vertices, rigid group per vertex) and the last key frame's grid cells; the
// payload (a zlib stream: bitmaps of the non-zero values, then those values, compact format 2) is
// inflated here, synchronously (`inflateExactly`).

const MAGIC = 0x54534346; // "FCST" little-endian
export const KIND_COMPACT = 7;
const HEAD = 52; // 32-byte frame header + 20-byte compact sub-header
export const COMPACT_FORMAT = 2; // sub-header bytes 42-43

// Inflate (RFC 1950 zlib wrapper around RFC 1951 deflate), written from the RFCs. The browser's
// DecompressionStream('deflate') decodes the same streams, but its stream machinery cost ~1.5 ms per
// frame in Chromium against ~0.1 ms of actual inflating; this synchronous one is bounded by the
// frame's declared size (a zlib bomb stops at `want` bytes) and checks the Adler-32.

const LEN_BASE = [3, 4, 5, 6, 7, 8, 9, 10, 11, 13, 15, 17, 19, 23, 27, 31, 35, 43, 51, 59, 67, 83, 99, 115, 131, 163, 195, 227, 258];
const LEN_EXTRA = [0, 0, 0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2, 3, 3, 3, 3, 4, 4, 4, 4, 5, 5, 5, 5, 0];
const DIST_BASE = [1, 2, 3, 4, 5, 7, 9, 13, 17, 25, 33, 49, 65, 97, 129, 193, 257, 385, 513, 769, 1025, 1537, 2049, 3073, 4097, 6145, 8193, 12289, 16385, 24577];
const DIST_EXTRA = [0, 0, 0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 5, 5, 6, 6, 7, 7, 8, 8, 9, 9, 10, 10, 11, 11, 12, 12, 13, 13];
const CL_ORDER = [16, 17, 18, 0, 8, 7, 9, 6, 10, 5, 11, 4, 12, 3, 13, 2, 14, 1, 15];
const FAST = 10; // bits looked up at once; longer codes are decoded canonically, bit by bit
const FAST_MASK = (1 << FAST) - 1;

function bad(why) {
  return new Error(`compact payload is not a valid zlib stream (${why})`);
}

/**
 * A canonical Huffman code from its code lengths: {fast: Int32Array(1 << FAST) of (symbol << 4 | length)
 * for codes of up to FAST bits (0: longer or unused), count[len], symbol[] in canonical order}.
 */
function huffman(lengths, n, check = 1) {
  const count = new Uint16Array(16);
  for (let i = 0; i < n; i++) count[lengths[i]]++;
  count[0] = 0;
  let left = 1, max = 0;
  for (let len = 1; len < 16; len++) {
    left = (left << 1) - count[len];
    if (left < 0) throw bad('over-subscribed code');
    if (count[len]) max = len;
  }
  // as zlib: a sent code may be incomplete only as a single one-bit code, never the code-length
  // code (check 2); the fixed codes (check 0) are as RFC 1951 defines them
  if (check && max > 0 && left > 0 && (check === 2 || max !== 1)) throw bad('incomplete code');
  const offs = new Uint16Array(16);
  for (let len = 1; len < 15; len++) offs[len + 1] = offs[len] + count[len];
  const symbol = new Uint16Array(n);
  for (let i = 0; i < n; i++) if (lengths[i]) symbol[offs[lengths[i]]++] = i;
  const fast = new Int32Array(1 << FAST);
  let code = 0, k = 0;
  for (let len = 1; len <= FAST; len++, code <<= 1) {
    for (let c = 0; c < count[len]; c++, code++, k++) {
      let rev = 0; // deflate sends codes most significant bit first: index by the reversed code
      for (let b = 0; b < len; b++) rev |= ((code >>> b) & 1) << (len - 1 - b);
      const e = (symbol[k] << 4) | len;
      for (let j = rev; j < 1 << FAST; j += 1 << len) fast[j] = e;
    }
  }
  return { fast, count, symbol };
}

/**
 * For a literal/length code's `fast` table: Int32Array(1 << FAST) of (s2 << 8 | s1 | total length
 * << 16) where the FAST bits start with two literal codes s1, s2 (0 elsewhere). A code is known by
 * its first `length` bits, so the second is read from the bits after the first when it fits.
 */
function literalPairs(fast) {
  const two = new Int32Array(1 << FAST);
  for (let i = 0; i < 1 << FAST; i++) {
    const e1 = fast[i], l1 = e1 & 15;
    if (e1 === 0 || e1 >> 4 > 255) continue;
    const e2 = fast[i >>> l1], l2 = e2 & 15;
    if (e2 === 0 || e2 >> 4 > 255 || l1 + l2 > FAST) continue;
    two[i] = (e1 >> 4) | ((e2 >> 4) << 8) | ((l1 + l2) << 16);
  }
  return two;
}

let FIXED = null;
function fixedCodes() {
  if (FIXED === null) {
    const l = new Uint8Array(288);
    l.fill(8, 0, 144); l.fill(9, 144, 256); l.fill(7, 256, 280); l.fill(8, 280, 288);
    FIXED = [huffman(l, 288, 0), huffman(new Uint8Array(30).fill(5), 30, 0)];
  }
  return FIXED;
}

/**
 * Inflate the zlib stream `src` (Uint8Array) to exactly `want` bytes, or throw; into `into` (a
 * Uint8Array of at least `want` bytes, reused from call to call) when given.
 */
export function inflateExactly(src, want, into = null) {
  const out = into && into.length >= want ? into.subarray(0, want) : new Uint8Array(want);
  const end = src.length;
  if (end < 6) throw bad('too short');
  const cmf = src[0], flg = src[1];
  if ((cmf & 15) !== 8 || cmf >> 4 > 7 || ((cmf << 8) | flg) % 31 !== 0 || flg & 32) throw bad('bad header');
  let pos = 2, bits = 0, nb = 0, o = 0; // input byte, bit buffer (LSB first) and its size, output byte

  const need = (n) => { // at least n (<= 24) bits in the buffer
    while (nb < n) {
      if (pos >= end) throw bad('truncated');
      bits |= src[pos++] << nb;
      nb += 8;
    }
  };
  const take = (n) => {
    need(n);
    const v = bits & ((1 << n) - 1);
    bits >>>= n;
    nb -= n;
    return v;
  };
  const sym = (h) => {
    while (nb < 24 && pos < end) { bits |= src[pos++] << nb; nb += 8; }
    const e = h.fast[bits & ((1 << FAST) - 1)];
    if (e !== 0) {
      const len = e & 15;
      if (len > nb) throw bad('truncated');
      bits >>>= len; nb -= len;
      return e >> 4;
    }
    let code = 0, first = 0, index = 0; // canonical decoding, one bit at a time
    for (let len = 1; len < 16; len++) {
      if (len > nb) throw bad('truncated');
      code |= (bits >>> (len - 1)) & 1;
      const c = h.count[len];
      if (code - first < c) { bits >>>= len; nb -= len; return h.symbol[index + code - first]; }
      index += c; first = (first + c) << 1; code <<= 1;
    }
    throw bad('invalid code');
  };

  let last = 0;
  while (!last) {
    last = take(1);
    const type = take(2);
    if (type === 0) { // stored: byte-aligned LEN, NLEN, then LEN bytes
      bits >>>= nb & 7; nb -= nb & 7;
      pos -= nb >> 3; bits = 0; nb = 0;
      if (pos + 4 > end) throw bad('truncated');
      const len = src[pos] | (src[pos + 1] << 8), nlen = src[pos + 2] | (src[pos + 3] << 8);
      if ((len ^ 0xffff) !== nlen) throw bad('stored block length check');
      pos += 4;
      if (pos + len > end) throw bad('truncated');
      if (o + len > want) throw new Error(`compact payload inflates to more than ${want} bytes`);
      out.set(src.subarray(pos, pos + len), o);
      pos += len; o += len;
      continue;
    }
    let lit, dist;
    if (type === 1) [lit, dist] = fixedCodes();
    else if (type === 2) {
      const nlen = take(5) + 257, ndist = take(5) + 1, ncode = take(4) + 4;
      if (nlen > 286 || ndist > 30) throw bad('bad code counts');
      const cl = new Uint8Array(19);
      for (let i = 0; i < ncode; i++) cl[CL_ORDER[i]] = take(3);
      const clh = huffman(cl, 19, 2);
      const lengths = new Uint8Array(nlen + ndist);
      for (let i = 0; i < nlen + ndist;) {
        const s = sym(clh);
        if (s < 16) { lengths[i++] = s; continue; }
        let rep, v = 0;
        if (s === 16) {
          if (i === 0) throw bad('repeat with no previous length');
          v = lengths[i - 1]; rep = 3 + take(2);
        } else rep = s === 17 ? 3 + take(3) : 11 + take(7);
        if (i + rep > nlen + ndist) throw bad('too many lengths');
        lengths.fill(v, i, i + rep); i += rep;
      }
      if (lengths[256] === 0) throw bad('no end-of-block code');
      lit = huffman(lengths.subarray(0, nlen), nlen);
      dist = huffman(lengths.subarray(nlen), ndist);
    } else throw bad('reserved block type');
    // the symbols of the block, the fast path inline with the bit buffer in locals (a call per
    // symbol to `sym` and its captured state cost about half the inflating)
    const lf = lit.fast, two = literalPairs(lf);
    for (;;) {
      while (nb < 24 && pos < end) { bits |= src[pos++] << nb; nb += 8; }
      const pair = two[bits & FAST_MASK];
      if (pair !== 0 && o + 2 <= want) { // two literals whose codes fit in the FAST bits
        const len = pair >>> 16;
        if (len <= nb) {
          out[o] = pair & 255; out[o + 1] = (pair >>> 8) & 255; o += 2;
          bits >>>= len; nb -= len;
          continue;
        }
      }
      let s;
      const e = lf[bits & FAST_MASK];
      if (e !== 0) {
        const len = e & 15;
        if (len > nb) throw bad('truncated');
        bits >>>= len; nb -= len;
        s = e >> 4;
      } else s = sym(lit);
      if (s < 256) {
        if (o >= want) throw new Error(`compact payload inflates to more than ${want} bytes`);
        out[o++] = s;
      } else if (s === 256) break;
      else {
        s -= 257;
        if (s >= 29) throw bad('bad length code');
        const len = LEN_BASE[s] + take(LEN_EXTRA[s]);
        const d = sym(dist);
        if (d >= 30) throw bad('bad distance code');
        const back = DIST_BASE[d] + take(DIST_EXTRA[d]);
        if (back > o) throw bad('distance too far back');
        if (o + len > want) throw new Error(`compact payload inflates to more than ${want} bytes`);
        if (back === 1) out.fill(out[o - 1], o, o + len);
        else if (back >= len) out.copyWithin(o, o - back, o - back + len);
        else for (let j = 0; j < len; j++) out[o + j] = out[o + j - back];
        o += len;
      }
    }
  }
  pos -= nb >> 3; // unread whole bytes go back; then the Adler-32, big-endian, ends the stream
  if (pos + 4 !== end) throw bad(pos + 4 > end ? 'truncated' : 'trailing bytes');
  if (o !== want) throw new Error(`compact payload inflates to ${o} bytes, expected ${want}`);
  // Adler-32 in blocks of up to 3800 bytes (int32 sums cannot overflow): four lanes of bytes
  // i = 4m + r, each with its running sum A_r and sum of running sums B_r (independent chains);
  // a block of n bytes adds sum(A_r) to a and n * a + sum(4 B_r - r A_r) to b
  let a = 1, b = 0;
  for (let i = 0; i < want;) {
    const n4 = (Math.min(want, i + 3800) - i) & ~3, e4 = i + n4;
    let a0 = 0, a1 = 0, a2 = 0, a3 = 0, b0 = 0, b1 = 0, b2 = 0, b3 = 0;
    for (; i < e4; i += 4) {
      a0 = (a0 + out[i]) | 0; b0 = (b0 + a0) | 0;
      a1 = (a1 + out[i + 1]) | 0; b1 = (b1 + a1) | 0;
      a2 = (a2 + out[i + 2]) | 0; b2 = (b2 + a2) | 0;
      a3 = (a3 + out[i + 3]) | 0; b3 = (b3 + a3) | 0;
    }
    b = (b + n4 * a + 4 * (b0 + b1 + b2 + b3) - (a1 + 2 * a2 + 3 * a3)) % 65521; // exact: < 2^53
    a = (a + a0 + a1 + a2 + a3) % 65521;
    if (n4 === 0) { // the last 1-3 bytes
      for (; i < want; i++) { a = (a + out[i]) % 65521; b = (b + a) % 65521; }
    }
  }
  const adler = ((src[pos] << 24) | (src[pos + 1] << 16) | (src[pos + 2] << 8) | src[pos + 3]) >>> 0;
  if (((b << 16) | a) >>> 0 !== adler) throw bad('Adler-32 mismatch');
  return out;
}

/**
 * The cells and positions of a frame, in one pass over the vertices: per axis a running sum of the
 * unzigzagged differences `zz` (wrapping at 32 bits) plus the reference cells `ref`, kept in `q` when
 * given (a key frame), scaled by the step and moved by the vertex's group transform into `pos`.
 */
function place(zz, ref, q, pos, T, s, runs, V) {
  let ax = 0, ay = 0, az = 0;
  for (let r = 0; r + 2 < runs.length; r += 2) { // a run of one group: its transform, step folded in
    const m = 12 * runs[r + 1];
    const a0 = T[m] * s, a1 = T[m + 1] * s, a2 = T[m + 2] * s, a3 = T[m + 3];
    const b0 = T[m + 4] * s, b1 = T[m + 5] * s, b2 = T[m + 6] * s, b3 = T[m + 7];
    const c0 = T[m + 8] * s, c1 = T[m + 9] * s, c2 = T[m + 10] * s, c3 = T[m + 11];
    for (let i = runs[r], e = runs[r + 2]; i < e; i++) {
      const ux = zz[i], uy = zz[V + i], uz = zz[2 * V + i];
      ax = (ax + ((ux >>> 1) ^ -(ux & 1))) | 0;
      ay = (ay + ((uy >>> 1) ^ -(uy & 1))) | 0;
      az = (az + ((uz >>> 1) ^ -(uz & 1))) | 0;
      const x = (ref[i] + ax) | 0, y = (ref[V + i] + ay) | 0, z = (ref[2 * V + i] + az) | 0;
      if (q !== null) { q[i] = x; q[V + i] = y; q[2 * V + i] = z; }
      pos[3 * i] = a0 * x + a1 * y + a2 * z + a3;
      pos[3 * i + 1] = b0 * x + b1 * y + b2 * z + b3;
      pos[3 * i + 2] = c0 * x + c1 * y + c2 * z + c3;
    }
  }
}

function popcount8(m) {
  m = m - ((m >> 1) & 0x55);
  m = (m & 0x33) + ((m >> 2) & 0x33);
  return (m + (m >> 4)) & 15;
}

export class CompactDecoder {
  /** rest: Float32Array(3V) rest vertices; groups: Uint8Array(V) rigid group per vertex (topology). */
  constructor(rest, groups) {
    this.V = groups.length;
    if (rest.length !== 3 * this.V) throw new Error('rest must hold 3 values per vertex');
    this.rest = rest;
    this.groups = groups;
    this.nGroups = groups.reduce((m, g) => Math.max(m, g), 0) + 1;
    const runs = []; // [start, group] of each run of one group along the vertex order
    for (let i = 0; i < this.V; i++) if (i === 0 || groups[i] !== groups[i - 1]) runs.push(i, groups[i]);
    runs.push(this.V, 0);
    this.runs = Int32Array.from(runs);
    this.keySeq = null; // seq of the key frame held
    this.keyStep = 0;
    this.keyQ = null; // Int32Array(3V), axis-major: keyQ[a * V + i]
    this.baseStep = 0;
    this.base = null; // Int32Array(3V) rest cells, axis-major
    this.nb = (this.V + 7) >> 3; // bytes of one axis's bitmap
    this.zz = new Int32Array(3 * this.V); // zigzagged differences of a frame, reused
    this.raw = new Uint8Array(3 * this.nb + 3 * this.V); // inflated payload, reused (grows)
    this.spare = null; // Int32Array(3V): the next key frame's cells go here (the held key's stay)
  }

  /** The frame's fields, or throws on a malformed frame (no payload decoding). */
  parse(buffer) {
    if (buffer.byteLength < HEAD) throw new Error(`compact frame of ${buffer.byteLength} bytes is shorter than its headers`);
    const dv = new DataView(buffer);
    if (dv.getUint32(0, true) !== MAGIC) throw new Error('not a facecast frame (bad magic)');
    if (dv.getUint8(4) !== 1) throw new Error(`unsupported frame version ${dv.getUint8(4)}`);
    if (dv.getUint8(5) !== KIND_COMPACT) throw new Error(`not a compact frame (kind ${dv.getUint8(5)})`);
    const format = dv.getUint16(42, true);
    if (format !== COMPACT_FORMAT) throw new Error(`compact format ${format} is not supported (this page reads ${COMPACT_FORMAT}): reload the page`);
    const flags = dv.getUint16(6, true);
    if (flags & ~1) throw new Error(`unknown flag bits ${flags}`);
    const f = {
      key: (flags & 1) === 1, seq: dv.getUint32(8, true), count: dv.getUint32(12, true),
      t: dv.getFloat64(16, true), wall: dv.getFloat64(24, true), ref: dv.getUint32(32, true),
      step: dv.getFloat32(36, true), G: dv.getUint8(40), planes: dv.getUint8(41), zlen: dv.getUint32(44, true),
      nnz: dv.getUint32(48, true),
    };
    if (!Number.isFinite(f.t) || !Number.isFinite(f.wall)) throw new Error('media and wall times must be finite');
    if (!(f.step > 0 && f.step <= 1e6)) throw new Error(`grid step ${f.step} out of range`);
    if (f.G < 1) throw new Error('a compact frame carries at least one transform');
    if (f.planes < 1 || f.planes > 4) throw new Error(`planes must be 1-4, got ${f.planes}`);
    if (f.nnz > 3 * f.count) throw new Error(`nnz ${f.nnz} is over the frame's 3 x ${f.count} values`);
    if (f.key && f.ref !== f.seq) throw new Error('a key frame must name itself');
    if (buffer.byteLength !== HEAD + 48 * f.G + f.zlen) throw new Error('compact frame length does not match its fields');
    f.transforms = new Float32Array(buffer.slice(HEAD, HEAD + 48 * f.G)); // G x [3][4]
    for (let k = 0; k < 12 * f.G; k++) {
      const x = f.transforms[k];
      if (!Number.isFinite(x) || (k % 4 !== 3 && Math.abs(x) > 1.001)) throw new Error('bad transform');
    }
    f.payload = new Uint8Array(buffer, HEAD + 48 * f.G, f.zlen);
    return f;
  }

  /**
   * Decode one frame: {seq, t, wall, key, positions: Float32Array(3V) x,y,z per vertex}, or null for
   * a delta whose key frame this decoder does not hold (show nothing new; wait for the next key).
   * Throws on a malformed frame.
   */
  async decode(buffer, out = null) {
    const f = this.parse(buffer);
    const V = this.V;
    if (f.count !== V) throw new Error(`frame has ${f.count} vertices, the face has ${V}`);
    if (f.G < this.nGroups) throw new Error(`frame has ${f.G} transforms, the face has ${this.nGroups} rigid groups`);
    let ref;
    if (f.key) {
      if (this.baseStep !== f.step) {
        const base = new Int32Array(3 * V);
        for (let i = 0; i < V; i++) {
          for (let a = 0; a < 3; a++) base[a * V + i] = Math.floor(this.rest[3 * i + a] / f.step + 0.5);
        }
        this.base = base;
        this.baseStep = f.step;
      }
      ref = this.base;
    } else if (this.keyQ === null || this.keySeq !== f.ref) {
      return null;
    } else if (this.keyStep !== f.step) {
      throw new Error("a delta frame's grid step differs from its key frame's");
    } else {
      ref = this.keyQ;
    }
    const n = 3 * V, P = f.planes, K = f.nnz, nb = this.nb;
    const want = 3 * nb + P * K;
    if (this.raw.length < want) this.raw = new Uint8Array(want);
    const raw = inflateExactly(f.payload, want, this.raw);
    const zz = this.zz; // zigzagged differences, 3V of them: 0 but where the bitmaps say
    zz.fill(0);
    let c = 0; // the next non-zero value; its byte k at 3 nb + k K + c
    const v0 = 3 * nb;
    for (let a = 0; a < 3; a++) {
      const bm = a * nb, za = a * V;
      for (let b = 0; b < nb; b++) {
        let m = raw[bm + b];
        if (m === 0) continue;
        if (c + 8 > K && c + popcount8(m) > K) throw new Error(`the bitmaps mark more than nnz = ${K} values`);
        const i0 = 8 * b;
        if (i0 + 8 > V && m >> (V - i0)) throw new Error('bitmap bits past the last vertex must be 0');
        do {
          const i = i0 + (31 - Math.clz32(m & -m));
          let u = raw[v0 + c];
          if (P > 1) u |= raw[v0 + K + c] << 8;
          if (P > 2) u |= raw[v0 + 2 * K + c] << 16;
          if (P > 3) u |= raw[v0 + 3 * K + c] << 24;
          if (u === 0) throw new Error('a value the bitmap marks as non-zero is 0');
          zz[za + i] = u;
          c++;
          m &= m - 1;
        } while (m !== 0);
      }
    }
    if (c !== K) throw new Error(`the bitmaps mark ${c} non-zero values, nnz says ${K}`);
    const q = f.key ? this.spare || new Int32Array(n) : null; // a key's cells are kept
    const pos = out && out.length === n ? out : new Float32Array(n);
    place(zz, ref, q, pos, f.transforms, f.step, this.runs, V);
    if (f.key) {
      this.spare = this.keyQ;
      this.keyQ = q;
      this.keySeq = f.seq;
      this.keyStep = f.step;
    }
    return { seq: f.seq, t: f.t, wall: f.wall, key: f.key, count: V, positions: pos };
  }
}
