// A module Worker that owns a session's watch WebSocket. It reads and decodes every frame the moment
// it arrives, so the socket never backs up behind the page's drawing (software GL can block the main
// thread for tens of milliseconds), keeps only the newest vertex frame, and hands it to the page when
// the page asks for the next one: at most one frame is in flight to the page.
//
// Page -> worker: {type: 'connect', id, url, protocols} | {type: 'next'} | {type: 'close'}
// Worker -> page: {type: 'open'|'close'|'text'|'frame'|'error', id, ...}
import { decodeTopology, decodeVertexFrame } from './protocol.js';
import { CompactDecoder, KIND_COMPACT } from './compact.js';

let ws = null, id = 0, newest = null, wanted = false;
let received = 0, dropped = 0, superseded = 0, lastSeq = null, decodeMs = [];
// compact: frames are decoded here, in order (decoding is asynchronous), and handed to the page as
// float32 frames; wireBytes/wireTotal count what came over the network.
let compact = null, chain = Promise.resolve(), wireBytes = 0, wireTotal = 0;

async function compactDecoder(topologyUrl) {
  const res = await fetch(topologyUrl);
  if (!res.ok) throw new Error(`topology: HTTP ${res.status}`);
  const topo = decodeTopology(await res.arrayBuffer());
  return new CompactDecoder(topo.vertices, topo.groups);
}

/** `buf` (decoded positions after a 32-byte header) made a VERTICES_F32 frame with the compact frame's header fields. */
function asF32(data, buf) {
  new Uint8Array(buf, 0, 32).set(new Uint8Array(data, 0, 32));
  const dv = new DataView(buf);
  dv.setUint8(5, 1); dv.setUint16(6, 0, true);
  return buf;
}

function deliver() {
  if (!newest || !wanted) return;
  const f = newest;
  newest = null; wanted = false;
  postMessage({ type: 'frame', id, buffer: f, received, dropped, superseded, decodeMs, wireBytes, wireTotal }, [f]);
  decodeMs = [];
}

function connect(url, connId, protocols = []) {
  if (ws) { ws.onclose = null; ws.onmessage = null; ws.close(); }
  id = connId; newest = null; lastSeq = null; compact = null; chain = Promise.resolve();
  const sock = new WebSocket(url, protocols);  // they carry the token (protocol.js tokenProtocols)
  sock.binaryType = 'arraybuffer';
  ws = sock;
  sock.onopen = () => postMessage({ type: 'open', id: connId });
  sock.onclose = (ev) => { if (ws === sock) ws = null; postMessage({ type: 'close', id: connId, code: ev.code, reason: ev.reason }); };
  sock.onmessage = (ev) => {
    if (typeof ev.data === 'string') {
      const msg = JSON.parse(ev.data);
      if (msg.type === 'hello' && msg.encoding === 'compact') {
        const made = compactDecoder(msg.topology_url);
        chain = chain.then(async () => { compact = await made; });
      }
      postMessage({ type: 'text', id: connId, data: ev.data });
      return;
    }
    wireBytes = ev.data.byteLength; wireTotal += wireBytes;
    if (new DataView(ev.data).getUint8(5) === KIND_COMPACT) {
      const data = ev.data;
      chain = chain.then(async () => {
        if (ws !== sock || !compact) return;
        const t0 = performance.now();
        const buf = new ArrayBuffer(32 + 12 * compact.V);  // decoded straight into the f32 frame
        const out = await compact.decode(data, new Float32Array(buf, 32));
        if (out === null) return; // its key frame has not come: keep showing the last good face
        take(asF32(data, buf), out, t0);
      }).catch((e) => postMessage({ type: 'error', id: connId, message: e.message }));
      return;
    }
    const t0 = performance.now();
    let frame;
    try { frame = decodeVertexFrame(ev.data); } catch (e) { postMessage({ type: 'error', id: connId, message: e.message }); return; }
    take(ev.data, frame, t0);
  };
}

function take(data, frame, t0) {
  decodeMs.push(performance.now() - t0);
  if (decodeMs.length > 240) decodeMs.splice(0, decodeMs.length - 240);
  if (lastSeq !== null && frame.seq > lastSeq + 1) dropped += frame.seq - lastSeq - 1;
  lastSeq = frame.seq; received += 1;
  if (newest) superseded += 1;  // a newer frame came before the page could take this one
  newest = data;
  deliver();
}

onmessage = (ev) => {
  const m = ev.data;
  if (m.type === 'connect') connect(m.url, m.id, m.protocols);
  else if (m.type === 'next') { wanted = true; deliver(); }
  else if (m.type === 'close') { if (ws) { ws.onclose = null; ws.close(); ws = null; } newest = null; }
};
