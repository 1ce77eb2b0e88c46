// DeformMaster playground page: draws the session the server streams
// (binary frames over /ws) as WebGL point sprites in three views, and sends
// the user's commands back as JSON. No libraries, nothing downloaded.
"use strict";

const FRAME_MAGIC = 0x46504d44; // "DMPF" little-endian
const HEADER_WORDS = 12;
const NEAR = 0.01, FAR = 20.0;
const HAND_COLORS = [[0.94, 0.63, 0.29], [0.35, 0.66, 0.90]];
const EXPERT_COLORS = [[0.31, 0.47, 0.65], [0.95, 0.56, 0.17], [0.35, 0.63, 0.31]];
const EXPERT_NAMES = ["Neo-Hookean", "corotated", "St. Venant–Kirchhoff"];
const HAND_KEYS = [
  { w: "f", s: "b", a: "l", d: "r", e: "u", q: "d" },
  { i: "f", k: "b", j: "l", l: "r", o: "u", u: "d" },
];

const $ = (id) => document.getElementById(id);

// ---------- small vector helpers (world frame) ----------
const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const norm = (a) => Math.hypot(a[0], a[1], a[2]);
const unit = (a) => { const n = norm(a) || 1; return scale(a, 1 / n); };

// A camera in OpenCV axes: rows of R are the camera's right, down, forward.
function cameraFromPage(c) {
  const m = c.world_to_camera;
  return {
    width: c.width, height: c.height, fx: c.fx, fy: c.fy, cx: c.cx, cy: c.cy,
    R: [m[0].slice(0, 3), m[1].slice(0, 3), m[2].slice(0, 3)],
    t: [m[0][3], m[1][3], m[2][3]],
  };
}
function cameraCentre(cam) {
  const R = cam.R, t = cam.t; // centre = -R^T t
  return [0, 1, 2].map((a) => -(R[0][a] * t[0] + R[1][a] * t[1] + R[2][a] * t[2]));
}
function cameraAxis(cam, row) { return cam.R[row].slice(); }
function lookAt(cam, eye, target, up) {
  const f = unit(sub(target, eye));
  let r = cross(f, up);
  if (norm(r) < 1e-9) r = [1, 0, 0];
  r = unit(r);
  const d = cross(f, r);
  const R = [r, d, f];
  const t = R.map((row) => -dot(row, eye));
  return Object.assign({}, cam, { R, t });
}

// ---------- WebGL point-sprite view ----------
const VERTEX_SHADER = `
attribute vec3 position; attribute vec3 color; attribute float radius; attribute float opacity;
uniform vec3 r0; uniform vec3 r1; uniform vec3 r2; uniform vec3 tr;
uniform vec4 intr; uniform vec2 size; uniform float pointScale;
varying vec3 vColor; varying float vOpacity;
void main() {
  vec3 c = vec3(dot(r0, position), dot(r1, position), dot(r2, position)) + tr;
  float z = max(c.z, ${NEAR.toFixed(3)});
  float u = intr.x * c.x / z + intr.z, v = intr.y * c.y / z + intr.w;
  float a = (${FAR.toFixed(1)} + ${NEAR.toFixed(3)}) / (${FAR.toFixed(1)} - ${NEAR.toFixed(3)});
  float b = -2.0 * ${FAR.toFixed(1)} * ${NEAR.toFixed(3)} / (${FAR.toFixed(1)} - ${NEAR.toFixed(3)});
  gl_Position = c.z > ${NEAR.toFixed(3)} ? vec4((2.0 * u / size.x - 1.0) * z, (1.0 - 2.0 * v / size.y) * z, a * z + b, z) : vec4(0.0, 0.0, -2.0, 1.0);
  gl_PointSize = clamp(2.0 * radius * intr.y / z * pointScale, 1.0, 64.0);
  vColor = color; vOpacity = opacity;
}`;
const FRAGMENT_SHADER = `
precision mediump float;
varying vec3 vColor; varying float vOpacity;
void main() {
  vec2 d = gl_PointCoord * 2.0 - 1.0;
  float r2 = dot(d, d);
  if (r2 > 1.0 || vOpacity * exp(-2.0 * r2) < 0.3) discard;
  float shade = 0.78 + 0.22 * sqrt(1.0 - r2);
  gl_FragColor = vec4(vColor * shade, 1.0);
}`;
const LINE_VERTEX = `
attribute vec3 position; uniform vec3 r0; uniform vec3 r1; uniform vec3 r2; uniform vec3 tr;
uniform vec4 intr; uniform vec2 size;
void main() {
  vec3 c = vec3(dot(r0, position), dot(r1, position), dot(r2, position)) + tr;
  float z = max(c.z, ${NEAR.toFixed(3)});
  float a = (${FAR.toFixed(1)} + ${NEAR.toFixed(3)}) / (${FAR.toFixed(1)} - ${NEAR.toFixed(3)});
  float b = -2.0 * ${FAR.toFixed(1)} * ${NEAR.toFixed(3)} / (${FAR.toFixed(1)} - ${NEAR.toFixed(3)});
  gl_Position = vec4((2.0 * (intr.x * c.x / z + intr.z) / size.x - 1.0) * z, (1.0 - 2.0 * (intr.y * c.y / z + intr.w) / size.y) * z, a * z + b, z);
}`;
const LINE_FRAGMENT = `precision mediump float; void main() { gl_FragColor = vec4(0.24, 0.26, 0.31, 1.0); }`;

function compile(gl, vs, fs) {
  const program = gl.createProgram();
  for (const [type, src] of [[gl.VERTEX_SHADER, vs], [gl.FRAGMENT_SHADER, fs]]) {
    const s = gl.createShader(type);
    gl.shaderSource(s, src);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
    gl.attachShader(program, s);
  }
  gl.linkProgram(program);
  if (!gl.getProgramParameter(program, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(program));
  return program;
}

class View {
  constructor(canvas, camera) {
    this.canvas = canvas;
    this.camera = camera;
    const gl = canvas.getContext("webgl", { antialias: true, preserveDrawingBuffer: true });
    if (!gl) throw new Error("WebGL is not available in this browser");
    this.gl = gl;
    this.sprites = compile(gl, VERTEX_SHADER, FRAGMENT_SHADER);
    this.lines = compile(gl, LINE_VERTEX, LINE_FRAGMENT);
    this.buffers = {};
    for (const name of ["position", "color", "radius", "opacity", "handPosition", "handColor", "handRadius", "handOpacity", "floor"]) {
      this.buffers[name] = gl.createBuffer();
    }
    gl.enable(gl.DEPTH_TEST);
    gl.clearColor(0.05, 0.06, 0.075, 1);
  }
  upload(name, data) {
    const gl = this.gl;
    gl.bindBuffer(gl.ARRAY_BUFFER, this.buffers[name]);
    gl.bufferData(gl.ARRAY_BUFFER, data, gl.DYNAMIC_DRAW);
  }
  setCameraUniforms(program) {
    const gl = this.gl, c = this.camera;
    const u = (n) => gl.getUniformLocation(program, n);
    gl.uniform3fv(u("r0"), c.R[0]); gl.uniform3fv(u("r1"), c.R[1]); gl.uniform3fv(u("r2"), c.R[2]);
    gl.uniform3fv(u("tr"), c.t);
    gl.uniform4f(u("intr"), c.fx, c.fy, c.cx, c.cy);
    gl.uniform2f(u("size"), c.width, c.height);
  }
  attribute(program, name, buffer, size) {
    const gl = this.gl, loc = gl.getAttribLocation(program, name);
    if (loc < 0) return;
    gl.bindBuffer(gl.ARRAY_BUFFER, this.buffers[buffer]);
    gl.enableVertexAttribArray(loc);
    gl.vertexAttribPointer(loc, size, gl.FLOAT, false, 0, 0);
  }
  draw(count, floorVertices) {
    const gl = this.gl;
    gl.viewport(0, 0, this.canvas.width, this.canvas.height);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.useProgram(this.lines);
    this.setCameraUniforms(this.lines);
    this.attribute(this.lines, "position", "floor", 3);
    gl.drawArrays(gl.LINES, 0, floorVertices);
    gl.useProgram(this.sprites);
    this.setCameraUniforms(this.sprites);
    gl.uniform1f(gl.getUniformLocation(this.sprites, "pointScale"), 1.0);
    this.attribute(this.sprites, "position", "position", 3);
    this.attribute(this.sprites, "color", "color", 3);
    this.attribute(this.sprites, "radius", "radius", 1);
    this.attribute(this.sprites, "opacity", "opacity", 1);
    gl.drawArrays(gl.POINTS, 0, count);
    this.attribute(this.sprites, "position", "handPosition", 3);
    this.attribute(this.sprites, "color", "handColor", 3);
    this.attribute(this.sprites, "radius", "handRadius", 1);
    this.attribute(this.sprites, "opacity", "handOpacity", 1);
    gl.drawArrays(gl.POINTS, 0, 2);
  }
}

// ---------- colour maps ----------
function viridis(x) {
  const stops = [[0.267, 0.005, 0.329], [0.229, 0.322, 0.546], [0.128, 0.567, 0.551], [0.369, 0.789, 0.383], [0.993, 0.906, 0.144]];
  const s = Math.min(Math.max(x, 0), 1) * (stops.length - 1);
  const i = Math.min(Math.floor(s), stops.length - 2), f = s - i;
  return [0, 1, 2].map((a) => stops[i][a] * (1 - f) + stops[i + 1][a] * f);
}

// ---------- the page ----------
const app = {
  scene: null, views: [], count: 0, frame: 0, simMs: 0,
  hands: [[0, 0, 0], [0, 0, 0]], attached: 0,
  material: null, nuTouched: false,
  keys: new Set(), handVelocity: [[0, 0, 0], [0, 0, 0]],
  drawnFrames: 0, receivedFrames: 0, lastFpsTime: performance.now(), dirty: false,
  socket: null, orbit: null, recording: false,
};

function message(text, isError) {
  const el = $("message");
  el.textContent = text;
  el.className = isError ? "error" : "";
}

function send(command) {
  if (app.socket && app.socket.readyState === WebSocket.OPEN) app.socket.send(JSON.stringify(command));
}

function floorLines(scene) {
  const up = scene.up, c = scene.centre;
  let e0 = Math.abs(up[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0];
  e0 = unit(sub(e0, scale(up, dot(e0, up))));
  const e1 = cross(up, e0);
  const base = add(c, scale(up, scene.floor_height - dot(c, up)));
  const half = 2.0 * scene.extent, n = 10, out = [];
  for (let i = -n; i <= n; i++) {
    const s = (i / n) * half;
    for (const [a, b] of [[e0, e1], [e1, e0]]) {
      out.push(...add(base, add(scale(a, s), scale(b, -half))), ...add(base, add(scale(a, s), scale(b, half))));
    }
  }
  return new Float32Array(out);
}

function spriteColors() {
  const s = app.scene, n = s.sprites.count, out = new Float32Array(3 * n);
  const mode = $("show-youngs").checked ? "youngs" : $("show-expert").checked ? "expert" : "appearance";
  const [lo, hi] = s.youngs_log10_range;
  for (let i = 0; i < n; i++) {
    let c;
    if (mode === "youngs") c = viridis((Math.log10(s.sprite_youngs_pa[i] * app.material.e_scale) - lo) / (hi - lo));
    else if (mode === "expert") c = EXPERT_COLORS[s.sprite_expert[i]];
    else c = [s.sprites.colors[3 * i], s.sprites.colors[3 * i + 1], s.sprites.colors[3 * i + 2]];
    out.set(c, 3 * i);
  }
  const legend = $("legend");
  if (mode === "expert") {
    legend.innerHTML = EXPERT_NAMES.map((name, k) =>
      `<span class="swatch" style="background:rgb(${EXPERT_COLORS[k].map((v) => Math.round(255 * v)).join(",")})"></span>${name}`).join("");
  } else if (mode === "youngs") {
    legend.textContent = `log10 E from ${lo.toFixed(1)} (purple) to ${hi.toFixed(1)} Pa (yellow), scale included`;
  } else legend.textContent = s.sprites.kind === "gaussian_splats" ? "splat colours" : "particle colours";
  return out;
}

function refreshColors() {
  const colors = spriteColors();
  for (const v of app.views) v.upload("color", colors);
  app.dirty = true;
}

function setupViews(scene) {
  const canvases = ["main-canvas", "novel1-canvas", "novel2-canvas"].map($);
  app.views = canvases.map((canvas, k) => new View(canvas, cameraFromPage(scene.cameras[k])));
  const s = scene.sprites, floor = floorLines(scene);
  const handRadius = new Float32Array([0.012, 0.012]);
  for (const v of app.views) {
    v.upload("radius", new Float32Array(s.radii));
    v.upload("opacity", new Float32Array(s.opacities));
    v.upload("handColor", new Float32Array([...HAND_COLORS[0], ...HAND_COLORS[1]]));
    v.upload("handRadius", handRadius);
    v.upload("handOpacity", new Float32Array([1, 1]));
    v.upload("floor", floor);
    v.floorVertices = floor.length / 3;
  }
  const main = app.views[0].camera, eye = cameraCentre(main), rel = sub(eye, scene.centre);
  let e0 = Math.abs(scene.up[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0];
  e0 = unit(sub(e0, scale(scene.up, dot(e0, scene.up))));
  const e1 = cross(scene.up, e0), h = dot(rel, scene.up), r = norm(rel);
  app.orbit = { e0, e1, radius: r, azimuth: Math.atan2(dot(rel, e1), dot(rel, e0)), elevation: Math.asin(h / r) };
  refreshColors();
}

function orbitMain(dAzimuth, dElevation) {
  const o = app.orbit, s = app.scene;
  o.azimuth += dAzimuth;
  o.elevation = Math.min(Math.max(o.elevation + dElevation, -0.2), 1.45);
  const horizontal = add(scale(o.e0, Math.cos(o.azimuth)), scale(o.e1, Math.sin(o.azimuth)));
  const dir = add(scale(horizontal, Math.cos(o.elevation)), scale(s.up, Math.sin(o.elevation)));
  const eye = add(s.centre, scale(dir, o.radius));
  app.views[0].camera = lookAt(app.views[0].camera, eye, s.centre, s.up);
  updateHandVelocities(true);
  app.dirty = true;
}

function onFrame(buffer) {
  const view = new DataView(buffer);
  if (buffer.byteLength < 4 * HEADER_WORDS || view.getUint32(0, true) !== FRAME_MAGIC) return;
  app.frame = view.getUint32(4, true);
  app.simMs = view.getFloat32(8, true);
  for (let k = 0; k < 2; k++) for (let a = 0; a < 3; a++) app.hands[k][a] = view.getFloat32(12 + 12 * k + 4 * a, true);
  app.attached = view.getUint32(36, true);
  const count = view.getUint32(44, true);
  const positions = new Float32Array(buffer, 4 * HEADER_WORDS, 3 * count);
  // Released hands are drawn small and faded toward the background.
  const handPositions = new Float32Array([...app.hands[0], ...app.hands[1]]);
  for (const v of app.views) {
    v.upload("position", positions);
    v.upload("handPosition", handPositions);
    v.upload("handRadius", new Float32Array([0, 1].map((k) => (app.attached >> k) & 1 ? 0.014 : 0.009)));
  }
  app.count = count;
  app.receivedFrames++;
  app.dirty = true;
}

function render() {
  if (app.dirty && app.views.length) {
    for (const v of app.views) v.draw(app.count, v.floorVertices);
    app.drawnFrames++;
    app.dirty = false;
    $("frame").textContent = app.frame;
    $("sim-ms").textContent = app.simMs.toFixed(1);
    for (let k = 0; k < 2; k++) {
      const held = (app.attached >> k) & 1;
      $(`hand${k}-status`).textContent = `hand ${k + 1}: ${held ? "holding" : "free"} at (${app.hands[k].map((c) => c.toFixed(3)).join(", ")})`;
    }
  }
  const now = performance.now();
  if (now - app.lastFpsTime >= 500) {
    const seconds = (now - app.lastFpsTime) / 1000;
    $("fps").textContent = (app.drawnFrames / seconds).toFixed(1);
    $("fps").dataset.updates = String(Number($("fps").dataset.updates || 0) + 1);
    $("fps").title = `${(app.receivedFrames / seconds).toFixed(1)} simulation frames/s received`;
    app.drawnFrames = 0; app.receivedFrames = 0; app.lastFpsTime = now;
  }
  requestAnimationFrame(render);
}

// ---------- input ----------
function handBasis() {
  const cam = app.views[0].camera, up = app.scene.up;
  let forward = cameraAxis(cam, 2);
  forward = unit(sub(forward, scale(up, dot(forward, up))));
  let right = cameraAxis(cam, 0);
  right = unit(sub(right, scale(up, dot(right, up))));
  return { f: forward, b: scale(forward, -1), r: right, l: scale(right, -1), u: up, d: scale(up, -1) };
}

function updateHandVelocities(force) {
  if (!app.scene) return;
  const basis = handBasis(), speed = parseFloat($("speed").value);
  HAND_KEYS.forEach((map, k) => {
    let v = [0, 0, 0];
    for (const key of app.keys) if (map[key]) v = add(v, basis[map[key]]);
    v = norm(v) > 0 ? scale(unit(v), speed) : v;
    const old = app.handVelocity[k];
    if (force || v.some((c, a) => Math.abs(c - old[a]) > 1e-9)) {
      app.handVelocity[k] = v;
      send({ type: "hand_velocity", hand: k, velocity: v });
    }
  });
}

function isHandKey(key) { return HAND_KEYS.some((m) => key in m); }

document.addEventListener("keydown", (e) => {
  const key = e.key.toLowerCase();
  if (!isHandKey(key) || e.ctrlKey || e.metaKey) return;
  app.keys.add(key);
  updateHandVelocities(false);
  e.preventDefault();
});
document.addEventListener("keyup", (e) => {
  app.keys.delete(e.key.toLowerCase());
  updateHandVelocities(false);
});
window.addEventListener("blur", () => { app.keys.clear(); updateHandVelocities(false); });

function setupMainCanvas() {
  const canvas = $("main-canvas");
  let drag = null;
  canvas.addEventListener("contextmenu", (e) => e.preventDefault());
  canvas.addEventListener("mousedown", (e) => {
    if (e.button === 2 || e.altKey) drag = { x: e.clientX, y: e.clientY };
  });
  window.addEventListener("mousemove", (e) => {
    if (!drag) return;
    orbitMain(-(e.clientX - drag.x) * 0.01, (e.clientY - drag.y) * 0.01);
    drag = { x: e.clientX, y: e.clientY };
  });
  window.addEventListener("mouseup", () => { drag = null; });
  canvas.addEventListener("click", (e) => {
    if (e.altKey || !app.scene) return;
    const rect = canvas.getBoundingClientRect();
    const u = ((e.clientX - rect.left) * canvas.width) / rect.width;
    const v = ((e.clientY - rect.top) * canvas.height) / rect.height;
    const cam = app.views[0].camera;
    const dCam = [(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1];
    const direction = [0, 1, 2].map((a) => cam.R[0][a] * dCam[0] + cam.R[1][a] * dCam[1] + cam.R[2][a] * dCam[2]);
    const checked = document.querySelector('input[name="grab-hand"]:checked');
    const hand = e.shiftKey ? 1 : parseInt(checked ? checked.value : "0", 10);
    send({ type: "grab", hand, origin: cameraCentre(cam), direction });
  });
}

let materialTimer = null;
function sendMaterial() {
  const eScale = Math.pow(10, parseFloat($("e-scale").value));
  const nu = app.nuTouched ? parseFloat($("nu").value) : null;
  const damping = parseFloat($("damping").value);
  app.material = { e_scale: eScale, nu, damping };
  $("e-scale-out").textContent = `×${eScale.toFixed(2)}`;
  $("nu-out").textContent = nu === null ? "fitted" : nu.toFixed(2);
  $("damping-out").textContent = `${damping.toFixed(1)}/s`;
  if ($("show-youngs").checked) refreshColors();
  clearTimeout(materialTimer);
  materialTimer = setTimeout(() => send({ type: "material", e_scale: eScale, nu, damping }), 120);
}

function setupControls(scene) {
  const m = scene.material;
  app.material = m;
  $("e-scale").value = Math.log10(m.e_scale);
  $("nu").min = scene.nu_range[0]; $("nu").max = scene.nu_range[1];
  $("nu").value = m.nu === null ? scene.nu_median : m.nu;
  $("damping").min = scene.damping_range[0]; $("damping").max = scene.damping_range[1];
  $("damping").value = m.damping;
  $("e-scale").addEventListener("input", sendMaterial);
  $("nu").addEventListener("input", () => { app.nuTouched = true; sendMaterial(); });
  $("damping").addEventListener("input", sendMaterial);
  $("e-scale-out").textContent = `×${m.e_scale.toFixed(2)}`;
  $("damping-out").textContent = `${m.damping.toFixed(1)}/s`;
  $("show-expert").addEventListener("change", () => { if ($("show-expert").checked) $("show-youngs").checked = false; refreshColors(); });
  $("show-youngs").addEventListener("change", () => { if ($("show-youngs").checked) $("show-expert").checked = false; refreshColors(); });
  $("release0").addEventListener("click", () => send({ type: "release", hand: 0 }));
  $("release1").addEventListener("click", () => send({ type: "release", hand: 1 }));
  $("speed").addEventListener("input", () => {
    $("speed-out").textContent = `${parseFloat($("speed").value).toFixed(2)} m/s`;
    updateHandVelocities(true);
  });
  $("reset").addEventListener("click", () => {
    send({ type: "reset" });
    if (app.recording) { app.recording = false; $("record").textContent = "● Record"; $("record").classList.remove("recording"); }
  });
  $("record").addEventListener("click", () => {
    app.recording = !app.recording;
    send({ type: app.recording ? "record_start" : "record_stop" });
    $("record").textContent = app.recording ? "■ Stop & save" : "● Record";
    $("record").classList.toggle("recording", app.recording);
    if (!app.recording) message("writing the bundle…");
  });
}

async function pollState() {
  try {
    const state = await (await fetch("/api/state")).json();
    $("substeps").textContent = `${state.substeps_per_frame} substeps/frame · grid ${state.grid}³ · ${(1000 * state.frame_dt).toFixed(1)} ms simulated per frame`;
    if (state.last_error && state.last_error !== app.lastError) { app.lastError = state.last_error; message(state.last_error, true); }
  } catch (e) { /* the server went away; the socket handler reports it */ }
  setTimeout(pollState, 700);
}

function connect() {
  const socket = new WebSocket(`ws://${location.host}/ws`);
  socket.binaryType = "arraybuffer";
  socket.onmessage = (e) => {
    if (typeof e.data === "string") {
      const reply = JSON.parse(e.data);
      message(reply.message, !reply.ok);
    } else onFrame(e.data);
  };
  socket.onclose = () => { message("connection to the server lost; retrying…", true); setTimeout(connect, 1000); };
  socket.onopen = () => { message("connected"); updateHandVelocities(true); };
  app.socket = socket;
}

async function main() {
  try {
    const scene = await (await fetch("/api/scene")).json();
    app.scene = scene;
    $("model-info").textContent = `${scene.sprites.count} ${scene.sprites.kind === "gaussian_splats" ? "Gaussian splats" : "particles"}`;
    setupViews(scene);
    setupControls(scene);
    setupMainCanvas();
    connect();
    pollState();
    requestAnimationFrame(render);
  } catch (e) {
    message(`could not start: ${e.message}`, true);
  }
}
main();
