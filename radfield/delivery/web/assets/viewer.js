// The page: loads view.json and model.bin, reads the URL hash, runs the controls, asks the sort
// worker for the depth order of each new camera, and draws with renderer.js.
// The contract with the Python writer (files, hash, data-ready, data-error) is in the export's
// docs (radfield/delivery/web); the camera convention is radfield's (OpenCV axes, c2w row-major).

import { parseModel, ModelError } from "./model.js";
import { Renderer, RenderError } from "./renderer.js";
import { depthOrder } from "./sort-worker.js";

const $ = (id) => document.getElementById(id);
const PLAY_SECONDS = 4;            // one pass of Play over [0, 1] (as the server viewer)
const ROTATE_PER_PIXEL = 0.005;    // radians per dragged pixel
const LIGHT_FALLBACK = { elevation: 45, distanceTimesRadius: 3 };

// --- small vector and matrix helpers (row-major 3x3 / 4x4 as nested arrays) ---------------------
const sub = (a, b) => a.map((x, i) => x - b[i]);
const add = (a, b) => a.map((x, i) => x + b[i]);
const scale = (a, s) => a.map((x) => x * s);
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const normalize = (a) => scale(a, 1 / Math.hypot(...a));
const column = (m, j) => [m[0][j], m[1][j], m[2][j]];
const mul3 = (a, b) => [0, 1, 2].map((i) => [0, 1, 2].map((j) => a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j]));
const apply3 = (m, v) => [dot(m[0], v), dot(m[1], v), dot(m[2], v)];

// rotation by `angle` about unit `axis` (Rodrigues)
function axisAngle(axis, angle) {
  const [x, y, z] = normalize(axis), c = Math.cos(angle), s = Math.sin(angle), t = 1 - c;
  return [[t * x * x + c, t * x * y - s * z, t * x * z + s * y],
          [t * x * y + s * z, t * y * y + c, t * y * z - s * x],
          [t * x * z - s * y, t * y * z + s * x, t * z * z + c]];
}

function quatFromMatrix(m) {   // (w, x, y, z), w >= 0
  const t = m[0][0] + m[1][1] + m[2][2];
  let q;
  if (t > 0) {
    const s = 2 * Math.sqrt(1 + t);
    q = [s / 4, (m[2][1] - m[1][2]) / s, (m[0][2] - m[2][0]) / s, (m[1][0] - m[0][1]) / s];
  } else if (m[0][0] > m[1][1] && m[0][0] > m[2][2]) {
    const s = 2 * Math.sqrt(1 + m[0][0] - m[1][1] - m[2][2]);
    q = [(m[2][1] - m[1][2]) / s, s / 4, (m[0][1] + m[1][0]) / s, (m[0][2] + m[2][0]) / s];
  } else if (m[1][1] > m[2][2]) {
    const s = 2 * Math.sqrt(1 + m[1][1] - m[0][0] - m[2][2]);
    q = [(m[0][2] - m[2][0]) / s, (m[0][1] + m[1][0]) / s, s / 4, (m[1][2] + m[2][1]) / s];
  } else {
    const s = 2 * Math.sqrt(1 + m[2][2] - m[0][0] - m[1][1]);
    q = [(m[1][0] - m[0][1]) / s, (m[0][2] + m[2][0]) / s, (m[1][2] + m[2][1]) / s, s / 4];
  }
  return q[0] < 0 ? q.map((x) => -x) : q;
}

function matrixFromQuat([w, x, y, z]) {
  const n = Math.hypot(w, x, y, z);
  [w, x, y, z] = [w / n, x / n, y / n, z / n];
  return [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
          [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
          [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]];
}

const poseOf = (c2w) => ({ rot: [0, 1, 2].map((i) => c2w[i].slice(0, 3)), pos: [c2w[0][3], c2w[1][3], c2w[2][3]] });
const c2wOf = ({ rot, pos }) => [[...rot[0], pos[0]], [...rot[1], pos[1]], [...rot[2], pos[2]], [0, 0, 0, 1]];

// --- errors: a visible message and <html data-error>, never a blank canvas ----------------------
let rejectReady;
function showError(message) {
  $("loading").hidden = true;
  $("message").textContent = message;
  $("message").hidden = false;
  document.documentElement.setAttribute("data-error", message);
  if (rejectReady) rejectReady(new Error(message));
}

// --- the URL hash: view=split:K | cam=px,py,pz,qw,qx,qy,qz,fovy_deg, ui=0, time, light, lightdir, intensity
function parseHash() {
  const params = new URLSearchParams(location.hash.replace(/^#/, ""));
  const numbers = (key, count) => {
    if (!params.has(key)) return null;
    const v = params.get(key).split(",").map(Number);
    if (v.length !== count || !v.every(Number.isFinite)) throw new Error(`#${key}=${params.get(key)} is not ${count} numbers`);
    return v;
  };
  return { view: params.get("view"), cam: numbers("cam", 8), ui: params.get("ui") !== "0",
           time: numbers("time", 1)?.[0] ?? null, light: numbers("light", 3), lightdir: numbers("lightdir", 3),
           intensity: numbers("intensity", 1)?.[0] ?? null };
}

function datasetCamera(views, key) {
  const [split, index] = String(key).split(":");
  const cam = views.cameras?.[split]?.[Number(index)];
  if (!cam || !/^[0-9]+$/.test(index)) throw new Error(`view.json has no camera ${key}`);
  return cam;
}

// The reference camera scaled to fit the canvas (its intrinsics exactly when the sizes agree).
function fitted(cam, width, height, c2w) {
  if (cam.width === width && cam.height === height) return { ...cam, c2w };
  const s = Math.min(width / cam.width, height / cam.height);
  return { width, height, fx: cam.fx * s, fy: cam.fy * s, cx: cam.cx * s + (width - cam.width * s) / 2,
           cy: cam.cy * s + (height - cam.height * s) / 2, c2w };
}

// conditions/light.py: _basis, light_at, light_angles (azimuth, elevation in degrees about `up`)
function lightBasis(up) {
  up = normalize(up);
  const helper = Math.abs(up[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0];
  const e1 = normalize(sub(helper, scale(up, dot(helper, up))));
  return [e1, cross(up, e1), up];
}
function lightAt(centre, up, azimuth, elevation, distance, intensity) {
  const [e1, e2, u] = lightBasis(up), a = (azimuth * Math.PI) / 180, e = (elevation * Math.PI) / 180;
  const towards = add(scale(add(scale(e1, Math.cos(a)), scale(e2, Math.sin(a))), Math.cos(e)), scale(u, Math.sin(e)));
  return distance === null ? { direction: scale(towards, -1), intensity } : { position: add(centre, scale(towards, distance)), intensity };
}
function lightAngles(centre, up, light) {
  const [e1, e2, u] = lightBasis(up);
  let towards, distance = null;
  if (light.position) {
    const offset = sub(light.position, centre);
    distance = Math.hypot(...offset);
    towards = scale(offset, 1 / Math.max(distance, 1e-12));
  } else towards = scale(normalize(light.direction), -1);
  const elevation = (Math.asin(Math.min(1, Math.max(-1, dot(towards, u)))) * 180) / Math.PI;
  return { azimuth: (Math.atan2(dot(towards, e2), dot(towards, e1)) * 180) / Math.PI, elevation, distance };
}

async function fetchOk(url, as) {
  const response = await fetch(url);
  if (!response.ok) throw new ModelError(`${url}: HTTP ${response.status}`);
  return as === "json" ? response.json() : response.arrayBuffer();
}

async function main() {
  // start-up, in parts (window.radfield.timings): fetching view.json and model.bin, parsing and
  // decoding it, the textures and programs, the first depth order, the first frame
  const timings = window.radfield.timings;
  let t = performance.now();
  const lap = (key) => {
    const now = performance.now();
    timings[key] = now - t;
    t = now;
  };
  const hash = parseHash();
  const views = await fetchOk("view.json", "json");
  const bytes = await fetchOk(views.model || "model.bin", "buffer");
  lap("fetch_ms");
  const model = parseModel(bytes);
  lap("parse_ms");
  const canvas = $("canvas");
  const renderer = new Renderer(canvas, model);
  lap("upload_ms");
  renderer.setBackground(views.background ?? [1, 1, 1]);
  if (views.near !== undefined) {
    if (!(typeof views.near === "number" && views.near > 0 && Number.isFinite(views.near))) throw new Error(`view.json: near ${views.near} is not a positive number`);
    renderer.near = views.near;
  }
  const centre = views.centre ?? [0, 0, 0], up = normalize(views.up ?? [0, 0, 1]), radius = views.radius ?? 1;
  $("title").textContent = views.title ?? "radfield";
  document.title = views.title ? `${views.title} · radfield` : "radfield";

  // --- the camera: a reference camera (intrinsics, size) and its pose; `key` while unmoved
  const state = { ref: null, pose: null, key: null, target: [...centre], time: 0, light: null, playing: false };
  function jumpTo(key) {
    const cam = datasetCamera(views, key);
    state.ref = cam;
    state.pose = poseOf(cam.c2w);
    state.key = key;
    return cam;
  }
  let start;
  if (hash.cam) {
    const [px, py, pz, qw, qx, qy, qz, fovy] = hash.cam;
    const base = datasetCamera(views, views.start);
    const fy = base.height / 2 / Math.tan((fovy * Math.PI) / 360);
    state.ref = { name: "link", width: base.width, height: base.height, fx: fy, fy, cx: base.width / 2, cy: base.height / 2 };
    state.pose = { rot: matrixFromQuat([qw, qx, qy, qz]), pos: [px, py, pz] };
    start = state.ref;
  } else start = jumpTo(hash.view ?? views.start);

  // --- conditions: the hash's, else the camera's, else the start values
  if (model.dynamic) {
    state.time = hash.time ?? start.time ?? views.conditions?.time?.start ?? 0;
    if (!(state.time >= 0 && state.time <= 1)) throw new Error(`time ${state.time} is outside [0, 1]`);
  }
  if (model.relight) {
    const startLight = views.conditions?.light?.start;
    let light = start.light ?? startLight;
    if (!light) {
      const d = LIGHT_FALLBACK.distanceTimesRadius * radius;
      light = lightAt(centre, up, 0, LIGHT_FALLBACK.elevation, d, d * d);
    }
    const intensity = hash.intensity ?? (hash.light || hash.lightdir ? (startLight ?? light).intensity : light.intensity);
    if (hash.light) light = { position: hash.light, intensity };
    else if (hash.lightdir) light = { direction: normalize(hash.lightdir), intensity };
    else light = { ...light, intensity };
    state.light = light;
  }
  renderer.setTime(state.time);
  if (state.light) renderer.setLight(state.light);

  // --- the depth order, from the worker, once per camera pose
  const worker = new Worker(new URL("./sort-worker.js", import.meta.url), { type: "module" });
  worker.postMessage({ means: model.tensors.means });
  const sort = { asked: 0, busy: false, drawnFor: -1, uploadedFor: -1, lastMs: 0 };
  let drawing = false;

  function currentCamera() {
    return fitted(state.ref, canvas.width, canvas.height, c2wOf(state.pose));
  }
  function depthRow() {
    const { rot, pos } = state.pose;   // the third row of world-to-camera: (R^T)_2 and -(R^T t)_2
    const r2 = column(rot, 2);
    return [...r2, -dot(r2, pos)];
  }
  function askSort() {
    if (timings.sort_ms === null) sort.firstAsked = performance.now();
    sort.asked++;
    if (!sort.busy) {
      sort.busy = true;
      worker.postMessage({ id: sort.asked, row: depthRow() });
    }
  }
  worker.onmessage = (event) => {
    if (timings.sort_ms === null) timings.sort_ms = performance.now() - sort.firstAsked;   // the first order, waited for
    sort.busy = false;
    sort.lastMs = event.data.ms;
    renderer.setOrder(event.data.order);
    sort.uploadedFor = event.data.id;
    if (sort.uploadedFor !== sort.asked) {   // the camera moved meanwhile: sort again for the latest
      sort.busy = true;
      worker.postMessage({ id: sort.asked, row: depthRow() });
    }
    drawNow();
  };
  worker.onerror = (e) => showError(`the sort worker failed: ${e.message}`);

  // --- drawing: on demand (software GL would spin the CPU on a continuous loop)
  const fps = { times: [] };
  function drawNow() {
    if (sort.uploadedFor < 0) return;   // no order yet
    renderer.setCamera(currentCamera());
    renderer.setTime(state.time);
    if (state.light) renderer.setLight(state.light);
    const start = performance.now();
    renderer.draw();
    const first = sort.uploadedFor === sort.asked && !document.documentElement.hasAttribute("data-ready");
    if (first) renderer.finish();   // the first frame at the asked view: waited for, so its time is real
    const now = performance.now();
    if (first) timings.first_frame_ms = now - start;
    fps.times.push(now);
    while (fps.times.length > 1 && now - fps.times[0] > 1000) fps.times.shift();
    if (fps.times.length > 1) {
      // frames drawn one after another (the camera moving, Play): their rate
      const rate = ((fps.times.length - 1) * 1000) / (now - fps.times[0]);
      $("fps").textContent = `${rate.toFixed(1)} fps · sort ${sort.lastMs.toFixed(1)} ms`;
    } else if (first) {
      // drawn on demand: a resting view shows what its frame took
      $("fps").textContent = `${(1000 / (now - start)).toFixed(1)} fps (one frame: ${(now - start).toFixed(0)} ms)`;
    }
    if (first) {
      // the first frame at the requested view, with that view's depth order
      $("loading").hidden = true;
      document.documentElement.setAttribute("data-ready", "");
      readyResolve();
    }
  }
  function requestDraw() {
    if (drawing) return;
    drawing = true;
    requestAnimationFrame(() => {
      drawing = false;
      drawNow();
    });
  }
  function cameraChanged() {
    state.key = null;
    askSort();
    requestDraw();
  }

  function resize() {
    canvas.width = Math.max(1, window.innerWidth);
    canvas.height = Math.max(1, window.innerHeight);
    canvas.style.width = `${canvas.width}px`;
    canvas.style.height = `${canvas.height}px`;
    requestDraw();
  }
  window.addEventListener("resize", resize);
  resize();

  // --- controls: orbit about `target` with `up`, or fly
  let drag = null;
  canvas.addEventListener("contextmenu", (e) => e.preventDefault());
  canvas.addEventListener("pointerdown", (e) => {
    drag = { x: e.clientX, y: e.clientY, pan: e.button === 2 || e.shiftKey };
    canvas.setPointerCapture(e.pointerId);
  });
  canvas.addEventListener("pointerup", () => (drag = null));
  canvas.addEventListener("pointermove", (e) => {
    if (!drag) return;
    const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    drag.x = e.clientX;
    drag.y = e.clientY;
    const { rot, pos } = state.pose;
    const right = column(rot, 0), down = column(rot, 1);
    if (drag.pan) {
      // move camera and target in the image plane, one pixel of drag = one pixel at the target
      const s = Math.hypot(...sub(state.target, pos)) / currentCamera().fy;
      const shift = add(scale(right, -dx * s), scale(down, -dy * s));
      state.pose = { rot, pos: add(pos, shift) };
      state.target = add(state.target, shift);
    } else {
      const turn = mul3(axisAngle(right, -dy * ROTATE_PER_PIXEL), axisAngle(up, -dx * ROTATE_PER_PIXEL));
      const mode = $("mode").value;
      const pivot = mode === "orbit" ? state.target : pos;
      const look = mode === "orbit" ? turn : mul3(axisAngle(right, dy * ROTATE_PER_PIXEL), axisAngle(up, dx * ROTATE_PER_PIXEL));
      state.pose = { rot: mul3(look, rot), pos: add(pivot, apply3(look, sub(pos, pivot))) };
    }
    cameraChanged();
  });
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    const { rot, pos } = state.pose;
    const f = Math.exp(e.deltaY * 0.001);
    state.pose = { rot, pos: add(state.target, scale(sub(pos, state.target), f)) };
    cameraChanged();
  }, { passive: false });
  const keys = new Set();
  window.addEventListener("keydown", (e) => {
    if (e.target.tagName === "INPUT" || e.target.tagName === "SELECT" || $("mode").value !== "fly") return;
    const k = e.key.toLowerCase();
    if ("wasdqe".includes(k) && k.length === 1) {
      if (!keys.size) requestAnimationFrame(fly);
      keys.add(k);
    }
  });
  window.addEventListener("keyup", (e) => keys.delete(e.key.toLowerCase()));
  let lastFly = null;
  function fly(now) {
    if (!keys.size) {
      lastFly = null;
      return;
    }
    const dt = lastFly === null ? 1 / 60 : Math.min(0.1, (now - lastFly) / 1000);
    lastFly = now;
    const { rot, pos } = state.pose, step = radius * 0.6 * dt;
    const axes = { w: column(rot, 2), s: scale(column(rot, 2), -1), d: column(rot, 0), a: scale(column(rot, 0), -1), e: up, q: scale(up, -1) };
    let move = [0, 0, 0];
    for (const k of keys) move = add(move, scale(axes[k], step));
    state.pose = { rot, pos: add(pos, move) };
    state.target = add(state.target, move);
    cameraChanged();
    requestAnimationFrame(fly);
  }

  // --- the panel: cameras, time, light, copy link, FPS
  const select = $("cameras");
  for (const split of Object.keys(views.cameras ?? {})) {
    (views.cameras[split] ?? []).forEach((cam, i) => {
      const option = new Option(`${split} ${i}${cam.name ? ` · ${cam.name}` : ""}`, `${split}:${i}`);
      select.add(option);
    });
  }
  if (state.key) select.value = state.key;
  select.addEventListener("change", () => {
    const cam = jumpTo(select.value);
    state.target = [...centre];
    if (model.dynamic && cam.time !== undefined) setTime(cam.time);
    if (model.relight && cam.light) setLight(cam.light);
    askSort();
    requestDraw();
    state.key = select.value;
  });

  function setTime(xi) {
    state.time = Math.min(1, Math.max(0, xi));
    $("time").value = state.time;
    $("time-out").textContent = state.time.toFixed(2);
    requestDraw();
  }
  if (model.dynamic) {
    $("time-row").hidden = $("play-row").hidden = false;
    setTime(state.time);
    $("time").addEventListener("input", () => setTime(Number($("time").value)));
    let last = null;
    const play = (now) => {
      if (!state.playing) return;
      if (last !== null) setTime((state.time + (now - last) / 1000 / PLAY_SECONDS) % 1);
      last = now;
      requestAnimationFrame(play);
    };
    $("play").addEventListener("click", () => {
      state.playing = !state.playing;
      $("play").textContent = state.playing ? "Pause" : "Play";
      last = null;
      if (state.playing) requestAnimationFrame(play);
    });
  }

  function setLight(light) {
    state.light = light;
    const a = lightAngles(centre, up, light);
    $("azimuth").value = a.azimuth;
    $("elevation").value = a.elevation;
    $("azimuth-out").textContent = `${Math.round(a.azimuth)}°`;
    $("elevation-out").textContent = `${Math.round(a.elevation)}°`;
    $("distance-row").hidden = a.distance === null;
    if (a.distance !== null) {
      const [lo, hi] = views.conditions?.light?.distances ?? [a.distance / 4, a.distance * 4];
      $("distance").min = Math.min(lo, a.distance);
      $("distance").max = Math.max(hi, a.distance);
      $("distance").value = a.distance;
      $("distance-out").textContent = a.distance.toPrecision(3);
    }
    requestDraw();
  }
  if (model.relight) {
    $("azimuth-row").hidden = $("elevation-row").hidden = false;
    setLight(state.light);
    const moved = () => {
      const point = state.light.position !== undefined;
      setLight(lightAt(centre, up, Number($("azimuth").value), Number($("elevation").value),
                       point ? Number($("distance").value) : null, state.light.intensity));
    };
    for (const id of ["azimuth", "elevation", "distance"]) $(id).addEventListener("input", moved);
  }

  const round = (x) => Number(x.toPrecision(7));
  $("copy").addEventListener("click", async () => {
    const params = new URLSearchParams();
    if (state.key) params.set("view", state.key);
    else {
      const { rot, pos } = state.pose;
      const fovy = (2 * Math.atan(state.ref.height / 2 / state.ref.fy) * 180) / Math.PI;
      params.set("cam", [...pos, ...quatFromMatrix(rot), fovy].map(round).join(","));
    }
    if (model.dynamic) params.set("time", String(round(state.time)));
    if (model.relight) {
      if (state.light.position) params.set("light", state.light.position.map(round).join(","));
      else params.set("lightdir", state.light.direction.map(round).join(","));
      params.set("intensity", String(round(state.light.intensity)));
    }
    const hashText = "#" + params.toString().replace(/%2C/g, ",").replace(/%3A/g, ":");
    history.replaceState(null, "", hashText);
    try {
      await navigator.clipboard.writeText(location.href);
      $("copy").textContent = "Copied";
    } catch {
      $("copy").textContent = "In the address bar";
    }
    setTimeout(() => ($("copy").textContent = "Copy link"), 1500);
  });
  $("panel").hidden = !hash.ui;

  // --- the page's API for tools: ready, bench
  window.radfield.bench = (frames = 20) => {
    // the sort as the worker runs it, timed here (the worker would add a message round trip)
    const row = depthRow();
    const t0 = performance.now();
    const order = depthOrder(model.tensors.means, row);
    const sortMs = performance.now() - t0;
    renderer.setOrder(order);
    renderer.setCamera(currentCamera());
    renderer.draw();
    renderer.finish();   // warm-up
    const start = performance.now();
    for (let i = 0; i < frames; i++) {
      renderer.draw();
      renderer.finish();
    }
    const ms = (performance.now() - start) / frames;
    return { ms_per_frame: ms, fps: 1000 / ms, sort_ms: sortMs, primitives: model.P, width: canvas.width,
             height: canvas.height, supersample: model.supersample, accumulation: renderer.accumFormat === renderer.gl.RGBA32F ? "rgba32f" : "rgba16f" };
  };
  askSort();
}

// `ready` exists from the start (a tool may await it before the model has loaded): it resolves with
// the first frame at the requested view, and rejects with the page's error message
let readyResolve;
// timings: the start-up's parts in ms (null until done); loaded = fetch + parse + upload + sort
window.radfield = { ready: new Promise((resolve, reject) => { readyResolve = resolve; rejectReady = reject; }), bench: null,
                    timings: { fetch_ms: null, parse_ms: null, upload_ms: null, sort_ms: null, first_frame_ms: null } };
window.radfield.ready.catch(() => {});

main().catch((e) => {
  console.error(e);
  const what = e instanceof ModelError || e instanceof RenderError ? e.message : `cannot show the model: ${e.message}`;
  showError(what);
});
