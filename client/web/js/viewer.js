// Watching a session: fetch the face topology, subscribe over WebSocket, draw the newest frame.
// Reconnects with back-off when the connection drops (server restart) and says so.
import { decodeTopology, decodeVertexFrame, KIND } from './protocol.js';

export class Viewer {
  constructor(renderer, { onStatus = () => {}, onStats = () => {} } = {}) {
    this.renderer = renderer; this.onStatus = onStatus; this.onStats = onStats;
    this.ws = null; this.pending = null; this.face = null; this.closedByUser = false;
    this.stats = { frames: 0, bytes: 0, dropped: 0, lastSeq: null, latencies: [], decodeMs: [], times: [] };
  }

  async loadFace(name) {
    if (this.face === name) return;
    const res = await fetch(`/v1/faces/${encodeURIComponent(name)}/topology`);
    if (!res.ok) throw new Error(`topology of face ${name}: HTTP ${res.status}`);
    const topo = decodeTopology(await res.arrayBuffer());
    this.renderer.setMesh(topo.vertices, topo.triangles, topo.partIds, topo.partNames);
    this.topology = topo; this.face = name;
  }

  watch(session, token, encoding = 'i16') {
    this.closedByUser = false;
    this.target = { session, token, encoding };
    this.connect(0);
  }

  connect(attempt) {
    const { session, token, encoding } = this.target;
    const proto = location.protocol === 'https:' ? 'wss' : 'ws';
    const ws = new WebSocket(`${proto}://${location.host}/v1/sessions/${session}/watch?token=${encodeURIComponent(token)}&encoding=${encoding}`);
    ws.binaryType = 'arraybuffer';
    this.ws = ws;
    ws.onopen = () => this.onStatus(attempt ? 'reconnected' : 'connected', 'ok');
    ws.onmessage = (ev) => this.onMessage(ev);
    ws.onclose = (ev) => {
      if (this.closedByUser || ws !== this.ws) return;
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
      setTimeout(() => this.connect(attempt + 1), delay);
    };
  }

  close() { this.closedByUser = true; if (this.ws) this.ws.close(); }

  async onMessage(ev) {
    if (typeof ev.data === 'string') {
      const msg = JSON.parse(ev.data);
      if (msg.type === 'hello') {
        this.hello = msg;
        await this.loadFace(msg.face);
        this.onStatus(`watching ${msg.session} (${msg.face}, ${msg.encoding}, producer ${msg.producer_connected ? 'on' : 'off'})`, 'ok');
      } else if (msg.type === 'status') {
        this.onStatus(`producer ${msg.producer_connected ? 'connected' : 'not connected'}; ${msg.viewers} viewer(s)`, 'ok');
      } else if (msg.type === 'error') {
        this.onStatus(`server: ${msg.message}`, msg.fatal ? 'error' : 'warn');
      }
      return;
    }
    const t0 = performance.now();
    const frame = decodeVertexFrame(ev.data);
    const s = this.stats;
    s.decodeMs.push(performance.now() - t0);
    if (s.lastSeq !== null && frame.seq > s.lastSeq + 1) s.dropped += frame.seq - s.lastSeq - 1;
    s.lastSeq = frame.seq; s.frames += 1; s.bytes = ev.data.byteLength;
    if (frame.wall > 0) s.latencies.push(Date.now() - frame.wall * 1000);
    s.times.push(performance.now());
    this.pending = frame;  // only the newest frame is drawn
  }

  /** Upload the newest frame, if any; returns true when something changed. */
  flush() {
    const f = this.pending;
    if (!f || !this.renderer.mesh || f.count !== this.renderer.mesh.V) return false;
    this.pending = null;
    if (f.kind === KIND.VERTICES_I16) this.renderer.setFrameI16(f.q, f.offset, f.scale);
    else this.renderer.setFrameF32(f.positions);
    return true;
  }

  summary() {
    const s = this.stats, now = performance.now();
    s.times = s.times.filter((x) => now - x < 2000);
    const recent = (a) => a.slice(-120);
    const pct = (a, p) => { if (!a.length) return NaN; const b = [...a].sort((x, y) => x - y); return b[Math.min(b.length - 1, Math.floor(p * b.length))]; };
    s.latencies = recent(s.latencies); s.decodeMs = recent(s.decodeMs);
    return { fps: s.times.length / 2, latencyP50: pct(s.latencies, 0.5), latencyP95: pct(s.latencies, 0.95),
             bytes: s.bytes, dropped: s.dropped, frames: s.frames, decodeMs: pct(s.decodeMs, 0.5) };
  }
}
