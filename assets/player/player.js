// acags view: plays a dynamic Gaussian scene served by `acags view` (one standard 3DGS PLY per
// frame). A small WebGL2 splatter that follows acags' rasterizer conventions (gsplat's): pinhole
// camera with the rig's intrinsics (OpenCV axes), 2D covariance J W Σ Wᵀ Jᵀ + 0.3 px² with the
// Jacobian's 1.3× field-of-view clamp, opacity-aware extent, α = min(0.999, o·exp(−σ)), α < 1/255
// skipped, black background. One rule differs: acags composites front to back and leaves out the
// Gaussian that would take a pixel's transmittance below 1e-4 and everything behind it; blending
// back to front with the fixed-function blender cannot see the transmittance, so the player
// draws them. Behind a few near-opaque layers that changes a pixel by up to T·α of the first
// skipped Gaussian (T < 1e-4 / (1 − α): up to ~0.1 in the worst case); on the default run the
// page still matches acags' render to 69.9 dB (docs/results.md, "Export fidelity"). It blends
// into a float target when the browser offers one, so that many layers do not accumulate 8-bit
// rounding.
//
// URL parameters: camera=I (start camera), frame=F (dataset frame), scale=S (canvas = S × the
// rig's resolution; default fits the window), capture=F1,F2 (test hook: steps the time slider
// to each frame, reads the canvas, and writes PNG data URLs and the page's resource list into
// #capture; then one after a 60-pixel drag as key `orbit`).
'use strict';

const NEAR_PLANE = 0.01;
const SH_C0 = 0.28209479177387814;
const SH_COEFFS = [1, 4, 9, 16];

const $ = (id) => document.getElementById(id);
const params = new URLSearchParams(location.search);
const errors = [];

function setStatus(text, isError = false) {
  const s = $('status');
  s.textContent = text;
  s.classList.toggle('error', isError);
}

window.addEventListener('error', (e) => {
  errors.push(String(e.message));
  setStatus('error: ' + e.message, true);
});
window.addEventListener('unhandledrejection', (e) => {
  errors.push(String(e.reason));
  setStatus('error: ' + e.reason, true);
});

// ---------------------------------------------------------------- PLY (binary little endian)

function parsePly(buffer, name) {
  const bytes = new Uint8Array(buffer);
  const head = new TextDecoder().decode(bytes.subarray(0, Math.min(bytes.length, 1 << 16)));
  const end = head.indexOf('end_header\n');
  if (!head.startsWith('ply\n') || end < 0) throw new Error(`${name}: not a PLY file`);
  const lines = head.slice(0, end).split('\n');
  if (!lines.includes('format binary_little_endian 1.0')) {
    throw new Error(`${name}: only binary little-endian PLY is supported`);
  }
  let count = -1;
  const props = [];
  for (const line of lines) {
    const w = line.trim().split(/\s+/);
    if (w[0] === 'element') {
      if (w[1] !== 'vertex' || count >= 0) throw new Error(`${name}: unexpected element ${w[1]}`);
      count = parseInt(w[2], 10);
    } else if (w[0] === 'property') {
      if (w[1] !== 'float') throw new Error(`${name}: property ${w[2]} is ${w[1]}, expected float`);
      props.push(w[2]);
    }
  }
  const stride = props.length;
  const offset = end + 'end_header\n'.length;
  if (!(count >= 0) || bytes.length !== offset + 4 * stride * count) {
    throw new Error(`${name}: ${bytes.length} bytes do not hold ${count} vertices`);
  }
  const data = new Float32Array(buffer.slice(offset));
  const at = (p) => {
    const i = props.indexOf(p);
    if (i < 0) throw new Error(`${name}: vertex property ${p} is missing`);
    return i;
  };
  const rest = props.filter((p) => p.startsWith('f_rest_')).length;
  const degree = [0, 9, 24, 45].indexOf(rest);
  if (degree < 0) throw new Error(`${name}: ${rest} f_rest properties (SH degree 0-3 expected)`);
  const k = SH_COEFFS[degree];
  const ix = [at('x'), at('y'), at('z')];
  const idc = [at('f_dc_0'), at('f_dc_1'), at('f_dc_2')];
  const irest = Array.from({ length: 3 * (k - 1) }, (_, j) => at('f_rest_' + j));
  const iop = at('opacity');
  const isc = [at('scale_0'), at('scale_1'), at('scale_2')];
  const irot = [at('rot_0'), at('rot_1'), at('rot_2'), at('rot_3')];

  const means = new Float32Array(3 * count);
  const cov = new Float32Array(6 * count); // xx xy xz yy yz zz
  const opacity = new Float32Array(count);
  const sh = new Float32Array(3 * k * count); // [n][coeff][channel]
  for (let i = 0; i < count; i++) {
    const row = i * stride;
    for (let a = 0; a < 3; a++) means[3 * i + a] = data[row + ix[a]];
    opacity[i] = 1 / (1 + Math.exp(-data[row + iop]));
    let [w, x, y, z] = irot.map((j) => data[row + j]);
    const n = Math.hypot(w, x, y, z) || 1;
    w /= n; x /= n; y /= n; z /= n;
    const s = isc.map((j) => Math.exp(data[row + j]));
    // M = R S; Σ = M Mᵀ.
    const r = [
      1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
      2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
      2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ];
    const m = [0, 1, 2, 3, 4, 5, 6, 7, 8].map((e) => r[e] * s[e % 3]);
    const dot = (p, q) => m[3 * p] * m[3 * q] + m[3 * p + 1] * m[3 * q + 1] + m[3 * p + 2] * m[3 * q + 2];
    cov.set([dot(0, 0), dot(0, 1), dot(0, 2), dot(1, 1), dot(1, 2), dot(2, 2)], 6 * i);
    for (let c = 0; c < 3; c++) sh[(i * k) * 3 + c] = data[row + idc[c]];
    // f_rest is channel-major: f_rest[c·(k−1) + j] is coefficient j + 1 of channel c.
    for (let c = 0; c < 3; c++) {
      for (let j = 1; j < k; j++) sh[(i * k + j) * 3 + c] = data[row + irest[c * (k - 1) + j - 1]];
    }
  }
  return { count, degree, k, means, cov, opacity, sh, bytes: buffer.byteLength };
}

// Real SH basis, Inria 3DGS constants and signs, at unit direction (x, y, z).
function shBasis(degree, x, y, z, out) {
  out[0] = SH_C0;
  if (degree < 1) return;
  out[1] = -0.4886025119029199 * y;
  out[2] = 0.4886025119029199 * z;
  out[3] = -0.4886025119029199 * x;
  if (degree < 2) return;
  const xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  out[4] = 1.0925484305920792 * xy;
  out[5] = -1.0925484305920792 * yz;
  out[6] = 0.31539156525252005 * (2 * zz - xx - yy);
  out[7] = -1.0925484305920792 * xz;
  out[8] = 0.5462742152960396 * (xx - yy);
  if (degree < 3) return;
  out[9] = -0.5900435899266435 * y * (3 * xx - yy);
  out[10] = 2.890611442640554 * xy * z;
  out[11] = -0.4570457994644658 * y * (4 * zz - xx - yy);
  out[12] = 0.3731763325901154 * z * (2 * zz - 3 * xx - 3 * yy);
  out[13] = -0.4570457994644658 * x * (4 * zz - xx - yy);
  out[14] = 1.445305721320277 * z * (xx - yy);
  out[15] = -0.5900435899266435 * x * (xx - 3 * yy);
}

// ---------------------------------------------------------------- camera

// A pinhole camera: rows of the world-to-camera rotation R, centre c, intrinsics at scale 1.
function cameraFrom(manifestCamera) {
  const m = manifestCamera.world_to_camera;
  const R = [m[0].slice(0, 3), m[1].slice(0, 3), m[2].slice(0, 3)];
  const t = [m[0][3], m[1][3], m[2][3]];
  const c = [0, 1, 2].map((j) => -(R[0][j] * t[0] + R[1][j] * t[1] + R[2][j] * t[2]));
  return { R, c, fx: manifestCamera.fx, fy: manifestCamera.fy, cx: manifestCamera.cx, cy: manifestCamera.cy };
}

function translationOf(cam) {
  return cam.R.map((row) => -(row[0] * cam.c[0] + row[1] * cam.c[1] + row[2] * cam.c[2]));
}

// Rodrigues rotation of v about unit axis k by angle a.
function rotate(v, k, a) {
  const cos = Math.cos(a), sin = Math.sin(a);
  const d = k[0] * v[0] + k[1] * v[1] + k[2] * v[2];
  const x = [k[1] * v[2] - k[2] * v[1], k[2] * v[0] - k[0] * v[2], k[0] * v[1] - k[1] * v[0]];
  return [0, 1, 2].map((i) => v[i] * cos + x[i] * sin + k[i] * d * (1 - cos));
}

// Orbits `cam` about `target` by angle a around world axis k (camera axes turn with it).
function orbit(cam, target, k, a) {
  const off = [0, 1, 2].map((i) => cam.c[i] - target[i]);
  const r = rotate(off, k, a);
  cam.c = [0, 1, 2].map((i) => target[i] + r[i]);
  cam.R = cam.R.map((row) => rotate(row, k, a));
}

// ---------------------------------------------------------------- WebGL2 splatter

const VERTEX_SHADER = `#version 300 es
precision highp float;
layout(location = 0) in vec2 a_corner;
layout(location = 1) in vec3 a_mean;
layout(location = 2) in vec3 a_cov_a;   // xx xy xz
layout(location = 3) in vec3 a_cov_b;   // yy yz zz
layout(location = 4) in vec4 a_color;   // rgb, opacity
uniform mat3 u_rotation;                // world -> camera
uniform vec3 u_translation;
uniform vec4 u_intrinsics;              // fx fy cx cy (pixels)
uniform vec4 u_limits;                  // Jacobian clamp: +x −x +y −y (x/z, y/z)
uniform vec2 u_size;                    // width, height (pixels)
out vec3 v_color;
out float v_opacity;
out vec3 v_conic;
out vec2 v_mean;
void cull() { gl_Position = vec4(0.0, 0.0, 2.0, 1.0); }
void main() {
  vec3 p = u_rotation * a_mean + u_translation;
  if (!(p.z >= ${NEAR_PLANE}) || a_color.a < 1.0 / 255.0) { cull(); return; }
  mat3 S = mat3(a_cov_a.x, a_cov_a.y, a_cov_a.z,
                a_cov_a.y, a_cov_b.x, a_cov_b.y,
                a_cov_a.z, a_cov_b.y, a_cov_b.z);
  mat3 C = u_rotation * S * transpose(u_rotation);
  float fx = u_intrinsics.x, fy = u_intrinsics.y;
  float tx = p.z * clamp(p.x / p.z, -u_limits.y, u_limits.x);
  float ty = p.z * clamp(p.y / p.z, -u_limits.w, u_limits.z);
  vec3 j0 = vec3(fx / p.z, 0.0, -fx * tx / (p.z * p.z));
  vec3 j1 = vec3(0.0, fy / p.z, -fy * ty / (p.z * p.z));
  float sxx = dot(j0, C * j0) + 0.3;
  float sxy = dot(j0, C * j1);
  float syy = dot(j1, C * j1) + 0.3;
  float det = sxx * syy - sxy * sxy;
  if (!(det > 0.0)) { cull(); return; }
  v_conic = vec3(syy, -sxy, sxx) / det;
  v_mean = vec2(fx * p.x / p.z + u_intrinsics.z, fy * p.y / p.z + u_intrinsics.w);
  float extent = min(3.33, sqrt(2.0 * log(a_color.a * 255.0)));
  vec2 radius = ceil(extent * sqrt(vec2(sxx, syy)));
  if (radius.x <= 0.0 && radius.y <= 0.0) { cull(); return; }
  // One pixel of margin: the fragment test, not the quad, decides coverage.
  vec2 pixel = v_mean + a_corner * (radius + 1.0);
  gl_Position = vec4(pixel.x / u_size.x * 2.0 - 1.0, 1.0 - pixel.y / u_size.y * 2.0, 0.0, 1.0);
  v_color = a_color.rgb;
  v_opacity = a_color.a;
}`;

const FRAGMENT_SHADER = `#version 300 es
precision highp float;
in vec3 v_color;
in float v_opacity;
in vec3 v_conic;
in vec2 v_mean;
uniform vec2 u_size;
out vec4 o_color;
void main() {
  // Pixel centre in image coordinates (y down), gsplat's (x + 0.5, y + 0.5).
  vec2 pixel = vec2(gl_FragCoord.x, u_size.y - gl_FragCoord.y);
  vec2 d = v_mean - pixel;
  float sigma = 0.5 * (v_conic.x * d.x * d.x + v_conic.z * d.y * d.y) + v_conic.y * d.x * d.y;
  if (sigma < 0.0) discard;
  float alpha = min(0.999, v_opacity * exp(-sigma));
  if (alpha < 1.0 / 255.0) discard;
  o_color = vec4(v_color * alpha, alpha);
}`;

const BLIT_VERTEX = `#version 300 es
void main() {
  vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
  gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}`;

const BLIT_FRAGMENT = `#version 300 es
precision highp float;
uniform sampler2D u_image;
out vec4 o_color;
void main() {
  vec4 c = texelFetch(u_image, ivec2(gl_FragCoord.xy), 0);
  o_color = vec4(clamp(c.rgb, 0.0, 1.0), 1.0);
}`;

function compile(gl, vs, fs) {
  const program = gl.createProgram();
  for (const [type, src] of [[gl.VERTEX_SHADER, vs], [gl.FRAGMENT_SHADER, fs]]) {
    const s = gl.createShader(type);
    gl.shaderSource(s, src);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error('shader: ' + gl.getShaderInfoLog(s));
    gl.attachShader(program, s);
  }
  gl.linkProgram(program);
  if (!gl.getProgramParameter(program, gl.LINK_STATUS)) throw new Error('program: ' + gl.getProgramInfoLog(program));
  return program;
}

class Splatter {
  constructor(canvas) {
    const gl = canvas.getContext('webgl2', { alpha: false, antialias: false, preserveDrawingBuffer: true, premultipliedAlpha: false });
    if (!gl) throw new Error('this browser has no WebGL2');
    this.gl = gl;
    this.program = compile(gl, VERTEX_SHADER, FRAGMENT_SHADER);
    this.blit = compile(gl, BLIT_VERTEX, BLIT_FRAGMENT);
    this.uniforms = {};
    for (const u of ['u_rotation', 'u_translation', 'u_intrinsics', 'u_limits', 'u_size']) {
      this.uniforms[u] = gl.getUniformLocation(this.program, u);
    }
    this.vao = gl.createVertexArray();
    gl.bindVertexArray(this.vao);
    const corners = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, corners);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 1, -1, -1, 1, 1, 1]), gl.STATIC_DRAW);
    gl.enableVertexAttribArray(0);
    gl.vertexAttribPointer(0, 2, gl.FLOAT, false, 0, 0);
    this.instances = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, this.instances);
    const stride = 13 * 4;
    for (const [loc, size, offset] of [[1, 3, 0], [2, 3, 3], [3, 3, 6], [4, 4, 9]]) {
      gl.enableVertexAttribArray(loc);
      gl.vertexAttribPointer(loc, size, gl.FLOAT, false, stride, offset * 4);
      gl.vertexAttribDivisor(loc, 1);
    }
    gl.bindVertexArray(null);
    // A float target: 32-bit where it can be blended, else 16-bit, else the canvas itself.
    const colorFloat = gl.getExtension('EXT_color_buffer_float');
    const floatBlend = gl.getExtension('EXT_float_blend');
    this.targetFormat = colorFloat ? (floatBlend ? gl.RGBA32F : gl.RGBA16F) : null;
    this.precision = colorFloat ? (floatBlend ? 'float32' : 'float16') : 'unorm8';
    this.size = [0, 0];
    this.scratch = null;
  }

  resize(width, height) {
    const gl = this.gl;
    if (this.size[0] === width && this.size[1] === height) return;
    this.size = [width, height];
    if (!this.targetFormat) return;
    if (this.texture) gl.deleteTexture(this.texture);
    if (this.framebuffer) gl.deleteFramebuffer(this.framebuffer);
    this.texture = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, this.texture);
    gl.texStorage2D(gl.TEXTURE_2D, 1, this.targetFormat, width, height);
    // Float textures are not filterable by default: with a mipmapped/linear filter a read
    // would see an incomplete texture.
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    this.framebuffer = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.framebuffer);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, this.texture, 0);
    if (gl.checkFramebufferStatus(gl.FRAMEBUFFER) !== gl.FRAMEBUFFER_COMPLETE) {
      this.targetFormat = null;
      this.precision = 'unorm8';
    }
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
  }

  // Instance data of `frame` seen from `cam`, back to front (ties: the higher index first, the
  // reverse of acags' stable front-to-back order).
  instancesFor(frame, cam) {
    const n = frame.count;
    const R = cam.R, t = translationOf(cam);
    const keys = new Float32Array(n);
    const order = new Uint32Array(n);
    let live = 0;
    for (let i = 0; i < n; i++) {
      const x = frame.means[3 * i], y = frame.means[3 * i + 1], z = frame.means[3 * i + 2];
      const depth = R[2][0] * x + R[2][1] * y + R[2][2] * z + t[2];
      if (depth >= NEAR_PLANE) { keys[live] = depth; order[live] = i; live++; }
    }
    const sorted = radixSortByKey(keys.subarray(0, live), order.subarray(0, live));
    const out = new Float32Array(13 * live);
    const basis = new Float32Array(16);
    const k = frame.k;
    for (let s = 0; s < live; s++) {
      const i = sorted[live - 1 - s];
      const o = 13 * s;
      out[o] = frame.means[3 * i]; out[o + 1] = frame.means[3 * i + 1]; out[o + 2] = frame.means[3 * i + 2];
      out.set(frame.cov.subarray(6 * i, 6 * i + 6), o + 3);
      let dx = out[o] - cam.c[0], dy = out[o + 1] - cam.c[1], dz = out[o + 2] - cam.c[2];
      const norm = Math.hypot(dx, dy, dz);
      if (norm > 0) { dx /= norm; dy /= norm; dz /= norm; } else { dx = 0; dy = 0; dz = 1; }
      shBasis(frame.degree, dx, dy, dz, basis);
      for (let c = 0; c < 3; c++) {
        let v = 0;
        for (let j = 0; j < k; j++) v += basis[j] * frame.sh[(i * k + j) * 3 + c];
        out[o + 9 + c] = Math.max(v + 0.5, 0);
      }
      out[o + 12] = frame.opacity[i];
    }
    return { data: out, count: live };
  }

  draw(frame, cam, width, height, scale) {
    const gl = this.gl;
    this.resize(width, height);
    const { data, count } = this.instancesFor(frame, cam);
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.targetFormat ? this.framebuffer : null);
    gl.viewport(0, 0, width, height);
    gl.clearColor(0, 0, 0, 0);
    gl.clear(gl.COLOR_BUFFER_BIT);
    gl.useProgram(this.program);
    const R = cam.R;
    // GLSL matrices are column-major: column j holds R[·][j].
    gl.uniformMatrix3fv(this.uniforms.u_rotation, false, [R[0][0], R[1][0], R[2][0], R[0][1], R[1][1], R[2][1], R[0][2], R[1][2], R[2][2]]);
    gl.uniform3fv(this.uniforms.u_translation, translationOf(cam));
    const fx = cam.fx * scale, fy = cam.fy * scale, cx = cam.cx * scale, cy = cam.cy * scale;
    gl.uniform4f(this.uniforms.u_intrinsics, fx, fy, cx, cy);
    const margin = 0.15; // acags' FOV_CLAMP_MARGIN
    gl.uniform4f(this.uniforms.u_limits,
      (width - cx) / fx + margin * width / fx, cx / fx + margin * width / fx,
      (height - cy) / fy + margin * height / fy, cy / fy + margin * height / fy);
    gl.uniform2f(this.uniforms.u_size, width, height);
    gl.enable(gl.BLEND);
    gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
    gl.disable(gl.DEPTH_TEST);
    gl.bindVertexArray(this.vao);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.instances);
    gl.bufferData(gl.ARRAY_BUFFER, data, gl.DYNAMIC_DRAW);
    gl.drawArraysInstanced(gl.TRIANGLE_STRIP, 0, 4, count);
    gl.bindVertexArray(null);
    gl.disable(gl.BLEND);
    if (this.targetFormat) {
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
      gl.viewport(0, 0, width, height);
      gl.useProgram(this.blit);
      gl.activeTexture(gl.TEXTURE0);
      gl.bindTexture(gl.TEXTURE_2D, this.texture);
      gl.drawArrays(gl.TRIANGLES, 0, 3);
    }
    return count;
  }
}

// Indices `order` sorted by ascending positive float `keys` (stable: equal keys keep their
// order). LSD radix sort on the float bits, which order like the values for positive floats.
function radixSortByKey(keys, order) {
  const n = keys.length;
  let k = new Uint32Array(keys.buffer, keys.byteOffset, n).slice();
  let v = order.slice();
  let k2 = new Uint32Array(n), v2 = new Uint32Array(n);
  const counts = new Uint32Array(256);
  for (let shift = 0; shift < 32; shift += 8) {
    counts.fill(0);
    for (let i = 0; i < n; i++) counts[(k[i] >>> shift) & 255]++;
    let sum = 0;
    for (let b = 0; b < 256; b++) { const c = counts[b]; counts[b] = sum; sum += c; }
    for (let i = 0; i < n; i++) {
      const b = (k[i] >>> shift) & 255;
      const at = counts[b]++;
      k2[at] = k[i]; v2[at] = v[i];
    }
    [k, k2] = [k2, k];
    [v, v2] = [v2, v];
  }
  return v;
}

// ---------------------------------------------------------------- the player

class Player {
  constructor(manifest) {
    this.manifest = manifest;
    this.frames = new Array(manifest.frames.length).fill(null);
    this.loading = new Map();
    this.failed = new Map();
    this.loadedBytes = 0;
    this.index = 0;
    this.playing = false;
    this.fps = manifest.fps;
    this.canvas = $('view');
    this.splatter = new Splatter(this.canvas);
    const fit = Math.min((innerWidth - 20) / manifest.width, (innerHeight - 120) / manifest.height);
    this.scale = parseFloat(params.get('scale')) || Math.max(0.25, Math.floor(fit * 4) / 4);
    this.canvas.width = Math.round(manifest.width * this.scale);
    this.canvas.height = Math.round(manifest.height * this.scale);
    this.cameraIndex = manifest.start_camera;
    if (params.has('camera')) this.cameraIndex = parseInt(params.get('camera'), 10);
    if (!(this.cameraIndex >= 0 && this.cameraIndex < manifest.cameras.length)) {
      throw new Error(`camera ${params.get('camera')} does not exist (the rig has ${manifest.cameras.length})`);
    }
    this.resetCamera();
    this.bindControls();
  }

  resetCamera() {
    this.cam = cameraFrom(this.manifest.cameras[this.cameraIndex]);
    this.target = null; // set from the first frame drawn (median depth along the view axis)
    this.draw();
  }

  bindControls() {
    const m = this.manifest;
    const slider = $('time');
    slider.max = String(m.frames.length - 1);
    slider.addEventListener('input', () => this.setFrame(parseInt(slider.value, 10)));
    $('play').addEventListener('click', () => this.togglePlay());
    const fps = $('fps');
    fps.value = String(this.fps);
    fps.addEventListener('change', () => {
      const v = parseFloat(fps.value);
      if (v > 0 && v <= 120) this.fps = v; else fps.value = String(this.fps);
    });
    const select = $('camera');
    m.cameras.forEach((c, i) => {
      const o = document.createElement('option');
      o.value = String(i);
      o.textContent = `${i} ${c.name} (${c.split})`;
      select.appendChild(o);
    });
    select.value = String(this.cameraIndex);
    select.addEventListener('change', () => { this.cameraIndex = parseInt(select.value, 10); this.resetCamera(); });
    $('reset').addEventListener('click', () => this.resetCamera());
    addEventListener('keydown', (e) => {
      // Fields, lists and buttons keep their own keys; no modifier shortcuts.
      const tag = e.target.tagName;
      if ((tag === 'INPUT' && e.target.type !== 'range') || tag === 'SELECT' || tag === 'BUTTON') return;
      if (e.ctrlKey || e.metaKey || e.altKey) return;
      const n = m.frames.length;
      if (e.key === ' ') { if (!e.repeat) this.togglePlay(); e.preventDefault(); }
      // preventDefault: a focused slider would move a second step by itself.
      if (e.key === 'ArrowRight') { this.setFrame((this.index + 1) % n); e.preventDefault(); }
      if (e.key === 'ArrowLeft') { this.setFrame((this.index + n - 1) % n); e.preventDefault(); }
    });
    // Orbit: drag turns about the start camera's up axis and the current right axis, around a
    // target on the view axis; the wheel moves towards or away from it.
    let last = null;
    this.canvas.addEventListener('pointerdown', (e) => {
      last = [e.clientX, e.clientY];
      this.canvas.setPointerCapture(e.pointerId);
      this.canvas.classList.add('dragging');
    });
    const release = () => { last = null; this.canvas.classList.remove('dragging'); };
    for (const ev of ['pointerup', 'pointercancel', 'lostpointercapture']) this.canvas.addEventListener(ev, release);
    this.canvas.addEventListener('pointermove', (e) => {
      if (!last || !this.target) return;
      const [dx, dy] = [e.clientX - last[0], e.clientY - last[1]];
      last = [e.clientX, e.clientY];
      this.dragBy(dx, dy);
    });
    this.canvas.addEventListener('wheel', (e) => {
      if (!this.target) return;
      e.preventDefault();
      const f = Math.exp(e.deltaY * 0.001);
      this.cam.c = this.cam.c.map((v, i) => this.target[i] + (v - this.target[i]) * f);
      this.draw();
    }, { passive: false });
  }

  // A drag of (dx, dy) pixels: orbit about the target.
  dragBy(dx, dy) {
    if (!this.target) return;
    orbit(this.cam, this.target, this.up, -dx * 0.005);
    orbit(this.cam, this.target, this.cam.R[0], dy * 0.005);
    this.draw();
  }

  togglePlay() {
    this.playing = !this.playing;
    $('play').textContent = this.playing ? 'Pause' : 'Play';
    if (this.playing && this.timer == null) {
      this.nextAt = performance.now() + 1000 / this.fps;
      this.schedule();
    }
  }

  // Playback runs on a timer at the chosen rate (each step draws at once); a frame that has not
  // arrived yet is held until it has.
  schedule() {
    this.timer = setTimeout(() => this.tick(), Math.max(0, this.nextAt - performance.now()));
  }

  tick() {
    this.timer = null;
    if (!this.playing) return;
    const interval = 1000 / this.fps;
    const next = (this.index + 1) % this.frames.length;
    if (this.frames[next]) this.setFrame(next);
    const now = performance.now();
    // On a fixed schedule, resynchronised after a stall (a slow draw, a frame still loading).
    this.nextAt = now - this.nextAt > 2 * interval ? now + interval : this.nextAt + interval;
    this.schedule();
  }

  setFrame(i) {
    if (i !== this.index && this.onFrame) this.onFrame(i);
    this.index = i;
    $('time').value = String(i);
    this.load(i).catch((e) => setStatus(`frame ${this.manifest.frames[i]}: ${e.message || e}`, true));
    this.draw();
  }

  // Loads frame i (once); resolves with it.
  load(i) {
    if (this.frames[i]) return Promise.resolve(this.frames[i]);
    if (this.loading.has(i)) return this.loading.get(i);
    const url = `frames/${this.manifest.frames[i]}.ply`;
    const p = fetch(url).then(async (r) => {
      if (!r.ok) throw new Error(`${url}: ${r.status} ${await r.text()}`);
      const frame = parsePly(await r.arrayBuffer(), url);
      this.frames[i] = frame;
      this.loadedBytes += frame.bytes;
      this.failed.delete(i);
      if (i === this.index) this.draw();
      this.showInfo();
      return frame;
    }).finally(() => this.loading.delete(i)); // a failed frame can be asked for again
    this.loading.set(i, p);
    return p;
  }

  // Loads every frame, from the current one on, one request at a time; a frame that fails is
  // reported and skipped (asking for it again, by stepping to it, retries).
  async loadAll() {
    const n = this.frames.length;
    const start = this.index; // fixed: the slider may move while frames load
    for (let s = 0; s < n; s++) {
      const i = (start + s) % n;
      try {
        await this.load(i);
      } catch (e) {
        this.failed.set(i, String(e.message || e));
      }
    }
    if (this.failed.size) {
      const [i, why] = this.failed.entries().next().value;
      setStatus(`${this.failed.size} frame(s) failed to load, e.g. frame ${this.manifest.frames[i]}: ${why}`, true);
    } else {
      setStatus('');
    }
  }

  draw() {
    const frame = this.frames[this.index];
    if (!frame) { this.showInfo(); return; }
    if (!this.target) this.placeTarget(frame);
    this.drawnCount = this.splatter.draw(frame, this.cam, this.canvas.width, this.canvas.height, this.scale);
    this.showInfo();
  }

  placeTarget(frame) {
    const R = this.cam.R, t = translationOf(this.cam);
    const depths = [];
    for (let i = 0; i < frame.count; i += Math.max(1, Math.floor(frame.count / 4096))) {
      const z = R[2][0] * frame.means[3 * i] + R[2][1] * frame.means[3 * i + 1] + R[2][2] * frame.means[3 * i + 2] + t[2];
      if (z > NEAR_PLANE) depths.push(z);
    }
    depths.sort((a, b) => a - b);
    const d = depths.length ? depths[depths.length >> 1] : 1;
    this.target = [0, 1, 2].map((j) => this.cam.c[j] + R[2][j] * d);
    this.up = R[1].map((v) => -v); // OpenCV: y points down
  }

  showInfo() {
    const m = this.manifest;
    const frame = this.frames[this.index];
    const loaded = this.frames.filter(Boolean).length;
    $('frame-label').textContent = `frame ${m.frames[this.index]} (${this.index + 1}/${m.frames.length})`;
    const mib = (b) => (b / (1 << 20)).toFixed(2) + ' MiB';
    const parts = [
      frame ? `${frame.count.toLocaleString()} Gaussians (${(this.drawnCount ?? 0).toLocaleString()} in front of the camera)` : 'loading frame…',
      `${loaded}/${m.frames.length} frames loaded (${mib(this.loadedBytes)} of PLY)`,
      m.file_bytes ? `scene.acags ${mib(m.file_bytes)}` : null,
      `SH degree ${m.sh_degree}`,
      `${this.canvas.width}×${this.canvas.height}, ${this.splatter.precision} blending`,
    ];
    $('info').textContent = parts.filter(Boolean).join(' · ');
  }
}

// Timers, not animation frames: headless Chromium's virtual time runs timers but skips ahead of
// animation frames once the network is idle.
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

// Test hook: step the slider to each frame and read the canvas.
async function capture(player, list, allLoaded) {
  const out = { frames: {}, precision: player.splatter.precision, errors };
  const slider = $('time');
  for (const f of list) {
    const i = player.manifest.frames.indexOf(f);
    if (i < 0) throw new Error(`capture: frame ${f} is not in the scene`);
    await player.load(i);
    slider.value = String(i);
    slider.dispatchEvent(new Event('input'));
    await sleep(0);
    out.frames[f] = player.canvas.toDataURL('image/png');
  }
  // Then a 60-pixel drag to the right, as the mouse would give it.
  player.dragBy(60, 0);
  await sleep(0);
  out.orbit = player.canvas.toDataURL('image/png');
  // Play (the button) for half a second once every frame is in, then pause: how many frames
  // playback advanced.
  await allLoaded;
  const before = player.index;
  let advanced = 0;
  player.onFrame = () => advanced++;
  $('play').click();
  await sleep(500);
  $('play').click();
  const paused = advanced;
  await sleep(300);
  player.onFrame = null;
  out.played = {
    from: player.manifest.frames[before],
    to: player.manifest.frames[player.index],
    steps: paused,
    steps_after_pause: advanced - paused,
    loaded: player.frames.filter(Boolean).length,
  };
  out.resources = performance.getEntriesByType('resource').map((e) => e.name);
  out.page = location.href;
  $('capture').textContent = JSON.stringify(out);
  document.body.dataset.captured = 'true';
}

async function main() {
  const r = await fetch('scene.json');
  if (!r.ok) throw new Error(`scene.json: ${r.status}`);
  const manifest = await r.json();
  document.title = `acags view · ${manifest.title}`;
  const player = new Player(manifest);
  if (params.has('frame')) {
    const i = manifest.frames.indexOf(parseInt(params.get('frame'), 10));
    if (i < 0) throw new Error(`frame ${params.get('frame')} is not in the scene (${manifest.frames[0]}..${manifest.frames[manifest.frames.length - 1]})`);
    player.index = i;
    $('time').value = String(i);
  }
  setStatus('loading frames…');
  const all = player.loadAll();
  if (params.has('capture')) {
    await capture(player, params.get('capture').split(',').map((s) => parseInt(s, 10)), all);
  }
  await all;
  if (params.get('play') === '1') player.togglePlay();
}

main().catch((e) => {
  errors.push(String(e.message || e));
  setStatus('error: ' + (e.message || e), true);
  if (params.has('capture')) {
    $('capture').textContent = JSON.stringify({ errors });
    document.body.dataset.captured = 'true';
  }
});
