// The facecast page: watch a live session, start a demo, drive the face, play files, lip-sync the mic.
import { FaceRenderer } from './renderer.js';
import { Viewer } from './viewer.js';
import { Producer } from './producer.js';
import { EXPRESSIONS, VISEMES, SLIDERS } from './controls.js';

const $ = (id) => document.getElementById(id);
const state = { session: null, tokens: {}, producer: null, mic: null, drawTimes: [] };
const sleep = (ms) => new Promise((resolve) => { setTimeout(resolve, ms); });

// ---- secrets: never shown -----------------------------------------------------------------------
// The admin key and session tokens are credentials: the page keeps them in storage and memory only.
// Every text it shows goes through redact(), which masks any of them (and any ?token=/&key= value).
function secrets() {
  const all = [$('admin-key').value.trim()];
  for (const t of Object.values(state.tokens)) all.push(t.producer, t.viewer);
  return all.filter((s) => s && s.length >= 6);
}

function redact(text) {
  let out = String(text);
  for (const s of secrets()) out = out.split(s).join('•••');
  return out.replace(/([?&#](?:token|key|producer)=)[^&\s]+/g, '$1•••');
}

function setStatus(text, level = 'ok') {
  const el = $('status');
  el.textContent = redact(text);
  el.className = `overlay status ${level}`;
}

const setInfo = (id, text) => { $(id).textContent = redact(text); };

// ---- admin key, the page's link, REST ------------------------------------------------------------
// A link may carry the admin key (#key=…) or a session with its tokens (#session=…&token=…&producer=…).
// The key goes to localStorage, a session's tokens to sessionStorage (this tab only, so a reload
// still watches it); the address bar keeps only #session=… .
const hashParams = new URLSearchParams(location.hash.slice(1));
if (hashParams.get('key')) localStorage.setItem('facecast-admin-key', hashParams.get('key'));
$('admin-key').value = localStorage.getItem('facecast-admin-key') || '';
if (['compact', 'i16', 'f32'].includes(hashParams.get('encoding'))) $('encoding').value = hashParams.get('encoding');
$('admin-key').addEventListener('change', () => localStorage.setItem('facecast-admin-key', $('admin-key').value.trim()));
const link = { session: hashParams.get('session'), token: hashParams.get('token'), producer: hashParams.get('producer') };
if (link.session && link.token) {
  sessionStorage.setItem(`facecast-link-${link.session}`, JSON.stringify(link));
} else if (link.session) {
  Object.assign(link, JSON.parse(sessionStorage.getItem(`facecast-link-${link.session}`) || '{}'));
}
{
  const shown = new URLSearchParams(hashParams);
  for (const k of ['key', 'token', 'producer']) shown.delete(k);
  const hash = shown.toString();
  if (hash !== location.hash.slice(1)) history.replaceState(null, '', `${location.pathname}${location.search}${hash ? `#${hash}` : ''}`);
}

class ApiError extends Error {
  constructor(message, status) { super(message); this.status = status; }
}

async function api(method, path, body, { form = false } = {}) {
  const headers = {};
  const key = $('admin-key').value.trim();
  if (key) headers.Authorization = `Bearer ${key}`;
  if (body && !form) headers['Content-Type'] = 'application/json';
  const res = await fetch(path, { method, headers, body: form ? body : body ? JSON.stringify(body) : undefined });
  const text = await res.text();
  const data = text ? (() => { try { return JSON.parse(text); } catch { return { error: text }; } })() : null;
  if (!res.ok) {
    const why = data && (data.error || data.detail);
    const where = path.split('?')[0];  // a query may hold a token
    throw new ApiError(redact(`${method} ${where}: ${res.status} ${typeof why === 'string' ? why : JSON.stringify(why)}`), res.status);
  }
  return data;
}

/** The query that authorises producer routes (demo, play): none with the admin key, else the producer token. */
function producerQuery(sessionId) {
  const t = state.tokens[sessionId];
  if ($('admin-key').value.trim() || !t || !t.producer) return '';
  return `?token=${encodeURIComponent(t.producer)}`;
}

async function refreshSessions() {
  const list = $('session-list');
  try {
    const data = await api('GET', '/v1/sessions');
    const sessions = data.sessions || data;
    list.innerHTML = '<option value="">— live sessions —</option>';
    for (const s of sessions) {
      const o = document.createElement('option');
      o.value = s.id;
      o.textContent = `${s.id.slice(0, 8)} · ${s.face} · ${s.input}${s.stats && s.stats.producer_connected ? ' · live' : ''}`;
      list.appendChild(o);
    }
  } catch (e) {
    setStatus(`cannot list sessions: ${e.message} (enter the admin key printed by 'facecast serve')`, 'warn');
  }
}

async function newSession(input) {
  const s = await api('POST', '/v1/sessions', { input });
  state.tokens[s.id] = { producer: s.producer_token, viewer: s.viewer_token };
  return s;
}

async function watch(sessionId) {
  if (!state.tokens[sessionId]) {
    const t = await api('GET', `/v1/sessions/${sessionId}/tokens`);
    state.tokens[sessionId] = { producer: t.producer_token, viewer: t.viewer_token };
  }
  if (state.producer && state.producer.session !== sessionId) { state.producer.close(); state.producer = null; }
  if (state.layerProducer && state.layerProducer.session !== sessionId) { state.layerProducer.close(); state.layerProducer = null; }
  state.session = sessionId;
  viewer.close();
  viewer.watch(sessionId, state.tokens[sessionId].viewer, $('encoding').value);
  if (idleOn && state.tokens[sessionId].producer) setLayer('idle', { kind: 'idle', seed: 1 }).catch(() => {});
}

/** Close a producer's connection; resolves once it is closed. */
function closed(p) {
  const ws = p && p.ws;
  if (!ws || ws.readyState === WebSocket.CLOSED) { if (p) p.close(); return Promise.resolve(); }
  const done = new Promise((resolve) => { ws.addEventListener('close', resolve, { once: true }); });
  p.close();
  return done;
}

/** Free the session's producer slot the page itself holds (buttons and sliders, or the microphone). */
async function releaseProducer() {
  const p = state.producer;
  state.producer = null;
  if (state.mic) await stopMic();
  await closed(p);
}

/**
 * The page's FAP producer for the watched session (created on first use). It takes the session's
 * producer slot over from whatever the page or the server runs there: the microphone, a server
 * demo or a playing file (stopped). Calls while it connects (a dragged slider) share the connection.
 */
let connecting = null;
function producer() {
  if (!connecting) connecting = openProducer().finally(() => { connecting = null; });
  return connecting;
}

async function openProducer() {
  if (state.mic) { await releaseProducer(); state.session = null; }  // the microphone's session takes audio
  if (!state.session) {
    const s = await newSession('fap');
    await watch(s.id);
  }
  // a producer that lost its connection reconnects by itself (producer.js): keep it meanwhile
  const live = state.producer && (state.producer.open || state.producer.reconnecting);
  if (!state.producer || state.producer.session !== state.session || !live) {
    await closed(state.producer);
    try { await api('DELETE', `/v1/sessions/${state.session}/demo${producerQuery(state.session)}`); } catch { /* no demo running */ }
    state.producer = new Producer(state.session, state.tokens[state.session].producer, setStatus);
    await state.producer.connect({ input: 'fap' });
  }
  return state.producer;
}

// ---- layers: the controls over a voice ----------------------------------------------------------
// While a voice drives the mouth (the microphone, or any session that takes audio), the page does
// not take the primary producer slot: expression buttons set an expression layer over REST, the
// sliders stream as an 'expression' producer (head and look sliders set head and gaze layers),
// and the idle toggle sets the idle layer, all mixed by the server into every frame of the voice.
const layered = () => Boolean(state.mic) || Boolean(viewer.hello && viewer.hello.input !== 'fap');

/** PUT (or, with no spec, DELETE) the layer `name` of the watched session. */
async function setLayer(name, spec) {
  if (!state.session) { const s = await newSession('fap'); await watch(s.id); }
  const path = `/v1/sessions/${state.session}/layers/${name}${producerQuery(state.session)}`;
  if (spec) return api('PUT', path, spec);
  try { await api('DELETE', path); } catch (e) { if (e.status !== 404) throw e; }
  return null;
}

/** The page's 'expression' producer on the watched session (its sliders over the voice). */
let layerConnecting = null;
function expressionProducer() {
  if (!layerConnecting) {
    layerConnecting = (async () => {
      const p = state.layerProducer;
      if (!p || !p.open || p.session !== state.session) {
        if (p) p.close();
        state.layerProducer = new Producer(state.session, state.tokens[state.session].producer, setStatus);
        await state.layerProducer.connect({ input: 'fap', role: 'expression' });
      }
      return state.layerProducer;
    })().finally(() => { layerConnecting = null; });
  }
  return layerConnecting;
}

const AU_TO_DEG = 180 / Math.PI * 1e-5;
/** The sliders as layers: expression FAPs to the expression producer, head and look as layers. */
async function slidersAsLayers(moved) {
  const v = (f) => sliderValues[f] || 0;
  if (moved === '48' || moved === '49') {
    const yaw = v('49') * AU_TO_DEG, pitch = v('48') * AU_TO_DEG;
    await setLayer('head', yaw || pitch ? { kind: 'head', pose: { yaw, pitch } } : null);
  } else if (moved === '23,24') {
    const yaw = v('23') * 1e-5;  // radians
    await setLayer('gaze', yaw ? { kind: 'gaze', target: { direction: [Math.sin(yaw), 0, Math.cos(yaw)] } } : null);
  } else {
    const faps = {};
    for (const [k, x] of Object.entries(sliderValues)) if (!['23', '24', '48', '49'].includes(k)) faps[k] = x;
    (await expressionProducer()).sendFaps(faps);
  }
}

let idleOn = false;
async function toggleIdle() {
  idleOn = !idleOn;
  $('idle').textContent = `Idle: ${idleOn ? 'on' : 'off'}`;
  $('idle').setAttribute('aria-pressed', String(idleOn));
  try {
    await setLayer('idle', idleOn ? { kind: 'idle', seed: 1 } : null);
    setInfo('layer-info', idleOn ? 'idle on: blinks, glances, sway and breathing mixed over the face' : 'idle off');
  } catch (e) { setStatus(e.message, 'error'); }
}

// ---- rendering ----------------------------------------------------------------------------------
// WebGL context attributes from the query string, for comparisons: ?alpha=true&desynchronized=true
const contextAttributes = {};
for (const [k, v] of new URLSearchParams(location.search)) {
  if (['alpha', 'desynchronized', 'antialias', 'depth', 'stencil'].includes(k)) contextAttributes[k] = v === 'true';
}
const renderer = new FaceRenderer($('view'), contextAttributes);
const viewer = new Viewer(renderer, { onStatus: setStatus });
// Counters for the stats overlay and benchmarks: animation frames, canvas draws, and draws that
// showed a new vertex frame (a draw is one presented canvas update: nothing is drawn off-frame).
const counters = { rafs: 0, draws: 0, newFrameDraws: 0 };
let dirty = true;
function frameLoop() {
  counters.rafs++;
  const fresh = viewer.flush();
  if (fresh) dirty = true;
  if (dirty && renderer.mesh) {
    renderer.draw();
    dirty = false;
    counters.draws++;
    if (fresh) counters.newFrameDraws++;
    const now = performance.now();
    state.drawTimes.push(now);
    while (state.drawTimes.length && now - state.drawTimes[0] > 2000) state.drawTimes.shift();
  }
  requestAnimationFrame(frameLoop);
}
requestAnimationFrame(frameLoop);

// Adaptive quality when frames arrive faster than the browser draws them (software GL), one step a
// second, each kept for the session: light per vertex instead of per pixel, then draw the coarse
// level of detail (about half the triangles; eyes and teeth kept whole), then render fewer pixels
// (down to half resolution); when it keeps up again, go back towards full resolution.
let adapt = true;
const qualityText = () => `${Math.round(100 * renderer.scale)} %${renderer.shading === 'vertex' ? ' · vertex lit' : ''}`
  + `${renderer.lod ? ' · coarse' : ''}${adapt ? '' : ' (fixed)'}`;
setInterval(() => {
  if (!adapt) return;
  const s = viewer.summary(), drawFps = state.drawTimes.length / 2;
  if (s.fps > 5 && drawFps < 0.8 * s.fps) {
    if (renderer.shading === 'pixel') renderer.shading = 'vertex';
    else if (!renderer.lod) renderer.lod = 1;
    else if (renderer.scale > 0.5) renderer.scale = Math.max(0.5, renderer.scale * 0.85);
  } else if (drawFps >= 0.95 * s.fps && renderer.scale < 1) renderer.scale = Math.min(1, renderer.scale * 1.1);
  $('st-scale').textContent = qualityText();
}, 1000);

/**
 * Fix the render quality and stop adapting: scale (drawing-buffer pixels per CSS pixel), shading
 * ('pixel' | 'vertex'), lod (0: every triangle, 1: the coarse level).
 */
function setQuality({ scale, shading, lod } = {}) {
  adapt = false;
  if (scale !== undefined && scale !== null) renderer.scale = scale;
  if (shading) renderer.shading = shading;
  if (lod !== undefined && lod !== null) renderer.lod = lod;
  $('st-scale').textContent = qualityText();
}

setInterval(() => {
  const s = viewer.summary();
  const ms = (x) => (Number.isFinite(x) ? `${x.toFixed(x < 10 ? 2 : 0)} ms` : '–');
  $('st-fps').textContent = s.fps.toFixed(1);
  $('st-lat').textContent = `${ms(s.latencyP50)} / ${ms(s.latencyP95)}`;
  $('st-bytes').textContent = s.bytes ? `${(s.bytes / 1024).toFixed(1)} KiB` + (s.bitsPerSecond > 0 ? ` · ${(s.bitsPerSecond / 1e6).toFixed(2)} Mbit/s` : '') : '–';
  $('st-drop').textContent = String(s.dropped);
  $('st-decode').textContent = ms(s.decodeMs);
  $('st-draw').textContent = (state.drawTimes.length / 2).toFixed(1);
  window.facecastStats = { ...s, drawFps: state.drawTimes.length / 2 };
}, 500);

// ---- controls -----------------------------------------------------------------------------------
renderer.camera.attach(renderer.canvas, () => { dirty = true; });
new ResizeObserver(() => { dirty = true; }).observe(renderer.canvas);

$('refresh').onclick = refreshSessions;
$('watch').onclick = () => { const id = $('session-list').value; if (id) watch(id).catch((e) => setStatus(e.message, 'error')); };
$('encoding').onchange = () => { if (state.session) watch(state.session); };
$('demo').onclick = async () => {
  try {
    const s = await newSession('fap');
    await api('POST', `/v1/sessions/${s.id}/demo`);
    await watch(s.id);
    refreshSessions();
  } catch (e) { setStatus(e.message, 'error'); }
};

const sliderValues = {};
for (const [label, values] of [[EXPRESSIONS, 'expression'], [VISEMES, 'viseme']]) {
  const box = $(values === 'expression' ? 'expressions' : 'visemes');
  for (const item of label) {
    const b = document.createElement('button');
    b.textContent = item.name;
    b.title = item.title || item.name;
    b.onclick = async () => {
      try {
        if (layered()) {
          if (values === 'viseme') { setInfo('layer-info', 'the voice drives the mouth; visemes are its own'); return; }
          await setLayer('expression', { kind: 'expression', expression: item.name, amount: 1 });
          setInfo('layer-info', `${item.name} mixed over the voice`);
          return;
        }
        const p = await producer();
        p.sendFaps({ ...sliderValues }, values === 'viseme' ? [item.id, 0, 63] : null,
                   values === 'expression' ? [item.id, 63, 0, 0] : null);
      } catch (e) { setStatus(e.message, 'error'); }
    };
    box.appendChild(b);
  }
}
for (const s of SLIDERS) {
  const row = document.createElement('label');
  row.className = 'slider';
  row.innerHTML = `<span>${s.name}</span><input type="range" min="${s.min}" max="${s.max}" value="0" step="1" data-fap="${s.fap}"><output>0</output>`;
  const input = row.querySelector('input'), out = row.querySelector('output');
  input.oninput = async () => {
    out.textContent = input.value;
    for (const f of s.fap.split(',')) sliderValues[f] = Number(input.value);
    try {
      if (layered()) await slidersAsLayers(s.fap);
      else (await producer()).sendFaps({ ...sliderValues });
    } catch (e) { setStatus(e.message, 'error'); }
  };
  $('sliders').appendChild(row);
}
$('neutral').onclick = async () => {
  for (const k of Object.keys(sliderValues)) sliderValues[k] = 0;
  for (const i of document.querySelectorAll('#sliders input')) { i.value = 0; i.nextElementSibling.textContent = '0'; }
  try {
    if (layered()) {
      for (const name of ['expression', 'head', 'gaze']) await setLayer(name, null);
      if (state.layerProducer && state.layerProducer.open) state.layerProducer.sendFaps({ ...sliderValues });
      return;
    }
    (await producer()).sendFaps({ ...sliderValues }, [0, 0, 63], [0, 0, 0, 0]);
  } catch (e) { setStatus(e.message, 'error'); }
};
$('idle').onclick = toggleIdle;

const MARKERS = /\.(c3d|trc|csv)$/i;
$('file').onchange = () => {
  const file = $('file').files[0];
  $('layout-row').hidden = !(file && MARKERS.test(file.name));
};

/**
 * POST the upload to /play. The page's own producer has just been closed: until the server has seen
 * it go, /play answers 409, so that answer is retried for a few seconds.
 */
async function postPlay(sessionId, form) {
  for (let attempt = 0; ; attempt++) {
    try {
      return await api('POST', `/v1/sessions/${sessionId}/play${producerQuery(sessionId)}`, form, { form: true });
    } catch (e) {
      if (e.status !== 409 || attempt >= 8) throw e;
      await sleep(Math.min(1000, 100 * 2 ** attempt));
    }
  }
}

$('play').onclick = async () => {
  const file = $('file').files[0];
  if (!file) { setStatus('choose a .fap, audio or marker file first', 'warn'); return; }
  const layout = $('layout').files[0];
  if (MARKERS.test(file.name) && !layout) {
    setStatus(`${file.name} is a marker take: choose its marker layout (.json) too`, 'warn');
    $('layout-row').hidden = false;
    return;
  }
  try {
    await releaseProducer();  // Play takes over from the page's buttons, sliders and microphone
    if (!state.session) { const s = await newSession('fap'); await watch(s.id); }
    const form = new FormData();
    form.append('file', file, file.name);
    if (layout && MARKERS.test(file.name)) form.append('layout', layout, layout.name);
    const isAudio = /\.(wav|flac|ogg)$/i.test(file.name);
    const audio = $('audio');
    if (isAudio) { audio.src = URL.createObjectURL(file); audio.load(); }
    const res = await postPlay(state.session, form);
    setInfo('play-info', `playing ${file.name}: ${res.frames} frames at ${res.fps} fps (${res.seconds.toFixed(1)} s)`);
    if (isAudio) {
      // Start the sound when the server starts the motion: both run from the same start instant.
      const delay = Math.max(0, res.start_wall * 1000 - Date.now() + (viewer.summary().latencyP50 || 0));
      setTimeout(() => audio.play().catch(() => setStatus('the browser blocked sound playback; click the page', 'warn')), delay);
    }
  } catch (e) { setInfo('play-info', e.message); setStatus(e.message, 'error'); }
};

/** Stop the microphone; resolves once its producer connection is closed. */
async function stopMic() {
  const mic = state.mic;
  state.mic = null;
  $('mic').textContent = 'Start microphone lip-sync';
  if (!mic) return;
  const done = closed(mic.producer);
  mic.stop();
  await done;
}

$('mic').onclick = async () => {
  if (state.mic) { await stopMic(); return; }
  try {
    const { Microphone } = await import('./microphone.js');
    await releaseProducer();
    const s = await newSession('audio');
    await watch(s.id);
    const p = new Producer(s.id, state.tokens[s.id].producer, setStatus);
    state.mic = new Microphone(p, (info) => setInfo('mic-info', info));
    await state.mic.start();
    $('mic').textContent = 'Stop microphone';
  } catch (e) { setStatus(`microphone: ${e.message}`, 'error'); }
};

// ---- start: watch the session named in the URL, else the newest live one, else a demo -----------
(async () => {
  try {
    if (link.session && link.token) {
      state.tokens[link.session] = { viewer: link.token, producer: link.producer || null };
      await watch(link.session);
      return;
    }
    const faces = await api('GET', '/v1/faces');
    const list = faces.faces || faces;
    const first = list[0] && (list[0].name || list[0]);
    if (first) await viewer.loadFace(first);
    dirty = true;
    setStatus(`face ${first} loaded; start a demo, pick a live session, or drive the face`, 'ok');
    if ($('admin-key').value) refreshSessions();
  } catch (e) { setStatus(`cannot reach the server: ${e.message}`, 'error'); }
})();

window.addEventListener('hashchange', () => location.reload());  // a new #session=…&token=… link
window.facecast = { renderer, viewer, state, counters, setQuality, watch, newSession, api, setLayer };
