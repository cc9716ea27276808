// WebGL2 face renderer: one indexed mesh, positions streamed per frame, lit per part, orbit camera.
// Positions arrive either as float32 or as int16 with a per-frame offset/scale; int16 frames are
// uploaded as they are and dequantised in the vertex shader, so a frame costs one bufferSubData.

// The lighting model, shared by both shading modes: a key and a fill light, a specular highlight and
// a rim. Surfaces facing away (the inside of the mouth, two-sided sheets) are lit from the viewer's side.
const LIGHT = `
vec3 light(vec3 n, vec3 v, vec3 base) {
  if (dot(n, v) < 0.0) n = -n;
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
uniform vec3 u_eye;
vec3 position() { return u_quantized ? u_offset + a_i16 * u_scale : a_f32; }`;

/** Per-pixel lighting: normal, position and colour interpolated, lit in the fragment shader. */
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
void main() { outColor = vec4(light(normalize(v_normal), normalize(u_eye - v_pos), v_color), 1.0); }`,
};

/** Per-vertex lighting (Gouraud): the fragment shader only writes the interpolated colour. */
const VERTEX = {
  vert: `${HEAD}
out vec3 v_lit;
${LIGHT}
void main() {
  vec3 p = position();
  v_lit = light(normalize(a_normal), normalize(u_eye - p), a_color);
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
      for (const n of ['u_viewProj', 'u_offset', 'u_scale', 'u_quantized', 'u_eye']) loc[n] = gl.getUniformLocation(prog, n);
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
    const rgb = new Float32Array(3 * V);
    for (let i = 0; i < V; i++) rgb.set(PART_COLORS[partNames[partIds[i]]] || PART_COLORS.skin, 3 * i);
    const color = buf(smoothColors(rgb, triangles, V), this.loc.a_color, 3, gl.FLOAT);
    const { order, groups } = this.ordered(triangles, partIds, partNames, V);
    const ibo = gl.createBuffer();
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, ibo);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, order, gl.STATIC_DRAW);
    this.normals = new VertexNormals(triangles, V);
    this.mouthShell = mouthShell(triangles, partIds, partNames, V);
    this.mesh = { vao, ibo, f32, i16, nrm, color, V, count: triangles.length, groups, partIds, partNames, coarse: null,
                  quantized: false,
                  offset: [0, 0, 0], scale: [1, 1, 1], positions: new Float32Array(rest) };
    this.positionArrays(false);
    this.updateNormals(rest);
    let lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (let i = 0; i < rest.length; i += 3) {
      for (let a = 0; a < 3; a++) { lo[a] = Math.min(lo[a], rest[i + a]); hi[a] = Math.max(hi[a], rest[i + a]); }
    }
    const centre = [0, 1, 2].map((a) => (lo[a] + hi[a]) / 2);
    const size = Math.max(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]);
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
    const eye = this.camera.eye();
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
    const M = this.camera.viewProj(c.width / c.height);
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
    const W = c.width, H = c.height, pad = 1;
    return [Math.max(0, Math.floor((x0 + 1) / 2 * W) - pad), Math.max(0, Math.floor((y0 + 1) / 2 * H) - pad),
            Math.min(W, Math.ceil((x1 + 1) / 2 * W) + pad), Math.min(H, Math.ceil((y1 + 1) / 2 * H) + pad)];
  }
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
function shortIndices(V) { return V <= 65535; }

/** Small parts whose shape matters more than their triangle count: never coarsened. */
const FINE = /^(teeth|eye_l|eye_r|iris|eyelashes|eye_extras)/;

/**
 * A coarser triangle list over the same vertices (vertex clustering along the mesh): each vertex not
 * yet taken becomes a representative and takes its untaken edge neighbours of the same part; every
 * triangle is mapped to representatives and dropped when two corners meet. Edges only merge
 * vertices that share an edge, so openings (mouth, eyes) never weld shut and shared edges stay
 * shared (no cracks). The vertices keep streaming and their normals stay those of the full mesh.
 * triangles: Uint32Array 3F; partIds: Uint8Array V; keep[part id] true: that part is left as it is.
 * Returns Uint32Array 3F' (F' <= F).
 */
export function coarsen(triangles, V, partIds, keep = null) {
  const start = new Uint32Array(V + 1);
  for (let i = 0; i < triangles.length; i++) start[triangles[i] + 1] += 2;
  for (let v = 0; v < V; v++) start[v + 1] += start[v];
  const fill = start.slice(0, V), adj = new Uint32Array(start[V]);
  for (let i = 0; i < triangles.length; i += 3) {
    const a = triangles[i], b = triangles[i + 1], c = triangles[i + 2];
    adj[fill[a]++] = b; adj[fill[a]++] = c; adj[fill[b]++] = c; adj[fill[b]++] = a; adj[fill[c]++] = a; adj[fill[c]++] = b;
  }
  const rep = new Int32Array(V).fill(-1);
  for (let v = 0; v < V; v++) {
    if (rep[v] >= 0) continue;
    rep[v] = v;
    if (keep && keep[partIds[v]]) continue;
    for (let k = start[v]; k < start[v + 1]; k++) {
      const u = adj[k];
      if (rep[u] < 0 && partIds[u] === partIds[v]) rep[u] = v;
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

/** Area-weighted vertex normals with typed arrays (no allocation per frame). */
export class VertexNormals {
  constructor(triangles, V) {
    this.tri = triangles; this.V = V; this.out = new Float32Array(3 * V);
  }
  /** positions: Float32Array(3V) or Int16Array(3V) with per-axis scale (then normals of the scaled mesh). */
  compute(p, scale) {
    const t = this.tri, n = this.out, sx = scale ? scale[0] : 1, sy = scale ? scale[1] : 1, sz = scale ? scale[2] : 1;
    n.fill(0);
    for (let i = 0; i < t.length; i += 3) {
      const a = 3 * t[i], b = 3 * t[i + 1], c = 3 * t[i + 2];
      const ux = (p[b] - p[a]) * sx, uy = (p[b + 1] - p[a + 1]) * sy, uz = (p[b + 2] - p[a + 2]) * sz;
      const vx = (p[c] - p[a]) * sx, vy = (p[c + 1] - p[a + 1]) * sy, vz = (p[c + 2] - p[a + 2]) * sz;
      const nx = uy * vz - uz * vy, ny = uz * vx - ux * vz, nz = ux * vy - uy * vx;
      n[a] += nx; n[a + 1] += ny; n[a + 2] += nz;
      n[b] += nx; n[b + 1] += ny; n[b + 2] += nz;
      n[c] += nx; n[c + 1] += ny; n[c + 2] += nz;
    }
    return n;  // normalised in the fragment shader
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
