// A module Worker that owns a session's watch WebSocket. It reads and decodes every frame the moment
// it arrives, so the socket never backs up behind the page's drawing (software GL can block the main
// thread for tens of milliseconds), keeps only the newest vertex frame, and hands it to the page when
// the page asks for the next one: at most one frame is in flight to the page.
//
// Page -> worker: {type: 'connect', id, url, protocols} | {type: 'next'} | {type: 'close'}
// Worker -> page: {type: 'open'|'close'|'text'|'frame'|'error', id, ...}
import { decodeVertexFrame } from './protocol.js';

let ws = null, id = 0, newest = null, wanted = false;
let received = 0, dropped = 0, superseded = 0, lastSeq = null, decodeMs = [];

function deliver() {
  if (!newest || !wanted) return;
  const f = newest;
  newest = null; wanted = false;
  postMessage({ type: 'frame', id, buffer: f, received, dropped, superseded, decodeMs }, [f]);
  decodeMs = [];
}

function connect(url, connId, protocols = []) {
  if (ws) { ws.onclose = null; ws.onmessage = null; ws.close(); }
  id = connId; newest = null; lastSeq = null;
  const sock = new WebSocket(url, protocols);  // they carry the token (protocol.js tokenProtocols)
  sock.binaryType = 'arraybuffer';
  ws = sock;
  sock.onopen = () => postMessage({ type: 'open', id: connId });
  sock.onclose = (ev) => { if (ws === sock) ws = null; postMessage({ type: 'close', id: connId, code: ev.code, reason: ev.reason }); };
  sock.onmessage = (ev) => {
    if (typeof ev.data === 'string') { postMessage({ type: 'text', id: connId, data: ev.data }); return; }
    const t0 = performance.now();
    let frame;
    try { frame = decodeVertexFrame(ev.data); } catch (e) { postMessage({ type: 'error', id: connId, message: e.message }); return; }
    decodeMs.push(performance.now() - t0);
    if (decodeMs.length > 240) decodeMs.splice(0, decodeMs.length - 240);
    if (lastSeq !== null && frame.seq > lastSeq + 1) dropped += frame.seq - lastSeq - 1;
    lastSeq = frame.seq; received += 1;
    if (newest) superseded += 1;  // a newer frame came before the page could take this one
    newest = ev.data;
    deliver();
  };
}

onmessage = (ev) => {
  const m = ev.data;
  if (m.type === 'connect') connect(m.url, m.id, m.protocols);
  else if (m.type === 'next') { wanted = true; deliver(); }
  else if (m.type === 'close') { if (ws) { ws.onclose = null; ws.close(); ws = null; } newest = null; }
};
