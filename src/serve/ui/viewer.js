// The viewer: loads the served mesh and models, turns mouse drags into grasps, asks the server for
// the deformation of the surface (one request in flight, always for the latest grasps) and shows it.
// `window.nakViewer` exposes its state to the browser test (tests/python/test_viewer.py).

import { DeformationClient } from "./grpc_web.js";
import { OrbitCamera, Renderer, Surface, add, dot, scale, sub } from "./scene.js";

const $ = (id) => document.getElementById(id);
const MM = 1e3;
const HANDLE_PIXELS = 14;
const RATE_WINDOW_MS = 1000;
const READOUT_INTERVAL_MS = 250;

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
  // The answer the next frame shows (undefined: nothing new; null: the organ at rest), and the one
  // on screen, for the readout (refreshed at `readoutAt`, ms).
  latest: undefined,
  shown: null,
  readoutAt: 0,
  // Timestamps (ms) of answers received and of frames that showed a new one (answers arriving
  // within one frame share it), and [timestamp, round trip] (ms), for the readout and the test.
  received: [],
  deformationFrames: [],
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
  const [mesh, { models, defaultModel }] = await Promise.all([client.getMesh(), client.listModels()]);
  surface = new Surface(mesh);
  camera = new OrbitCamera(surface.center, surface.radius);
  renderer = new Renderer($("view"), surface);
  renderer.upload();
  $("mesh-name").textContent = `${mesh.name}: ${mesh.nodeCount} nodes, ${surface.count} on the surface`;
  const picker = $("model");
  // The server's default, unless it is the Kelvinlet (what an unnamed request gets without --regime).
  const chosen = defaultModel && defaultModel !== "kelvinlet" ? defaultModel : undefined;
  for (const model of byRegimeThenAccuracy(models, chosen)) {
    const option = document.createElement("option");
    option.value = model.name;
    const dcm = testDcm(model);
    const score = Number.isFinite(dcm) ? `DCM ${dcm.toFixed(1)} %` : "";
    option.textContent = [model.name, model.kind, model.regime, score].filter(Boolean).join(" · ");
    picker.append(option);
  }
  // The server's own default when it chose one (`nak serve --regime`: the most accurate model of the
  // regime its organ is in); else the most accurate model on held-out data; when none has a score (a
  // new organ, served with its Green's functions but no network yet), an exact model before the
  // Kelvinlet prior.
  const scored = models.filter((m) => Number.isFinite(testDcm(m)));
  const best = scored.sort((a, b) => testDcm(b) - testDcm(a))[0];
  const fallback = models.find((m) => m.kind === "exact") ?? models.find((m) => m.name === "kelvinlet");
  state.model = chosen ?? best?.name ?? fallback?.name ?? models[0]?.name ?? "";
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

// Each regime's models together, the server's default's regime first (`nak serve --regime`), the most
// accurate on held-out data first and unscored ones (the prior, the exact models) after them, in the
// server's order.
function byRegimeThenAccuracy(models, chosen) {
  const preferred = models.find((m) => m.name === chosen)?.regime;
  const regimes = [...new Set([preferred, ...models.map((m) => m.regime)].filter((r) => r !== undefined))];
  const score = (m) => (Number.isFinite(testDcm(m)) ? testDcm(m) : -Infinity);
  return [...models].sort((a, b) => regimes.indexOf(a.regime) - regimes.indexOf(b.regime) || score(b) - score(a));
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

// The grasps changed: the next frame asks for their deformation.
function requestUpdate() {
  state.dirty = true;
}

// Called once per frame: sends the latest grasps when nothing is in flight. A drag never queues
// stale requests, and no more answers are asked for than frames can show (on a machine where the
// browser and the server share the cores, every extra answer would slow the frames down).
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
    setStatus(null);
  } catch (error) {
    setStatus(error.message);
  } finally {
    state.inFlight = false;
  }
}

function note(list, value, keep) {
  list.push(value);
  if (list.length > keep) list.splice(0, list.length - keep);
}

// Keeps an answer (null: the organ at rest) for the next frame to show. Answers can arrive faster
// than frames are drawn; only the latest one before a frame is worth applying.
function show(answer) {
  note(state.received, performance.now(), 2000);
  state.latest = answer;
  state.needsDraw = true;
}

// Applies the latest answer to the surface; the readout shows it at its next refresh.
function apply(answer) {
  surface.update(answer ? answer.displacements : null);
  renderer.upload();
  state.scaleMax = niceScale(surface.largest, state.scaleMax);
  if (answer) state.shown = answer;
}

// A round colour-scale maximum (1, 2 or 5 × 10^k m, at least 1 mm) that changes only when the field
// leaves it or shrinks below the next round value down, so the colours do not flicker during a drag.
function niceScale(largest, current) {
  if (largest <= current && largest > current / 2.5) return current;
  const target = Math.max(largest, 0.001);
  const power = 10 ** Math.floor(Math.log10(target));
  return [1, 2, 5, 10].map((m) => m * power).find((v) => v >= target);
}

// Refreshes the readout from the answer on screen. Four times a second is as fast as anyone reads,
// and every change repaints the panel, which a software compositor pays for in frames.
function readout(now) {
  if (now - state.readoutAt < READOUT_INTERVAL_MS) return;
  state.readoutAt = now;
  const us = (v) => `${v.toFixed(0)} µs`;
  const windowStart = now - RATE_WINDOW_MS;
  setText("rate", `${state.deformationFrames.filter((t) => t >= windowStart).length} /s`);
  setText("render-scale", `${Math.round(renderer.renderScale * 100)} %`);
  setText("scale-max", `${(state.scaleMax * MM).toFixed(0)} mm`);
  const answer = state.shown;
  if (!answer) return;
  // The median of the last second's round trips: one answer's is mostly noise.
  const trips = roundTripsSince(windowStart).sort((a, b) => a - b);
  if (trips.length) setText("rtt", us(trips[Math.floor(trips.length / 2)] * 1e3));
  setText("server-total", us(answer.timing.total));
  setText("server-resolve", us(answer.timing.resolve));
  setText("server-queue", us(answer.timing.queue));
  setText("server-prior", us(answer.timing.prior));
  setText("server-network", us(answer.timing.network));
  setText("held", String(answer.interactionPoints));
  setText("largest", `${(surface.largest * MM).toFixed(1)} mm`);
  setText("forces", answer.graspForces.length ? answer.graspForces.map((f) => `${Math.hypot(...f).toFixed(2)} N`).join(", ") : "–");
}

// Changes an element's text only when it differs: an unchanged value costs no repaint.
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
  pump();
  readout(now);
  const drawing = state.needsDraw;
  if (drawing) {
    state.needsDraw = false;
    const fresh = state.latest !== undefined;
    if (fresh) {
      apply(state.latest);
      state.latest = undefined;
      note(state.deformationFrames, now, 2000);
    }
    renderer.timeFrame(now, state.drewLastFrame);
    renderer.draw(camera, state.scaleMax, graspers());
    state.framesDrawn++;
  }
  state.drewLastFrame = drawing;
  requestAnimationFrame(frame);
}

const GRASPER_COLORS = [[1, 1, 1, 1], [1, 0.7, 0.28, 1]];
// Force arrows: metres of arrow per newton, and the longest drawn.
const ARROW_M_PER_N = 0.01;
const ARROW_MAX_M = 0.06;

// Each grasper: a small dot where it took hold, a large one where it is now, a line between them and,
// for models that give forces, an arrow along the force it exerts (answers list forces in the order
// the request listed its graspers).
function graspers() {
  const forces = state.shown ? state.shown.graspForces : [];
  let held = 0;
  return state.graspers.flatMap((g, i) => {
    if (!g) return [];
    const to = add(g.point, g.displacement);
    const force = forces[held++];
    const newtons = force ? Math.hypot(...force) : 0;
    const length = Math.min(newtons * ARROW_M_PER_N, ARROW_MAX_M);
    const forceTip = newtons > 0 ? add(to, force.map((f) => (f / newtons) * length)) : undefined;
    return [{ from: g.point, to, color: GRASPER_COLORS[i], forceTip }];
  });
}

// ---- for the browser test ----------------------------------------------------------------------

// Round trips (ms) of the answers received after `since` (ms).
function roundTripsSince(since) {
  return state.roundTrips.filter(([t]) => t >= since).map(([, ms]) => ms);
}

// Events per second between the first and the last of `times` (ms) after `since`.
function rate(times, since) {
  const recent = times.filter((t) => t >= since);
  return recent.length < 2 ? 0 : ((recent.length - 1) * 1000) / (recent[recent.length - 1] - recent[0]);
}

window.nakViewer = {
  get ready() { return state.ready; },
  get error() { return state.error; },
  get busy() { return state.inFlight || state.dirty || state.latest !== undefined; },
  get updates() { return state.deformationFrames.length; },
  get framesDrawn() { return state.framesDrawn; },
  get renderScale() { return renderer.renderScale; },
  get graspers() { return state.graspers.filter(Boolean).length; },
  // Answers received, and frames drawn with a new answer, per second after `since` (ms).
  answerRate(since) { return rate(state.received, since); },
  deformationFrameRate(since) { return rate(state.deformationFrames, since); },
  roundTripsMs: roundTripsSince,
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
