// Node's test runner over client/web/js/mesh.js (run: node --test tests/js/; tests/test_web_mesh_js.py
// runs it from pytest). Small meshes are built here; no browser, no WebGL.
import assert from 'node:assert/strict';
import test from 'node:test';

import {
  VertexNormals, bounds, cacheOrder, coarsen, drawOrder, mouthShell, mouthWindow, partColors, shortIndices,
  smoothColors, vertexRuns,
} from '../../client/web/js/mesh.js';

const close = (a, b, eps = 1e-6) => Math.abs(a - b) <= eps;

/** A closed box (8 vertices, 12 triangles, outward winding) scaled by s and moved by t. */
function box(s = [1, 1, 1], t = [0, 0, 0]) {
  const p = new Float32Array(24);
  for (let v = 0; v < 8; v++) for (let a = 0; a < 3; a++) p[3 * v + a] = ((v >> a) & 1) * s[a] + t[a];
  const tris = Uint32Array.from([0, 2, 1, 1, 2, 3, 4, 5, 6, 5, 7, 6, 0, 1, 4, 1, 5, 4,
                                 2, 6, 3, 3, 6, 7, 0, 4, 2, 2, 4, 6, 1, 3, 5, 3, 7, 5]);
  return { p, tris, V: 8 };
}

test('bounds: corners, centre and the longest side', () => {
  const { p } = box([2, 4, 1], [-1, 3, 10]);
  const b = bounds(p);
  assert.deepEqual(b.lo, [-1, 3, 10]);
  assert.deepEqual(b.hi, [1, 7, 11]);
  assert.deepEqual(b.centre, [0, 5, 10.5]);
  assert.equal(b.size, 4);
  const empty = bounds(new Float32Array(0));
  assert.deepEqual(empty.lo, [Infinity, Infinity, Infinity]);
});

test('part colours: by part name, the fallback for parts without one', () => {
  const rgb = partColors(Uint8Array.from([0, 1, 2]), ['skin', 'tongue', 'unnamed'],
                         { skin: [1, 0, 0], tongue: [0, 1, 0] }, [0, 0, 1]);
  assert.deepEqual(Array.from(rgb), [1, 0, 0, 0, 1, 0, 0, 0, 1]);
});

test('vertex normals point out of a closed box, and int16 frames give the same directions', () => {
  const { p, tris, V } = box([2, 3, 4], [5, -1, 0]);
  const n = new VertexNormals(tris, V, p).compute(p, null);
  for (let v = 0; v < V; v++) {
    const c = [6, 0.5, 2];  // the box's centre
    const out = [0, 1, 2].map((a) => p[3 * v + a] - c[a]);
    const d = out[0] * n[3 * v] + out[1] * n[3 * v + 1] + out[2] * n[3 * v + 2];
    assert.ok(d > 0, `normal of vertex ${v} points inwards`);
  }
  // the same box as int16 with a per-axis scale: normals of the scaled mesh, same directions
  const scale = [0.5, 0.25, 2], q = new Int16Array(24);
  for (let i = 0; i < 24; i++) q[i] = Math.round((p[i] - [5, -1, 0][i % 3]) / scale[i % 3]);
  const nq = Float32Array.from(new VertexNormals(tris, V, p).compute(q, scale));
  for (let v = 0; v < V; v++) {
    const a = Array.from(n.subarray(3 * v, 3 * v + 3)), b = Array.from(nq.subarray(3 * v, 3 * v + 3));
    const la = Math.hypot(...a), lb = Math.hypot(...b);
    for (let k = 0; k < 3; k++) assert.ok(close(a[k] / la, b[k] / lb, 1e-5), `vertex ${v}: ${a} vs ${b}`);
  }
});

/**
 * The corner of the unit cube at the origin where three faces meet: the faces x = 0 and y = 0 one
 * triangle each, the face z = 0 a fan of k triangles from the corner out to a quarter circle (outward
 * winding). Returns the unit normal at the corner.
 */
function cubeCornerNormal(k) {
  const p = [0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 1, 0], tris = [0, 1, 2, 0, 2, 3];
  let prev = 1;
  for (let i = 1; i <= k; i++) {
    const t = (Math.PI / 2) * (i / k);
    const q = i === k ? 3 : p.push(Math.cos(t), Math.sin(t), 0) / 3 - 1;
    tris.push(0, q, prev);
    prev = q;
  }
  const rest = Float32Array.from(p), n = new VertexNormals(Uint32Array.from(tris), p.length / 3, rest).compute(rest, null);
  const l = Math.hypot(n[0], n[1], n[2]);
  return [n[0] / l, n[1] / l, n[2] / l];
}

test('a vertex normal does not depend on how the faces around it are cut into triangles', () => {
  // Three faces meeting at right angles: the normal is the diagonal whether the face z = 0 is one
  // triangle or a fan of thin ones (area weights tilted it up to 10 degrees towards that face; the
  // skin grid's pole at the default head's crown is such a fan).
  const diagonal = -1 / Math.sqrt(3);
  for (const k of [1, 2, 8, 40]) {
    const n = cubeCornerNormal(k);
    const off = Math.acos(Math.min(1, (n[0] + n[1] + n[2]) * diagonal)) * 180 / Math.PI;
    assert.ok(off < 0.5, `a fan of ${k}: the corner's normal is ${off.toFixed(2)} degrees off the diagonal (${n})`);
  }
});

test('vertex normals reuse one output array and reset it each frame', () => {
  const { p, tris, V } = box();
  const vn = new VertexNormals(tris, V, p);
  const first = Float32Array.from(vn.compute(p, null));
  const again = vn.compute(p, null);
  assert.equal(again, vn.out);
  assert.deepEqual(Array.from(again), Array.from(first));
});

test('16-bit indices up to 65535 vertices', () => {
  assert.equal(shortIndices(65535), true);
  assert.equal(shortIndices(65536), false);
});

test('draw order keeps every triangle once with the two-sided sheets last', () => {
  const tris = new Uint32Array([0, 1, 2, 2, 3, 4, 4, 5, 6, 6, 7, 0, 8, 9, 10]);
  const partIds = new Uint8Array([0, 1, 2, 0, 1, 2, 0, 1, 3, 3, 3]);
  const names = ['skin', 'eyelashes', 'teeth_upper', 'cornea_l'];
  const { order, groups } = drawOrder(tris, partIds, names);
  const out = [];
  for (let i = 0; i < 15; i += 3) out.push(Array.from(order.subarray(i, i + 3)));
  assert.deepEqual([...out].sort(), [[0, 1, 2], [2, 3, 4], [4, 5, 6], [6, 7, 0], [8, 9, 10]].sort());
  // skin (0,1,2), (6,7,0) culled, then the interior teeth (2,3,4) culled in a draw of their own; the
  // eyelash sheet (4,5,6) next, unculled; the transparent cornea (8,9,10) last and in no draw group
  assert.deepEqual(out.slice(2), [[2, 3, 4], [4, 5, 6], [8, 9, 10]]);
  assert.deepEqual(groups, [{ first: 0, count: 6, cull: true }, { first: 6, count: 3, cull: true, interior: true },
                            { first: 9, count: 3, cull: false }]);
});

test('part colours blend across shared edges only', () => {
  // a strip of 6 vertices (0-5, red then blue from vertex 3) and a separate triangle (6-8, green)
  const tris = new Uint32Array([0, 1, 2, 1, 3, 2, 2, 3, 4, 3, 5, 4, 6, 7, 8]);
  const rgb = new Float32Array(27);
  for (let v = 0; v < 9; v++) rgb.set(v < 3 ? [1, 0, 0] : v < 6 ? [0, 0, 1] : [0, 1, 0], 3 * v);
  const c = smoothColors(rgb, tris, 9, 1);
  const at = (v, k) => c[3 * v + k];
  assert.ok(at(2, 2) > 0 && at(2, 2) < at(3, 2) && at(3, 2) < 1 && at(2, 0) > at(3, 0) && at(3, 0) > 0);
  for (let v = 0; v < 9; v++) assert.ok(close(at(v, 0) + at(v, 1) + at(v, 2), 1, 1e-6));  // colours stay colours
  assert.deepEqual(Array.from(c.subarray(18)), [0, 1, 0, 0, 1, 0, 0, 1, 0]);           // no edge: unchanged
});

test('coarsening keeps openings open and fine parts whole', () => {
  // Two 6x6-vertex grids side by side (part 0 and part 1), not joined: an opening between them.
  const tris = [], partIds = new Uint8Array(72);
  for (let p = 0; p < 2; p++) for (let y = 0; y < 5; y++) for (let x = 0; x < 5; x++) {
    const v = 36 * p + 6 * y + x;
    tris.push(v, v + 1, v + 7, v, v + 7, v + 6);
    if (p) partIds[v] = partIds[v + 1] = partIds[v + 6] = partIds[v + 7] = 1;
  }
  const split = (flat) => { const o = []; for (let i = 0; i < flat.length; i += 3) o.push(Array.from(flat.slice(i, i + 3))); return o; };
  const all = split(coarsen(Uint32Array.from(tris), 72, partIds));
  assert.ok(all.length > 0 && all.length < 60, `${all.length} of 100 triangles`);
  assert.ok(all.every((t) => new Set(t).size === 3), 'degenerate triangles left');
  assert.ok(!all.some((t) => t.some((v) => v < 36) && t.some((v) => v >= 36)), 'the two grids were welded together');
  const kept = split(coarsen(Uint32Array.from(tris), 72, partIds, [false, true]));
  assert.equal(kept.filter((t) => t.every((v) => v >= 36)).length, 50, 'the kept part lost triangles');
  assert.equal(kept.filter((t) => t.every((v) => v < 36)).length, all.filter((t) => t.every((v) => v < 36)).length);
});

test('coarsening keeps the vertices on a border between parts, and a wide fan on its apex', () => {
  // An 8x8-vertex grid, rows 0-3 part 0 and rows 4-7 part 1 (joined: rows 3 and 4 are the border).
  const tris = [], partIds = new Uint8Array(64);
  for (let v = 32; v < 64; v++) partIds[v] = 1;
  for (let y = 0; y < 7; y++) for (let x = 0; x < 7; x++) {
    const v = 8 * y + x;
    tris.push(v, v + 1, v + 9, v, v + 9, v + 8);
  }
  const grid = coarsen(Uint32Array.from(tris), 64, partIds);
  assert.ok(grid.length < tris.length, 'nothing coarsened');
  const used = new Set(grid);
  for (let v = 24; v < 40; v++) assert.ok(used.has(v), `border vertex ${v} was merged away`);
  // A fan of 24 triangles around its apex, the last vertex (the ring is visited first): the apex stays
  // the fan's centre instead of being pulled onto one ring vertex.
  const fan = [];
  for (let i = 0; i < 24; i++) fan.push(24, i, (i + 1) % 24);
  const cone = coarsen(Uint32Array.from(fan), 25, new Uint8Array(25));
  assert.ok(cone.length < fan.length, 'nothing coarsened');
  for (let i = 0; i < cone.length; i += 3) assert.ok(Array.from(cone.slice(i, i + 3)).includes(24), 'a triangle lost the apex');
});

test('vertex-cache order keeps every triangle and shades fewer vertices', () => {
  // a 40x40-quad grid, its triangles shuffled (a fixed linear congruential sequence)
  const n = 40, V = (n + 1) * (n + 1), tris = [];
  for (let y = 0; y < n; y++) for (let x = 0; x < n; x++) {
    const v = y * (n + 1) + x;
    tris.push([v, v + 1, v + n + 2], [v, v + n + 2, v + n + 1]);
  }
  let seed = 12345;
  for (let i = tris.length - 1; i > 0; i--) {
    seed = (seed * 1103515245 + 12345) % 2147483648;
    const j = seed % (i + 1); [tris[i], tris[j]] = [tris[j], tris[i]];
  }
  const shuffled = Uint32Array.from(tris.flat()), ordered = cacheOrder(shuffled, V);
  // each triangle rotated to start at its smallest index: same winding, same triangle
  const canon = (flat) => {
    const out = [];
    for (let i = 0; i < flat.length; i += 3) {
      const t = Array.from(flat.slice(i, i + 3)), k = t.indexOf(Math.min(...t));
      out.push([...t.slice(k), ...t.slice(0, k)].join(','));
    }
    return out.sort();
  };
  assert.deepEqual(canon(ordered), canon(shuffled));
  const before = vertexRuns(shuffled), after = vertexRuns(ordered);
  assert.ok(after < 0.5 * before, `${after} vs ${before}`);
  assert.ok(after < 1.3 * V, `${after} vertex shader runs for ${V} vertices`);
  // a draw of at most one segment is left as it is
  const small = Uint32Array.from([0, 1, 2, 2, 1, 3]);
  assert.deepEqual(Array.from(cacheOrder(small, 4)), Array.from(small));
});

/**
 * A shell with a mouth: a skin sheet of 4x4 vertices whose centre quad (z = 0) is open and whose border
 * ring is bent back to z = -3 (the neck's hole, behind everything), a mouth-socket pocket sealed onto
 * the opening (a box behind it, z down to -1) and a tongue triangle inside.
 */
function mouthMesh() {
  const p = [], tris = [], part = [];
  for (let y = 0; y < 4; y++) for (let x = 0; x < 4; x++) {  // the border ring bent back, behind the mouth
    p.push(x - 1.5, y - 1.5, x % 3 && y % 3 ? 0 : -3); part.push(0);
  }
  for (let y = 0; y < 3; y++) for (let x = 0; x < 3; x++) {
    if (x === 1 && y === 1) continue;  // the mouth opening
    const v = 4 * y + x;
    tris.push(v, v + 1, v + 5, v, v + 5, v + 4);
  }
  const rim = [5, 6, 10, 9];  // the opening's corners, in order around it
  const back = rim.map((v) => { p.push(p[3 * v], p[3 * v + 1], -1); part.push(1); return p.length / 3 - 1; });
  for (let k = 0; k < 4; k++) {  // the pocket's sides and back (part 1: mouth_socket)
    const a = rim[k], b = rim[(k + 1) % 4], c = back[(k + 1) % 4], d = back[k];
    tris.push(c, b, a, d, c, a);  // a triangle's part is its first corner's
  }
  tris.push(back[0], back[1], back[2], back[0], back[2], back[3]);
  const t0 = p.length / 3;
  p.push(-0.2, -0.2, -0.8, 0.2, -0.2, -0.8, 0, 0.2, -0.8); part.push(2, 2, 2);
  tris.push(t0, t0 + 1, t0 + 2);
  return { p: Float32Array.from(p), tris: Uint32Array.from(tris), partIds: Uint8Array.from(part),
           names: ['skin', 'mouth_socket', 'tongue'], V: p.length / 3 };
}

test('mouth shell: the rim, the shell\'s other holes, the interior and the tongue', () => {
  const m = mouthMesh();
  const ms = mouthShell(m.tris, m.partIds, m.names, m.V);
  assert.ok(ms, 'no mouth shell found');
  assert.deepEqual([...ms.rim].sort((a, b) => a - b), [5, 6, 9, 10]);
  assert.equal(ms.holes.length, 1);                 // the sheet's outer border (the "neck")
  assert.equal(ms.holes[0].length, 12);
  assert.deepEqual(Array.from(ms.tongue), [m.V - 3, m.V - 2, m.V - 1]);
  assert.ok(ms.interior.length >= 7);               // the pocket and the tongue
  // without a mouth socket there is no shell to use: the interior is drawn whole
  assert.equal(mouthShell(m.tris, m.partIds, ['skin', 'teeth_upper', 'tongue'], m.V), null);
});

test('mouth window: the opening\'s rectangle from in front, nothing to cull from behind', () => {
  const m = mouthMesh();
  const ms = mouthShell(m.tris, m.partIds, m.names, m.V);
  const at = (i, a) => m.p[3 * i + a];
  // orthographic-like projection looking down -z from z = 10 (w = 1): x, y in [-2, 2] -> [-1, 1]
  const M = [0.5, 0, 0, 0, 0, 0.5, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1];
  const w = mouthWindow(ms, at, [0, 0, 10], M, 400, 400);
  assert.ok(w, 'no window from in front of the face');
  const [x0, y0, x1, y1] = w;
  // the opening spans x, y in [-0.5, 0.5] -> pixels 150..250, one spare pixel each side
  assert.ok(x0 <= 150 && x0 >= 148 && y0 <= 150 && y0 >= 148, `${w}`);
  assert.ok(x1 >= 250 && x1 <= 252 && y1 >= 250 && y1 <= 252, `${w}`);
  // from behind the sheet the eye is on the interior's side of the outer border: no window
  assert.equal(mouthWindow(ms, at, [0, 0, -10], M, 400, 400), null);
  // a vertex behind the eye (w <= 0) cannot be projected: no window
  const behind = [0.5, 0, 0, 0, 0, 0.5, 0, 0, 0, 0, 0, 0, 0, 0, 0, -1];
  assert.equal(mouthWindow(ms, at, [0, 0, 10], behind, 400, 400), null);
});
