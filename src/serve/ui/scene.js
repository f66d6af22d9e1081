// The organ's surface on screen: an orbit camera, a WebGL2 renderer that colours the deformed surface
// by displacement magnitude, and ray picking against the deformed triangles.

// Viridis at five stops; index.html's scale bar uses the same stops.
const COLORMAP = [
  [0.267, 0.005, 0.329], [0.231, 0.322, 0.545], [0.129, 0.569, 0.549], [0.369, 0.788, 0.384],
  [0.992, 0.906, 0.145],
];

const VERTEX_SHADER = `#version 300 es
uniform mat4 viewProjection;
uniform float pointSize;
in vec3 position;
in vec3 normal;
in float magnitude;
out vec3 vNormal;
out float vMagnitude;
void main() {
  gl_Position = viewProjection * vec4(position, 1.0);
  // Markers drawn as points sit on the surface: nudge them towards the camera so they win the
  // depth test against the triangles they lie on.
  gl_Position.z -= pointSize > 0.0 ? 0.002 * gl_Position.w : 0.0;
  gl_PointSize = pointSize;
  vNormal = normal;
  vMagnitude = magnitude;
}`;

const FRAGMENT_SHADER = `#version 300 es
precision highp float;
uniform vec3 colormap[5];
uniform float scaleMax;
uniform vec3 eyeDirection;
uniform vec4 markerColor;
uniform bool roundPoints;
in vec3 vNormal;
in float vMagnitude;
out vec4 color;
vec3 viridis(float t) {
  float x = clamp(t, 0.0, 1.0) * 4.0;
  int i = int(min(floor(x), 3.0));
  return mix(colormap[i], colormap[i + 1], x - float(i));
}
void main() {
  if (markerColor.a > 0.0) {
    if (roundPoints && length(gl_PointCoord - 0.5) > 0.5) discard;
    color = markerColor;
    return;
  }
  // Two-sided headlight: the light sits at the camera, so the side facing the viewer is always lit;
  // a highlight shows the shape where the colour is uniform (an organ at rest).
  float facing = abs(dot(normalize(vNormal), eyeDirection));
  vec3 base = viridis(vMagnitude / scaleMax);
  color = vec4(base * (0.3 + 0.7 * facing) + vec3(0.35) * pow(facing, 24.0), 1.0);
}`;

// ---- small vector and matrix helpers -----------------------------------------------------------

export const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
export const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
export const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
export const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const normalize = (a) => scale(a, 1 / Math.hypot(a[0], a[1], a[2]));

// Column-major 4×4 product a·b.
function multiply(a, b) {
  const out = new Float32Array(16);
  for (let col = 0; col < 4; col++) {
    for (let row = 0; row < 4; row++) {
      let sum = 0;
      for (let k = 0; k < 4; k++) sum += a[k * 4 + row] * b[col * 4 + k];
      out[col * 4 + row] = sum;
    }
  }
  return out;
}

// ---- camera ------------------------------------------------------------------------------------

// Orbits `target` at `distance`; y is up (gravity points along −y, docs/design.md §2).
export class OrbitCamera {
  constructor(target, radius) {
    this.target = target;
    this.distance = 2.6 * radius;
    this.minDistance = 0.3 * radius;
    this.maxDistance = 10 * radius;
    this.yaw = 0;
    this.pitch = 0.35;
    this.fovY = (40 * Math.PI) / 180;
    this.near = 0.01 * radius;
    this.far = 40 * radius;
  }
  orbit(dx, dy) {
    this.yaw -= dx * 0.008;
    this.pitch = Math.max(-1.5, Math.min(1.5, this.pitch + dy * 0.008));
  }
  zoom(factor) {
    this.distance = Math.max(this.minDistance, Math.min(this.maxDistance, this.distance * factor));
  }
  // Eye position and the camera's right, up and forward axes.
  frame() {
    const c = Math.cos(this.pitch);
    const back = [c * Math.sin(this.yaw), Math.sin(this.pitch), c * Math.cos(this.yaw)];
    const eye = add(this.target, scale(back, this.distance));
    const forward = scale(back, -1);
    const right = normalize(cross(forward, [0, 1, 0]));
    const up = cross(right, forward);
    return { eye, right, up, forward };
  }
  viewProjection(aspect) {
    const { eye, right, up, forward } = this.frame();
    const view = new Float32Array([
      right[0], up[0], -forward[0], 0, right[1], up[1], -forward[1], 0, right[2], up[2], -forward[2], 0,
      -dot(right, eye), -dot(up, eye), dot(forward, eye), 1,
    ]);
    const f = 1 / Math.tan(this.fovY / 2);
    const { near, far } = this;
    const projection = new Float32Array([
      f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) / (near - far), -1, 0, 0, (2 * far * near) / (near - far), 0,
    ]);
    return multiply(projection, view);
  }
  // The ray through pixel (x, y) of a width × height viewport.
  ray(x, y, width, height) {
    const { eye, right, up, forward } = this.frame();
    const t = Math.tan(this.fovY / 2);
    const u = ((2 * x) / width - 1) * t * (width / height);
    const v = (1 - (2 * y) / height) * t;
    return { origin: eye, direction: normalize(add(forward, add(scale(right, u), scale(up, v)))) };
  }
  // Pixel coordinates of a world point, or null behind the camera.
  project(point, width, height) {
    const { eye, right, up, forward } = this.frame();
    const d = sub(point, eye);
    const depth = dot(d, forward);
    if (depth <= 0) return null;
    const t = Math.tan(this.fovY / 2);
    const u = dot(d, right) / (depth * t * (width / height));
    const v = dot(d, up) / (depth * t);
    return [((u + 1) * width) / 2, ((1 - v) * height) / 2];
  }
}

// ---- surface -----------------------------------------------------------------------------------

// The surface as drawn: rest positions of the surface nodes, the current displacement of each, and
// the triangles and marker points over them (indices into the surface nodes).
export class Surface {
  constructor(mesh) {
    const local = new Map(mesh.surfaceNodes.map((node, i) => [node, i]));
    const count = mesh.surfaceNodes.length;
    this.count = count;
    this.rest = new Float32Array(count * 3);
    mesh.surfaceNodes.forEach((node, i) => this.rest.set(mesh.positions.subarray(3 * node, 3 * node + 3), 3 * i));
    this.triangles = Uint32Array.from(mesh.triangles, (node) => local.get(node));
    this.displacement = new Float32Array(count * 3);
    this.position = this.rest.slice();
    this.normal = new Float32Array(count * 3);
    this.magnitude = new Float32Array(count);
    const markers = (names) => [...new Set(names.flatMap((n) => mesh.nodeSets[n] ?? []))]
      .filter((node) => local.has(node)).map((node) => local.get(node));
    this.graspRegionPoints = Uint32Array.from(markers(mesh.graspRegions));
    this.fixedPoints = Uint32Array.from(markers(["fixed"]));
    const lo = [Infinity, Infinity, Infinity];
    const hi = [-Infinity, -Infinity, -Infinity];
    for (let i = 0; i < count; i++) {
      for (let c = 0; c < 3; c++) {
        lo[c] = Math.min(lo[c], this.rest[3 * i + c]);
        hi[c] = Math.max(hi[c], this.rest[3 * i + c]);
      }
    }
    this.center = scale(add(lo, hi), 0.5);
    this.radius = Math.hypot(...sub(hi, lo)) / 2;
    this.update(null);
  }
  // Sets the displacement field (surface order; null: at rest) and recomputes what depends on it.
  update(displacement) {
    if (displacement) this.displacement.set(displacement);
    else this.displacement.fill(0);
    // Runs for every answer shown: plain indexed arithmetic, no temporary arrays.
    const { rest, displacement: u, position } = this;
    let largest = 0;
    for (let i = 0; i < this.count; i++) {
      const x = u[3 * i];
      const y = u[3 * i + 1];
      const z = u[3 * i + 2];
      position[3 * i] = rest[3 * i] + x;
      position[3 * i + 1] = rest[3 * i + 1] + y;
      position[3 * i + 2] = rest[3 * i + 2] + z;
      const magnitude = Math.sqrt(x * x + y * y + z * z);
      this.magnitude[i] = magnitude;
      if (magnitude > largest) largest = magnitude;
    }
    this.largest = largest;
    this.computeNormals();
  }
  // Area-weighted vertex normals of the deformed surface.
  computeNormals() {
    const p = this.position;
    const n = this.normal;
    n.fill(0);
    const t = this.triangles;
    for (let k = 0; k < t.length; k += 3) {
      const a = 3 * t[k];
      const b = 3 * t[k + 1];
      const c = 3 * t[k + 2];
      const e1x = p[b] - p[a];
      const e1y = p[b + 1] - p[a + 1];
      const e1z = p[b + 2] - p[a + 2];
      const e2x = p[c] - p[a];
      const e2y = p[c + 1] - p[a + 1];
      const e2z = p[c + 2] - p[a + 2];
      // e1 × e2: the face normal scaled by twice its area.
      const fx = e1y * e2z - e1z * e2y;
      const fy = e1z * e2x - e1x * e2z;
      const fz = e1x * e2y - e1y * e2x;
      for (const v of [a, b, c]) {
        n[v] += fx;
        n[v + 1] += fy;
        n[v + 2] += fz;
      }
    }
  }
  vertex(array, i) {
    return [array[3 * i], array[3 * i + 1], array[3 * i + 2]];
  }
  // The nearest triangle the ray hits (Möller–Trumbore), with the hit's barycentric weights.
  pick(ray) {
    let best = null;
    const t = this.triangles;
    for (let k = 0; k < t.length; k += 3) {
      const a = this.vertex(this.position, t[k]);
      const e1 = sub(this.vertex(this.position, t[k + 1]), a);
      const e2 = sub(this.vertex(this.position, t[k + 2]), a);
      const p = cross(ray.direction, e2);
      const det = dot(e1, p);
      if (Math.abs(det) < 1e-12) continue;
      const s = sub(ray.origin, a);
      const u = dot(s, p) / det;
      if (u < 0 || u > 1) continue;
      const q = cross(s, e1);
      const v = dot(ray.direction, q) / det;
      if (v < 0 || u + v > 1) continue;
      const distance = dot(e2, q) / det;
      if (distance > 0 && (!best || distance < best.distance)) {
        best = { distance, nodes: [t[k], t[k + 1], t[k + 2]], weights: [1 - u - v, u, v] };
      }
    }
    return best;
  }
  // `array` (rest, position or displacement) interpolated at a pick's barycentric point.
  at(pick, array) {
    return pick.nodes.reduce((sum, node, i) => add(sum, scale(this.vertex(array, node), pick.weights[i])), [0, 0, 0]);
  }
}

// ---- renderer ----------------------------------------------------------------------------------

export class Renderer {
  constructor(canvas, surface) {
    const gl = canvas.getContext("webgl2", { antialias: false });
    if (!gl) throw new Error("this browser has no WebGL2");
    this.gl = gl;
    this.canvas = canvas;
    this.surface = surface;
    this.program = link(gl, VERTEX_SHADER, FRAGMENT_SHADER);
    this.uniforms = {};
    for (const name of ["viewProjection", "pointSize", "colormap", "scaleMax", "eyeDirection", "markerColor", "roundPoints"]) {
      this.uniforms[name] = gl.getUniformLocation(this.program, name);
    }
    this.vao = gl.createVertexArray();
    gl.bindVertexArray(this.vao);
    this.buffers = {
      position: this.attribute("position", 3),
      normal: this.attribute("normal", 3),
      magnitude: this.attribute("magnitude", 1),
    };
    // The graspers: a few points of their own, drawn over everything.
    this.grasperVao = gl.createVertexArray();
    gl.bindVertexArray(this.grasperVao);
    this.grasperPositions = this.attribute("position", 3);
    gl.vertexAttrib3f(gl.getAttribLocation(this.program, "normal"), 0, 0, 1);
    gl.vertexAttrib1f(gl.getAttribLocation(this.program, "magnitude"), 0);
    gl.bindVertexArray(this.vao);
    this.triangles = this.indices(surface.triangles);
    this.graspRegionPoints = this.indices(surface.graspRegionPoints);
    this.fixedPoints = this.indices(surface.fixedPoints);
    gl.enable(gl.DEPTH_TEST);
    gl.clearColor(0.106, 0.118, 0.141, 1);
    // Pixels rendered per CSS pixel (× devicePixelRatio); lowered by `slowFrame` where drawing cannot
    // keep up (a software rasterizer, a weak GPU on a large screen), so deformation stays live.
    this.renderScale = 1;
    this.frameIntervals = [];
    this.lastDraw = null;
  }
  // Notes that a frame was drawn at `now` (ms) right after another; after ten slow ones in a row
  // (over 25 ms apart: below 40 frames per second), renders fewer pixels, down to half in each axis.
  timeFrame(now, previousDrawn) {
    if (previousDrawn && this.lastDraw !== null) this.frameIntervals.push(now - this.lastDraw);
    this.lastDraw = now;
    if (this.frameIntervals.length < 10) return;
    const slow = this.frameIntervals.every((ms) => ms > 25);
    this.frameIntervals = [];
    if (slow && this.renderScale > 0.5) this.renderScale = Math.max(0.5, this.renderScale * 0.8);
  }
  attribute(name, size) {
    const gl = this.gl;
    const buffer = gl.createBuffer();
    const location = gl.getAttribLocation(this.program, name);
    gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
    gl.enableVertexAttribArray(location);
    gl.vertexAttribPointer(location, size, gl.FLOAT, false, 0, 0);
    return buffer;
  }
  indices(array) {
    const gl = this.gl;
    const buffer = gl.createBuffer();
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, buffer);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, array, gl.STATIC_DRAW);
    return { buffer, count: array.length };
  }
  // Uploads the surface's current positions, normals and magnitudes.
  upload() {
    const gl = this.gl;
    for (const name of ["position", "normal", "magnitude"]) {
      gl.bindBuffer(gl.ARRAY_BUFFER, this.buffers[name]);
      gl.bufferData(gl.ARRAY_BUFFER, this.surface[name], gl.DYNAMIC_DRAW);
    }
  }
  // Framebuffer pixels per CSS pixel.
  pixelRatio() {
    return (window.devicePixelRatio || 1) * this.renderScale;
  }
  resize() {
    const ratio = this.pixelRatio();
    const width = Math.round(this.canvas.clientWidth * ratio);
    const height = Math.round(this.canvas.clientHeight * ratio);
    if (this.canvas.width !== width || this.canvas.height !== height) {
      this.canvas.width = width;
      this.canvas.height = height;
    }
  }
  // The surface and its markers, then `graspers` ({from, to, color, forceTip?}, world points) on top.
  draw(camera, scaleMax, graspers) {
    const gl = this.gl;
    this.resize();
    gl.viewport(0, 0, this.canvas.width, this.canvas.height);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.useProgram(this.program);
    gl.bindVertexArray(this.vao);
    const u = this.uniforms;
    gl.uniformMatrix4fv(u.viewProjection, false, camera.viewProjection(this.canvas.width / this.canvas.height));
    gl.uniform3fv(u.colormap, COLORMAP.flat());
    gl.uniform1f(u.scaleMax, scaleMax);
    gl.uniform3fv(u.eyeDirection, scale(camera.frame().forward, -1));
    this.drawElements(gl.TRIANGLES, this.triangles, 0, [0, 0, 0, 0]);
    this.drawElements(gl.POINTS, this.graspRegionPoints, 5, [1.0, 0.37, 0.84, 1]);
    this.drawElements(gl.POINTS, this.fixedPoints, 4, [0.56, 0.64, 0.75, 1]);
    this.drawGraspers(graspers);
  }
  drawGraspers(graspers) {
    const gl = this.gl;
    if (!graspers.length) return;
    gl.bindVertexArray(this.grasperVao);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.grasperPositions);
    // Three vertices per grasper: where it took hold, where it is, the tip of its force arrow.
    const vertices = graspers.flatMap((g) => [...g.from, ...g.to, ...(g.forceTip ?? g.to)]);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array(vertices), gl.DYNAMIC_DRAW);
    gl.disable(gl.DEPTH_TEST);
    graspers.forEach((g, i) => {
      gl.uniform4fv(this.uniforms.markerColor, g.color);
      this.setPoints(0);
      gl.drawArrays(gl.LINES, 3 * i, 2);
      this.setPoints(8);
      gl.drawArrays(gl.POINTS, 3 * i, 1);
      this.setPoints(14);
      gl.drawArrays(gl.POINTS, 3 * i + 1, 1);
      if (!g.forceTip) return;
      gl.uniform4fv(this.uniforms.markerColor, FORCE_COLOR);
      this.setPoints(0);
      gl.drawArrays(gl.LINES, 3 * i + 1, 2);
      this.setPoints(7);
      gl.drawArrays(gl.POINTS, 3 * i + 2, 1);
    });
    gl.enable(gl.DEPTH_TEST);
    gl.bindVertexArray(this.vao);
  }
  // Points of `size` CSS pixels, drawn round; 0: not points (triangles, lines).
  setPoints(size) {
    this.gl.uniform1f(this.uniforms.pointSize, size * this.pixelRatio());
    this.gl.uniform1i(this.uniforms.roundPoints, size > 0 ? 1 : 0);
  }
  drawElements(mode, indices, pointSize, markerColor) {
    const gl = this.gl;
    this.setPoints(pointSize);
    gl.uniform4fv(this.uniforms.markerColor, markerColor);
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, indices.buffer);
    gl.drawElements(mode, indices.count, gl.UNSIGNED_INT, 0);
  }
}

// The force arrows: the force each grasper exerts on the tissue, from where the grasper is.
const FORCE_COLOR = [0.35, 0.85, 1.0, 1];

function link(gl, vertexSource, fragmentSource) {
  const program = gl.createProgram();
  for (const [type, source] of [[gl.VERTEX_SHADER, vertexSource], [gl.FRAGMENT_SHADER, fragmentSource]]) {
    const shader = gl.createShader(type);
    gl.shaderSource(shader, source);
    gl.compileShader(shader);
    if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(shader));
    gl.attachShader(program, shader);
  }
  gl.linkProgram(program);
  if (!gl.getProgramParameter(program, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(program));
  return program;
}
