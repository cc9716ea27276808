// Pure mesh algorithms of the web viewer (no DOM, no WebGL): bounds, part colours, vertex normals,
// draw order and draw groups, the mouth's shell and scissor window, vertex-cache order, coarsening.
// Arrays are typed and flat: positions Float32Array 3V (or Int16Array 3V with a per-axis scale),
// triangles Uint32Array 3F, part ids Uint8Array V. Tested with Node's test runner (mesh.test.js).

/**
 * Axis-aligned bounds of positions (Float32Array 3V): {lo [3], hi [3], centre [3], size: the longest
 * side}; lo = [Infinity ...] and hi = [-Infinity ...] when there is no vertex.
 */
export function bounds(positions) {
  const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
  for (let i = 0; i < positions.length; i += 3) {
    for (let a = 0; a < 3; a++) { lo[a] = Math.min(lo[a], positions[i + a]); hi[a] = Math.max(hi[a], positions[i + a]); }
  }
  const centre = [0, 1, 2].map((a) => (lo[a] + hi[a]) / 2);
  const size = Math.max(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]);
  return { lo, hi, centre, size };
}

/** Per-vertex colours (Float32Array 3V): colors[part name] of each vertex's part, else fallback [3]. */
export function partColors(partIds, partNames, colors, fallback) {
  const V = partIds.length, rgb = new Float32Array(3 * V);
  for (let i = 0; i < V; i++) rgb.set(colors[partNames[partIds[i]]] || fallback, 3 * i);
  return rgb;
}

/**
 * Per-vertex colours (Float32Array 3V) averaged with their edge neighbours `passes` times: a part
 * border that zig-zags along the mesh (a lip's vermilion line across skewed rows) becomes a soft
 * line instead of stripes. Separate meshes share no edge, so eyes and teeth stay as they are.
 */
export function smoothColors(rgb, triangles, V, passes = 2) {
  let cur = rgb;
  for (let p = 0; p < passes; p++) {
    const sum = Float32Array.from(cur), n = new Float32Array(V).fill(1);
    for (let i = 0; i < triangles.length; i += 3) {
      for (let k = 0; k < 3; k++) {
        const a = triangles[i + k], b = triangles[i + (k + 1) % 3];
        for (let c = 0; c < 3; c++) { sum[3 * a + c] += cur[3 * b + c]; sum[3 * b + c] += cur[3 * a + c]; }
        n[a]++; n[b]++;
      }
    }
    for (let v = 0; v < V; v++) for (let c = 0; c < 3; c++) sum[3 * v + c] /= n[v];
    cur = sum;
  }
  return cur;
}

/** Parts drawn without back-face culling: open sheets that are seen from both sides. */
export const TWO_SIDED = /^(eyelashes|eye_extras|eye_socket)/;
/** Parts drawn last: hidden behind the lips most of the time, so the depth test rejects them early. */
const INTERIOR = /^(mouth_socket|teeth|gums|tongue)/;
/** Transparent parts (the cornea over an eyeball's iris; the tear film and eye-occlusion overlays): not drawn. */
export const TRANSPARENT = /^(cornea|eye_extras)/;

/**
 * Triangle order for drawing: one-sided outer parts (skin, eyes) first, then the mouth's interior,
 * then the two-sided sheets; transparent parts go last and are in no group (not drawn). Returns the
 * reordered indices (Uint32Array 3F) and the draw groups [{first, count, cull, interior?}] in index
 * units (one draw call each; empty groups left out).
 */
export function drawOrder(triangles, partIds, partNames) {
  const F = triangles.length / 3, rank = new Uint8Array(F);
  const partRank = partNames.map((n) => (TRANSPARENT.test(n) ? 3 : TWO_SIDED.test(n) ? 2 : INTERIOR.test(n) ? 1 : 0));
  const counts = [0, 0, 0, 0];
  for (let f = 0; f < F; f++) { const r = partRank[partIds[triangles[3 * f]]] ?? 0; rank[f] = r; counts[r]++; }
  const order = new Uint32Array(3 * F), next = [0, counts[0], counts[0] + counts[1], counts[0] + counts[1] + counts[2]];
  for (let f = 0; f < F; f++) {
    const o = 3 * next[rank[f]]++;
    order[o] = triangles[3 * f]; order[o + 1] = triangles[3 * f + 1]; order[o + 2] = triangles[3 * f + 2];
  }
  const groups = [{ first: 0, count: 3 * counts[0], cull: true },
                  { first: 3 * counts[0], count: 3 * counts[1], cull: true, interior: true },
                  { first: 3 * (counts[0] + counts[1]), count: 3 * counts[2], cull: false }];
  return { order, groups: groups.filter((g) => g.count > 0) };
}

/** Parts of the head's shell: the surface that closes the head around the mouth's pocket. */
const SHELL = /^(skin|lip|mouth_socket|eye_socket)/;

/**
 * Where the mouth's interior can be seen from: {rim: vertex ids of the mouth socket's open edge (the
 * lips' inner rim), holes: [vertex ids of each other hole of the shell, in order around it], interior:
 * vertex ids of the interior parts, tongue: those of the tongue}, or null when the mesh is not a shell sealed onto a mouth socket
 * (then the interior is always drawn whole). A triangle's part is its first corner's (as in drawOrder).
 */
export function mouthShell(triangles, partIds, partNames, V) {
  const socket = partNames.indexOf('mouth_socket');
  if (socket < 0) return null;
  const shellPart = partNames.map((n) => SHELL.test(n)), interiorPart = partNames.map((n) => INTERIOR.test(n));
  // boundary edges (used by one triangle) of the shell and of the socket alone
  const edges = (keep) => {
    const count = new Map();
    for (let i = 0; i < triangles.length; i += 3) {
      if (!keep(partIds[triangles[i]])) continue;
      for (let k = 0; k < 3; k++) {
        const a = triangles[i + k], b = triangles[i + (k + 1) % 3], key = a < b ? a * V + b : b * V + a;
        count.set(key, (count.get(key) || 0) + 1);
      }
    }
    const out = [];
    for (const [key, n] of count) if (n === 1) out.push([Math.floor(key / V), key % V]);
    return out;
  };
  const rimEdges = edges((p) => p === socket);
  if (!rimEdges.length) return null;
  const shellEdges = edges((p) => shellPart[p]);
  const shellKeys = new Set(shellEdges.map(([a, b]) => a * V + b));
  if (rimEdges.some(([a, b]) => shellKeys.has(a * V + b))) return null;  // the socket is not sealed onto the shell
  // the shell's holes as loops of vertices
  const next = new Map();
  for (const [a, b] of shellEdges) {
    next.set(a, [...(next.get(a) || []), b]); next.set(b, [...(next.get(b) || []), a]);
  }
  if ([...next.values()].some((l) => l.length !== 2)) return null;  // not simple loops
  const seen = new Set(), holes = [];
  for (const s of next.keys()) {
    if (seen.has(s)) continue;
    const loop = [s]; seen.add(s);
    let prev = -1, cur = s;
    for (;;) {
      const [u, w] = next.get(cur), nxt = u !== prev ? u : w;
      if (seen.has(nxt)) break;
      loop.push(nxt); seen.add(nxt); prev = cur; cur = nxt;
    }
    holes.push(Uint32Array.from(loop));
  }
  const rim = Uint32Array.from(new Set(rimEdges.flat()));
  const tongue = [];
  for (let v = 0; v < V; v++) if (/^tongue/.test(partNames[partIds[v]])) tongue.push(v);
  const inner = new Set();
  for (let i = 0; i < triangles.length; i += 3) {
    if (interiorPart[partIds[triangles[i]]]) for (let k = 0; k < 3; k++) inner.add(triangles[i + k]);
  }
  return { rim, holes, interior: Uint32Array.from(inner), tongue: Uint32Array.from(tongue) };
}

/**
 * Triangles reordered for the vertex cache of a software GL's vertex stage. Mesa's draw module (llvmpipe)
 * cuts an indexed draw into segments of `segment` triangles (341: 1023 indices), and within a segment
 * shades a vertex again whenever a direct-mapped cache of `slots` entries (index mod 256) misses. This
 * greedy pass fills each segment with a compact patch: it keeps a model of that cache and always takes
 * the open triangle whose corners hit it most (then the oldest seen), starting a patch where the last
 * one left off. Same triangles, same winding, only their order changes. triangles: Uint32Array 3F (one
 * draw call: segments start at its first triangle). Returns a new Uint32Array 3F.
 */
export function cacheOrder(triangles, V, segment = 341, slots = 256) {
  const F = triangles.length / 3;
  if (F <= segment) return Uint32Array.from(triangles);
  // vertex -> triangles (CSR)
  const start = new Uint32Array(V + 1);
  for (let i = 0; i < triangles.length; i++) start[triangles[i] + 1]++;
  for (let v = 0; v < V; v++) start[v + 1] += start[v];
  const fill = start.slice(0, V), vt = new Uint32Array(triangles.length);
  for (let i = 0; i < triangles.length; i++) vt[fill[triangles[i]]++] = (i / 3) | 0;
  const done = new Uint8Array(F), cache = new Int32Array(slots).fill(-1);
  const hits = (f) => {
    let h = 0;
    for (let k = 0; k < 3; k++) { const v = triangles[3 * f + k]; if (cache[v % slots] === v) h++; }
    return h;
  };
  // Candidates by the number of their corners in the cache (1..3), each a queue taken oldest first
  // (a round patch); entries go stale and are re-checked when taken.
  const buckets = [null, [], [], []], heads = [0, 0, 0, 0];
  const out = new Uint32Array(triangles.length);
  let n = 0, cursor = 0, inSegment = 0;
  const emit = (f) => {
    done[f] = 1;
    for (let k = 0; k < 3; k++) {
      const v = triangles[3 * f + k];
      out[3 * n + k] = v;
      cache[v % slots] = v;
    }
    n++;
    for (let k = 0; k < 3; k++) {
      const v = triangles[3 * f + k];
      for (let j = start[v]; j < start[v + 1]; j++) {
        const g = vt[j];
        if (!done[g]) { const h = hits(g); if (h) buckets[h].push(g); }
      }
    }
  };
  let last = -1;  // a triangle of the previous patch: the next one starts next to it
  while (n < F) {
    if (inSegment === segment) {  // a new segment: Mesa starts with an empty cache
      inSegment = 0; cache.fill(-1);
      for (const b of buckets) if (b) b.length = 0;
      heads.fill(0);
      // seed next to where the last patch ended, else the first triangle left
      let seed = -1;
      if (last >= 0) {
        for (let k = 0; k < 3 && seed < 0; k++) {
          const v = triangles[3 * last + k];
          for (let j = start[v]; j < start[v + 1]; j++) if (!done[vt[j]]) { seed = vt[j]; break; }
        }
      }
      if (seed >= 0) { emit(seed); inSegment++; last = seed; continue; }
    }
    let f = -1;
    for (let h = 3; h >= 1 && f < 0; h--) {
      const b = buckets[h];
      while (heads[h] < b.length) {
        const g = b[heads[h]++];
        if (done[g]) continue;
        const real = hits(g);
        if (real === h) { f = g; break; }
        if (real > 0) buckets[real].push(g);
      }
    }
    if (f < 0) {  // nothing touches the cache: the first triangle not yet taken
      while (done[cursor]) cursor++;
      f = cursor;
    }
    emit(f); inSegment++; last = f;
  }
  return out;
}

/**
 * Vertex shader runs of a draw of `triangles` in Mesa's draw module (segments of `segment` triangles,
 * a direct-mapped cache of `slots` vertices per segment): the count cacheOrder lowers.
 */
export function vertexRuns(triangles, segment = 341, slots = 256) {
  const cache = new Int32Array(slots);
  let runs = 0;
  for (let i = 0; i < triangles.length; i++) {
    if (i % (3 * segment) === 0) cache.fill(-1);
    const v = triangles[i];
    if (cache[v % slots] !== v) { cache[v % slots] = v; runs++; }
  }
  return runs;
}

/** Whether the index buffers of a mesh of V vertices hold 16-bit indices (else 32-bit). */
export function shortIndices(V) { return V <= 65535; }

/** Small parts whose shape matters more than their triangle count: never coarsened. */
export const FINE = /^(teeth|eye_l|eye_r|iris|eyelashes|eye_extras)/;

/**
 * A coarser triangle list over the same vertices (vertex clustering along the mesh): each vertex not
 * yet taken becomes a representative and takes its untaken edge neighbours of the same part; every
 * triangle is mapped to representatives and dropped when two corners meet. Edges only merge
 * vertices that share an edge, so openings (mouth, eyes) never weld shut and shared edges stay
 * shared (no cracks). The vertices keep streaming and their normals stay those of the full mesh.
 * A vertex on a border between parts (the rims of the eyes and lips, where the normals turn into the
 * sockets) neither takes nor is taken: merged, it spread a dark rim over the big triangles around. The
 * apex of a wide fan (more than `fan` triangles, a grid's pole) is never taken: merged into one of its
 * neighbours, the whole fan swung over to that one and dented the crown.
 * triangles: Uint32Array 3F; partIds: Uint8Array V; keep[part id] true: that part is left as it is.
 * Returns Uint32Array 3F' (F' <= F).
 */
export function coarsen(triangles, V, partIds, keep = null, fan = 12) {
  const start = new Uint32Array(V + 1);
  for (let i = 0; i < triangles.length; i++) start[triangles[i] + 1] += 2;
  for (let v = 0; v < V; v++) start[v + 1] += start[v];
  const fill = start.slice(0, V), adj = new Uint32Array(start[V]);
  for (let i = 0; i < triangles.length; i += 3) {
    const a = triangles[i], b = triangles[i + 1], c = triangles[i + 2];
    adj[fill[a]++] = b; adj[fill[a]++] = c; adj[fill[b]++] = c; adj[fill[b]++] = a; adj[fill[c]++] = a; adj[fill[c]++] = b;
  }
  // 1: never taken (a wide fan's apex), 2: neither takes nor is taken (on a border between parts)
  const stays = new Uint8Array(V);
  for (let v = 0; v < V; v++) {
    if (start[v + 1] - start[v] > 2 * fan) stays[v] = 1;
    for (let k = start[v]; k < start[v + 1]; k++) if (partIds[adj[k]] !== partIds[v]) { stays[v] = 2; break; }
  }
  const rep = new Int32Array(V).fill(-1);
  for (let v = 0; v < V; v++) {
    if (rep[v] >= 0) continue;
    rep[v] = v;
    if ((keep && keep[partIds[v]]) || stays[v] === 2) continue;
    for (let k = start[v]; k < start[v + 1]; k++) {
      const u = adj[k];
      if (rep[u] < 0 && !stays[u] && partIds[u] === partIds[v]) rep[u] = v;
    }
  }
  const out = new Uint32Array(triangles.length);
  let n = 0;
  for (let i = 0; i < triangles.length; i += 3) {
    const a = rep[triangles[i]], b = rep[triangles[i + 1]], c = rep[triangles[i + 2]];
    if (a !== b && b !== c && a !== c) { out[n++] = a; out[n++] = b; out[n++] = c; }
  }
  return out.slice(0, n);
}

/**
 * Angle-weighted vertex normals: each triangle's unit normal weighted by its angle at the vertex, with
 * typed arrays (no allocation per frame). Unlike area weights they do not depend on how the surface
 * around a vertex is cut into triangles: on the default head a fan of long thin triangles (the skin
 * grid's pole at the crown) and a row of slivers (next to a grid vertex moved onto a feature point)
 * tilted area-weighted normals towards their big neighbours, which showed under per-pixel lighting as
 * a disc and a dark seam on the crown and streaks down the skull. The angles are the rest pose's,
 * worked out once (a frame moves them little: within 0.6 degrees of its own angles' normals for 99 %
 * of the head's vertices in joy). A frame still normalises each triangle's normal and weights it three
 * times: 1.5-1.9x the area-weighted cost under Node (`bench/web_normals.py`, about 1 ms on the 25k head).
 */
export class VertexNormals {
  /** triangles: Uint32Array 3F; V vertices; rest: Float32Array 3V, the pose whose corner angles weight every frame. */
  constructor(triangles, V, rest) {
    this.tri = triangles; this.V = V; this.out = new Float32Array(3 * V);
    this.angles = new Float32Array(triangles.length);  // radians, per corner
    const t = triangles, p = rest;
    for (let i = 0; i < t.length; i += 3) {
      const a = 3 * t[i], b = 3 * t[i + 1], c = 3 * t[i + 2];
      const ux = p[b] - p[a], uy = p[b + 1] - p[a + 1], uz = p[b + 2] - p[a + 2];
      const vx = p[c] - p[a], vy = p[c + 1] - p[a + 1], vz = p[c + 2] - p[a + 2];
      const len = Math.hypot(uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx);  // |u x v| at every corner
      const uu = ux * ux + uy * uy + uz * uz, uv = ux * vx + uy * vy + uz * vz, vv = vx * vx + vy * vy + vz * vz;
      this.angles[i] = Math.atan2(len, uv); this.angles[i + 1] = Math.atan2(len, uu - uv); this.angles[i + 2] = Math.atan2(len, vv - uv);
    }
  }
  /** positions: Float32Array(3V) or Int16Array(3V) with per-axis scale (then normals of the scaled mesh). */
  compute(p, scale) {
    const t = this.tri, n = this.out, w = this.angles, sx = scale ? scale[0] : 1, sy = scale ? scale[1] : 1, sz = scale ? scale[2] : 1;
    n.fill(0);
    for (let i = 0; i < t.length; i += 3) {
      const a = 3 * t[i], b = 3 * t[i + 1], c = 3 * t[i + 2];
      const ux = (p[b] - p[a]) * sx, uy = (p[b + 1] - p[a + 1]) * sy, uz = (p[b + 2] - p[a + 2]) * sz;
      const vx = (p[c] - p[a]) * sx, vy = (p[c + 1] - p[a + 1]) * sy, vz = (p[c + 2] - p[a + 2]) * sz;
      const nx = uy * vz - uz * vy, ny = uz * vx - ux * vz, nz = ux * vy - uy * vx;
      const len2 = nx * nx + ny * ny + nz * nz;
      if (len2 === 0) continue;  // degenerate in this frame: no direction
      const k = 1 / Math.sqrt(len2), wa = w[i] * k, wb = w[i + 1] * k, wc = w[i + 2] * k;
      n[a] += nx * wa; n[a + 1] += ny * wa; n[a + 2] += nz * wa;
      n[b] += nx * wb; n[b + 1] += ny * wb; n[b + 2] += nz * wb;
      n[c] += nx * wc; n[c + 1] += ny * wc; n[c + 2] += nz * wc;
    }
    return n;  // normalised in the fragment shader
  }
}

/**
 * The drawing-buffer rectangle [x0, y0, x1, y1) (pixels, y up) outside which nothing of the mouth's
 * interior can be seen, or null when that cannot be shown (then it is drawn whole); see
 * FaceRenderer.mouthWindow. ms: mouthShell's result; at(i, a): coordinate a of vertex i this frame
 * (world units); eye [3]: the camera's position; M: the column-major view-projection (16); W, H: the
 * drawing buffer's size in pixels.
 */
export function mouthWindow(ms, at, eye, M, W, H) {
  for (const hole of ms.holes) {
    // centroid and Newell normal of the hole's rim
    const cen = [0, 0, 0], n = [0, 0, 0];
    for (let j = 0; j < hole.length; j++) for (let a = 0; a < 3; a++) cen[a] += at(hole[j], a) / hole.length;
    for (let j = 0; j < hole.length; j++) {
      const p = hole[j], q = hole[(j + 1) % hole.length];
      for (let a = 0; a < 3; a++) {
        const b = (a + 1) % 3, d = (a + 2) % 3;
        n[a] += (at(p, b) - at(q, b)) * (at(p, d) + at(q, d));
      }
    }
    const dist = (x, y, z) => (x - cen[0]) * n[0] + (y - cen[1]) * n[1] + (z - cen[2]) * n[2];
    let lo = Infinity, hi = -Infinity;
    for (const v of hole) { const d = dist(at(v, 0), at(v, 1), at(v, 2)); lo = Math.min(lo, d); hi = Math.max(hi, d); }
    let ilo = Infinity, ihi = -Infinity;
    for (const v of ms.interior) { const d = dist(at(v, 0), at(v, 1), at(v, 2)); ilo = Math.min(ilo, d); ihi = Math.max(ihi, d); }
    const e = dist(eye[0], eye[1], eye[2]);
    const above = ilo > hi && e > hi, below = ihi < lo && e < lo;
    if (!above && !below) return null;
  }
  let x0 = Infinity, y0 = Infinity, x1 = -Infinity, y1 = -Infinity, front = -Infinity;
  const add = (v) => {
    const x = at(v, 0), y = at(v, 1), z = at(v, 2);
    const w = M[3] * x + M[7] * y + M[11] * z + M[15];
    if (!(w > 1e-6)) return false;  // behind the eye
    const sx = (M[0] * x + M[4] * y + M[8] * z + M[12]) / w, sy = (M[1] * x + M[5] * y + M[9] * z + M[13]) / w;
    x0 = Math.min(x0, sx); x1 = Math.max(x1, sx); y0 = Math.min(y0, sy); y1 = Math.max(y1, sy);
    return true;
  };
  let back = Infinity;
  for (const v of ms.rim) {
    if (!add(v)) return null;
    back = Math.min(back, at(v, 2)); front = Math.max(front, at(v, 2));
  }
  // Whatever of the interior comes forward of the rim's deepest point less the rim's depth (z points
  // out of the face) may have left the pocket (a thrust tongue, teeth through a lip): the window takes
  // it in too.
  const reach = back - (front - back);
  for (const v of ms.interior) if (at(v, 2) >= reach && !add(v)) return null;
  // The tongue bends and thrusts out of the mouth (through the skin, at the limits): all of it counts.
  for (const v of ms.tongue) if (!add(v)) return null;
  // to pixels, rounded outwards with a pixel to spare, clamped to the drawing buffer
  const pad = 1;
  return [Math.max(0, Math.floor((x0 + 1) / 2 * W) - pad), Math.max(0, Math.floor((y0 + 1) / 2 * H) - pad),
          Math.min(W, Math.ceil((x1 + 1) / 2 * W) + pad), Math.min(H, Math.ceil((y1 + 1) / 2 * H) + pad)];
}
