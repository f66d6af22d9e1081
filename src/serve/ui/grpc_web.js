// nak.v1.Deformation over gRPC-Web: the protobuf wire format for the few messages the viewer uses,
// and the gRPC-Web framing around them (proto/nak/v1/deformation.proto is the contract).

const SERVICE = "/nak.v1.Deformation/";

export class GrpcError extends Error {
  constructor(code, message) {
    super(`${CODE_NAMES[code] ?? `status ${code}`}: ${message}`);
    this.code = code;
  }
}

const CODE_NAMES = {
  1: "CANCELLED", 2: "UNKNOWN", 3: "INVALID_ARGUMENT", 4: "DEADLINE_EXCEEDED", 5: "NOT_FOUND",
  7: "PERMISSION_DENIED", 8: "RESOURCE_EXHAUSTED", 9: "FAILED_PRECONDITION", 12: "UNIMPLEMENTED",
  13: "INTERNAL", 14: "UNAVAILABLE", 16: "UNAUTHENTICATED",
};

// ---- protobuf writer -------------------------------------------------------------------------

class Writer {
  constructor() {
    this.bytes = [];
  }
  varint(value) {
    // Values here are below 2^53 (sequence numbers, enums, lengths): plain arithmetic is exact.
    let v = value;
    while (v >= 0x80) {
      this.bytes.push((v % 0x80) | 0x80);
      v = Math.floor(v / 0x80);
    }
    this.bytes.push(v);
    return this;
  }
  tag(field, wireType) {
    return this.varint(field * 8 + wireType);
  }
  uint(field, value) {
    return value ? this.tag(field, 0).varint(value) : this;
  }
  float(field, value) {
    if (!value) return this;
    const buffer = new DataView(new ArrayBuffer(4));
    buffer.setFloat32(0, value, true);
    this.tag(field, 5);
    for (let i = 0; i < 4; i++) this.bytes.push(buffer.getUint8(i));
    return this;
  }
  string(field, text) {
    if (!text) return this;
    return this.delimited(field, Array.from(new TextEncoder().encode(text)));
  }
  message(field, writer) {
    return this.delimited(field, writer.bytes);
  }
  delimited(field, bytes) {
    this.tag(field, 2).varint(bytes.length);
    for (const b of bytes) this.bytes.push(b);
    return this;
  }
  finish() {
    return new Uint8Array(this.bytes);
  }
}

// ---- protobuf reader -------------------------------------------------------------------------

// Reads varints from `bytes`, front to back.
class Cursor {
  constructor(bytes) {
    this.bytes = bytes;
    this.at = 0;
  }
  get done() {
    return this.at >= this.bytes.length;
  }
  varint() {
    let result = 0;
    let scale = 1;
    for (;;) {
      if (this.done) throw new Error("truncated protobuf varint");
      const b = this.bytes[this.at++];
      result += (b & 0x7f) * scale;
      if (b < 0x80) return result;
      scale *= 0x80;
    }
  }
}

// Calls `visit(field, wireType, value)` for every field of `bytes`: value is a number for varints
// and fixed32 (as a float when `floats` names the field), a Uint8Array for length-delimited fields.
function readFields(bytes, visit, floats = new Set()) {
  const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const cursor = new Cursor(bytes);
  while (!cursor.done) {
    const key = cursor.varint();
    const field = Math.floor(key / 8);
    const wireType = key % 8;
    const at = cursor.at;
    if (wireType === 0) {
      visit(field, wireType, cursor.varint());
    } else if (wireType === 1) {
      visit(field, wireType, view.getFloat64(at, true));
      cursor.at += 8;
    } else if (wireType === 2) {
      const length = cursor.varint();
      const from = cursor.at;
      if (from + length > bytes.length) throw new Error("truncated protobuf field");
      visit(field, wireType, bytes.subarray(from, from + length));
      cursor.at = from + length;
    } else if (wireType === 5) {
      visit(field, wireType, floats.has(field) ? view.getFloat32(at, true) : view.getUint32(at, true));
      cursor.at += 4;
    } else {
      throw new Error(`unsupported protobuf wire type ${wireType}`);
    }
  }
}

// A repeated uint32: packed (one length-delimited run of varints) or a single unpacked element.
function uint32s(wireType, value, into) {
  if (wireType === 0) {
    into.push(value);
    return;
  }
  const cursor = new Cursor(value);
  while (!cursor.done) into.push(cursor.varint());
}

const text = (bytes) => new TextDecoder().decode(bytes);

// Little-endian f32 / u32 arrays from bytes that may sit at any offset of their buffer.
const f32s = (bytes) => new Float32Array(bytes.slice().buffer);
const u32s = (bytes) => new Uint32Array(bytes.slice().buffer);

// ---- messages ----------------------------------------------------------------------------------

function decodeMesh(bytes) {
  const mesh = { name: "", nodeCount: 0, positions: null, triangles: null, nodeSets: {}, surfaceNodes: [],
                 graspRegions: [] };
  readFields(bytes, (field, wireType, value) => {
    if (field === 1) mesh.name = text(value);
    else if (field === 3) mesh.nodeCount = value;
    else if (field === 4) mesh.positions = f32s(value);
    else if (field === 5) mesh.triangles = u32s(value);
    else if (field === 6) {
      const set = { name: "", nodes: [] };
      readFields(value, (f, w, v) => {
        if (f === 1) set.name = text(v);
        else if (f === 2) uint32s(w, v, set.nodes);
      });
      mesh.nodeSets[set.name] = set.nodes;
    } else if (field === 8) uint32s(wireType, value, mesh.surfaceNodes);
    else if (field === 10) {
      readFields(value, (f, _, v) => {
        if (f !== 5) return;
        readFields(v, (g, __, name) => {
          if (g === 1) mesh.graspRegions.push(text(name));
        });
      });
    }
  });
  return mesh;
}

const MODEL_KINDS = { 1: "prior", 2: "exact", 3: "neural" };

// ListModelsResponse: the models, and the one a request naming none gets.
function decodeModels(bytes) {
  const models = [];
  let defaultModel = "";
  readFields(bytes, (field, _, value) => {
    if (field === 2) defaultModel = text(value);
    if (field !== 1) return;
    const model = { name: "", kind: "", regime: "", metadata: {} };
    readFields(value, (f, __, v) => {
      if (f === 1) model.name = text(v);
      else if (f === 2) model.kind = MODEL_KINDS[v] ?? "";
      else if (f === 4) model.regime = text(v);
      else if (f === 5) {
        // A map entry: key = 1, value = 2.
        const entry = ["", ""];
        readFields(v, (g, ___, part) => { entry[g - 1] = text(part); });
        model.metadata[entry[0]] = entry[1];
      }
    });
    models.push(model);
  });
  return { models, defaultModel };
}

const VEC3_FIELDS = new Set([1, 2, 3]);
const TIMING_FIELDS = new Set([1, 2, 3, 4, 5]);

function decodeVec3(bytes) {
  const v = [0, 0, 0];
  readFields(bytes, (f, _, x) => { v[f - 1] = x; }, VEC3_FIELDS);
  return v;
}

function decodePrediction(bytes) {
  // proto3 leaves out zeros: a stage that took no time (no network, no queue) is absent.
  const timing = { resolve: 0, prior: 0, network: 0, total: 0, queue: 0 };
  const answer = { sequence: 0, nodeCount: 0, displacements: new Float32Array(0), timing, model: "",
                   interactionPoints: 0, graspForces: [] };
  readFields(bytes, (field, _, value) => {
    if (field === 1) answer.sequence = value;
    else if (field === 2) answer.nodeCount = value;
    else if (field === 3) answer.displacements = f32s(value);
    else if (field === 5) {
      const names = { 1: "resolve", 2: "prior", 3: "network", 4: "total", 5: "queue" };
      readFields(value, (f, __, us) => { answer.timing[names[f]] = us; }, TIMING_FIELDS);
    } else if (field === 6) answer.model = text(value);
    else if (field === 7) answer.interactionPoints = value;
    else if (field === 9) answer.graspForces.push(decodeVec3(value));
  });
  return answer;
}

function vec3(v) {
  return new Writer().float(1, v[0]).float(2, v[1]).float(3, v[2]);
}

const SELECTION_SURFACE = 1;

// A PredictRequest answered for the surface nodes, in the order of Mesh.surface_nodes.
function encodePredictRequest({ model, sequence, grasps }) {
  const request = new Writer().string(1, model);
  for (const grasp of grasps) {
    const message = new Writer().message(2, vec3(grasp.point)).float(3, grasp.radius).message(4, vec3(grasp.displacement));
    request.message(2, message);
  }
  return request.uint(3, sequence).uint(4, SELECTION_SURFACE).finish();
}

// ---- gRPC-Web ----------------------------------------------------------------------------------

// One unary call: a length-prefixed message out, data frames and a trailer frame back.
async function unary(method, message, token) {
  const body = new Uint8Array(5 + message.length);
  new DataView(body.buffer).setUint32(1, message.length, false);
  body.set(message, 5);
  const headers = { "content-type": "application/grpc-web+proto", "x-grpc-web": "1" };
  if (token) headers.authorization = `Bearer ${token}`;
  const response = await fetch(SERVICE + method, { method: "POST", headers, body });
  if (!response.ok) throw new GrpcError(2, `HTTP ${response.status} from ${method}`);
  // A refusal before any message comes as trailers-only: the status is in the headers.
  const headerStatus = response.headers.get("grpc-status");
  if (headerStatus !== null && headerStatus !== "0") {
    throw new GrpcError(Number(headerStatus), decodeURIComponent(response.headers.get("grpc-message") ?? ""));
  }
  const frames = new Uint8Array(await response.arrayBuffer());
  const view = new DataView(frames.buffer);
  let payload = null;
  let trailers = {};
  for (let at = 0; at + 5 <= frames.length;) {
    const flag = frames[at];
    const length = view.getUint32(at + 1, false);
    const frame = frames.subarray(at + 5, at + 5 + length);
    at += 5 + length;
    if (flag & 0x80) trailers = parseTrailers(text(frame));
    else payload = frame;
  }
  const status = Number(trailers["grpc-status"] ?? headerStatus ?? 2);
  if (status !== 0) throw new GrpcError(status, decodeURIComponent(trailers["grpc-message"] ?? ""));
  if (payload === null) throw new GrpcError(13, `${method} answered no message`);
  return payload;
}

function parseTrailers(block) {
  const trailers = {};
  for (const line of block.split("\r\n")) {
    const colon = line.indexOf(":");
    if (colon > 0) trailers[line.slice(0, colon).trim().toLowerCase()] = line.slice(colon + 1).trim();
  }
  return trailers;
}

// The calls the viewer makes, each returning the decoded answer.
export class DeformationClient {
  constructor(token) {
    this.token = token;
  }
  async getMesh() {
    return decodeMesh(await unary("GetMesh", new Uint8Array(0), this.token));
  }
  async listModels() {
    return decodeModels(await unary("ListModels", new Uint8Array(0), this.token));
  }
  async predict(request) {
    return decodePrediction(await unary("Predict", encodePredictRequest(request), this.token));
  }
}
