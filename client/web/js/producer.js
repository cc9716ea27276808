// Producing into a session from the page: FAP frames (buttons, sliders) or PCM chunks (microphone).
import { fapMessage, pcmF32Frame, tokenProtocols } from './protocol.js';

export class Producer {
  constructor(session, token, onStatus = () => {}) {
    this.session = session; this.token = token; this.onStatus = onStatus;
    this.ws = null; this.open = false; this.seq = 0; this.t0 = performance.now(); this.samples = 0;
  }

  /** Connect and send the hello; resolves when the server answers `ready`. */
  connect(hello) {
    const proto = location.protocol === 'https:' ? 'wss' : 'ws';
    const url = `${proto}://${location.host}/v1/sessions/${this.session}/produce`;
    const ws = new WebSocket(url, tokenProtocols(this.token));  // the token is not in the URL
    ws.binaryType = 'arraybuffer';
    this.ws = ws;
    return new Promise((resolve, reject) => {
      ws.onopen = () => ws.send(JSON.stringify({ type: 'hello', role: 'producer', protocol: 1, ...hello }));
      ws.onmessage = (ev) => {
        if (typeof ev.data !== 'string') return;
        const msg = JSON.parse(ev.data);
        if (msg.type === 'ready') { this.open = true; this.ready = msg; resolve(this); }
        if (msg.type === 'error') {
          this.onStatus(`producer: ${msg.message}`, msg.fatal ? 'error' : 'warn');
          if (!this.open) reject(new Error(msg.message));
        }
      };
      ws.onclose = (ev) => {
        this.open = false;
        if (ev.code !== 1000) this.onStatus(`producer connection closed (${ev.code} ${ev.reason || ''})`, 'warn');
        reject(new Error(`closed ${ev.code}`));
      };
    });
  }

  /** Send one FAP frame now: faps maps FAP number -> value. */
  sendFaps(faps, viseme = null, expression = null) {
    if (!this.open) return;
    const t = (performance.now() - this.t0) / 1000;
    this.ws.send(fapMessage(this.seq++, t, faps, viseme, expression));
  }

  /** Send mono float32 samples at `rate`. */
  sendPcm(samples, rate) {
    if (!this.open) return;
    this.ws.send(pcmF32Frame(this.seq++, samples, rate, this.samples));
    this.samples += samples.length;
  }

  close() { this.open = false; if (this.ws) this.ws.close(1000); }
}
