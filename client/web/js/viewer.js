// Watching a session: fetch the face topology, subscribe over WebSocket (in a Worker: ./receiver.js),
// draw the newest frame. Reconnects with back-off when the connection drops (server restart) and says so.
import { decodeTopology, decodeVertexFrame, KIND, tokenProtocols } from './protocol.js';

export class Viewer {
  constructor(renderer, { onStatus = () => {}, onStats = () => {} } = {}) {
    this.renderer = renderer; this.onStatus = onStatus; this.onStats = onStats;
    this.pending = null; this.face = null; this.closedByUser = false; this.connId = 0; this.attempt = 0;
    this.worker = new Worker(new URL('./receiver.js', import.meta.url), { type: 'module' });
    this.worker.onmessage = (ev) => this.onWorker(ev.data);
    this.worker.onerror = (ev) => this.onStatus(`receiver worker: ${ev.message}`, 'error');
    this.stats = { frames: 0, bytes: 0, dropped: 0, superseded: 0, lastSeq: null, latencies: [], decodeMs: [], times: [] };
  }

  async loadFace(name) {
    if (this.face === name) return;
    const res = await fetch(`/v1/faces/${encodeURIComponent(name)}/topology`);
    if (!res.ok) throw new Error(`topology of face ${name}: HTTP ${res.status}`);
    const topo = decodeTopology(await res.arrayBuffer());
    this.renderer.setMesh(topo.vertices, topo.triangles, topo.partIds, topo.partNames);
    this.topology = topo; this.face = name;
  }

  watch(session, token, encoding = 'compact') {
    this.closedByUser = false;
    this.target = { session, token, encoding };
    this.connect(0);
  }

  connect(attempt) {
    const { session, token, encoding } = this.target;
    const proto = location.protocol === 'https:' ? 'wss' : 'ws';
    const url = `${proto}://${location.host}/v1/sessions/${session}/watch?encoding=${encoding}`;
    const id = ++this.connId;
    this.attempt = attempt;
    this.pending = null;
    this.worker.postMessage({ type: 'connect', id, url, protocols: tokenProtocols(token) });
    this.worker.postMessage({ type: 'next' });
  }

  close() { this.closedByUser = true; this.worker.postMessage({ type: 'close' }); }

  /** Messages from the receiving worker (./receiver.js) for the current connection. */
  onWorker(m) {
    if (m.id !== this.connId) return;  // from a connection that was replaced
    if (m.type === 'open') this.onStatus(this.attempt ? 'reconnected' : 'connected', 'ok');
    else if (m.type === 'text') this.onText(JSON.parse(m.data));
    else if (m.type === 'frame') this.onFrame(m);
    else if (m.type === 'error') this.onStatus(`bad frame: ${m.message}`, 'warn');
    else if (m.type === 'close') this.onClose(m);
  }

  onClose(ev) {
    const { session } = this.target, attempt = this.attempt;
    if (this.closedByUser) return;
    if (ev.code === 4404 && attempt > 0) {
      this.onStatus(`reconnected, but session ${session} is gone (the server restarted); start a demo or pick a live session`, 'error');
      return;
    }
    if (ev.code >= 4400 && ev.code !== 4429 && ev.code !== 4500) {
      this.onStatus(`disconnected: ${ev.reason || 'refused'} (${ev.code})`, 'error');
      return;
    }
    const delay = Math.min(5000, 250 * 2 ** attempt);
    this.onStatus(`connection lost (${ev.code}); reconnecting in ${(delay / 1000).toFixed(1)} s…`, 'warn');
    const id = this.connId;
    setTimeout(() => { if (id === this.connId && !this.closedByUser) this.connect(attempt + 1); }, delay);
  }

  async onText(msg) {
    if (msg.type === 'hello') {
      this.hello = msg;
      await this.loadFace(msg.face);
      this.onStatus(`watching ${msg.session} (${msg.face}, ${msg.encoding}, producer ${msg.producer_connected ? 'on' : 'off'})`, 'ok');
    } else if (msg.type === 'status') {
      this.onStatus(`producer ${msg.producer_connected ? 'connected' : 'not connected'}; ${msg.viewers} viewer(s)`, 'ok');
    } else if (msg.type === 'error') {
      this.onStatus(`server: ${msg.message}`, msg.fatal ? 'error' : 'warn');
    }
  }

  /** A frame handed over by the worker (already checked there; decoding here only makes views). */
  onFrame(m) {
    const frame = decodeVertexFrame(m.buffer), s = this.stats;
    s.decodeMs.push(...m.decodeMs);
    s.frames = m.received; s.dropped = m.dropped; s.superseded = m.superseded; s.bytes = m.wireBytes;
    if (frame.wall > 0) s.latencies.push(Date.now() - frame.wall * 1000);
    s.times.push([performance.now(), m.received, m.wireTotal]);
    this.pending = frame;  // only the newest frame is drawn
  }

  /** Upload the newest frame, if any, and ask the worker for the next; returns true when something changed. */
  flush() {
    const f = this.pending;
    if (!f || !this.renderer.mesh) return false;
    this.pending = null;
    this.worker.postMessage({ type: 'next' });
    if (f.count !== this.renderer.mesh.V) return false;  // a frame for another face (being switched)
    if (f.kind === KIND.VERTICES_I16) this.renderer.setFrameI16(f.q, f.offset, f.scale);
    else this.renderer.setFrameF32(f.positions);
    return true;
  }

  summary() {
    const s = this.stats, now = performance.now();
    s.times = s.times.filter(([t]) => now - t < 2000);
    // Frames received per second over the last two seconds (the worker receives more than it hands over).
    const fps = s.times.length ? (s.times.at(-1)[1] - s.times[0][1] + 1) / 2 : 0;
    const recent = (a) => a.slice(-120);
    const pct = (a, p) => { if (!a.length) return NaN; const b = [...a].sort((x, y) => x - y); return b[Math.min(b.length - 1, Math.floor(p * b.length))]; };
    s.latencies = recent(s.latencies); s.decodeMs = recent(s.decodeMs);
    return { fps, latencyP50: pct(s.latencies, 0.5), latencyP95: pct(s.latencies, 0.95),
             bytes: s.bytes, dropped: s.dropped, frames: s.frames, decodeMs: pct(s.decodeMs, 0.5),
             bitsPerSecond: s.times.length > 1 ? 8 * (s.times.at(-1)[2] - s.times[0][2]) / ((s.times.at(-1)[0] - s.times[0][0]) / 1000) : NaN };
  }
}
