// Producing into a session from the page: FAP frames (buttons, sliders) or PCM chunks (microphone).
// Once connected, a producer whose connection drops (its node went away, a failover) reconnects by
// itself with the same hello: backoff from 50 ms, doubling, capped at 1 s, jittered; for at most a
// minute (an unknown session: 5 s). Refusals another try would not change (a wrong token, a closed
// session, a flood) end it. Frames sent while it is away are dropped (live input is not worth
// sending late); the last FAP frame is sent again on reconnection, so the face keeps its pose.
import { fapMessage, pcmF32Frame, tokenProtocols } from './protocol.js';

/** Close codes after which a new connection may succeed (see client/api.py's RETRYABLE). */
const RETRYABLE = new Set([1001, 1006, 1011, 1012, 1013, 1014, 4409, 4500, 4502, 4503]);
const NOT_FOUND = 4404;
export const RETRY = { first: 50, cap: 1000, giveUp: 60000, missing: 5000 };  // milliseconds

/** Wait before try `n` (0, 1, ...): first * 2^n capped, times a random factor in [0.5, 1]. */
export function backoff(n, random = Math.random) {
  return Math.min(RETRY.cap, RETRY.first * 2 ** Math.min(n, 30)) * (0.5 + 0.5 * random());
}

export class Producer {
  constructor(session, token, onStatus = () => {}) {
    this.session = session; this.token = token; this.onStatus = onStatus;
    this.ws = null; this.open = false; this.seq = 0; this.t0 = performance.now(); this.samples = 0;
    this.closed = false;        // close() was called: never reconnect
    this.reconnecting = false;  // between a lost connection and the next `ready`
    this.reconnects = 0;
    this.last = null;           // the last FAP frame's arguments, re-sent after a reconnection
  }

  /** Connect and send the hello; resolves when the server answers `ready`. */
  connect(hello) {
    this.hello = hello;
    return this.open_(hello);
  }

  open_(hello) {
    const proto = location.protocol === 'https:' ? 'wss' : 'ws';
    const url = `${proto}://${location.host}/v1/sessions/${this.session}/produce`;
    const ws = new WebSocket(url, tokenProtocols(this.token));  // the token is not in the URL
    ws.binaryType = 'arraybuffer';
    this.ws = ws;
    return new Promise((resolve, reject) => {
      let ready = false, errorCode = null;
      ws.onopen = () => ws.send(JSON.stringify({ type: 'hello', role: 'producer', protocol: 1, ...hello }));
      ws.onmessage = (ev) => {
        if (typeof ev.data !== 'string') return;
        const msg = JSON.parse(ev.data);
        if (msg.type === 'ready') { ready = true; this.open = true; this.ready = msg; resolve(this); }
        if (msg.type === 'error') {
          errorCode = msg.code;
          this.onStatus(`producer: ${msg.message}`, msg.fatal ? 'error' : 'warn');
          if (!this.open) reject(Object.assign(new Error(msg.message), { code: msg.code }));
        }
      };
      ws.onclose = (ev) => {
        this.open = false;
        if (!ready) { reject(Object.assign(new Error(`closed ${ev.code}`), { code: errorCode || ev.code })); return; }
        if (this.closed || this.ws !== ws) return;
        const code = ev.code === 1000 || ev.code === 1005 ? ev.code : errorCode || ev.code;
        if (RETRYABLE.has(code) || code === NOT_FOUND) this.reconnect(code);
        else if (code !== 1000) this.onStatus(`producer connection closed (${ev.code} ${ev.reason || ''})`, 'warn');
      };
    });
  }

  /** Open the connection again after it was lost with `code`, with backoff; see the header. */
  async reconnect(code) {
    this.reconnecting = true;
    this.onStatus(`producer connection lost (${code}); reconnecting…`, 'warn');
    const t0 = performance.now();
    let missingSince = code === NOT_FOUND ? t0 : null;
    for (let n = 0; !this.closed; n++) {
      const wait = backoff(n);
      const now = performance.now();
      if (now + wait - t0 > RETRY.giveUp || (missingSince !== null && now + wait - missingSince > RETRY.missing)) break;
      await new Promise((resolve) => { setTimeout(resolve, wait); });
      if (this.closed) break;
      try {
        await this.open_(this.hello);
        this.reconnecting = false;
        this.reconnects++;
        this.onStatus(`producer reconnected after ${((performance.now() - t0) / 1000).toFixed(2)} s`, 'ok');
        if (this.last) this.sendFaps(...this.last);
        return;
      } catch (e) {
        if (!(RETRYABLE.has(e.code) || e.code === NOT_FOUND)) break;  // final
        missingSince = e.code === NOT_FOUND ? (missingSince ?? performance.now()) : null;
      }
    }
    this.reconnecting = false;
    if (!this.closed) this.onStatus('producer: could not reconnect; start again', 'error');
  }

  /** Send one FAP frame now: faps maps FAP number -> value. */
  sendFaps(faps, viseme = null, expression = null) {
    this.last = [faps, viseme, expression];
    if (!this.open) return;
    const t = (performance.now() - this.t0) / 1000;
    this.ws.send(fapMessage(this.seq++, t, faps, viseme, expression));
  }

  /** Send mono float32 samples at `rate` (while reconnecting they are dropped; the media time goes on). */
  sendPcm(samples, rate) {
    if (this.open) this.ws.send(pcmF32Frame(this.seq++, samples, rate, this.samples));
    this.samples += samples.length;
  }

  close() { this.closed = true; this.open = false; if (this.ws) this.ws.close(1000); }
}
