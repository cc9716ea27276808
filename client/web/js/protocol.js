// The facecast wire formats in JavaScript, written from protocol/README.md and protocol/topology.py.
// Decoding returns typed-array views into the received buffer: no copies, no per-vertex loops.

export const KIND = { VERTICES_F32: 1, VERTICES_I16: 2, PCM_I16: 3, PCM_F32: 4, MARKERS: 5, FAPS: 6 };
const MAGIC = 0x54534346; // "FCST" little-endian
const HEADER = 32;

/** Decode a binary vertex frame. Returns {kind, seq, count, t, wall, positions|q, offset, scale}. */
export function decodeVertexFrame(buffer) {
  if (buffer.byteLength < HEADER) throw new Error(`frame of ${buffer.byteLength} bytes is shorter than its header`);
  const dv = new DataView(buffer);
  if (dv.getUint32(0, true) !== MAGIC) throw new Error('not a facecast frame (bad magic)');
  if (dv.getUint8(4) !== 1) throw new Error(`unsupported frame version ${dv.getUint8(4)}`);
  const kind = dv.getUint8(5), seq = dv.getUint32(8, true), count = dv.getUint32(12, true);
  const t = dv.getFloat64(16, true), wall = dv.getFloat64(24, true);
  if (kind === KIND.VERTICES_F32) {
    if (buffer.byteLength !== HEADER + 12 * count) throw new Error('f32 frame length does not match its count');
    return { kind, seq, count, t, wall, positions: new Float32Array(buffer, HEADER, 3 * count) };
  }
  if (kind === KIND.VERTICES_I16) {
    if (buffer.byteLength !== 56 + 6 * count) throw new Error('i16 frame length does not match its count');
    return { kind, seq, count, t, wall, offset: new Float32Array(buffer, 32, 3),
             scale: new Float32Array(buffer, 44, 3), q: new Int16Array(buffer, 56, 3 * count) };
  }
  throw new Error(`unexpected frame kind ${kind} for a viewer`);
}

/** Decode the topology blob of GET /v1/faces/{name}/topology. */
export function decodeTopology(buffer) {
  const dv = new DataView(buffer);
  const magic = String.fromCharCode(...new Uint8Array(buffer, 0, 4));
  if (magic !== 'FCTP') throw new Error('not a facecast topology');
  const V = dv.getUint32(8, true), F = dv.getUint32(12, true);
  const P = dv.getUint16(16, true), G = dv.getUint16(18, true), N = dv.getUint32(20, true);
  const mmPerUnit = dv.getFloat32(24, true);
  const pad = (n) => (n + 3) & ~3;
  const names = new TextDecoder().decode(new Uint8Array(buffer, 32, N)).split('\n');
  let off = 32 + pad(N);
  const vertices = new Float32Array(buffer, off, 3 * V); off += 12 * V;
  const triangles = new Uint32Array(buffer, off, 3 * F); off += 12 * F;
  const partIds = new Uint8Array(buffer, off, V); off += pad(V);
  const groups = new Uint8Array(buffer, off, V);
  return { V, F, vertices, triangles, partIds, partNames: names.slice(0, P),
           groupNames: names.slice(P, P + G), groups, mmPerUnit };
}

/** WebSocket subprotocols that carry a session token: browsers cannot set an Authorization header,
 *  and a token in the URL would reach server logs. The server accepts with 'facecast.v1'. */
export function tokenProtocols(token) {
  return ['facecast.v1', `facecast.token.${token}`];
}

/** A JSON FAP frame for a producer: faps maps FAP number (3-68) to its value. */
export function fapMessage(seq, t, faps, viseme = null, expression = null) {
  const msg = { type: 'fap', seq, t, wall: Date.now() / 1000, faps };
  if (viseme) msg.viseme = viseme;
  if (expression) msg.expression = expression;
  return JSON.stringify(msg);
}

/** A binary PCM_F32 chunk (mono float32 samples at `rate`) starting at `sampleOffset`. */
export function pcmF32Frame(seq, samples, rate, sampleOffset) {
  const n = samples.length, buf = new ArrayBuffer(48 + 4 * n), dv = new DataView(buf);
  dv.setUint32(0, MAGIC, true); dv.setUint8(4, 1); dv.setUint8(5, KIND.PCM_F32); dv.setUint16(6, 0, true);
  dv.setUint32(8, seq >>> 0, true); dv.setUint32(12, n, true);
  dv.setFloat64(16, sampleOffset / rate, true); dv.setFloat64(24, Date.now() / 1000, true);
  dv.setUint32(32, rate, true); dv.setUint16(36, 1, true); dv.setUint16(38, 0, true);
  dv.setBigUint64(40, BigInt(sampleOffset), true);
  new Float32Array(buf, 48, n).set(samples);
  return buf;
}
