// GLSL ES 3.00 sources of the renderer. Each piece mirrors a Python function of radfield's
// renderer (named in its comment); `splatShaders` assembles the program for one model, with the
// model's sizes and kind compiled in as #defines (loops over hidden units have constant bounds).
//
// Conventions (core/render/rasterize.py: render): OpenCV camera (x right, y down, z forward);
// the ray of pixel (row i from the TOP, column j) goes through (j + 1/2, i + 1/2); WebGL's
// gl_FragCoord.y counts from the bottom, so v = height - gl_FragCoord.y. One point sprite per
// primitive covers its integer pixel bounds [x0, x1] x [y0, y1] (QUAD); the fragment shader returns the
// premultiplied (alpha c, alpha) that the blend (ONE_MINUS_DST_ALPHA, ONE) composites front to back
// (eq. 4: C += T alpha c, with T = 1 - the accumulated alpha).

const HEADER = `#version 300 es
precision highp float;
precision highp int;
precision highp sampler2D;
`;

// Per-primitive parameters live in RGBA32F textures (renderer.js: packTextures); primitive p's
// texel k of a texture with STRIDE texels a primitive is at index p * STRIDE + k, row-major in a
// TEX_W wide texture.
const FETCH = `
vec4 texel(sampler2D tex, int index) { return texelFetch(tex, ivec2(index % TEX_W, index / TEX_W), 0); }
// one float of a flat per-primitive array packed four to a texel
float flat1(sampler2D tex, int base, int i) { return texel(tex, base + (i >> 2))[i & 3]; }
vec3 flat3(sampler2D tex, int base, int i) { return vec3(flat1(tex, base, i), flat1(tex, base, i + 1), flat1(tex, base, i + 2)); }
`;

// sin and cos after an explicit reduction to [-pi, pi]: GPUs' fast sin/cos lose accuracy far from
// 0, and the MLP phases reach hundreds of radians (omega0 = 30). The reduction's own error is of
// the order of the float32 rounding the phase already has.
const TRIG = `
const float TWO_PI = 6.283185307179586;
float wrapped(float x) { return x - TWO_PI * floor(x * 0.15915494309189535 + 0.5); }
float sinr(float x) { return sin(wrapped(x)); }
float cosr(float x) { return cos(wrapped(x)); }
`;

// core/splat/sh.py: sh_basis / eval_sh (3DGS order and signs); sh_to_color adds 0.5.
const SH = `
// the K x 3 coefficients from ceil(3K / 4) texels, each fetched once (SHC(j): coefficient j's RGB)
#define SH_TEXELS ((3 * (SH_DEGREE + 1) * (SH_DEGREE + 1) + 3) / 4)
#define SHC(j) vec3(sh[3 * (j)], sh[3 * (j) + 1], sh[3 * (j) + 2])
vec3 shValue(int base, vec3 dir) {
  float sh[4 * SH_TEXELS];
  for (int i = 0; i < SH_TEXELS; i++) {
    vec4 t = texel(uCol, base + i);
    sh[4 * i] = t.x; sh[4 * i + 1] = t.y; sh[4 * i + 2] = t.z; sh[4 * i + 3] = t.w;
  }
  vec3 v = 0.28209479177387814 * shDC(base, SHC(0));
#if SH_DEGREE >= 1
  float x = dir.x, y = dir.y, z = dir.z;
  v += -0.4886025119029199 * y * SHC(1) + 0.4886025119029199 * z * SHC(2) - 0.4886025119029199 * x * SHC(3);
#endif
#if SH_DEGREE >= 2
  float xx = x * x, yy = y * y, zz = z * z;
  v += 1.0925484305920792 * x * y * SHC(4) - 1.0925484305920792 * y * z * SHC(5)
       + 0.31539156525252005 * (2.0 * zz - xx - yy) * SHC(6)
       - 1.0925484305920792 * x * z * SHC(7) + 0.5462742152960396 * (xx - yy) * SHC(8);
#endif
#if SH_DEGREE >= 3
  v += -0.5900435899266435 * y * (3.0 * xx - yy) * SHC(9)
       + 2.890611442640554 * x * y * z * SHC(10)
       - 0.4570457994644658 * y * (4.0 * zz - xx - yy) * SHC(11)
       + 0.3731763325901154 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * SHC(12)
       - 0.4570457994644658 * x * (4.0 * zz - xx - yy) * SHC(13)
       + 1.445305721320277 * z * (xx - yy) * SHC(14)
       - 0.5900435899266435 * x * (xx - 3.0 * yy) * SHC(15);
#endif
  return v;
}
`;

// The SH DC coefficient; for the dynamic kinds S(xi) = S0 + phi(xi) . sh_t
// (core/kinds/dynamic.py: sh_at_time, eq. 10-12; phi(xi) is the uniform uPhi, made by the page).
const SH_DC = `
vec3 shDC(int base, vec3 dc) {
#ifdef DYNAMIC
  for (int i = 0; i < 12; i++) dc += uPhi[i] * flat3(uCol, base, COL_SH_T + 3 * i);
#endif
  return dc;
}
`;

// core/geometry/rotations.py: quat_to_rotmat (of a normalised quaternion w x y z); mat3 columns.
const QUAT = `
mat3 rotation(vec4 q) {
  float w = q.x, x = q.y, y = q.z, z = q.w;
  return mat3(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y),
              2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x),
              2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y));
}
`;

// core/kinds/relight.py: relit_colour (eq. 14) with light_at_primitives and color_network:
// c = (c_dc + W2 softplus(W1 [R^T d, R^T d_l] + b1) + b2) * E, c_dc the SH value + 0.5 (no clamp).
const RELIGHT = `
float softplus(float x) { return x > 20.0 ? x : log(1.0 + exp(x)); }   // torch's threshold 20
vec3 relitColour(int base, vec3 mean, vec3 dir, vec4 quat) {
  vec3 towards; float irradiance;
  if (uLightIsPoint) {
    vec3 toLight = uLight - mean;
    float r2 = dot(toLight, toLight);
    towards = toLight / sqrt(r2);
    irradiance = uIntensity / r2;
  } else {
    towards = uLight;            // -direction, unit (the page normalises it)
    irradiance = uIntensity;
  }
  mat3 rt = transpose(rotation(quat));
  vec3 dOwn = rt * dir, lOwn = rt * towards;
  float x[6] = float[6](dOwn.x, dOwn.y, dOwn.z, lOwn.x, lOwn.y, lOwn.z);
  vec3 net = flat3(uCol, base, COL_NET + 10 * H_COLOR);                  // color_b2
  for (int h = 0; h < H_COLOR; h++) {
    float pre = flat1(uCol, base, COL_NET + 6 * H_COLOR + h);            // color_b1
    for (int i = 0; i < 6; i++) pre += flat1(uCol, base, COL_NET + 6 * h + i) * x[i];
    float hidden = softplus(pre);
    // color_w2 (3, H): row r, column h
    net += hidden * vec3(flat1(uCol, base, COL_NET + 7 * H_COLOR + h), flat1(uCol, base, COL_NET + 8 * H_COLOR + h),
                         flat1(uCol, base, COL_NET + 9 * H_COLOR + h));
  }
  return (shValue(base, dir) + 0.5 + net) * irradiance;
}
`;

// A primitive's colour in this view, every kind (rasterize.py: sh_to_color at d = normalize(mu -
// campos), max(SH + 0.5, 0); relightable kinds: relit_colour, drawn as max(c, 0)).
const VIEW_COLOUR = `
vec3 viewColour(int base, int g, vec3 mean) {
  vec3 dir = normalize(mean - uCampos);
#ifdef RELIGHT
  return max(relitColour(base, mean, dir, texel(uGeo, g + GEO_QUAT)), 0.0);
#else
  return max(shValue(base, dir) + 0.5, 0.0);
#endif
}
`;

const COMMON_UNIFORMS = `
uniform vec2 uSize;          // render target (pixels)
uniform vec4 uIntr;          // fx, fy, cx, cy of the render target
uniform float uNear;
uniform mat3 uW2C;           // world-to-camera rotation
uniform vec3 uW2Ct;          // ... and translation
uniform mat3 uC2W;           // camera-to-world rotation
uniform vec3 uCampos;
uniform sampler2D uGeo, uCol, uMlp;
uniform float uPhi[12];      // dynamic: the temporal basis phi(xi) (core/kinds/dynamic.py: temporal_basis)
uniform float uTime;         // dynamic: xi
uniform vec3 uLight;         // relight: the point light's position, or the unit direction towards it
uniform bool uLightIsPoint;
uniform float uIntensity;
uniform vec4 uClamp;         // gaussian: the EWA Jacobian clamp (lo_x, hi_x, lo_y, hi_y)
`;

// The primitive's integer pixel bounds (x0, y0, x1, y1) (rows from the top) as one point sprite
// (not an instanced quad: SwiftShader pays ~10 us per instance of an instanced draw, and runs the
// vertex shader once per point instead of four times): a square of whole pixels, its side the
// box's longer side, that holds the box; the fragment shader zeroes the square's pixels outside the
// box (vBox). Primitives whose pixel blocks are all done are culled (early termination). The
// target is drawn in tiles (uTile, the viewport) no larger than the point size
// limit, the box clipped to the tile, so the square always fits.
const QUAD = `
in uint aId;                 // the primitive, in front-to-back order
uniform vec4 uTile;          // the tile drawn (the viewport): x0, y0 (rows from the top), width, height
uniform sampler2D uOpen;     // per BLOCK x BLOCK pixel block (rows from the bottom): its largest transmittance
flat out vec4 vBox;          // the clipped box (x0, y0, x1, y1), for the fragments outside it
// Returns false for a culled primitive (its per-view values need not be computed).
bool emitQuad(bool visible, ivec4 box) {
  // clip_bounds (core/splat/view.py): boxes clipped to the image (here: to the tile, a part of
  // it), the empty ones dropped
  ivec4 tile = ivec4(uTile);
  box = ivec4(max(box.xy, tile.xy), min(box.zw, tile.xy + tile.zw - 1));
  if (!visible || box.z < box.x || box.w < box.y) {
    gl_Position = vec4(2.0, 2.0, 2.0, 1.0);   // outside the clip volume: culled
    return false;
  }
  // early termination per primitive: culled where every BLOCK x BLOCK pixel block its box touches
  // is done (the largest transmittance in the block below T_MIN, uOpen: BLOCKS_FRAGMENT, made
  // between chunks of the depth order); boxes over more than SPAN x SPAN blocks are drawn
  ivec2 lo = ivec2(box.x, int(uSize.y) - 1 - box.w) / BLOCK, hi = ivec2(box.z, int(uSize.y) - 1 - box.y) / BLOCK;   // rows from the bottom
  if (hi.x - lo.x < SPAN && hi.y - lo.y < SPAN) {
    bool open = false;
    for (int j = 0; j < SPAN; j++)
      for (int i = 0; i < SPAN; i++)
        if (!open && lo.x + i <= hi.x && lo.y + j <= hi.y) open = texelFetch(uOpen, lo + ivec2(i, j), 0).r >= 1e-4;
    if (!open) {
      gl_Position = vec4(2.0, 2.0, 2.0, 1.0);
      return false;
    }
  }
  vBox = vec4(box);
  ivec2 size = box.zw - box.xy + 1;
  int side = max(size.x, size.y);
  // the square's centre: its left/top pixel edge is the box's, moved back by half the extra
  // (whole pixels, so that no pixel centre lies on the square's edge), plus half its side
  vec2 px = vec2(box.xy - (side - size) / 2) + 0.5 * float(side);
  gl_PointSize = float(side);
  gl_Position = vec4(2.0 * (px.x - uTile.x) / uTile.z - 1.0, 1.0 - 2.0 * (px.y - uTile.y) / uTile.w, 0.0, 1.0);
  return true;
}
`;

const BOX = `
// core/splat/view.py: conic_box's rounding, and the clamp to +-(max(W, H) + 1) before the cast
ivec4 pixelBox(float u0, float v0, float u1, float v1) {
  float big = max(uSize.x, uSize.y) + 1.0;
  vec4 b = clamp(vec4(ceil(u0 - 0.5), ceil(v0 - 0.5), floor(u1 - 0.5), floor(v1 - 0.5)), -big, big);
  return ivec4(b);
}
// camera-frame covariance W Sigma W^T of the world covariance stored in geo texels 1, 2
mat3 cameraCovariance(int g) {
  vec4 s1 = texel(uGeo, g + 1), s2 = texel(uGeo, g + 2);
  mat3 sigma = mat3(s1.x, s1.y, s1.z, s1.y, s1.w, s2.x, s1.z, s2.x, s2.y);
  return uW2C * sigma * transpose(uW2C);
}
`;

// The fragment's pixel centre (column, row from the top, + 1/2) lies in the primitive's box (the
// square sprite's pixels outside it add nothing).
const BOX_FS = `
flat in vec4 vBox;
bool inBox(vec2 uv) { return all(greaterThanEqual(uv, vBox.xy + 0.5)) && all(lessThanEqual(uv, vBox.zw + 0.5)); }
`;

// ---------------------------------------------------------------------------------------------
// Neural primitives: bounds (core/splat/view.py: ellipsoid_bounds, conic_box), the per-view
// tensors (core/splat/neural.py: view_tensors, density_weights) and alpha (pair_alpha).
// ---------------------------------------------------------------------------------------------

const NEURAL_VS = `
flat out vec3 vColour;
flat out vec4 vM0, vM1, vM2; // rows of M R_cam (M = S^-1 R^T): camera-space d -> d' = M d-hat; .w: o' = M (o - mu)
flat out vec3 vMisc;         // 1 / max(s), b2 (times the rest-metric factor), that factor
#ifdef UNITS_IN_VARYINGS
// the per-view MLP tensors of view_tensors, one vec4 per hidden unit: (omega0 W1_k R_cam, c_k), and W2
flat out vec4 vUnit[N_HIDDEN];
flat out vec4 vW2[(N_HIDDEN + 3) / 4];
#else
// too many hidden units for the GPU's varyings: the fragment shader reads W1, b1, W2 from uMlp
flat out vec3 vU0;           // u0 = (o - mu) / max(s)
flat out int vMlp;           // the primitive's first texel in uMlp
#endif

void main() {
  int id = int(aId), g = id * GEO_STRIDE;
  vec4 t0 = texel(uGeo, g);
  vec3 mean = t0.xyz;
  vec3 mc = uW2C * mean + uW2Ct;
  mat3 sc = cameraCovariance(g);
  // ellipsoid_bounds: the dual conic C* = K (m m^T - Sigma) K^T of the bounding ellipsoid
  float zExt = sqrt(sc[2][2]), z = mc.z;
  bool inFront = z - zExt > uNear, visible = z + zExt > uNear;
  ivec4 box = ivec4(0, 0, int(uSize.x) - 1, int(uSize.y) - 1);   // cut by the near plane: the whole image
  if (inFront) {
    mat3 q = outerProduct(mc, mc) - sc;
    // K q K^T entries with K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (q symmetric)
    float fx = uIntr.x, fy = uIntr.y, cx = uIntr.z, cy = uIntr.w;
    vec3 k0q = fx * vec3(q[0][0], q[1][0], q[2][0]) + cx * vec3(q[0][2], q[1][2], q[2][2]);   // row 0 of K q
    vec3 k1q = fy * vec3(q[0][1], q[1][1], q[2][1]) + cy * vec3(q[0][2], q[1][2], q[2][2]);   // row 1
    vec3 k2q = vec3(q[0][2], q[1][2], q[2][2]);                                                // row 2
    float d00 = fx * k0q.x + cx * k0q.z, d02 = k0q.z;
    float d11 = fy * k1q.y + cy * k1q.z, d12 = k1q.z;
    float d22 = k2q.z;
    // conic_box: tangent lines u = const solve C*_00 - 2u C*_02 + u^2 C*_22 = 0 (likewise v)
    float ru = sqrt(max(d02 * d02 - d00 * d22, 0.0)), rv = sqrt(max(d12 * d12 - d11 * d22, 0.0));
    float ua = (d02 + ru) / d22, ub = (d02 - ru) / d22, va = (d12 + rv) / d22, vb = (d12 - rv) / d22;
    box = pixelBox(min(ua, ub), min(va, vb), max(ua, ub), max(va, vb));
  }
  if (!emitQuad(visible, box)) return;   // culled: no fragments read the varyings

  // view_tensors: what depends on the primitive and the camera only, once per primitive and view
  float smax = texel(uGeo, g + 2).z;
  vec3 m0 = texel(uGeo, g + 3).xyz, m1 = texel(uGeo, g + 4).xyz, m2 = texel(uGeo, g + 5).xyz;
  vec3 rel = uCampos - mean;
  vM0 = vec4(m0 * uC2W, dot(m0, rel));      // row of M R_cam, and o'
  vM1 = vec4(m1 * uC2W, dot(m1, rel));
  vM2 = vec4(m2 * uC2W, dot(m2, rel));
  // density_weights: the rest-space metric's factor sqrt(d^T G d) on (W2, b2) at the central ray
  float factor = 1.0;
#ifdef HAS_METRIC
  vec4 g0 = texel(uGeo, g + GEO_METRIC), g1 = texel(uGeo, g + GEO_METRIC + 1);
  vec3 dn = normalize(-rel);
  float quad = g0.x * dn.x * dn.x + g0.y * dn.y * dn.y + g0.z * dn.z * dn.z
             + 2.0 * (g0.w * dn.x * dn.y + g1.x * dn.x * dn.z + g1.y * dn.y * dn.z);
  factor = sqrt(max(quad, 0.0));
#endif
  vMisc = vec3(1.0 / smax, t0.w * factor, factor);
  int mlp = id * MLP_STRIDE;
#ifdef UNITS_IN_VARYINGS
  vec3 u0 = rel / smax;
  for (int k = 0; k < N_HIDDEN; k++) {
    vec4 wb = texel(uMlp, mlp + k);                     // (W1_k, b1_k)
    float b1 = wb.w;
#ifdef DYNAMIC
    b1 = b1 + uTime * flat1(uMlp, mlp + N_HIDDEN + (N_HIDDEN + 3) / 4, k);   // b1 + xi W_t (eq. 13)
#endif
    vec3 w = OMEGA0 * wb.xyz;
    vUnit[k] = vec4(w * uC2W, dot(w, u0) + OMEGA0 * b1);   // omega0 W1_k R_cam, c_k = omega0 (W1_k . u0 + b1_k)
  }
  // W2 four to a texel (the padding past N_HIDDEN is 0 in the texture)
  for (int i = 0; i < (N_HIDDEN + 3) / 4; i++) vW2[i] = texel(uMlp, mlp + N_HIDDEN + i) * factor;
#else
  vU0 = rel / smax;
  vMlp = mlp;
#endif

  vColour = viewColour(id * COL_STRIDE, g, mean);
}
`;

const NEURAL_FS = `
flat in vec3 vColour;
flat in vec4 vM0, vM1, vM2;
flat in vec3 vMisc;
#ifdef UNITS_IN_VARYINGS
flat in vec4 vUnit[N_HIDDEN];
flat in vec4 vW2[(N_HIDDEN + 3) / 4];
#else
flat in vec3 vU0;
flat in int vMlp;
#endif
out vec4 fragColour;

// kernels.py: sinc (unnormalised; its limit 1 at 0), from sin x
float sinc(float x, float sinX) { return x == 0.0 ? 1.0 : sinX / x; }
// kernels.py: window_integral, W(x) = 2 (sin x - x cos x) / x^3, by its series below |x| = 1
float windowIntegral(float x, float sinX, float cosX) {
  if (abs(x) < 1.0) {
    float x2 = x * x;
    return 2.0 / 3.0 - x2 * (1.0 / 15.0 - x2 * (1.0 / 420.0 - x2 * (1.0 / 22680.0 - x2 * (1.0 / 1995840.0 - x2 / 259459200.0))));
  }
  return 2.0 * (sinX - x * cosX) / (x * x * x);
}

void main() {
  // camera_directions: the unit ray through the pixel centre, and the near plane's ray distance
  vec2 uv = vec2(gl_FragCoord.x, uSize.y - gl_FragCoord.y);
  vec3 dc = vec3((uv.x - uIntr.z) / uIntr.x, (uv.y - uIntr.w) / uIntr.y, 1.0);
  float norm = length(dc);
  vec3 d = dc / norm;
  float lNear = uNear * norm;
  // ray_ellipsoid, closest-approach form (stable for grazing rays in float32)
  vec3 de = vec3(dot(vM0.xyz, d), dot(vM1.xyz, d), dot(vM2.xyz, d));   // d' = S^-1 R^T d-hat
  vec3 oe = vec3(vM0.w, vM1.w, vM2.w);
  float a2 = dot(de, de);
  float lMid = -dot(oe, de) / a2;
  vec3 closest = oe + lMid * de;
  float h = dot(closest, closest);
  if (!(h < 1.0) || !inBox(uv)) { fragColour = vec4(0.0); return; }   // no discard: it would turn off the early stencil test
  float halfChord = sqrt((1.0 - h) / a2);
  float lInRaw = lMid - halfChord, lOut = lMid + halfChord;
  float lIn = max(lInRaw, lNear);                       // camera inside: start at the near plane
  float invSmax = vMisc.x;
  float delta = max(lOut - lIn, 0.0) * invSmax;
  float tauM = 0.5 * (lIn + lOut) * invSmax;
#ifdef WINDOW
  // windowed_optical_depth: 1.5 kappa [sum_k W2_k (cos phi dl^3/4 W(x) + e dl^2/2 (cos phi sinc x + sin phi x W(x)/2))
  //                                    + b2 (dl^3/6 + e dl^2/2)]
  float clipE = (lIn - lInRaw) * invSmax;
  float kappa = a2 / (invSmax * invSmax);
  float d2 = 0.5 * delta * delta, d3 = 0.25 * delta * delta * delta;
#endif
  float depth = 0.0;
  FOR_EACH(k, N_HIDDEN) {
#ifdef UNITS_IN_VARYINGS
    float a = dot(vUnit[k].xyz, d);                     // a_k = omega0 W1_k . d-hat
    float c = vUnit[k].w;
    float w2 = vW2[k >> 2][k & 3];
#else
    vec4 wb = texel(uMlp, vMlp + k);                    // (W1_k, b1_k)
    float b1 = wb.w;
#ifdef DYNAMIC
    b1 = b1 + uTime * flat1(uMlp, vMlp + N_HIDDEN + (N_HIDDEN + 3) / 4, k);   // b1 + xi W_t (eq. 13)
#endif
    float a = OMEGA0 * dot(wb.xyz, uC2W * d);
    float c = OMEGA0 * dot(wb.xyz, vU0) + OMEGA0 * b1;
    float w2 = flat1(uMlp, vMlp + N_HIDDEN, k) * vMisc.z;
#endif
    float phase = wrapped(a * tauM + c), x = 0.5 * a * delta;
    float sinX = sinr(x);
#ifdef WINDOW
    float cosX = cosr(x), cosP = cos(phase);
    float wx = windowIntegral(x, sinX, cosX);
    depth += w2 * (cosP * d3 * wx + clipE * d2 * (cosP * sinc(x, sinX) + sin(phase) * (0.5 * x * wx)));
#else
    // neural_optical_depth: sum_k W2_k dl cos(a_k tau_m + c_k) sinc(a_k dl / 2) + b2 dl (eq. 7-8, stable sinc form)
    depth += w2 * delta * cos(phase) * sinc(x, sinX);
#endif
  }
  float b2 = vMisc.y;
#ifdef WINDOW
  depth = 1.5 * kappa * (depth + b2 * (delta * delta * delta / 6.0 + clipE * d2));
#else
  depth += b2 * delta;
#endif
  // alpha_from_optical_depth: 1 - exp(-max(0, I)), at most 0.99, 0 below 1/255 (eq. 9)
  float alpha = min(1.0 - exp(-max(depth, 0.0)), 0.99);
  if (alpha < 1.0 / 255.0) alpha = 0.0;   // (adds nothing to the front-to-back blend)
  fragColour = vec4(alpha * vColour, alpha);
}
`;

// ---------------------------------------------------------------------------------------------
// Gaussians: EWA splatting (core/splat/gaussian.py: ewa_view, splat_bounds; kernels.py: gaussian_alpha).
// ---------------------------------------------------------------------------------------------

const GAUSSIAN_VS = `
flat out vec3 vColour;
flat out vec2 vMean2d;
flat out vec3 vConic;
flat out float vOpacity;

void main() {
  int id = int(aId), g = id * GEO_STRIDE;
  vec4 t0 = texel(uGeo, g);
  vec3 mean = t0.xyz;
  vec3 mc = uW2C * mean + uW2Ct;
  float x = mc.x, y = mc.y, z = mc.z;
  float zs = z > uNear ? z : 1.0;
  float fx = uIntr.x, fy = uIntr.y;
  // ewa_view: the Jacobian at the point clamped to 1.3x the field of view (jacobian_clamp)
  float tx = zs * clamp(x / zs, uClamp.x, uClamp.y), ty = zs * clamp(y / zs, uClamp.z, uClamp.w);
  vec3 j0 = vec3(fx / zs, 0.0, -fx * tx / (zs * zs)), j1 = vec3(0.0, fy / zs, -fy * ty / (zs * zs));
  mat3 sc = cameraCovariance(g);
  float a = dot(j0, sc * j0) + 0.3, b = dot(j0, sc * j1), c = dot(j1, sc * j1) + 0.3;   // + EWA_BLUR
  float det = a * c - b * b;
  vConic = vec3(c, -b, a) / det;
  vMean2d = vec2(fx * x / zs + uIntr.z, fy * y / zs + uIntr.w);
  // splat_bounds: the 3-sigma box of the largest eigenvalue
  float lamMax = 0.5 * (a + c) + sqrt(max(0.25 * (a - c) * (a - c) + b * b, 0.0));
  float radius = ceil(3.0 * sqrt(lamMax));
  ivec4 box = pixelBox(vMean2d.x - radius, vMean2d.y - radius, vMean2d.x + radius, vMean2d.y + radius);
  if (!emitQuad(z > uNear && det > 0.0, box)) return;

  float logit = t0.w;
  int col = id * COL_STRIDE;
#ifdef DYNAMIC
  for (int i = 0; i < 12; i++) logit += uPhi[i] * flat1(uCol, col, COL_OPACITY_T + i);   // o + phi(xi) . opacity_t
#endif
  vOpacity = 1.0 / (1.0 + exp(-logit));
  vColour = viewColour(col, g, mean);
}
`;

const GAUSSIAN_FS = `
flat in vec3 vColour;
flat in vec2 vMean2d;
flat in vec3 vConic;
flat in float vOpacity;
out vec4 fragColour;

void main() {
  vec2 uv = vec2(gl_FragCoord.x, uSize.y - gl_FragCoord.y);   // the pixel centre, rows from the top
  float dx = uv.x - vMean2d.x, dy = uv.y - vMean2d.y;
  // gaussian_alpha
  float power = -0.5 * (vConic.x * dx * dx + vConic.z * dy * dy) - vConic.y * dx * dy;
  float alpha = min(vOpacity * exp(min(power, 0.0)), 0.99);
  if (alpha < 1.0 / 255.0 || power > 0.0 || !inBox(uv)) alpha = 0.0;   // no discard: it would turn off the early stencil test
  fragColour = vec4(alpha * vColour, alpha);
}
`;

// The fragment shader's loop over the hidden units, FOR_EACH(k, N_HIDDEN) { body }, is written out:
// one copy of the body per k, k a constant in each. SwiftShader (the software GL) reads an array of
// varyings at a loop variable's index through memory, lane by lane: that loop alone took 210 of
// 490 ms a frame (10k neural primitives at 800²; written out: 350 ms). It runs every instruction of a
// fragment whatever its branches took, so the copies cost no more than the loop did. (The vertex
// shaders' loops, written out, were not faster: they stay loops.) `counts`: each COUNT's value.
function writeOut(source, counts) {
  const loop = /FOR_EACH\((\w+), (\w+)\) \{/;
  for (let m = source.match(loop); m; m = source.match(loop)) {
    let depth = 1, end = m.index + m[0].length;
    for (; depth > 0; end++) depth += source[end] === "{" ? 1 : source[end] === "}" ? -1 : 0;
    const body = source.slice(m.index + m[0].length, end - 1);
    const count = counts[m[2]];
    const copies = Array.from({ length: count }, (_, i) => `{ const int ${m[1]} = ${i};${body}}`);
    source = source.slice(0, m.index) + copies.join("\n") + source.slice(end);
  }
  return source;
}

// The program that splats one model: its kind and sizes as #defines (layout: renderer.js).
// unitsInVaryings: the GPU has the varyings for one vec4 per hidden unit (renderer.js decides).
export function splatShaders(model, layout, unitsInVaryings) {
  const defines = [
    `#define TEX_W ${layout.texWidth}`,
    `#define GEO_STRIDE ${layout.geo.stride}`,
    `#define COL_STRIDE ${layout.col.stride}`,
    `#define MLP_STRIDE ${Math.max(layout.mlp.stride, 1)}`,
    `#define SH_DEGREE ${model.shDegree}`,
    `#define COL_SH_T ${layout.col.shT}`,
    `#define COL_OPACITY_T ${layout.col.opacityT}`,
    `#define COL_NET ${layout.col.net}`,
    `#define GEO_METRIC ${layout.geo.metric}`,
    `#define GEO_QUAT ${layout.geo.quat}`,
    `#define N_HIDDEN ${Math.max(model.N, 1)}`,
    `#define H_COLOR ${Math.max(model.H, 1)}`,
    `#define OMEGA0 float(${model.omega0})`,
    `#define BLOCK ${BLOCK}`,
    `#define SPAN ${SPAN}`,
  ];
  if (model.dynamic) defines.push("#define DYNAMIC");
  if (model.relight) defines.push("#define RELIGHT");
  if (model.window) defines.push("#define WINDOW");
  if (model.tensors.rest_metric) defines.push("#define HAS_METRIC");
  if (unitsInVaryings) defines.push("#define UNITS_IN_VARYINGS");
  const head = HEADER + defines.join("\n") + "\n" + COMMON_UNIFORMS + FETCH + TRIG;
  const colour = SH_DC + SH + QUAT + (model.relight ? RELIGHT : "") + VIEW_COLOUR;
  return model.neural
    ? { vertex: head + colour + QUAD + BOX + NEURAL_VS, fragment: writeOut(head + BOX_FS + NEURAL_FS, { N_HIDDEN: Math.max(model.N, 1) }) }
    : { vertex: head + colour + QUAD + BOX + GAUSSIAN_VS, fragment: head + BOX_FS + GAUSSIAN_FS };
}

// The final pass: each canvas pixel the mean of its n x n accumulated texels (antialias.py:
// render_supersampled's box average), each texel's colour sum plus the background through its
// transmittance 1 - alpha (rasterize.py: color = acc + T bg). Linear values, no sRGB conversion.
// Early termination (rasterize.py: T_MIN, composite.py: composite_pairs): between chunks of the
// depth order, the pixels whose transmittance fell below T_MIN get stencil 1, and later chunks
// skip them (the stencil test runs before the fragment shader).
export const TERMINATE_FRAGMENT = `#version 300 es
precision highp float;
precision highp sampler2D;
uniform sampler2D uAccum;
void main() {
  if (1.0 - texelFetch(uAccum, ivec2(gl_FragCoord.xy), 0).a >= 1e-4) discard;
}
`;

// The size (pixels) of the blocks of the early termination's culling, and the most blocks a box may
// span (per axis) to be tested (measured on SwiftShader, 100k primitives at 256^2: blocks of 16
// cull 26% of the frame time, of 8 a further 14%).
export const BLOCK = 8;
const SPAN = 4;

// Between chunks of the depth order, each BLOCK x BLOCK pixel block's largest transmittance 1 - A
// (emitQuad culls the primitives whose blocks are all below T_MIN: rasterize.py's early
// termination, per primitive; software GL shades stencil-rejected pixels, this it does not draw).
export const BLOCKS_FRAGMENT = `#version 300 es
#define BLOCK ${BLOCK}
precision highp float;
precision highp int;
precision highp sampler2D;
uniform sampler2D uAccum;
uniform ivec2 uTarget;       // the accumulation's size
out vec4 open;
void main() {
  ivec2 base = ivec2(gl_FragCoord.xy) * BLOCK, end = min(base + BLOCK, uTarget);
  float t = 0.0;
  for (int y = base.y; y < end.y; y++)
    for (int x = base.x; x < end.x; x++) t = max(t, 1.0 - texelFetch(uAccum, ivec2(x, y), 0).a);
  open = vec4(t);
}
`;

export const FINAL_VERTEX = `#version 300 es
void main() {
  // one triangle over the whole canvas
  vec2 p = vec2(float((gl_VertexID & 1) << 2) - 1.0, float((gl_VertexID & 2) << 1) - 1.0);
  gl_Position = vec4(p, 0.0, 1.0);
}
`;

export const FINAL_FRAGMENT = `#version 300 es
precision highp float;
precision highp int;
precision highp sampler2D;
uniform sampler2D uAccum;
uniform int uN;               // supersampling factor
uniform vec3 uBackground;
out vec4 fragColour;
void main() {
  ivec2 p = ivec2(gl_FragCoord.xy) * uN;   // both framebuffers count rows from the bottom
  vec3 sum = vec3(0.0);
  for (int b = 0; b < uN; b++)
    for (int a = 0; a < uN; a++) {
      vec4 acc = texelFetch(uAccum, p + ivec2(a, b), 0);
      sum += acc.rgb + (1.0 - acc.a) * uBackground;
    }
  fragColour = vec4(sum / float(uN * uN), 1.0);
}
`;
