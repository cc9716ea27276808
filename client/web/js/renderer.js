// WebGL2 face renderer: one indexed mesh, positions streamed per frame, lit per part, orbit camera.
// Positions arrive either as float32 or as int16 with a per-frame offset/scale; int16 frames are
// uploaded as they are and dequantised in the vertex shader, so a frame costs one bufferSubData.
// The mesh algorithms it uses (normals, bounds, draw order, coarsening ...) are mesh.js's.
import {
  FINE, VertexNormals, bounds, cacheOrder, coarsen, drawOrder, mouthShell, mouthWindow, partColors, shortIndices,
  smoothColors,
} from './mesh.js';

// The lighting model, shared by both shading modes: a key and a fill light, a specular highlight and
// a rim; n is the unit normal of the side being seen (see PIXEL and VERTEX), v the unit vector to the eye.
const LIGHT = `
vec3 light(vec3 n, vec3 v, vec3 base) {
  const vec3 key = vec3(0.3319, 0.4979, 0.8298);    // normalize(0.4, 0.6, 1.0)
  const vec3 fill = vec3(-0.8087, 0.1155, 0.5776);  // normalize(-0.7, 0.1, 0.5)
  float diff = max(dot(n, key), 0.0) * 0.75 + max(dot(n, fill), 0.0) * 0.25;
  float spec = pow(max(dot(n, normalize(key + v)), 0.0), 40.0) * 0.18;
  float r = 1.0 - max(dot(n, v), 0.0);
  return base * (0.22 + diff) + vec3(spec + r * r * r * 0.15);
}`;

const HEAD = `#version 300 es
precision highp float;
layout(location = 0) in vec3 a_f32;
layout(location = 1) in vec3 a_i16;
layout(location = 2) in vec3 a_normal;
layout(location = 3) in vec3 a_color;
uniform mat4 u_viewProj;
uniform vec3 u_offset;
uniform vec3 u_scale;
uniform bool u_quantized;
uniform bool u_twoSided;
uniform vec3 u_eye;
vec3 position() { return u_quantized ? u_offset + a_i16 * u_scale : a_f32; }`;

/**
 * Per-pixel lighting: normal, position and colour interpolated, lit in the fragment shader. The back of a
 * triangle (seen only on the two-sided sheets) is lit with the normal reversed. A front face is lit with
 * its own normal even where that points away from the eye (at a silhouette, in a crease): reversing it
 * there turned the lit side dark (a dark rim along the crown, dark patches on the eyelids).
 */
const PIXEL = {
  vert: `${HEAD}
out vec3 v_normal;
out vec3 v_pos;
out vec3 v_color;
void main() {
  vec3 p = position();
  v_pos = p; v_normal = a_normal; v_color = a_color;
  gl_Position = u_viewProj * vec4(p, 1.0);
}`,
  frag: `#version 300 es
precision highp float;
in vec3 v_normal;
in vec3 v_pos;
in vec3 v_color;
uniform vec3 u_eye;
out vec4 outColor;
${LIGHT}
void main() {
  vec3 n = normalize(v_normal);
  outColor = vec4(light(gl_FrontFacing ? n : -n, normalize(u_eye - v_pos), v_color), 1.0);
}`,
};

/**
 * Per-vertex lighting (Gouraud): the fragment shader only writes the interpolated colour. A vertex serves
 * both sides of a two-sided sheet, so there the side facing the eye is lit (u_twoSided); on closed,
 * culled surfaces the normal is kept as it is (see PIXEL).
 */
const VERTEX = {
  vert: `${HEAD}
out vec3 v_lit;
${LIGHT}
void main() {
  vec3 p = position(), n = normalize(a_normal), v = normalize(u_eye - p);
  v_lit = light(u_twoSided && dot(n, v) < 0.0 ? -n : n, v, a_color);
  gl_Position = u_viewProj * vec4(p, 1.0);
}`,
  frag: `#version 300 es
precision mediump float;
in vec3 v_lit;
out vec4 outColor;
void main() { outColor = vec4(v_lit, 1.0); }`,
};

/** Attribute locations, fixed in the shaders (one vertex array serves both programs). */
const ATTR = { a_f32: 0, a_i16: 1, a_normal: 2, a_color: 3 };

// Colours by part name; anything unnamed is skin.
export const PART_COLORS = {
  skin: [0.86, 0.64, 0.53], eye_l: [0.93, 0.93, 0.91], eye_r: [0.93, 0.93, 0.91],
  teeth_upper: [0.95, 0.93, 0.84], teeth_lower: [0.95, 0.93, 0.84],
  gums_upper: [0.78, 0.36, 0.38], gums_lower: [0.78, 0.36, 0.38], tongue: [0.80, 0.40, 0.42],
  mouth_socket: [0.45, 0.18, 0.2], eyelashes: [0.15, 0.1, 0.08], eye_extras: [0.9, 0.85, 0.85],
  eye_socket: [0.8, 0.55, 0.5], iris_l: [0.22, 0.33, 0.45], iris_r: [0.22, 0.33, 0.45],
  lip_upper: [0.74, 0.42, 0.42], lip_lower: [0.74, 0.42, 0.42],
};

function compile(gl, type, src) {
  const s = gl.createShader(type);
  gl.shaderSource(s, src);
  gl.compileShader(s);
  if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
  return s;
}

export class OrbitCamera {
  constructor(target = [0, 0, 0], radius = 1) {
    this.target = target; this.radius = radius; this.yaw = 0.35; this.pitch = 0.08;
  }
  /** Look at `target` from `radius` away (a new mesh). */
  frame(target, radius) { this.target = target; this.radius = radius; }
  eye() {
    const [tx, ty, tz] = this.target, r = this.radius;
    return [tx + r * Math.sin(this.yaw) * Math.cos(this.pitch), ty + r * Math.sin(this.pitch),
            tz + r * Math.cos(this.yaw) * Math.cos(this.pitch)];
  }
  viewProj(aspect) {
    const e = this.eye(), t = this.target;
    const f = norm(sub(t, e)), s = norm(cross(f, [0, 1, 0])), u = cross(s, f);
    const view = [s[0], u[0], -f[0], 0, s[1], u[1], -f[1], 0, s[2], u[2], -f[2], 0,
                  -dot(s, e), -dot(u, e), dot(f, e), 1];
    const near = this.radius * 0.05, far = this.radius * 10, k = 1 / Math.tan(0.45 / 2);
    const proj = [k / aspect, 0, 0, 0, 0, k, 0, 0, 0, 0, (far + near) / (near - far), -1,
                  0, 0, (2 * far * near) / (near - far), 0];
    return mul4(proj, view);
  }
  attach(canvas, onChange) {
    let drag = null;
    canvas.addEventListener('pointerdown', (e) => { drag = [e.clientX, e.clientY]; canvas.setPointerCapture(e.pointerId); });
    canvas.addEventListener('pointerup', () => { drag = null; });
    canvas.addEventListener('pointermove', (e) => {
      if (!drag) return;
      this.yaw -= (e.clientX - drag[0]) * 0.01;
      this.pitch = Math.max(-1.4, Math.min(1.4, this.pitch + (e.clientY - drag[1]) * 0.01));
      drag = [e.clientX, e.clientY];
      onChange();
    });
    canvas.addEventListener('wheel', (e) => {
      e.preventDefault();
      this.radius *= Math.exp(e.deltaY * 0.001);
      onChange();
    }, { passive: false });
  }
}

export class FaceRenderer {
  /**
   * @param {HTMLCanvasElement} canvas
   * @param {WebGLContextAttributes} attributes over the defaults (no multisampling, not preserved between
   * frames). An opaque buffer ({alpha: false}) measured no faster on llvmpipe with software compositing.
   */
  constructor(canvas, attributes = {}) {
    const gl = canvas.getContext('webgl2', { antialias: false, preserveDrawingBuffer: false,
                                             powerPreference: 'high-performance', ...attributes });
    if (!gl) throw new Error('this browser has no WebGL2');
    this.gl = gl; this.canvas = canvas;
    this.programs = {};
    for (const [name, src] of Object.entries({ pixel: PIXEL, vertex: VERTEX })) {
      const prog = gl.createProgram();
      gl.attachShader(prog, compile(gl, gl.VERTEX_SHADER, src.vert));
      gl.attachShader(prog, compile(gl, gl.FRAGMENT_SHADER, src.frag));
      gl.linkProgram(prog);
      if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
      const loc = { ...ATTR };
      for (const n of ['u_viewProj', 'u_offset', 'u_scale', 'u_quantized', 'u_twoSided', 'u_eye']) loc[n] = gl.getUniformLocation(prog, n);
      this.programs[name] = { prog, loc };
    }
    this.loc = ATTR;
    /** 'pixel' (lit per fragment) or 'vertex' (lit per vertex: far fewer shader runs in software GL). */
    this.shading = 'pixel';
    /** Level of detail: 0 draws every triangle, 1 a coarser mesh over the same, animated vertices (see coarsen). */
    this.lod = 0;
    /** Triangles in vertex-cache order within each draw group (fewer vertex shader runs in software GL). */
    this.vertexCacheOrder = true;
    /** Draw the mouth's interior only inside the screen rectangle of the mouth opening (see mouthWindow). */
    this.mouthScissor = true;
    this.mesh = null;
    this.camera = new OrbitCamera();
    this.scale = 1;  // < 1 renders fewer pixels (the browser scales the canvas up)
  }

  /** Set the topology: rest positions (Float32Array 3V), triangles (Uint32Array 3F), part ids (Uint8Array V). */
  setMesh(rest, triangles, partIds, partNames) {
    const gl = this.gl, V = rest.length / 3;
    const vao = gl.createVertexArray();
    gl.bindVertexArray(vao);
    const buf = (data, loc, size, type, normalized = false, usage = gl.STATIC_DRAW) => {
      const b = gl.createBuffer();
      gl.bindBuffer(gl.ARRAY_BUFFER, b);
      gl.bufferData(gl.ARRAY_BUFFER, data, usage);
      if (loc >= 0) { gl.enableVertexAttribArray(loc); gl.vertexAttribPointer(loc, size, type, normalized, 0, 0); }
      return b;
    };
    const f32 = buf(rest, this.loc.a_f32, 3, gl.FLOAT, false, gl.DYNAMIC_DRAW);
    const i16 = buf(new Int16Array(3 * V), this.loc.a_i16, 3, gl.SHORT, false, gl.DYNAMIC_DRAW);
    const nrm = buf(new Float32Array(3 * V), this.loc.a_normal, 3, gl.FLOAT, false, gl.DYNAMIC_DRAW);
    // Colours per vertex from its part, blended over the mesh at part borders (soft borders).
    const rgb = partColors(partIds, partNames, PART_COLORS, PART_COLORS.skin);
    const color = buf(smoothColors(rgb, triangles, V), this.loc.a_color, 3, gl.FLOAT);
    const { order, groups } = this.ordered(triangles, partIds, partNames, V);
    const ibo = gl.createBuffer();
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, ibo);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, order, gl.STATIC_DRAW);
    this.normals = new VertexNormals(triangles, V, rest);
    this.mouthShell = mouthShell(triangles, partIds, partNames, V);
    this.mesh = { vao, ibo, f32, i16, nrm, color, V, count: triangles.length, groups, partIds, partNames, coarse: null,
                  quantized: false,
                  offset: [0, 0, 0], scale: [1, 1, 1], positions: new Float32Array(rest) };
    this.positionArrays(false);
    this.updateNormals(rest);
    const { centre, size } = bounds(rest);
    this.camera.frame([centre[0], centre[1] + size * 0.05, centre[2]], size * 2.1);
  }

  /** The draw order (see drawOrder) with each draw group's triangles in vertex-cache order (see cacheOrder). */
  ordered(triangles, partIds, partNames, V) {
    const { order, groups } = drawOrder(triangles, partIds, partNames);
    if (this.vertexCacheOrder) for (const g of groups) order.set(cacheOrder(order.subarray(g.first, g.first + g.count), V), g.first);
    // 16-bit indices when the vertices fit (half the index bytes for the GL to read)
    return { order: shortIndices(V) ? Uint16Array.from(order) : order, groups };
  }

  /** Switch the vertex-cache order of the index buffers on or off (for comparisons): rebuilt at once. */
  setVertexCacheOrder(on) {
    this.vertexCacheOrder = on;
    const m = this.mesh;
    if (!m) return;
    const { order, groups } = this.ordered(this.normals.tri, m.partIds, m.partNames, m.V);
    this.gl.bindBuffer(this.gl.ELEMENT_ARRAY_BUFFER, m.ibo);
    this.gl.bufferData(this.gl.ELEMENT_ARRAY_BUFFER, order, this.gl.STATIC_DRAW);
    m.groups = groups; m.coarse = null;
  }

  /** A float32 frame: positions Float32Array(3V). */
  setFrameF32(positions) {
    const gl = this.gl, m = this.mesh;
    gl.bindBuffer(gl.ARRAY_BUFFER, m.f32);
    gl.bufferSubData(gl.ARRAY_BUFFER, 0, positions);
    if (m.quantized) this.positionArrays(false);
    m.quantized = false;
    m.positions = positions;
    this.updateNormals(positions);
  }

  /** An int16 frame: q Int16Array(3V), offset and scale [3]. Dequantised on the GPU. */
  setFrameI16(q, offset, scale) {
    const gl = this.gl, m = this.mesh;
    gl.bindBuffer(gl.ARRAY_BUFFER, m.i16);
    gl.bufferSubData(gl.ARRAY_BUFFER, 0, q);
    if (!m.quantized) this.positionArrays(true);
    m.quantized = true; m.offset = offset; m.scale = scale; m.q = q;
    this.updateNormalsQuantized(q, scale);
  }

  /** Read positions from the int16 array (quantized) or the float32 one; the other is not fetched. */
  positionArrays(quantized) {
    const gl = this.gl;
    gl.bindVertexArray(this.mesh.vao);
    if (quantized) { gl.enableVertexAttribArray(ATTR.a_i16); gl.disableVertexAttribArray(ATTR.a_f32); }
    else { gl.enableVertexAttribArray(ATTR.a_f32); gl.disableVertexAttribArray(ATTR.a_i16); }
    gl.bindVertexArray(null);
  }

  /** Current position of vertex i (world units), as drawn. */
  vertex(i) {
    const m = this.mesh;
    if (m.quantized) return [0, 1, 2].map((a) => m.offset[a] + m.q[3 * i + a] * m.scale[a]);
    return [m.positions[3 * i], m.positions[3 * i + 1], m.positions[3 * i + 2]];
  }

  /** CSS-pixel position of vertex i on the canvas. */
  project(i) {
    const c = this.canvas, p = this.vertex(i);
    const M = this.camera.viewProj(c.width / c.height);
    const x = M[0] * p[0] + M[4] * p[1] + M[8] * p[2] + M[12];
    const y = M[1] * p[0] + M[5] * p[1] + M[9] * p[2] + M[13];
    const w = M[3] * p[0] + M[7] * p[1] + M[11] * p[2] + M[15];
    return [(x / w + 1) / 2 * c.clientWidth, (1 - y / w) / 2 * c.clientHeight];
  }

  /** The coarse level's index buffer and draw groups (built on first use). */
  coarseLevel() {
    const gl = this.gl, m = this.mesh;
    if (!m.coarse) {
      const keep = m.partNames.map((n) => FINE.test(n));
      const { order, groups } = this.ordered(coarsen(this.normals.tri, m.V, m.partIds, keep), m.partIds, m.partNames, m.V);
      const ibo = gl.createBuffer();
      gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, ibo);
      gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, order, gl.STATIC_DRAW);
      m.coarse = { ibo, groups, count: order.length };
    }
    return m.coarse;
  }

  updateNormals(positions) {
    const n = this.normals.compute(positions, null);
    this.gl.bindBuffer(this.gl.ARRAY_BUFFER, this.mesh.nrm);
    this.gl.bufferSubData(this.gl.ARRAY_BUFFER, 0, n);
  }

  updateNormalsQuantized(q, scale) {
    const n = this.normals.compute(q, scale);
    this.gl.bindBuffer(this.gl.ARRAY_BUFFER, this.mesh.nrm);
    this.gl.bufferSubData(this.gl.ARRAY_BUFFER, 0, n);
  }

  draw() {
    const gl = this.gl, m = this.mesh, c = this.canvas;
    const k = (window.devicePixelRatio || 1) * this.scale;  // drawing-buffer pixels per CSS pixel
    const w = Math.max(1, Math.floor(c.clientWidth * k)), h = Math.max(1, Math.floor(c.clientHeight * k));
    if (c.width !== w || c.height !== h) { c.width = w; c.height = h; }
    gl.viewport(0, 0, c.width, c.height);
    gl.clearColor(0.11, 0.12, 0.14, 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    if (!m) return;
    gl.enable(gl.DEPTH_TEST);
    const { prog, loc } = this.programs[this.shading] || this.programs.pixel;
    gl.useProgram(prog);
    gl.bindVertexArray(m.vao);
    gl.uniformMatrix4fv(loc.u_viewProj, false, this.camera.viewProj(c.width / c.height));
    gl.uniform3fv(loc.u_eye, this.camera.eye());
    gl.uniform1i(loc.u_quantized, m.quantized ? 1 : 0);
    gl.uniform3fv(loc.u_offset, m.offset);
    gl.uniform3fv(loc.u_scale, m.scale);
    // Closed surfaces with back faces culled (about half their triangles never reach the
    // rasteriser), then the open single-sided sheets (lashes, eye extras, sockets) seen from both sides.
    const level = this.lod ? this.coarseLevel() : m;
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, level.ibo);
    const [type, bytes] = shortIndices(m.V) ? [gl.UNSIGNED_SHORT, 2] : [gl.UNSIGNED_INT, 4];
    const window_ = this.mouthScissor ? this.mouthWindow() : null;
    for (const g of level.groups) {
      if (g.interior && window_) {
        const [x0, y0, x1, y1] = window_;
        if (x1 <= x0 || y1 <= y0) continue;  // the opening is off screen: nothing inside can show
        gl.enable(gl.SCISSOR_TEST);
        gl.scissor(x0, y0, x1 - x0, y1 - y0);
      }
      if (g.cull) gl.enable(gl.CULL_FACE); else gl.disable(gl.CULL_FACE);
      gl.uniform1i(loc.u_twoSided, g.cull ? 0 : 1);
      gl.drawElements(gl.TRIANGLES, g.count, type, bytes * g.first);
      gl.disable(gl.SCISSOR_TEST);
    }
    gl.disable(gl.CULL_FACE);
    this.lastMouthWindow = window_;
  }

  /**
   * The drawing-buffer rectangle [x0, y0, x1, y1) (pixels, y up) outside which nothing of the mouth's
   * interior can be seen this frame, or null when that cannot be shown (then it is drawn whole).
   * The interior (teeth, gums, tongue, mouth socket) sits in the pocket the mouth socket makes behind
   * the lips; the pocket's only opening is the lips' inner rim, and the rest of the shell (skin, lips,
   * sockets) is closed but for its own holes (the neck). A ray from the eye reaches the interior either
   * through the rim, whose opening projects inside the rim's projected bounding box, or through a
   * hole of the shell: ruled out when the eye and every interior vertex lie on the same side of the
   * slab that holds the hole's rim (and so any surface spanning it). What may leave the pocket widens
   * the window: the whole tongue, and interior vertices forward of the rim's deepest point less its
   * depth. Positions are this frame's.
   */
  mouthWindow() {
    const ms = this.mouthShell, m = this.mesh, c = this.canvas;
    if (!ms || !m) return null;
    const P = m.quantized ? m.q : m.positions, o = m.quantized ? m.offset : [0, 0, 0], k = m.quantized ? m.scale : [1, 1, 1];
    const at = (i, a) => o[a] + P[3 * i + a] * k[a];
    return mouthWindow(ms, at, this.camera.eye(), this.camera.viewProj(c.width / c.height), c.width, c.height);
  }

}

function sub(a, b) { return [a[0] - b[0], a[1] - b[1], a[2] - b[2]]; }
function dot(a, b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
function cross(a, b) { return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]; }
function norm(a) { const l = Math.hypot(a[0], a[1], a[2]) || 1; return [a[0] / l, a[1] / l, a[2] / l]; }
function mul4(a, b) {
  const o = new Float32Array(16);
  for (let c = 0; c < 4; c++) for (let r = 0; r < 4; r++) {
    let s = 0;
    for (let k = 0; k < 4; k++) s += a[k * 4 + r] * b[c * 4 + k];
    o[c * 4 + r] = s;
  }
  return o;
}
