// The viewer: loads the served mesh and models, turns mouse drags into grasps, asks the server for
// the deformation of the surface (one request in flight, always for the latest grasps) and shows it.
// `window.nakViewer` exposes its state to the browser test (tests/python/test_viewer.py).

import { DeformationClient } from "./grpc_web.js";
import { OrbitCamera, Renderer, Surface, add, dot, scale, sub } from "./scene.js";

const $ = (id) => document.getElementById(id);
const MM = 1e3;
const HANDLE_PIXELS = 14;
const RATE_WINDOW_MS = 1000;

const state = {
  ready: false,
  error: null,
  model: "",
  radius: 0.01,
  // Up to two graspers: { point: rest-frame point (m), displacement: (m) }.
  graspers: [null, null],
  sequence: 0,
  inFlight: false,
  dirty: false,
  // Timestamps (ms) of applied answers, and [timestamp, round trip] (ms), for the readout and the test.
  applied: [],
  roundTrips: [],
  framesDrawn: 0,
  drewLastFrame: false,
  needsDraw: true,
  scaleMax: 0.001,
};

const client = new DeformationClient(new URLSearchParams(location.hash.slice(1)).get("token"));
let surface;
let camera;
let renderer;

async function start() {
  const [mesh, models] = await Promise.all([client.getMesh(), client.listModels()]);
  surface = new Surface(mesh);
  camera = new OrbitCamera(surface.center, surface.radius);
  renderer = new Renderer($("view"), surface);
  renderer.upload();
  $("mesh-name").textContent = `${mesh.name}: ${mesh.nodeCount} nodes, ${surface.count} on the surface`;
  const picker = $("model");
  for (const model of models) {
    const option = document.createElement("option");
    option.value = model.name;
    const dcm = testDcm(model);
    const score = Number.isFinite(dcm) ? `DCM ${dcm.toFixed(1)} %` : "";
    option.textContent = [model.name, model.kind, model.regime, score].filter(Boolean).join(" · ");
    picker.append(option);
  }
  // The most accurate model on held-out data first; the Kelvinlet prior when none has a score.
  const scored = models.filter((m) => Number.isFinite(testDcm(m)));
  const best = scored.sort((a, b) => testDcm(b) - testDcm(a))[0];
  state.model = best?.name ?? models.find((m) => m.name === "kelvinlet")?.name ?? models[0]?.name ?? "";
  picker.value = state.model;
  picker.addEventListener("change", () => {
    state.model = picker.value;
    requestUpdate();
  });
  $("radius").addEventListener("input", (event) => {
    state.radius = Number(event.target.value) / MM;
    $("radius-value").textContent = event.target.value;
    requestUpdate();
  });
  $("release").addEventListener("click", release);
  window.addEventListener("keydown", (event) => {
    if (event.key === "Escape") release();
  });
  listenToPointer($("view"));
  window.addEventListener("resize", () => { state.needsDraw = true; });
  state.ready = true;
  requestAnimationFrame(frame);
}

// The model's DCM (%) on its dataset's test split, measured through nak eval (manifest [metrics]).
function testDcm(model) {
  return Number.parseFloat(model.metadata["metrics.dcm_combined"]);
}

function release() {
  state.graspers = [null, null];
  requestUpdate();
}

// ---- talking to the server ---------------------------------------------------------------------

function requestUpdate() {
  state.dirty = true;
  pump();
}

// Sends the latest grasps when nothing is in flight: a drag never queues stale requests, and the
// update rate is what the server and the page can sustain.
async function pump() {
  if (state.inFlight || !state.dirty) return;
  state.dirty = false;
  const grasps = state.graspers.filter(Boolean).map((g) => ({ ...g, radius: state.radius }));
  if (grasps.length === 0) {
    show(null);
    return;
  }
  state.inFlight = true;
  const sequence = ++state.sequence;
  const sent = performance.now();
  try {
    const answer = await client.predict({ model: state.model, sequence, grasps });
    const received = performance.now();
    note(state.roundTrips, [received, received - sent], 2000);
    show(answer);
    readout(answer);
    setStatus(null);
  } catch (error) {
    setStatus(error.message);
  } finally {
    state.inFlight = false;
    pump();
  }
}

function note(list, value, keep) {
  list.push(value);
  if (list.length > keep) list.splice(0, list.length - keep);
}

// Applies an answer (null: the organ at rest).
function show(answer) {
  surface.update(answer ? answer.displacements : null);
  renderer.upload();
  note(state.applied, performance.now(), 2000);
  state.scaleMax = niceScale(surface.largest, state.scaleMax);
  state.needsDraw = true;
}

// A round colour-scale maximum (1, 2 or 5 × 10^k m, at least 1 mm) that changes only when the field
// leaves it or shrinks below the next round value down, so the colours do not flicker during a drag.
function niceScale(largest, current) {
  if (largest <= current && largest > current / 2.5) return current;
  const target = Math.max(largest, 0.001);
  const power = 10 ** Math.floor(Math.log10(target));
  return [1, 2, 5, 10].map((m) => m * power).find((v) => v >= target);
}

function readout(answer) {
  const us = (v) => `${v.toFixed(0)} µs`;
  // The median of the last second's round trips: one answer's is mostly noise.
  const now = performance.now();
  const recent = state.roundTrips.filter(([t]) => now - t <= RATE_WINDOW_MS).map(([, ms]) => ms).sort((a, b) => a - b);
  $("rtt").textContent = `${(recent[Math.floor(recent.length / 2)] * 1e3).toFixed(0)} µs`;
  $("server-total").textContent = us(answer.timing.total);
  $("server-resolve").textContent = us(answer.timing.resolve);
  $("server-queue").textContent = us(answer.timing.queue);
  $("server-prior").textContent = us(answer.timing.prior);
  $("server-network").textContent = us(answer.timing.network);
  $("held").textContent = String(answer.interactionPoints);
  $("largest").textContent = `${(surface.largest * MM).toFixed(1)} mm`;
  $("forces").textContent = answer.graspForces.length
    ? answer.graspForces.map((f) => `${Math.hypot(...f).toFixed(2)} N`).join(", ")
    : "–";
}

// Changes an element's text only when it differs: a DOM write every frame would relayout the panel.
function setText(id, value) {
  const element = $(id);
  if (element.textContent !== value) element.textContent = value;
}

function setStatus(message) {
  state.error = message;
  const panel = $("status");
  panel.style.display = message ? "block" : "none";
  panel.textContent = message ?? "";
}

// ---- pointer -----------------------------------------------------------------------------------

function listenToPointer(canvas) {
  let gesture = null;
  canvas.addEventListener("contextmenu", (event) => event.preventDefault());
  canvas.addEventListener("pointerdown", (event) => {
    canvas.setPointerCapture(event.pointerId);
    gesture = event.button === 0 ? grab(event) : null;
    gesture ??= { orbit: true, x: event.clientX, y: event.clientY };
  });
  canvas.addEventListener("pointermove", (event) => {
    if (!gesture) return;
    if (gesture.orbit) {
      camera.orbit(event.clientX - gesture.x, event.clientY - gesture.y);
      gesture.x = event.clientX;
      gesture.y = event.clientY;
      state.needsDraw = true;
      return;
    }
    const hit = planeHit(event, gesture.plane);
    if (!hit) return;
    state.graspers[gesture.index].displacement = add(gesture.start, sub(hit, gesture.plane.point));
    requestUpdate();
  });
  const end = () => { gesture = null; };
  canvas.addEventListener("pointerup", end);
  canvas.addEventListener("pointercancel", end);
  canvas.addEventListener("wheel", (event) => {
    event.preventDefault();
    camera.zoom(Math.exp(event.deltaY * 0.001));
    state.needsDraw = true;
  }, { passive: false });
}

// A drag that moves a grasper: an existing one whose dot is under the pointer, else a new one where
// the pointer meets the surface (the second with Shift). Null when the pointer misses the organ.
function grab(event) {
  const { width, height } = viewport();
  const handle = state.graspers.findIndex((g) => {
    const at = g && camera.project(add(g.point, g.displacement), width, height);
    return at && Math.hypot(at[0] - event.clientX, at[1] - event.clientY) < HANDLE_PIXELS;
  });
  let index = handle;
  if (index < 0) {
    const pick = surface.pick(camera.ray(event.clientX, event.clientY, width, height));
    if (!pick) return null;
    index = event.shiftKey ? 1 : 0;
    // Held where the surface is now, so placing a grasper on a deformed organ moves nothing.
    state.graspers[index] = { point: surface.at(pick, surface.rest), displacement: surface.at(pick, surface.displacement) };
    requestUpdate();
  }
  const grasper = state.graspers[index];
  // The grasper moves in the plane through it that faces the camera.
  const plane = { point: add(grasper.point, grasper.displacement), normal: camera.frame().forward };
  return { index, plane, start: grasper.displacement };
}

function planeHit(event, plane) {
  const { width, height } = viewport();
  const ray = camera.ray(event.clientX, event.clientY, width, height);
  const along = dot(ray.direction, plane.normal);
  if (Math.abs(along) < 1e-9) return null;
  const distance = dot(sub(plane.point, ray.origin), plane.normal) / along;
  return distance > 0 ? add(ray.origin, scale(ray.direction, distance)) : null;
}

function viewport() {
  const canvas = $("view");
  return { width: canvas.clientWidth, height: canvas.clientHeight };
}

// ---- drawing -----------------------------------------------------------------------------------

function frame() {
  const now = performance.now();
  const recent = state.applied.filter((t) => now - t <= RATE_WINDOW_MS).length;
  setText("rate", `${recent} /s`);
  setText("render-scale", `${Math.round(renderer.renderScale * 100)} %`);
  const drawing = state.needsDraw;
  if (drawing) {
    state.needsDraw = false;
    renderer.timeFrame(now, state.drewLastFrame);
    renderer.draw(camera, state.scaleMax);
    drawGraspers();
    $("scale-max").textContent = `${(state.scaleMax * MM).toFixed(0)} mm`;
    state.framesDrawn++;
  }
  state.drewLastFrame = drawing;
  requestAnimationFrame(frame);
}

// Each grasper: a ring where it took hold, a dot where it is now, and the line between them.
function drawGraspers() {
  const overlay = $("overlay");
  const { width, height } = viewport();
  // Resizing a canvas reallocates it: only when the window changed.
  if (overlay.width !== width || overlay.height !== height) {
    overlay.width = width;
    overlay.height = height;
  }
  const context = overlay.getContext("2d");
  context.clearRect(0, 0, width, height);
  context.lineWidth = 2;
  state.graspers.forEach((g, i) => {
    if (!g) return;
    const from = camera.project(g.point, width, height);
    const to = camera.project(add(g.point, g.displacement), width, height);
    if (!from || !to) return;
    context.strokeStyle = context.fillStyle = i === 0 ? "#ffffff" : "#ffb347";
    context.beginPath();
    context.arc(from[0], from[1], 5, 0, 2 * Math.PI);
    context.moveTo(from[0], from[1]);
    context.lineTo(to[0], to[1]);
    context.stroke();
    context.beginPath();
    context.arc(to[0], to[1], 7, 0, 2 * Math.PI);
    context.fill();
  });
}

// ---- for the browser test ----------------------------------------------------------------------

window.nakViewer = {
  get ready() { return state.ready; },
  get error() { return state.error; },
  get busy() { return state.inFlight || state.dirty; },
  get updates() { return state.applied.length; },
  get framesDrawn() { return state.framesDrawn; },
  get renderScale() { return renderer.renderScale; },
  get graspers() { return state.graspers.filter(Boolean).length; },
  // Answers applied per second between the first and last of those applied after `since` (ms).
  updateRate(since) {
    const times = state.applied.filter((t) => t >= since);
    return times.length < 2 ? 0 : ((times.length - 1) * 1000) / (times[times.length - 1] - times[0]);
  },
  // Round trips (ms) of the answers received after `since` (ms).
  roundTripsMs(since) { return state.roundTrips.filter(([t]) => t >= since).map(([, ms]) => ms); },
  // Where grasper `i`'s dot is on screen (CSS pixels), or null.
  handle(i) {
    const g = state.graspers[i];
    const { width, height } = viewport();
    return g ? camera.project(add(g.point, g.displacement), width, height) : null;
  },
  // Whether the organ is under pixel (x, y).
  hits(x, y) {
    const { width, height } = viewport();
    return surface.pick(camera.ray(x, y, width, height)) !== null;
  },
};

start().catch((error) => {
  setStatus(`cannot start: ${error.message}`);
  console.error(error);
});
