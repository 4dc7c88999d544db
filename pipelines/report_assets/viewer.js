/* texstream relightable viewer: WebGL2, no libraries.
 *
 * Renders a fitted model from its parameter textures with the fit's own shading
 * (render/shading.py, render/kernels.py): the fragment shader is a common prelude (the
 * parameter lookup P, the bilinear texel taps, the surface frame: interpolated vertex normal,
 * tangent = dp/du of the triangle made orthogonal to it, bitangent = n x t; the light uniforms), the
 * model's own GLSL from its plugin (M.shader, fit/models/<kind>/viewer.glsl) defining
 *     vec3 model_radiance(vec2 uv, vec3 pos, vec3 nrm, vec3 tng, vec3 eye, int part)
 * (the radiance toward the eye; part 0 = the full model, 1 and 2 = its diffuse and specular
 * parts), and a common main():
 *     pixel = exposure * model_radiance(...)
 * sRGB-encoded for display, or the error, photo and unseen views. The plugin's integer uniforms
 * (M.uniforms) and extra float textures (M.textures, units 3, 4, ...) come with the model data.
 * No cast shadows (the Warp renderer traces them; see docs/report.md).
 *
 * Cameras follow capture.json: camera_to_world 4x4 in OpenGL axes (x right, y up, looks down -z),
 * pinhole intrinsics fx, fy, cx, cy in pixels with pixel centres at +0.5.
 *
 * Test hook: window.texstreamViewer.{ready, errors, setView(view), status()}; the page writes the
 * status as JSON into #viewer-status. URL hash: #view=<url-encoded JSON> sets the first view and
 * #viewer-only shows the canvas alone at the view's width x height (screenshots).
 */
(function () {
  'use strict';
  var V = window.texstreamViewer = window.texstreamViewer || { ready: false, errors: [] };
  V.draws = 0;

  function fail(msg) {
    V.errors.push(String(msg));
    status();
  }
  function status() {
    var s = { ready: !!V.ready, errors: V.errors, draws: V.draws };
    if (V.state) {
      s.mode = V.state.mode;
      s.frame = V.state.frame;
      s.canvas = [V.canvas.width, V.canvas.height];
      if (V.selfTestMoved !== undefined) s.selftest_moved = V.selfTestMoved;
    }
    var el = document.getElementById('viewer-status');
    if (el) el.textContent = JSON.stringify(s);
    return s;
  }
  V.status = status;

  // ------------------------------------------------------------------ small vector math
  function sub(a, b) { return [a[0] - b[0], a[1] - b[1], a[2] - b[2]]; }
  function add(a, b) { return [a[0] + b[0], a[1] + b[1], a[2] + b[2]]; }
  function scl(a, s) { return [a[0] * s, a[1] * s, a[2] * s]; }
  function dot(a, b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
  function cross(a, b) { return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]; }
  function norm(a) { return Math.sqrt(dot(a, a)); }
  function unit(a) { var n = norm(a); return n > 0 ? scl(a, 1 / n) : [0, 0, 1]; }
  function rot(v, axis, ang) {  // Rodrigues: rotate v about unit axis by ang
    var c = Math.cos(ang), s = Math.sin(ang), k = unit(axis);
    return add(add(scl(v, c), scl(cross(k, v), s)), scl(k, dot(k, v) * (1 - c)));
  }
  function rgb(x) { return (typeof x === 'number') ? [x, x, x] : [+x[0], +x[1], +x[2]]; }

  function b64bytes(s) {
    var bin = atob(s), n = bin.length, u = new Uint8Array(n);
    for (var i = 0; i < n; i++) u[i] = bin.charCodeAt(i);
    return u;
  }
  function f32(s) { var b = b64bytes(s); return new Float32Array(b.buffer, 0, b.length >> 2); }
  function u32(s) { var b = b64bytes(s); return new Uint32Array(b.buffer, 0, b.length >> 2); }

  // ------------------------------------------------------------------ shaders
  var VS = [
    '#version 300 es',
    'precision highp float;',
    'in vec3 a_pos; in vec3 a_nrm; in vec2 a_uv; in vec3 a_tan;',
    'uniform mat3 u_R; uniform vec3 u_t;   // world-to-camera, OpenCV axes',
    'uniform vec4 u_K; uniform vec2 u_size; uniform vec2 u_nf;',
    'out vec3 v_pos; out vec3 v_nrm; out vec2 v_uv; out vec3 v_tan;',
    'void main() {',
    '  vec3 pc = u_R * a_pos + u_t;',
    '  float z = pc.z;',
    '  float px = u_K.x * pc.x + u_K.z * z;  // pixel x times z (capture convention)',
    '  float py = u_K.y * pc.y + u_K.w * z;  // pixel y (down) times z',
    '  float n = u_nf.x, f = u_nf.y;',
    '  gl_Position = vec4(2.0 * px / u_size.x - z, z - 2.0 * py / u_size.y,',
    '                     z * (f + n) / (f - n) - 2.0 * f * n / (f - n), z);',
    '  v_pos = a_pos; v_nrm = a_nrm; v_uv = a_uv; v_tan = a_tan;',
    '}'].join('\n');

  var FS_PRELUDE = [
    '#version 300 es',
    'precision highp float; precision highp int; precision highp sampler2DArray;',
    'precision highp sampler2D;',
    'uniform highp sampler2DArray u_params;  // RGBA32F layers: parameter k in layer k/4, channel k%4',
    'uniform sampler2D u_photo; uniform sampler2D u_seen;',
    'uniform int u_W; uniform int u_H;',
    'uniform int u_lkind; uniform vec3 u_lpd; uniform vec3 u_lI;',
    'uniform vec3 u_eye; uniform float u_exposure; uniform int u_mode; uniform float u_gain;',
    'uniform vec2 u_size; uniform int u_hasphoto;',
    'in vec3 v_pos; in vec3 v_nrm; in vec2 v_uv; in vec3 v_tan;',
    'out vec4 o_color;',
    'float P(ivec2 xy, int k) { return texelFetch(u_params, ivec3(xy, k / 4), 0)[k % 4]; }',
    '// texel_coords + bilinear_taps of shading.py (row 0 at the top, v up): continuous texel coordinates',
    '// (x, y), the top-left tap (x0, y0) of the four and the bilinear weights (fx, fy)',
    'struct Taps { float x; float y; int x0; int y0; float fx; float fy; };',
    'Taps texel_taps(vec2 uv) {',
    '  Taps a;',
    '  a.x = uv.x * float(u_W) - 0.5; a.y = (1.0 - uv.y) * float(u_H) - 0.5;',
    '  float xc = clamp(a.x, 0.0, float(u_W - 1)), yc = clamp(a.y, 0.0, float(u_H - 1));',
    '  a.x0 = max(min(int(floor(xc)), u_W - 2), 0); a.y0 = max(min(int(floor(yc)), u_H - 2), 0);',
    '  a.fx = xc - float(a.x0); a.fy = yc - float(a.y0);',
    '  return a;',
    '}',
    '// surface_frame: tangent = dp/du of the triangle (per face, from the model data), made orthogonal to n;',
    '// columns t, b, n',
    'mat3 surface_frame(vec3 nrm, vec3 tng) {',
    '  vec3 n = normalize(nrm);',
    '  vec3 T = tng - n * dot(n, tng);',
    '  if (length(T) < 1e-12 * max(length(tng), 1e-30) || length(tng) == 0.0) {',
    '    vec3 a = abs(n.x) > 0.9 ? vec3(0.0, 1.0, 0.0) : vec3(1.0, 0.0, 0.0);',
    '    T = a - n * dot(n, a);',
    '  }',
    '  vec3 t = normalize(T);',
    '  return mat3(t, cross(n, t), n);',
    '}',
    'vec3 srgb(vec3 x) {',
    '  x = clamp(x, 0.0, 1.0);',
    '  return mix(x * 12.92, 1.055 * pow(x, vec3(1.0 / 2.4)) - 0.055, step(vec3(0.0031308), x));',
    '}',
    'vec3 linear(vec3 x) {',
    '  return mix(x / 12.92, pow((x + 0.055) / 1.055, vec3(2.4)), step(vec3(0.04045), x));',
    '}'].join('\n');

  var FS_MAIN = [
    'void main() {',
    '  int part = (u_mode == 1) ? 1 : ((u_mode == 2) ? 2 : 0);',
    '  vec3 L = model_radiance(v_uv, v_pos, v_nrm, v_tan, u_eye, part);',
    '  vec3 pix = u_exposure * L;',
    '  vec3 outc = srgb(pix);',
    '  vec2 q = vec2(gl_FragCoord.x / u_size.x, 1.0 - gl_FragCoord.y / u_size.y);  // photo UV, row 0 at top',
    '  if (u_mode == 3) {  // error: |render - photo| (linear) times gain',
    '    outc = u_hasphoto != 0 ? srgb(u_gain * abs(pix - linear(texture(u_photo, q).rgb))) : vec3(0.5, 0.0, 0.5);',
    '  } else if (u_mode == 4) {  // the photo itself',
    '    outc = u_hasphoto != 0 ? texture(u_photo, q).rgb : vec3(0.5, 0.0, 0.5);',
    '  } else if (u_mode == 5) {  // texels no photo saw (nearest texel), magenta',
    '    Taps a = texel_taps(v_uv);',
    '    ivec2 nx = ivec2(clamp(int(floor(a.x + 0.5)), 0, u_W - 1), clamp(int(floor(a.y + 0.5)), 0, u_H - 1));',
    '    if (texelFetch(u_seen, nx, 0).r < 0.5) outc = mix(outc, vec3(1.0, 0.0, 1.0), 0.7);',
    '  }',
    '  o_color = vec4(outc, 1.0);',
    '}'].join('\n');

  var MODES = { full: 0, diffuse: 1, specular: 2, error: 3, photo: 4, unseen: 5 };

  function compile(gl, type, src) {
    var s = gl.createShader(type);
    gl.shaderSource(s, src);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error('shader compile: ' + gl.getShaderInfoLog(s));
    return s;
  }

  // ------------------------------------------------------------------ set-up
  function init() {
    var dataEl = document.getElementById('texstream-model');
    var canvas = document.getElementById('viewer-canvas');
    if (!dataEl || !canvas) { fail('viewer: page has no model data or canvas'); return; }
    var M = JSON.parse(dataEl.textContent);
    V.model = M;
    V.canvas = canvas;
    var gl = canvas.getContext('webgl2', { antialias: false, preserveDrawingBuffer: true, alpha: false });
    if (!gl) { fail('viewer: WebGL2 is not available in this browser'); return; }
    V.gl = gl;
    canvas.addEventListener('webglcontextlost', function (e) { e.preventDefault(); fail('viewer: WebGL context lost'); });

    var prog = gl.createProgram();
    gl.attachShader(prog, compile(gl, gl.VERTEX_SHADER, VS));
    gl.attachShader(prog, compile(gl, gl.FRAGMENT_SHADER, [FS_PRELUDE, M.shader, FS_MAIN].join('\n')));
    gl.bindAttribLocation(prog, 0, 'a_pos');
    gl.bindAttribLocation(prog, 1, 'a_nrm');
    gl.bindAttribLocation(prog, 2, 'a_uv');
    gl.bindAttribLocation(prog, 3, 'a_tan');
    gl.linkProgram(prog);
    if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error('shader link: ' + gl.getProgramInfoLog(prog));
    V.prog = prog;
    var U = {};
    ['u_R', 'u_t', 'u_K', 'u_size', 'u_nf', 'u_params', 'u_photo', 'u_seen', 'u_W', 'u_H',
      'u_lkind', 'u_lpd', 'u_lI', 'u_eye', 'u_exposure', 'u_mode', 'u_gain', 'u_hasphoto'
    ].concat(Object.keys(M.uniforms), M.textures.map(function (t) { return t.name; }))
      .forEach(function (k) { U[k] = gl.getUniformLocation(prog, k); });
    V.U = U;

    // mesh
    var vao = gl.createVertexArray();
    gl.bindVertexArray(vao);
    [[M.mesh.positions, 3], [M.mesh.normals, 3], [M.mesh.uvs, 2], [M.mesh.tangents, 3]].forEach(function (a, i) {
      var buf = gl.createBuffer();
      gl.bindBuffer(gl.ARRAY_BUFFER, buf);
      gl.bufferData(gl.ARRAY_BUFFER, f32(a[0]), gl.STATIC_DRAW);
      gl.enableVertexAttribArray(i);
      gl.vertexAttribPointer(i, a[1], gl.FLOAT, false, 0, 0);
    });
    var ibuf = gl.createBuffer();
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, ibuf);
    var idx = u32(M.mesh.indices);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, idx, gl.STATIC_DRAW);
    V.nIndices = idx.length;
    V.vao = vao;

    // parameter textures: exact float values, fetched with texelFetch (no filtering)
    var T = M.texture;
    var tex = gl.createTexture();
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D_ARRAY, tex);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    gl.texImage3D(gl.TEXTURE_2D_ARRAY, 0, gl.RGBA32F, T.width, T.height, T.layers, 0, gl.RGBA, gl.FLOAT, f32(T.data));
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    V.paramTex = tex;

    // seen map (R8, 255 = some photo saw the texel)
    var seen = gl.createTexture();
    gl.activeTexture(gl.TEXTURE2);
    gl.bindTexture(gl.TEXTURE_2D, seen);
    var sdata = M.seen ? b64bytes(M.seen) : new Uint8Array(T.width * T.height).fill(255);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.R8, T.width, T.height, 0, gl.RED, gl.UNSIGNED_BYTE, sdata);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);

    V.photoTex = gl.createTexture();
    V.photoFor = null;

    // the model's own float textures (RGBA32F, exact values, texelFetch): units 3, 4, ...; a 2D array where
    // the texture has layers
    M.textures.forEach(function (T, i) {
      var t = gl.createTexture(), target = T.layers ? gl.TEXTURE_2D_ARRAY : gl.TEXTURE_2D;
      gl.activeTexture(gl.TEXTURE3 + i);
      gl.bindTexture(target, t);
      if (T.layers) gl.texImage3D(target, 0, gl.RGBA32F, T.width, T.height, T.layers, 0, gl.RGBA, gl.FLOAT, f32(T.data));
      else gl.texImage2D(target, 0, gl.RGBA32F, T.width, T.height, 0, gl.RGBA, gl.FLOAT, f32(T.data));
      gl.texParameteri(target, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
      gl.texParameteri(target, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    });

    var s0 = M.frames.length ? M.frames[M.default_frame || 0] : null;
    V.state = {
      cam: null, exposure: 1, mode: 'full', frame: -1, gain: 4,
      light: { type: 'point', pos: add(M.center, [0, 0, 3 * M.radius]), intensity: [1, 1, 1] },
      exposureBase: 1, stops: 0
    };
    if (s0) applyFrame(M.default_frame || 0); else lookAt(add(M.center, [0, -3 * M.radius, 0]), M.center, [0, 0, 1], 512, 512, 40);
    var err = gl.getError();
    if (err !== gl.NO_ERROR) fail('viewer: GL error ' + err + ' during set-up');
  }

  // ------------------------------------------------------------------ camera and light state
  function camFromC2W(m, width, height, K) {
    // capture.json camera_to_world (OpenGL axes): columns right, up, back; last column the eye
    var c = {
      right: unit([m[0][0], m[1][0], m[2][0]]), up: unit([m[0][1], m[1][1], m[2][1]]),
      back: unit([m[0][2], m[1][2], m[2][2]]), eye: [m[0][3], m[1][3], m[2][3]],
      width: width, height: height
    };
    c.fx = K[0]; c.fy = K[1]; c.cx = K[2]; c.cy = K[3];
    return c;
  }
  function intrinsicsFromFov(fovYdeg, width, height) {
    var fy = 0.5 * height / Math.tan(0.5 * fovYdeg * Math.PI / 180);
    return [fy, fy, 0.5 * width, 0.5 * height];
  }
  function lookAt(eye, target, up, width, height, fovYdeg) {
    var back = unit(sub(eye, target));
    var right = cross(up, back);
    if (norm(right) < 1e-9) right = cross(Math.abs(back[1]) < 0.9 ? [0, 1, 0] : [1, 0, 0], back);
    right = unit(right);
    var c = { eye: eye.slice(), back: back, right: right, up: cross(back, right), width: width, height: height };
    var K = intrinsicsFromFov(fovYdeg, width, height);
    c.fx = K[0]; c.fy = K[1]; c.cx = K[2]; c.cy = K[3];
    V.state.cam = c;
  }
  function lightFromJSON(L) {
    var t = L.type || 'point';
    if (t !== 'point' && t !== 'directional') throw new Error('light type ' + t + " is not 'point' or 'directional'");
    return { type: t, pos: (t === 'point' ? L.position : L.direction).slice(0, 3).map(Number), intensity: rgb(L.intensity) };
  }
  function applyFrame(i) {
    var M = V.model, F = M.frames[i];
    if (!F) throw new Error('no frame ' + i + ' (the model has ' + M.frames.length + ')');
    V.state.cam = camFromC2W(F.camera_to_world, F.width, F.height, [F.fx, F.fy, F.cx, F.cy]);
    if (F.light) V.state.light = lightFromJSON(F.light);
    V.state.exposureBase = F.exposure;
    V.state.stops = 0;
    V.state.exposure = F.exposure;
    V.state.frame = i;
  }

  // setView: {frame, camera_to_world | eye/target/up, fx/fy/cx/cy | fov_y_deg, width, height,
  //           light: {type, position|direction, intensity}, exposure, mode, gain}
  function setView(v) {
    var S = V.state, M = V.model;
    try {
      if (v.frame !== undefined && v.frame !== null) applyFrame(v.frame | 0);
      var width = v.width || (S.cam ? S.cam.width : 512), height = v.height || (S.cam ? S.cam.height : 512);
      var K = null;
      if (v.fx !== undefined) K = [v.fx, v.fy === undefined ? v.fx : v.fy,
        v.cx === undefined ? width / 2 : v.cx, v.cy === undefined ? height / 2 : v.cy];
      else if (v.fov_y_deg !== undefined) K = intrinsicsFromFov(v.fov_y_deg, width, height);
      if (v.camera_to_world) {
        S.cam = camFromC2W(v.camera_to_world, width, height, K || [S.cam.fx, S.cam.fy, S.cam.cx, S.cam.cy]);
        S.frame = -1;
      } else if (v.eye) {
        lookAt(v.eye.map(Number), (v.target || M.center).map(Number), (v.up || [0, 0, 1]).map(Number), width, height,
          v.fov_y_deg || 40);
        if (K) { S.cam.fx = K[0]; S.cam.fy = K[1]; S.cam.cx = K[2]; S.cam.cy = K[3]; }
        S.frame = -1;
      } else if (K || v.width || v.height) {
        if (K) { S.cam.fx = K[0]; S.cam.fy = K[1]; S.cam.cx = K[2]; S.cam.cy = K[3]; }
        S.cam.width = width; S.cam.height = height;
      }
      if (v.light) { S.light = lightFromJSON(v.light); }
      if (v.exposure !== undefined) { S.exposureBase = +v.exposure; S.stops = 0; S.exposure = +v.exposure; }
      if (v.mode !== undefined) {
        if (!(v.mode in MODES)) throw new Error('unknown mode ' + v.mode + ' (use ' + Object.keys(MODES).join(', ') + ')');
        S.mode = v.mode;
      }
      if (v.gain !== undefined) S.gain = +v.gain;
      if (v.width && v.height) sizeCanvas(v.width, v.height);
      draw();
      syncControls();
    } catch (e) {
      fail('setView: ' + (e && e.message ? e.message : e));
    }
    return status();
  }
  V.setView = setView;

  function sizeCanvas(w, h) {
    var c = V.canvas;
    c.width = Math.round(w); c.height = Math.round(h);
    c.style.width = Math.round(w) + 'px'; c.style.height = Math.round(h) + 'px';
  }
  function fitCanvasToPanel() {
    // report mode: canvas at most 560 px wide (controls beside it), aspect of the camera's image
    if (document.body.classList.contains('viewer-only')) return;
    var cam = V.state.cam, panel = document.getElementById('viewer-panel');
    var w = Math.min(560, Math.max(240, (panel ? panel.clientWidth : 560) - 300));
    sizeCanvas(w, Math.round(w * cam.height / cam.width));
  }

  function uploadPhoto(i) {
    var gl = V.gl, F = i >= 0 ? V.model.frames[i] : null;
    if (V.photoFor === i) return !!(F && F.photo);
    V.photoFor = i;
    if (!F || !F.photo) return false;
    gl.activeTexture(gl.TEXTURE1);
    gl.bindTexture(gl.TEXTURE_2D, V.photoTex);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB8, F.photo.width, F.photo.height, 0, gl.RGB, gl.UNSIGNED_BYTE, b64bytes(F.photo.data));
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    return true;
  }

  // ------------------------------------------------------------------ draw
  function draw() {
    var gl = V.gl, S = V.state, M = V.model, U = V.U, cam = S.cam, cv = V.canvas;
    var W = cv.width, H = cv.height, sx = W / cam.width, sy = H / cam.height;
    // world-to-camera in OpenCV axes: rows right, -up, -back
    var R = [cam.right, scl(cam.up, -1), scl(cam.back, -1)];
    var t = [-dot(R[0], cam.eye), -dot(R[1], cam.eye), -dot(R[2], cam.eye)];
    var dist = norm(sub(cam.eye, M.center));
    var near = Math.max(0.5 * (dist - M.radius), 1e-4 * M.radius), far = dist + 2 * M.radius;
    gl.viewport(0, 0, W, H);
    gl.clearColor(S.background[0], S.background[1], S.background[2], 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.enable(gl.DEPTH_TEST);
    gl.disable(gl.CULL_FACE);
    gl.useProgram(V.prog);
    // column-major mat3 of R
    gl.uniformMatrix3fv(U.u_R, false, [R[0][0], R[1][0], R[2][0], R[0][1], R[1][1], R[2][1], R[0][2], R[1][2], R[2][2]]);
    gl.uniform3fv(U.u_t, t);
    gl.uniform4f(U.u_K, cam.fx * sx, cam.fy * sy, cam.cx * sx, cam.cy * sy);
    gl.uniform2f(U.u_size, W, H);
    gl.uniform2f(U.u_nf, near, far);
    gl.uniform1i(U.u_params, 0);
    gl.uniform1i(U.u_photo, 1);
    gl.uniform1i(U.u_seen, 2);
    gl.uniform1i(U.u_W, M.texture.width);
    gl.uniform1i(U.u_H, M.texture.height);
    M.textures.forEach(function (T, i) { gl.uniform1i(U[T.name], 3 + i); });
    Object.keys(M.uniforms).forEach(function (k) { gl.uniform1i(U[k], M.uniforms[k]); });
    gl.uniform1i(U.u_lkind, S.light.type === 'point' ? 0 : 1);
    gl.uniform3fv(U.u_lpd, S.light.pos);
    gl.uniform3fv(U.u_lI, S.light.intensity);
    gl.uniform3fv(U.u_eye, cam.eye);
    gl.uniform1f(U.u_exposure, S.exposure);
    gl.uniform1i(U.u_mode, MODES[S.mode]);
    gl.uniform1f(U.u_gain, S.gain);
    gl.uniform1i(U.u_hasphoto, (S.frame >= 0 && uploadPhoto(S.frame)) ? 1 : 0);
    gl.activeTexture(gl.TEXTURE1);
    gl.bindTexture(gl.TEXTURE_2D, V.photoTex);
    gl.bindVertexArray(V.vao);
    gl.drawElements(gl.TRIANGLES, V.nIndices, gl.UNSIGNED_INT, 0);
    var err = gl.getError();
    if (err !== gl.NO_ERROR) fail('viewer: GL error ' + err + ' while drawing');
    V.draws += 1;
    var note = document.getElementById('viewer-note');
    if (note) {
      var needsPhoto = (S.mode === 'error' || S.mode === 'photo');
      var F = S.frame >= 0 ? M.frames[S.frame] : null;
      note.textContent = needsPhoto && !(F && F.photo)
        ? 'The ' + S.mode + ' view needs a photo view: pick a photo marked [photo] (orbiting leaves it).'
        : (F ? 'View of ' + F.name + (F.held_out ? ' (held out)' : '') : 'Free view');
    }
  }
  V.draw = draw;

  // ------------------------------------------------------------------ interaction
  function orbitCamera(dx, dy) {
    var S = V.state, c = S.cam, M = V.model;
    var off = sub(c.eye, M.center);
    var ay = -dx * 0.008, ax = -dy * 0.008;
    off = rot(off, c.up, ay); c.right = rot(c.right, c.up, ay); c.back = rot(c.back, c.up, ay);
    off = rot(off, c.right, ax); c.up = rot(c.up, c.right, ax); c.back = rot(c.back, c.right, ax);
    c.eye = add(M.center, off);
    S.frame = -1;
  }
  function moveLight(dx, dy) {
    var S = V.state, c = S.cam, M = V.model, L = S.light;
    var ay = dx * 0.01, ax = dy * 0.01;
    if (L.type === 'point') {
      var off = sub(L.pos, M.center);
      off = rot(rot(off, c.up, ay), c.right, ax);
      L.pos = add(M.center, off);
    } else {
      L.pos = rot(rot(L.pos, c.up, ay), c.right, ax);
    }
    S.frame = -1;
  }
  function lightAngles() {  // azimuth / elevation of the light seen from the object, camera axes
    var S = V.state, c = S.cam, L = S.light;
    var d = L.type === 'point' ? unit(sub(L.pos, V.model.center)) : scl(unit(L.pos), -1);
    var el = Math.asin(Math.max(-1, Math.min(1, dot(d, c.up))));
    var az = Math.atan2(dot(d, c.right), dot(d, c.back));
    return [az * 180 / Math.PI, el * 180 / Math.PI];
  }
  function setLightAngles(azDeg, elDeg) {
    var S = V.state, c = S.cam, L = S.light, M = V.model;
    var az = azDeg * Math.PI / 180, el = elDeg * Math.PI / 180;
    var d = add(scl(add(scl(c.right, Math.sin(az)), scl(c.back, Math.cos(az))), Math.cos(el)), scl(c.up, Math.sin(el)));
    if (L.type === 'point') L.pos = add(M.center, scl(d, norm(sub(L.pos, M.center))));
    else L.pos = scl(d, -1);
    S.frame = -1;
  }
  function syncControls() {
    var S = V.state, q = function (id) { return document.getElementById(id); };
    if (!q('ctl-mode')) return;
    q('ctl-mode').value = S.mode;
    q('ctl-frame').value = String(S.frame);
    var a = lightAngles();
    q('ctl-laz').value = a[0]; q('ctl-lel').value = a[1];
    q('ctl-exp').value = S.stops;
    q('ctl-exp-out').textContent = (S.stops >= 0 ? '+' : '') + S.stops.toFixed(1) + ' EV';
  }
  function wire() {
    var cv = V.canvas, S = V.state, M = V.model;
    var q = function (id) { return document.getElementById(id); };
    var drag = null;
    cv.addEventListener('pointerdown', function (e) {
      drag = { x: e.clientX, y: e.clientY, light: e.shiftKey || e.button === 2 };
      cv.setPointerCapture(e.pointerId);
    });
    cv.addEventListener('pointermove', function (e) {
      if (!drag) return;
      var dx = e.clientX - drag.x, dy = e.clientY - drag.y;
      drag.x = e.clientX; drag.y = e.clientY;
      if (drag.light) moveLight(dx, dy); else orbitCamera(dx, dy);
      draw(); syncControls();
    });
    cv.addEventListener('pointerup', function () { drag = null; });
    cv.addEventListener('contextmenu', function (e) { e.preventDefault(); });
    cv.addEventListener('wheel', function (e) {
      e.preventDefault();
      var c = S.cam, k = Math.exp(0.001 * e.deltaY);
      c.eye = add(M.center, scl(sub(c.eye, M.center), k));
      S.frame = -1;
      draw(); syncControls();
    }, { passive: false });
    if (!q('ctl-mode')) return;
    var sel = q('ctl-frame');
    var free = document.createElement('option');
    free.value = '-1'; free.textContent = '(free view)';
    sel.appendChild(free);
    M.frames.forEach(function (F, i) {
      var o = document.createElement('option');
      o.value = String(i);
      o.textContent = F.name + (F.held_out ? ' (held out)' : '') + (F.photo ? ' [photo]' : '');
      sel.appendChild(o);
    });
    sel.addEventListener('change', function () {
      var i = +sel.value;
      if (i >= 0) { applyFrame(i); fitCanvasToPanel(); draw(); syncControls(); }
    });
    q('ctl-mode').addEventListener('change', function () { S.mode = q('ctl-mode').value; draw(); });
    var onLight = function () { setLightAngles(+q('ctl-laz').value, +q('ctl-lel').value); draw(); syncControls(); };
    q('ctl-laz').addEventListener('input', onLight);
    q('ctl-lel').addEventListener('input', onLight);
    q('ctl-exp').addEventListener('input', function () {
      S.stops = +q('ctl-exp').value; S.exposure = S.exposureBase * Math.pow(2, S.stops); draw(); syncControls();
    });
    syncControls();
  }

  // exercise the interaction handlers with synthetic events (the tests' #selftest): orbit, light drag,
  // wheel, every control; any exception lands in V.errors through window.onerror or the catch below
  function selfTest() {
    var cv = V.canvas, before = JSON.stringify([V.state.cam.eye, V.state.light.pos]);
    var pe = function (type, x, y, shift) {
      var e = new PointerEvent(type, { clientX: x, clientY: y, shiftKey: !!shift, pointerId: 1, bubbles: true });
      cv.dispatchEvent(e);
    };
    try {
      pe('pointerdown', 10, 10); pe('pointermove', 40, 25); pe('pointerup', 40, 25);
      pe('pointerdown', 10, 10, true); pe('pointermove', 30, 50, true); pe('pointerup', 30, 50, true);
      cv.dispatchEvent(new WheelEvent('wheel', { deltaY: 120, bubbles: true, cancelable: true }));
      var q = function (id) { return document.getElementById(id); };
      [['ctl-laz', '45', 'input'], ['ctl-lel', '30', 'input'], ['ctl-exp', '1.5', 'input'],
        ['ctl-mode', 'specular', 'change'], ['ctl-frame', '0', 'change']].forEach(function (c) {
        var el = q(c[0]);
        if (!el) return;
        if (c[0] === 'ctl-frame' && !V.model.frames.length) return;
        el.value = c[1];
        el.dispatchEvent(new Event(c[2], { bubbles: true }));
      });
      V.selfTestMoved = JSON.stringify([V.state.cam.eye, V.state.light.pos]) !== before;
    } catch (e) {
      fail('selftest: ' + (e && e.message ? e.message : e));
    }
  }
  V.selfTest = selfTest;

  // ------------------------------------------------------------------ start
  function parseHash() {
    var out = {};
    location.hash.replace(/^#/, '').split('&').forEach(function (kv) {
      if (!kv) return;
      var i = kv.indexOf('=');
      out[decodeURIComponent(i < 0 ? kv : kv.slice(0, i))] = i < 0 ? true : decodeURIComponent(kv.slice(i + 1));
    });
    return out;
  }
  function start() {
    try {
      var h = parseHash();
      if (h['viewer-only']) document.body.classList.add('viewer-only');
      init();
      if (!V.gl) return;
      V.state.background = h['viewer-only'] ? [0, 0, 0] : [0.16, 0.16, 0.18];
      fitCanvasToPanel();
      wire();
      V.ready = true;
      if (h.view) setView(JSON.parse(h.view)); else draw();
      if (h.selftest) selfTest();
    } catch (e) {
      V.ready = false;
      fail('viewer: ' + (e && e.message ? e.message : e));
    }
    status();
  }
  if (document.readyState === 'loading') document.addEventListener('DOMContentLoaded', start); else start();
})();
