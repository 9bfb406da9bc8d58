// The WebGL2 renderer: the model's parameters in float textures, one point sprite per primitive
// in front-to-back order into a float framebuffer (in tiles no larger than the point size limit;
// in chunks, with early termination between them), then the final pass to the canvas.
// What each shader computes, and which Python function it mirrors, is in shaders.js.

import { splatShaders, FINAL_VERTEX, FINAL_FRAGMENT, TERMINATE_FRAGMENT, BLOCKS_FRAGMENT, BLOCK } from "./shaders.js";

export class RenderError extends Error {}

// The depth order is drawn in CHUNKS pieces (at least CHUNK_MIN primitives each); between them
// early termination (transmittance < 1e-4, render()'s T_MIN): the primitives whose pixel blocks are
// all done are culled (shaders.js: BLOCKS_FRAGMENT, emitQuad), and on a GPU the pixels that are done
// are masked out by the stencil. Not on SwiftShader (software GL): it runs the fragment shader of
// stencil- (or depth-) rejected pixels all the same (measured: a stencil test that rejects
// everything leaves the frame time as it was), so there the stencil passes would only cost time.
const CHUNKS = 8;
const CHUNK_MIN = 256;

function compile(gl, type, source) {
  const shader = gl.createShader(type);
  gl.shaderSource(shader, source);
  gl.compileShader(shader);
  if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) {
    const log = gl.getShaderInfoLog(shader);
    console.error(source.split("\n").map((l, i) => `${i + 1}: ${l}`).join("\n"));
    throw new RenderError(`shader does not compile: ${log}`);
  }
  return shader;
}

function program(gl, vertex, fragment) {
  const p = gl.createProgram();
  gl.attachShader(p, compile(gl, gl.VERTEX_SHADER, vertex));
  gl.attachShader(p, compile(gl, gl.FRAGMENT_SHADER, fragment));
  gl.linkProgram(p);
  if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new RenderError(`program does not link: ${gl.getProgramInfoLog(p)}`);
  const uniforms = {};
  for (let i = 0; i < gl.getProgramParameter(p, gl.ACTIVE_UNIFORMS); i++) {
    const name = gl.getActiveUniform(p, i).name.replace(/\[0\]$/, "");
    uniforms[name] = gl.getUniformLocation(p, name);
  }
  return { program: p, uniforms };
}

// Where each per-primitive value lives (texels of 4 floats; see shaders.js for the readers):
//   geo: 0 (mean, b2 | opacity logit), 1-2 the world covariance R S^2 R^T (xx xy xz yy | yz zz)
//        and max(s); neural: 3-5 the rows of M = S^-1 R^T, [GEO_METRIC, +1] the rest metric;
//        relight: [GEO_QUAT] the unit quaternion
//   col: flat floats: sh (K x 3), then sh_t (12 x 3), opacity_t (12), the colour network
//        (color_w1 H x 6, color_b1 H, color_w2 3 x H, color_b2 3)
//   mlp: neural: N texels (W1_k, b1_k), W2 four to a texel, then W_t four to a texel
export function textureLayout(model, texWidth) {
  let geo = model.neural ? 6 : 3;
  const metric = model.tensors.rest_metric ? geo : -1;
  if (metric >= 0) geo += 2;
  const quat = model.relight ? geo : -1;
  if (quat >= 0) geo += 1;
  let col = 3 * model.K;
  const shT = model.dynamic ? col : -1;
  if (model.dynamic) col += 36;
  const opacityT = model.dynamic && !model.neural ? col : -1;
  if (opacityT >= 0) col += 12;
  const net = model.relight ? col : -1;
  if (model.relight) col += 10 * model.H + 3;
  const quarter = Math.ceil(model.N / 4);
  const mlp = model.neural ? model.N + quarter + (model.dynamic ? quarter : 0) : 0;
  return { texWidth, geo: { stride: geo, metric, quat }, col: { stride: Math.ceil(col / 4), shT, opacityT, net },
           mlp: { stride: mlp } };
}

// Fill the three textures' data (Float32Array each) from the model's tensors; view-independent
// products (covariance, M, max(s)) are made here once, in float64, then stored as float32.
// (Plain loops and index writes: no per-primitive arrays, 100k primitives take tens of ms.)
function packTextures(model, layout) {
  const { P, N, H, K, tensors: t } = model;
  const rows = (stride) => Math.max(1, Math.ceil((P * stride) / layout.texWidth));
  const size = (stride) => rows(stride) * layout.texWidth * 4;
  const geo = new Float32Array(size(layout.geo.stride));
  const col = new Float32Array(size(layout.col.stride));
  const mlp = new Float32Array(size(Math.max(layout.mlp.stride, 1)));
  const { means, quats, log_scales: logScales } = t;
  const r = new Float64Array(9);   // quat_to_rotmat, row-major
  for (let p = 0; p < P; p++) {
    const g = p * layout.geo.stride * 4;
    let qw = quats[4 * p], qx = quats[4 * p + 1], qy = quats[4 * p + 2], qz = quats[4 * p + 3];
    const qn = Math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz);
    qw /= qn; qx /= qn; qy /= qn; qz /= qn;
    r[0] = 1 - 2 * (qy * qy + qz * qz); r[1] = 2 * (qx * qy - qw * qz); r[2] = 2 * (qx * qz + qw * qy);
    r[3] = 2 * (qx * qy + qw * qz); r[4] = 1 - 2 * (qx * qx + qz * qz); r[5] = 2 * (qy * qz - qw * qx);
    r[6] = 2 * (qx * qz - qw * qy); r[7] = 2 * (qy * qz + qw * qx); r[8] = 1 - 2 * (qx * qx + qy * qy);
    const l0 = logScales[3 * p], l1 = logScales[3 * p + 1], l2 = logScales[3 * p + 2];
    const s0 = Math.exp(l0), s1 = Math.exp(l1), s2 = Math.exp(l2);
    const v0 = s0 * s0, v1 = s1 * s1, v2 = s2 * s2;
    // the world covariance R S^2 R^T
    const cov = (i, j) => r[3 * i] * r[3 * j] * v0 + r[3 * i + 1] * r[3 * j + 1] * v1 + r[3 * i + 2] * r[3 * j + 2] * v2;
    geo[g] = means[3 * p]; geo[g + 1] = means[3 * p + 1]; geo[g + 2] = means[3 * p + 2];
    geo[g + 3] = model.neural ? t.b2[p] : t.opacities[p];
    geo[g + 4] = cov(0, 0); geo[g + 5] = cov(0, 1); geo[g + 6] = cov(0, 2); geo[g + 7] = cov(1, 1);
    geo[g + 8] = cov(1, 2); geo[g + 9] = cov(2, 2); geo[g + 10] = Math.exp(Math.max(l0, l1, l2));
    if (model.neural) {
      // M = S^-1 R^T: row i is column i of R over s_i (kernels.py: ellipsoid_frame)
      const s = [s0, s1, s2];
      for (let i = 0; i < 3; i++) {
        geo[g + 12 + 4 * i] = r[i] / s[i]; geo[g + 13 + 4 * i] = r[3 + i] / s[i]; geo[g + 14 + 4 * i] = r[6 + i] / s[i];
      }
    }
    if (layout.geo.metric >= 0) geo.set(t.rest_metric.subarray(6 * p, 6 * p + 6), g + 4 * layout.geo.metric);
    if (layout.geo.quat >= 0) {
      const o = g + 4 * layout.geo.quat;
      geo[o] = qw; geo[o + 1] = qx; geo[o + 2] = qy; geo[o + 3] = qz;
    }

    const c = p * layout.col.stride * 4;
    col.set(t.sh.subarray(3 * K * p, 3 * K * (p + 1)), c);
    if (layout.col.shT >= 0) col.set(t.sh_t.subarray(36 * p, 36 * (p + 1)), c + layout.col.shT);
    if (layout.col.opacityT >= 0) col.set(t.opacity_t.subarray(12 * p, 12 * (p + 1)), c + layout.col.opacityT);
    if (layout.col.net >= 0) {
      let o = c + layout.col.net;
      col.set(t.color_w1.subarray(6 * H * p, 6 * H * (p + 1)), o);
      col.set(t.color_b1.subarray(H * p, H * (p + 1)), (o += 6 * H));
      col.set(t.color_w2.subarray(3 * H * p, 3 * H * (p + 1)), (o += H));
      col.set(t.color_b2.subarray(3 * p, 3 * (p + 1)), o + 3 * H);
    }

    if (model.neural) {
      const m = p * layout.mlp.stride * 4, { w1, b1 } = t;
      for (let k = 0; k < N; k++) {
        const u = 3 * (N * p + k);
        mlp[m + 4 * k] = w1[u]; mlp[m + 4 * k + 1] = w1[u + 1]; mlp[m + 4 * k + 2] = w1[u + 2]; mlp[m + 4 * k + 3] = b1[N * p + k];
      }
      mlp.set(t.w2.subarray(N * p, N * (p + 1)), m + 4 * N);
      if (model.dynamic) mlp.set(t.w_t.subarray(N * p, N * (p + 1)), m + 4 * (N + Math.ceil(N / 4)));
    }
  }
  return { geo, col, mlp };
}

// 4x4 rigid inverse of a camera-to-world (row-major nested arrays): [R^T, -R^T t].
export function invertRigid(c2w) {
  const r = [0, 1, 2].map((i) => [0, 1, 2].map((j) => c2w[j][i]));
  const t = [0, 1, 2].map((i) => -(r[i][0] * c2w[0][3] + r[i][1] * c2w[1][3] + r[i][2] * c2w[2][3]));
  return { r, t };
}

// row-major 3x3 -> the column-major Float32Array that uniformMatrix3fv takes
const columnMajor = (m) => new Float32Array([m[0][0], m[1][0], m[2][0], m[0][1], m[1][1], m[2][1], m[0][2], m[1][2], m[2][2]]);

export class Renderer {
  // canvas: the page's canvas; model: parseModel's result
  constructor(canvas, model) {
    const gl = canvas.getContext("webgl2", { alpha: false, antialias: false, depth: false, stencil: false,
                                             preserveDrawingBuffer: true, premultipliedAlpha: false });
    if (!gl) throw new RenderError("this browser has no WebGL2");
    this.gl = gl;
    this.model = model;
    // a float framebuffer we can blend into: RGBA32F where float blending exists, else RGBA16F
    const float32 = gl.getExtension("EXT_color_buffer_float") && gl.getExtension("EXT_float_blend");
    const half = gl.getExtension("EXT_color_buffer_float") || gl.getExtension("EXT_color_buffer_half_float");
    if (!float32 && !half) throw new RenderError("this GPU cannot render to float textures (EXT_color_buffer_float)");
    this.accumFormat = float32 ? gl.RGBA32F : gl.RGBA16F;
    this.accumType = float32 ? gl.FLOAT : gl.HALF_FLOAT;

    const maxSize = gl.getParameter(gl.MAX_TEXTURE_SIZE);
    this.layout = textureLayout(model, Math.min(4096, maxSize));
    const data = packTextures(model, this.layout);
    this.textures = {};
    for (const [name, array] of Object.entries(data)) {
      const height = array.length / 4 / this.layout.texWidth;
      if (height > maxSize) throw new RenderError(`the model is too large for this GPU's textures (${model.P} primitives)`);
      const tex = gl.createTexture();
      gl.bindTexture(gl.TEXTURE_2D, tex);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, this.layout.texWidth, height, 0, gl.RGBA, gl.FLOAT, array);
      this.textures[name] = tex;
    }
    // the neural per-view MLP tensors travel as flat varyings (N + N/4 vec4s, plus 6 others) where
    // the GPU has enough; else the fragment shader fetches the weights (slower on software GL)
    const units = model.neural && model.N + Math.ceil(model.N / 4) + 6 <= gl.getParameter(gl.MAX_VARYING_VECTORS);
    const shaders = splatShaders(model, this.layout, units);
    this.splat = program(gl, shaders.vertex, shaders.fragment);
    // point sprites are at most this many pixels wide: larger targets are drawn in tiles
    this.maxPointSize = Math.floor(gl.getParameter(gl.ALIASED_POINT_SIZE_RANGE)[1]);
    const info = gl.getExtension("WEBGL_debug_renderer_info");
    this.software = /SwiftShader|llvmpipe|software/i.test(gl.getParameter(info ? info.UNMASKED_RENDERER_WEBGL : gl.RENDERER));
    this.final = program(gl, FINAL_VERTEX, FINAL_FRAGMENT);
    this.terminate = program(gl, FINAL_VERTEX, TERMINATE_FRAGMENT);
    this.blocks = program(gl, FINAL_VERTEX, BLOCKS_FRAGMENT);

    // the vertex attribute aId: primitive ids in front-to-back order (sort-worker.js), one point each
    // (not instanced: SwiftShader pays ~10 us per instance of an instanced draw)
    this.vao = gl.createVertexArray();
    gl.bindVertexArray(this.vao);
    this.orderBuffer = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, this.orderBuffer);
    gl.bufferData(gl.ARRAY_BUFFER, 4 * model.P, gl.DYNAMIC_DRAW);
    const idLocation = gl.getAttribLocation(this.splat.program, "aId");
    gl.enableVertexAttribArray(idLocation);
    gl.vertexAttribIPointer(idLocation, 1, gl.UNSIGNED_INT, 0, 0);
    gl.bindVertexArray(null);
    this.emptyVao = gl.createVertexArray();

    this.accum = null;
    this.view = null;
    this.time = 0;
    this.phi = new Float32Array(12);
    this.light = null;
    this.background = [1, 1, 1];
    this.near = 0.01;   // render()'s default; view.json's "near" (a run's render.near) replaces it
  }

  // The depth order (Uint32Array of primitive ids, front to back).
  setOrder(order) {
    const gl = this.gl;
    gl.bindBuffer(gl.ARRAY_BUFFER, this.orderBuffer);
    gl.bufferSubData(gl.ARRAY_BUFFER, 0, order);
  }

  // camera: {width, height, fx, fy, cx, cy, c2w (4x4 row-major)} of the canvas; the frame is drawn
  // at n times its size with the intrinsics scaled (Camera.scaled(n)) and box-averaged.
  setCamera(camera) {
    const n = this.model.supersample;
    const width = camera.width * n, height = camera.height * n;
    const intr = [camera.fx * n, camera.fy * n, camera.cx * n, camera.cy * n];
    const { r, t } = invertRigid(camera.c2w);
    const c2wRot = [0, 1, 2].map((i) => [camera.c2w[i][0], camera.c2w[i][1], camera.c2w[i][2]]);
    // jacobian_clamp (core/splat/gaussian.py) of the render target's camera
    const mx = (0.15 * width) / intr[0], my = (0.15 * height) / intr[1];
    const clampXY = [-intr[2] / intr[0] - mx, (width - intr[2]) / intr[0] + mx, -intr[3] / intr[1] - my, (height - intr[3]) / intr[1] + my];
    this.view = { camera, width, height, intr, w2c: r, w2cT: t, c2wRot, campos: [camera.c2w[0][3], camera.c2w[1][3], camera.c2w[2][3]], clampXY };
    this.ensureTarget(width, height);
  }

  // xi and its basis phi(xi) (core/kinds/dynamic.py: temporal_basis), made in float64 as Python does
  setTime(xi) {
    const w = this.model.timeFrequency;
    this.time = xi;
    this.phi = new Float32Array([xi, xi ** 2, xi ** 3, xi ** 4, ...[1, 2, 3, 4].map((i) => Math.cos(i * w * xi)),
                                 ...[1, 2, 3, 4].map((i) => Math.sin(i * w * xi))]);
  }

  // {position: [x,y,z], intensity} or {direction: [x,y,z] (the way it shines), intensity}
  setLight(light) {
    this.light = light;
  }

  setBackground(rgb) {
    this.background = rgb;
  }

  ensureTarget(width, height) {
    const gl = this.gl;
    if (this.accum && this.accum.width === width && this.accum.height === height) return;
    if (this.accum) {
      gl.deleteTexture(this.accum.texture);
      gl.deleteRenderbuffer(this.accum.stencil);
      gl.deleteFramebuffer(this.accum.framebuffer);
      gl.deleteFramebuffer(this.accum.stencilOnly);
      gl.deleteTexture(this.accum.open);
      gl.deleteFramebuffer(this.accum.openFramebuffer);
    }
    const texture = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, texture);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.texStorage2D(gl.TEXTURE_2D, 1, this.accumFormat, width, height);
    const stencil = gl.createRenderbuffer();
    gl.bindRenderbuffer(gl.RENDERBUFFER, stencil);
    gl.renderbufferStorage(gl.RENDERBUFFER, gl.DEPTH24_STENCIL8, width, height);
    const framebuffer = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, framebuffer);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, texture, 0);
    gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.DEPTH_STENCIL_ATTACHMENT, gl.RENDERBUFFER, stencil);
    if (gl.checkFramebufferStatus(gl.FRAMEBUFFER) !== gl.FRAMEBUFFER_COMPLETE) {
      throw new RenderError(`cannot render to a ${width}x${height} float framebuffer`);
    }
    // the same stencil alone: the termination pass reads the colour texture while it writes the stencil
    const stencilOnly = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, stencilOnly);
    gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.DEPTH_STENCIL_ATTACHMENT, gl.RENDERBUFFER, stencil);
    // the largest transmittance of each BLOCK x BLOCK block (shaders.js: BLOCKS_FRAGMENT)
    const open = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, open);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    const blocks = [Math.ceil(width / BLOCK), Math.ceil(height / BLOCK)];
    gl.texStorage2D(gl.TEXTURE_2D, 1, this.accumFormat === gl.RGBA32F ? gl.R32F : gl.R16F, ...blocks);
    const openFramebuffer = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, openFramebuffer);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, open, 0);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    this.accum = { texture, framebuffer, stencil, stencilOnly, open, openFramebuffer, blocks, width, height };
  }

  // Draw one frame (the order must be set for this camera).
  draw() {
    const gl = this.gl, v = this.view, u = this.splat.uniforms;
    // every block open
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.accum.openFramebuffer);
    gl.clearColor(1, 1, 1, 1);
    gl.clear(gl.COLOR_BUFFER_BIT);
    // 1. the primitives into the float framebuffer, front to back: C += (1 - A) alpha c, A += (1 - A) alpha
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.accum.framebuffer);
    gl.viewport(0, 0, v.width, v.height);
    gl.clearColor(0, 0, 0, 0);
    gl.clearStencil(0);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.STENCIL_BUFFER_BIT);
    gl.useProgram(this.splat.program);
    const set = (name, fn, ...args) => u[name] !== undefined && u[name] !== null && fn.call(gl, u[name], ...args);
    set("uSize", gl.uniform2f, v.width, v.height);
    set("uIntr", gl.uniform4f, ...v.intr);
    set("uNear", gl.uniform1f, this.near);
    set("uW2C", gl.uniformMatrix3fv, false, columnMajor(v.w2c));
    set("uW2Ct", gl.uniform3f, ...v.w2cT);
    set("uC2W", gl.uniformMatrix3fv, false, columnMajor(v.c2wRot));
    set("uCampos", gl.uniform3f, ...v.campos);
    set("uClamp", gl.uniform4f, ...v.clampXY);
    set("uPhi", gl.uniform1fv, this.phi);
    set("uTime", gl.uniform1f, this.time);
    if (this.light) {
      const point = this.light.position !== undefined;
      let l = point ? this.light.position : this.light.direction.map((x) => -x);
      if (!point) {
        const norm = Math.hypot(...l);
        l = l.map((x) => x / norm);
      }
      set("uLight", gl.uniform3f, ...l);
      set("uLightIsPoint", gl.uniform1i, point ? 1 : 0);
      set("uIntensity", gl.uniform1f, this.light.intensity);
    }
    ["uGeo", "uCol", "uMlp"].forEach((name, unit) => {
      gl.activeTexture(gl.TEXTURE0 + unit);
      gl.bindTexture(gl.TEXTURE_2D, this.textures[name.slice(1).toLowerCase()]);
      set(name, gl.uniform1i, unit);
    });
    gl.activeTexture(gl.TEXTURE4);
    gl.bindTexture(gl.TEXTURE_2D, this.accum.open);
    set("uOpen", gl.uniform1i, 4);
    // the termination and block passes read the accumulation on its own unit (never sampled by the splat program)
    gl.activeTexture(gl.TEXTURE3);
    gl.bindTexture(gl.TEXTURE_2D, this.accum.texture);
    gl.useProgram(this.terminate.program);
    gl.uniform1i(this.terminate.uniforms.uAccum, 3);
    gl.useProgram(this.blocks.program);
    gl.uniform1i(this.blocks.uniforms.uAccum, 3);
    gl.uniform2i(this.blocks.uniforms.uTarget, v.width, v.height);

    // the tiles (x0, y0 (rows from the top), width, height): the target in nx x ny equal pieces,
    // each no wider or taller than a point sprite can be (shaders.js: emitQuad)
    const nx = Math.ceil(v.width / this.maxPointSize), ny = Math.ceil(v.height / this.maxPointSize);
    const tiles = [];
    for (let j = 0; j < ny; j++) {
      for (let i = 0; i < nx; i++) {
        const x0 = Math.floor((i * v.width) / nx), y0 = Math.floor((j * v.height) / ny);
        tiles.push([x0, y0, Math.floor(((i + 1) * v.width) / nx) - x0, Math.floor(((j + 1) * v.height) / ny) - y0]);
      }
    }

    const P = this.model.P, chunk = Math.max(CHUNK_MIN, Math.ceil(P / CHUNKS));
    if (!this.software) gl.enable(gl.STENCIL_TEST);
    for (let first = 0; first < P; first += chunk) {
      const count = Math.min(chunk, P - first);
      gl.bindFramebuffer(gl.FRAMEBUFFER, this.accum.framebuffer);
      gl.enable(gl.BLEND);
      gl.blendFunc(gl.ONE_MINUS_DST_ALPHA, gl.ONE);
      gl.stencilFunc(gl.EQUAL, 0, 0xff);          // pixels still open
      gl.stencilOp(gl.KEEP, gl.KEEP, gl.KEEP);
      gl.useProgram(this.splat.program);
      gl.bindVertexArray(this.vao);
      if (tiles.length > 1) gl.enable(gl.SCISSOR_TEST);   // a sprite's square may reach past its tile
      for (const [x0, y0, w, h] of tiles) {
        const glY = v.height - y0 - h;   // WebGL's rows count from the bottom
        gl.viewport(x0, glY, w, h);
        gl.scissor(x0, glY, w, h);
        gl.uniform4f(u.uTile, x0, y0, w, h);
        gl.drawArrays(gl.POINTS, first, count);   // shaders.js: emitQuad
      }
      gl.disable(gl.SCISSOR_TEST);
      gl.viewport(0, 0, v.width, v.height);
      gl.bindVertexArray(null);
      if (first + count < P) {
        // the blocks' largest transmittance, for the next chunks' culling
        gl.disable(gl.BLEND);
        gl.bindFramebuffer(gl.FRAMEBUFFER, this.accum.openFramebuffer);
        gl.viewport(0, 0, ...this.accum.blocks);
        gl.useProgram(this.blocks.program);
        gl.bindVertexArray(this.emptyVao);
        gl.drawArrays(gl.TRIANGLES, 0, 3);
        gl.viewport(0, 0, v.width, v.height);
      }
      if (first + count < P && !this.software) {
        // close the pixels whose transmittance fell below T_MIN
        gl.bindFramebuffer(gl.FRAMEBUFFER, this.accum.stencilOnly);
        gl.disable(gl.BLEND);
        gl.stencilFunc(gl.ALWAYS, 1, 0xff);
        gl.stencilOp(gl.KEEP, gl.KEEP, gl.REPLACE);
        gl.useProgram(this.terminate.program);
        gl.bindVertexArray(this.emptyVao);
        gl.drawArrays(gl.TRIANGLES, 0, 3);
        gl.bindVertexArray(null);
      }
    }
    gl.disable(gl.STENCIL_TEST);
    gl.disable(gl.BLEND);

    // 2. the final pass: background and the n x n box average, to the canvas
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.viewport(0, 0, v.camera.width, v.camera.height);
    gl.useProgram(this.final.program);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, this.accum.texture);
    gl.uniform1i(this.final.uniforms.uAccum, 0);
    gl.uniform1i(this.final.uniforms.uN, this.model.supersample);
    gl.uniform3f(this.final.uniforms.uBackground, ...this.background);
    gl.bindVertexArray(this.emptyVao);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    gl.bindVertexArray(null);
  }

  // Wait for the GPU to finish (a one-pixel read back: gl.finish alone need not block).
  finish() {
    const gl = this.gl;
    gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, new Uint8Array(4));
  }
}
