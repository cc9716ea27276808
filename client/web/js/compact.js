// VERTICES_COMPACT frames (kind 7), written from protocol/README.md section 3. A decoder holds the
// face's topology (rest vertices, rigid group per vertex) and the last key frame's grid cells; the
// payload is inflated with the platform's DecompressionStream('deflate') (zlib format).

const MAGIC = 0x54534346; // "FCST" little-endian
export const KIND_COMPACT = 7;
const HEAD = 48; // 32-byte frame header + 16-byte compact sub-header

/** Inflate a zlib stream to exactly `want` bytes; throws if it is invalid, shorter or longer. */
async function inflateExactly(bytes, want) {
  const out = new Uint8Array(want);
  let got = 0;
  const ds = new DecompressionStream('deflate');
  const writer = ds.writable.getWriter();
  writer.write(bytes).catch(() => {});
  writer.close().catch(() => {});
  const reader = ds.readable.getReader();
  try {
    for (;;) {
      const { done, value } = await reader.read();
      if (done) break;
      if (got + value.length > want) throw new Error(`compact payload inflates to more than ${want} bytes`);
      out.set(value, got);
      got += value.length;
    }
  } catch (e) {
    reader.cancel().catch(() => {});
    throw e instanceof Error && e.message.startsWith('compact') ? e : new Error(`compact payload is not a valid zlib stream (${e})`);
  }
  if (got !== want) throw new Error(`compact payload inflates to ${got} bytes, expected ${want}`);
  return out;
}

export class CompactDecoder {
  /** rest: Float32Array(3V) rest vertices; groups: Uint8Array(V) rigid group per vertex (topology). */
  constructor(rest, groups) {
    this.V = groups.length;
    if (rest.length !== 3 * this.V) throw new Error('rest must hold 3 values per vertex');
    this.rest = rest;
    this.groups = groups;
    this.nGroups = groups.reduce((m, g) => Math.max(m, g), 0) + 1;
    this.keySeq = null; // seq of the key frame held
    this.keyStep = 0;
    this.keyQ = null; // Int32Array(3V), axis-major: keyQ[a * V + i]
    this.baseStep = 0;
    this.base = null; // Int32Array(3V) rest cells, axis-major
    this.scratch = null; // Int32Array(3V) reused for delta frames' cells
  }

  /** The frame's fields, or throws on a malformed frame (no payload decoding). */
  parse(buffer) {
    if (buffer.byteLength < HEAD) throw new Error(`compact frame of ${buffer.byteLength} bytes is shorter than its headers`);
    const dv = new DataView(buffer);
    if (dv.getUint32(0, true) !== MAGIC) throw new Error('not a facecast frame (bad magic)');
    if (dv.getUint8(4) !== 1) throw new Error(`unsupported frame version ${dv.getUint8(4)}`);
    if (dv.getUint8(5) !== KIND_COMPACT) throw new Error(`not a compact frame (kind ${dv.getUint8(5)})`);
    const flags = dv.getUint16(6, true);
    if (flags & ~1) throw new Error(`unknown flag bits ${flags}`);
    const f = {
      key: (flags & 1) === 1, seq: dv.getUint32(8, true), count: dv.getUint32(12, true),
      t: dv.getFloat64(16, true), wall: dv.getFloat64(24, true), ref: dv.getUint32(32, true),
      step: dv.getFloat32(36, true), G: dv.getUint8(40), planes: dv.getUint8(41), zlen: dv.getUint32(44, true),
    };
    if (!Number.isFinite(f.t) || !Number.isFinite(f.wall)) throw new Error('media and wall times must be finite');
    if (!(f.step > 0 && f.step <= 1e6)) throw new Error(`grid step ${f.step} out of range`);
    if (f.G < 1) throw new Error('a compact frame carries at least one transform');
    if (f.planes < 1 || f.planes > 4) throw new Error(`planes must be 1-4, got ${f.planes}`);
    if (dv.getUint16(42, true) !== 0) throw new Error('reserved bytes must be 0');
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
    const n = 3 * V;
    const raw = await inflateExactly(f.payload, f.planes * n);
    const q = f.key || !this.scratch ? new Int32Array(n) : this.scratch; // a key's cells are kept
    const P = f.planes;
    for (let a = 0; a < 3; a++) {
      let acc = 0;
      const end = (a + 1) * V;
      if (P === 1) {
        for (let j = a * V; j < end; j++) {
          const u = raw[j];
          acc = (acc + ((u >>> 1) ^ -(u & 1))) | 0;
          q[j] = (ref[j] + acc) | 0;
        }
      } else {
        for (let j = a * V; j < end; j++) {
          let u = raw[j] | (raw[n + j] << 8);
          if (P > 2) u |= raw[2 * n + j] << 16;
          if (P > 3) u |= raw[3 * n + j] << 24;
          acc = (acc + ((u >>> 1) ^ -(u & 1))) | 0;
          q[j] = (ref[j] + acc) | 0;
        }
      }
    }
    if (f.key) {
      this.keyQ = q;
      this.keySeq = f.seq;
      this.keyStep = f.step;
    } else {
      this.scratch = q;
    }
    const pos = out && out.length === n ? out : new Float32Array(n);
    const T = f.transforms, s = f.step, g = this.groups;
    for (let i = 0; i < V; i++) {
      const m = 12 * g[i];
      const px = q[i] * s, py = q[V + i] * s, pz = q[2 * V + i] * s;
      pos[3 * i] = T[m] * px + T[m + 1] * py + T[m + 2] * pz + T[m + 3];
      pos[3 * i + 1] = T[m + 4] * px + T[m + 5] * py + T[m + 6] * pz + T[m + 7];
      pos[3 * i + 2] = T[m + 8] * px + T[m + 9] * py + T[m + 10] * pz + T[m + 11];
    }
    return { seq: f.seq, t: f.t, wall: f.wall, key: f.key, count: V, positions: pos };
  }
}
