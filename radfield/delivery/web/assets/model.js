// model.bin: parse and validate the safetensors file the Python writer makes
// (radfield/delivery/web/model_bin.py: encode), and decode it to float32 arrays.
//
// Layout (safetensors exactly): 8 bytes little-endian u64 N, N bytes of JSON header, then the data;
// header entries {dtype: "F32"|"F16"|"U16", shape: [...], data_offsets: [begin, end]} (offsets
// relative to the data), and "__metadata__" {string: string}. Every problem is a ModelError with a
// message that names the field, which the page shows instead of drawing anything.

export class ModelError extends Error {}

const KINDS = ["neural", "gaussian", "neural-dynamic", "gaussian-dynamic", "neural-relight", "gaussian-relight"];
const DTYPE_BYTES = { F32: 4, F16: 2, U16: 2, U8: 1 };
const TEMPORAL_TERMS = 12;   // a_1..4, b_1..4, c_1..4 (core/kinds/dynamic.py)
const MAX_HIDDEN = 16;       // neural MLP width the shaders are compiled for at most
const MAX_COLOR_HIDDEN = 32; // relight colour-network width at most

function fail(message) {
  throw new ModelError(`model.bin: ${message}`);
}

// float16 bits -> float32 value (IEEE 754 half; subnormals, inf and NaN included).
const F16_TABLE = (() => {
  const table = new Float32Array(65536);
  for (let h = 0; h < 65536; h++) {
    const sign = h & 0x8000 ? -1 : 1, exp = (h >> 10) & 0x1f, frac = h & 0x3ff;
    if (exp === 0) table[h] = sign * frac * 2 ** -24;
    else if (exp === 31) table[h] = frac ? NaN : sign * Infinity;
    else table[h] = sign * (1 + frac / 1024) * 2 ** (exp - 15);
  }
  return table;
})();

// model_bin.py: from_smallest_three, in float32 as Python decodes it: the removed (largest,
// positive) component sqrt(max(0, 1 - sum of the other three squared)) at quats_index.
function fromSmallestThree(three, index) {
  const f = Math.fround, P = index.length, q = new Float32Array(4 * P);
  for (let p = 0; p < P; p++) {
    const a = three[3 * p], b = three[3 * p + 1], c = three[3 * p + 2];
    const sum = f(f(f(a * a) + f(b * b)) + f(c * c));
    const largest = f(Math.sqrt(Math.max(0, f(1 - sum))));
    for (let i = 0, k = 0; i < 4; i++) q[4 * p + i] = i === index[p] ? largest : three[3 * p + k++];
  }
  return q;
}

// The tensors each kind has: name -> shape with "P" (primitives), "K" (SH coefficients),
// "N" (density MLP width), "H" (colour-network width) as symbols. Optional ones separately.
function schema(kind) {
  const s = { means: ["P", 3], log_scales: ["P", 3], quats: ["P", 4], sh: ["P", "K", 3] };
  const neural = kind.startsWith("neural");
  if (neural) Object.assign(s, { w1: ["P", "N", 3], b1: ["P", "N"], w2: ["P", "N"], b2: ["P"] });
  else s.opacities = ["P"];
  if (kind.endsWith("-dynamic")) {
    s.sh_t = ["P", TEMPORAL_TERMS, 3];
    if (neural) s.w_t = ["P", "N"];
    else s.opacity_t = ["P", TEMPORAL_TERMS];
  }
  if (kind.endsWith("-relight")) {
    Object.assign(s, { color_w1: ["P", "H", 6], color_b1: ["P", "H"], color_w2: ["P", 3, "H"], color_b2: ["P", 3] });
  }
  const optional = neural ? { rest_metric: ["P", 6] } : {};
  return { required: s, optional };
}

function finiteNumber(meta, key) {
  const text = meta[key];
  if (typeof text !== "string" || text.trim() === "" || !Number.isFinite(Number(text))) {
    fail(`metadata ${key}=${JSON.stringify(text)} is not a finite number`);
  }
  return Number(text);
}

function integerIn(meta, key, lo, hi, fallback) {
  if (meta[key] === undefined && fallback !== undefined) return fallback;
  const text = meta[key];
  if (typeof text !== "string" || !/^[0-9]+$/.test(text) || Number(text) < lo || Number(text) > hi) {
    fail(`metadata ${key}=${JSON.stringify(text)} is not an integer in ${lo}..${hi}`);
  }
  return Number(text);
}

function bounds3(meta, key) {
  let value;
  try {
    value = JSON.parse(meta[key]);
  } catch {
    fail(`metadata ${key} is not JSON`);
  }
  if (!Array.isArray(value) || value.length !== 3 || !value.every((x) => typeof x === "number" && Number.isFinite(x))) {
    fail(`metadata ${key} is not 3 finite numbers`);
  }
  return value;
}

// Decode one tensor's bytes to a Float32Array (U16 only for the means, in [min, max]; U8 only for
// quats_index, returned as a Uint8Array).
function decode(name, entry, data, meta) {
  const [begin, end] = entry.data_offsets;
  const count = entry.shape.reduce((a, b) => a * b, 1);
  // the bytes as a typed array of the dtype (copied where the offset is not aligned to it; the
  // typed arrays read the platform's byte order, little-endian on every browser's platform)
  const start = data.byteOffset + begin;
  const typed = (Type) => start % Type.BYTES_PER_ELEMENT === 0 ? new Type(data.buffer, start, count)
                                                              : new Type(data.buffer.slice(start, start + (end - begin)));
  if (entry.dtype === "U8") {
    if (name !== "quats_index") fail(`tensor ${name} has dtype U8 (only quats_index may)`);
    const index = typed(Uint8Array).slice();
    for (let i = 0; i < count; i++) {
      if (index[i] > 3) fail(`tensor quats_index holds ${index[i]} at primitive ${i} (an index 0..3)`);
    }
    return index;
  }
  let out;
  if (entry.dtype === "F32") {
    out = typed(Float32Array).slice();
  } else if (entry.dtype === "F16") {
    const half = typed(Uint16Array);
    out = new Float32Array(count);
    for (let i = 0; i < count; i++) out[i] = F16_TABLE[half[i]];
  } else {
    const bytes = typed(Uint16Array);
    out = new Float32Array(count);
    // 16-bit fixed point over the bounding box: mean = min + (max - min) q / 65535, in float64
    // then rounded to float32, as model_bin.decoded does
    if (name !== "means") fail(`tensor ${name} has dtype U16 (only the means may)`);
    if (meta.means_min === undefined || meta.means_max === undefined) fail("U16 means without means_min/means_max");
    const lo = bounds3(meta, "means_min"), hi = bounds3(meta, "means_max");
    for (let i = 0; i < count; i++) {
      const axis = i % 3;
      out[i] = lo[axis] + (hi[axis] - lo[axis]) * bytes[i] / 65535;
    }
  }
  for (let i = 0; i < count; i++) {
    if (!Number.isFinite(out[i])) {
      const row = Math.floor(i / Math.max(1, count / entry.shape[0]));
      fail(`tensor ${name} holds a non-finite value (NaN or Inf) at primitive ${row}`);
    }
  }
  return out;
}

// Parse model.bin (an ArrayBuffer) into {kind, meta, P, N, H, K, shDegree, supersample, omega0,
// window, timeFrequency, tensors: {name: Float32Array}}; throws ModelError on any mismatch.
export function parseModel(buffer) {
  if (!(buffer instanceof ArrayBuffer) || buffer.byteLength < 8) fail("the file is shorter than its 8-byte header size");
  const view = new DataView(buffer);
  const headerSize = Number(view.getBigUint64(0, true));
  if (headerSize < 2 || headerSize > buffer.byteLength - 8 || headerSize > 100e6) {
    fail(`header size ${headerSize} does not fit a file of ${buffer.byteLength} bytes (not a safetensors file, or truncated)`);
  }
  let header;
  try {
    header = JSON.parse(new TextDecoder("utf-8", { fatal: true }).decode(new Uint8Array(buffer, 8, headerSize)));
  } catch {
    fail("the header is not JSON (not a safetensors file)");
  }
  if (header === null || typeof header !== "object" || Array.isArray(header)) fail("the header is not a JSON object");
  const meta = header.__metadata__ ?? {};
  if (typeof meta !== "object" || Object.values(meta).some((v) => typeof v !== "string")) fail("__metadata__ is not {string: string}");
  if (meta.format !== "radfield-web") fail(`metadata format is ${JSON.stringify(meta.format)}, expected "radfield-web"`);
  if (meta.version !== "1") fail(`format version ${JSON.stringify(meta.version)} is not supported (this page reads 1)`);
  const kind = meta.kind;
  if (!KINDS.includes(kind)) fail(`metadata kind ${JSON.stringify(kind)} is not one of ${KINDS.join(", ")}`);
  const shDegree = integerIn(meta, "sh_degree", 0, 3);
  const supersample = integerIn(meta, "supersample", 1, 4, 1);
  const neural = kind.startsWith("neural");
  const omega0 = neural ? finiteNumber(meta, "omega0") : 0;
  let window = false;
  if (neural) {
    const w = meta.window ?? "0";
    if (w !== "0" && w !== "1") fail(`metadata window=${JSON.stringify(w)} is not "0" or "1"`);
    window = w === "1";
  }
  const timeFrequency = kind.endsWith("-dynamic") ? finiteNumber(meta, "time_frequency") : 0;

  // the entries: dtypes, shapes, offsets inside the data, no overlaps past the end
  const data = new Uint8Array(buffer, 8 + headerSize);
  const entries = Object.entries(header).filter(([name]) => name !== "__metadata__");
  for (const [name, e] of entries) {
    if (!e || typeof e !== "object" || !(e.dtype in DTYPE_BYTES)) fail(`tensor ${name} has dtype ${JSON.stringify(e?.dtype)}, expected F32, F16 or U16`);
    if (!Array.isArray(e.shape) || !e.shape.every((d) => Number.isInteger(d) && d >= 0)) fail(`tensor ${name} has a bad shape`);
    const off = e.data_offsets;
    if (!Array.isArray(off) || off.length !== 2 || !off.every((d) => Number.isInteger(d) && d >= 0) || off[0] > off[1]) {
      fail(`tensor ${name} has bad data_offsets`);
    }
    const size = e.shape.reduce((a, b) => a * b, 1) * DTYPE_BYTES[e.dtype];
    if (off[1] - off[0] !== size) fail(`tensor ${name}: data_offsets span ${off[1] - off[0]} bytes, its shape and dtype need ${size}`);
    if (off[1] > data.length) fail(`tensor ${name} ends at byte ${off[1]} of a data section of ${data.length} (the file is truncated)`);
  }
  const byName = Object.fromEntries(entries);
  const { required, optional } = schema(kind);
  if ("quats_index" in byName) {
    // the compact precision's "smallest three" quaternions (model_bin.py: smallest_three)
    required.quats = ["P", 3];
    required.quats_index = ["P"];
  }
  const missing = Object.keys(required).filter((n) => !(n in byName));
  const unknown = Object.keys(byName).filter((n) => !(n in required) && !(n in optional));
  if (missing.length) fail(`missing tensors ${missing.join(", ")} for kind ${kind}`);
  if (unknown.length) fail(`unexpected tensors ${unknown.join(", ")} for kind ${kind}`);

  // the symbolic sizes: P from the means, N from w1, H from color_w1, K from sh_degree
  const P = byName.means.shape[0];
  const dims = { P, K: (shDegree + 1) ** 2 };
  if (neural) dims.N = byName.w1.shape[1];
  if (kind.endsWith("-relight")) dims.H = byName.color_w1.shape[1];
  if (dims.N !== undefined && !(dims.N >= 1 && dims.N <= MAX_HIDDEN)) fail(`w1 has ${dims.N} hidden units, this page draws 1..${MAX_HIDDEN}`);
  if (dims.H !== undefined && !(dims.H >= 1 && dims.H <= MAX_COLOR_HIDDEN)) fail(`color_w1 has ${dims.H} hidden units, this page draws 1..${MAX_COLOR_HIDDEN}`);
  const tensors = {};
  for (const [name, shape] of Object.entries({ ...required, ...optional })) {
    const e = byName[name];
    if (!e) continue;
    const expected = shape.map((d) => (typeof d === "string" ? dims[d] : d));
    if (e.shape.length !== expected.length || e.shape.some((d, i) => d !== expected[i])) {
      fail(`tensor ${name} has shape [${e.shape}], expected [${expected}] (P=${P}${name === "sh" ? `, K=${dims.K} for sh_degree ${shDegree}` : ""})`);
    }
    if (e.dtype === "U16" && name !== "means") fail(`tensor ${name} has dtype U16 (only the means may)`);
    if (e.dtype === "U8" && name !== "quats_index") fail(`tensor ${name} has dtype U8 (only quats_index may)`);
    tensors[name] = decode(name, e, data, meta);
  }
  if (tensors.quats_index) {
    tensors.quats = fromSmallestThree(tensors.quats, tensors.quats_index);
    delete tensors.quats_index;
  }
  const q = tensors.quats;
  for (let p = 0; p < P; p++) {
    if (q[4 * p] === 0 && q[4 * p + 1] === 0 && q[4 * p + 2] === 0 && q[4 * p + 3] === 0) fail(`tensor quats has an all-zero row at primitive ${p}`);
  }
  return { kind, meta, P, N: dims.N ?? 0, H: dims.H ?? 0, K: dims.K, shDegree, supersample, omega0, window,
           timeFrequency, neural, dynamic: kind.endsWith("-dynamic"), relight: kind.endsWith("-relight"), tensors };
}
