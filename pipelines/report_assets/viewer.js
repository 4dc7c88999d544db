/* texstream relightable viewer: WebGL2, no libraries.
 *
 * Renders a fitted model from its parameter textures with the fit's own shading
 * (fit/kernels/shading.py, fit/kernels/render.py): per pixel the surface frame (interpolated vertex
 * normal, tangent = dp/du of the triangle made orthogonal to it, bitangent = n x t), the light's
 * unit direction and irradiance (point: intensity / r^2, directional: intensity), the Lafortune
 * BRDF evaluated at the four texels around the hit and blended with the bilinear weights, and
 *     pixel = exposure * f_r * E * cos(theta_i)   (0 where cos <= 0)
 * sRGB-encoded for display. Model kind "radiance" is unlit: pixel = exposure * radiance; "view_radiance"
 * is unlit too, its radiance the biquadratic of the local view direction of fit/kernels/shading.py
 * view_radiance (clamped at 0 like fit/kernels/render.py). "lfm" (light field mapping) is unlit: each
 * of the four texels around the hit sums its view-independent term and, per vertex of its triangle and
 * term, surface map times the vertex's view map looked up along the view direction in the vertex's
 * frame (disk or hemi-octahedral mapping, nearest or bilinear), as fit/kernels/lfm.py render_lfm_kernel.
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

  var FS = [
    '#version 300 es',
    'precision highp float; precision highp int; precision highp sampler2DArray;',
    'precision highp sampler2D;',
    'uniform highp sampler2DArray u_params;  // RGBA32F layers: parameter k in layer k/4, channel k%4',
    'uniform sampler2D u_photo; uniform sampler2D u_seen;',
    'uniform int u_W; uniform int u_H; uniform int u_kind; uniform int u_nlobes; uniform int u_aniso;',
    'uniform int u_lkind; uniform vec3 u_lpd; uniform vec3 u_lI;',
    'uniform vec3 u_eye; uniform float u_exposure; uniform int u_mode; uniform float u_gain;',
    'uniform vec2 u_size; uniform int u_hasphoto;',
    'in vec3 v_pos; in vec3 v_nrm; in vec2 v_uv; in vec3 v_tan;',
    'out vec4 o_color;',
    'float P(ivec2 xy, int k) { return texelFetch(u_params, ivec3(xy, k / 4), 0)[k % 4]; }',
    '// light field mapping (fit/kernels/lfm.py): per atlas texel d (params 0:3), its slots\' welded vertices',
    '// (3:6, -1: no texel) and surface maps G[slot j, term k] at 6 + 3 (j K + k); view maps tiled per vertex',
    '// in layer k of u_views; vertex frames (position, tangent, bitangent, normal) in u_vframe',
    'uniform highp sampler2DArray u_views; uniform highp sampler2D u_vframe;',
    'uniform int u_terms; uniform int u_vres; uniform int u_vmap; uniform int u_vlookup; uniform int u_vinterp;',
    'uniform int u_vcols; uniform int u_fcols; uniform int u_slookup;',
    'vec3 VF(int v, int i) { return texelFetch(u_vframe, ivec2(4 * (v % u_fcols) + i, v / u_fcols), 0).xyz; }',
    'vec3 HV(int k, int v, int ix, int iy) {',
    '  return texelFetch(u_views, ivec3((v % u_vcols) * u_vres + ix, (v / u_vcols) * u_vres + iy, k), 0).xyz;',
    '}',
    '// view_map_coords: continuous view-map coordinates of a local direction (texel centres at i + 0.5)',
    'vec2 view_map_coords(vec3 w) {',
    '  vec3 q = vec3(w.x, w.y, max(w.z, 0.0));',
    '  float len = length(q);',
    '  if (len <= 0.0) return vec2(0.5 * float(u_vres));',
    '  q /= len;',
    '  vec2 uv = q.xy;',
    '  if (u_vmap == 1) { float s = abs(q.x) + abs(q.y) + q.z; vec2 pp = q.xy / s; uv = vec2(pp.x + pp.y, pp.x - pp.y); }',
    '  return (uv + 1.0) * 0.5 * float(u_vres);',
    '}',
    '// texel_radiance: d + sum over the three slots and K terms of g h(view direction in the vertex frame);',
    '// part 1 = d only, 2 = the view-dependent terms only',
    'vec3 lfm_texel(ivec2 xy, vec3 p, int part) {',
    '  vec3 L = part == 2 ? vec3(0.0) : vec3(P(xy, 0), P(xy, 1), P(xy, 2));',
    '  if (part == 1) return L;',
    '  int hi = u_vres - 1;',
    '  for (int j = 0; j < 3; j++) {',
    '    int v = int(P(xy, 3 + j));',
    '    vec3 src = u_vinterp != 0 ? p : VF(v, 0);',
    '    vec3 d = normalize(u_eye - src);',
    '    vec2 c = view_map_coords(vec3(dot(d, VF(v, 1)), dot(d, VF(v, 2)), dot(d, VF(v, 3))));',
    '    ivec2 i0; ivec2 i1; float ax = 0.0, ay = 0.0;',
    '    if (u_vlookup == 0) {',
    '      i0 = clamp(ivec2(floor(c)), 0, hi); i1 = i0;',
    '    } else {',
    '      vec2 f = c - 0.5; vec2 f0 = floor(f);',
    '      ax = f.x - f0.x; ay = f.y - f0.y;',
    '      ivec2 b = ivec2(f0);',
    '      i1 = clamp(b + 1, 0, hi); i0 = clamp(b, 0, hi);',
    '    }',
    '    for (int k = 0; k < u_terms; k++) {',
    '      vec3 h = (1.0 - ax) * (1.0 - ay) * HV(k, v, i0.x, i0.y);',
    '      if (u_vlookup != 0) h += ax * (1.0 - ay) * HV(k, v, i1.x, i0.y) + (1.0 - ax) * ay * HV(k, v, i0.x, i1.y)',
    '                             + ax * ay * HV(k, v, i1.x, i1.y);',
    '      int o = 6 + 3 * (j * u_terms + k);',
    '      L += vec3(P(xy, o), P(xy, o + 1), P(xy, o + 2)) * h;',
    '    }',
    '  }',
    '  return L;',
    '}',
    '// lafortune_brdf of fit/kernels/shading.py; part 0 = all, 1 = diffuse only, 2 = lobes only',
    'vec3 brdf(ivec2 xy, vec3 u, vec3 v, int part) {',
    '  vec3 f = vec3(0.0);',
    '  if (part != 2) f = vec3(P(xy, 0), P(xy, 1), P(xy, 2));',
    '  if (part == 1) return f;',
    '  int stride = 6 + u_aniso;',
    '  for (int j = 0; j < u_nlobes; j++) {',
    '    int o = 3 + j * stride;',
    '    vec3 c = vec3(P(xy, o + 3), P(xy, o + 3), P(xy, o + 4));',
    '    if (u_aniso != 0) c = vec3(P(xy, o + 3), P(xy, o + 4), P(xy, o + 5));',
    '    float n = P(xy, o + stride - 1);',
    '    float s = c.x * u.x * v.x + c.y * u.y * v.y + c.z * u.z * v.z;',
    '    float lobe = s <= 0.0 ? 0.0 : exp(min(n * log(s), 30.0));',
    '    f += lobe * vec3(P(xy, o), P(xy, o + 1), P(xy, o + 2));',
    '  }',
    '  return f;',
    '}',
    'vec3 radiance_at(ivec2 xy) { return vec3(P(xy, 0), P(xy, 1), P(xy, 2)); }',
    '// view_radiance of shading.py: L + sum_k a_k phi_k(v), phi = (vx, vy, vx^2, vx vy, vy^2)',
    'vec3 view_radiance_at(ivec2 xy, vec3 v) {',
    '  float phi[5] = float[5](v.x, v.y, v.x * v.x, v.x * v.y, v.y * v.y);',
    '  vec3 L = radiance_at(xy);',
    '  for (int k = 0; k < 5; k++) { int o = 3 + 3 * k; L += phi[k] * vec3(P(xy, o), P(xy, o + 1), P(xy, o + 2)); }',
    '  return L;',
    '}',
    'vec3 srgb(vec3 x) {',
    '  x = clamp(x, 0.0, 1.0);',
    '  return mix(x * 12.92, 1.055 * pow(x, vec3(1.0 / 2.4)) - 0.055, step(vec3(0.0031308), x));',
    '}',
    'vec3 linear(vec3 x) {',
    '  return mix(x / 12.92, pow((x + 0.055) / 1.055, vec3(2.4)), step(vec3(0.04045), x));',
    '}',
    'void main() {',
    '  // texel_coords + bilinear_taps of shading.py (row 0 at the top, v up)',
    '  float x = v_uv.x * float(u_W) - 0.5, y = (1.0 - v_uv.y) * float(u_H) - 0.5;',
    '  float xc = clamp(x, 0.0, float(u_W - 1)), yc = clamp(y, 0.0, float(u_H - 1));',
    '  int x0 = max(min(int(floor(xc)), u_W - 2), 0), y0 = max(min(int(floor(yc)), u_H - 2), 0);',
    '  float fx = xc - float(x0), fy = yc - float(y0);',
    '  ivec2 t00 = ivec2(x0, y0), t10 = ivec2(x0 + 1, y0), t01 = ivec2(x0, y0 + 1), t11 = ivec2(x0 + 1, y0 + 1);',
    '  vec3 L = vec3(0.0);',
    '  if (u_kind == 3) {',
    '    // render_lfm_kernel: the nearest texel, or the four texels\' models blended bilinearly (texels with',
    '    // no model skipped, the weights renormalised); negative radiance clamped to 0',
    '    int lpart = (u_mode == 1) ? 1 : ((u_mode == 2) ? 2 : 0);',
    '    vec3 acc = vec3(0.0); float ws = 0.0;',
    '    if (u_slookup == 0) {',
    '      ivec2 nx = ivec2(clamp(int(floor(x + 0.5)), 0, u_W - 1), clamp(int(floor(y + 0.5)), 0, u_H - 1));',
    '      if (P(nx, 3) >= 0.0) { acc = lfm_texel(nx, v_pos, lpart); ws = 1.0; }',
    '    } else {',
    '      for (int q = 0; q < 4; q++) {',
    '        ivec2 tq = ivec2(x0 + q % 2, y0 + q / 2);',
    '        float w = (q % 2 == 0 ? 1.0 - fx : fx) * (q / 2 == 0 ? 1.0 - fy : fy);',
    '        if (w > 0.0 && P(tq, 3) >= 0.0) { acc += w * lfm_texel(tq, v_pos, lpart); ws += w; }',
    '      }',
    '    }',
    '    if (ws > 0.0) L = max(acc / ws, vec3(0.0));',
    '  } else if (u_kind == 1) {',
    '    L = (1.0 - fx) * (1.0 - fy) * radiance_at(t00) + fx * (1.0 - fy) * radiance_at(t10)',
    '      + (1.0 - fx) * fy * radiance_at(t01) + fx * fy * radiance_at(t11);',
    '  } else {',
    '    // surface_frame: tangent = dp/du of the triangle (per face, from the model data), made orthogonal to n',
    '    vec3 n = normalize(v_nrm);',
    '    vec3 T = v_tan - n * dot(n, v_tan);',
    '    if (length(T) < 1e-12 * max(length(v_tan), 1e-30) || length(v_tan) == 0.0) {',
    '      vec3 a = abs(n.x) > 0.9 ? vec3(0.0, 1.0, 0.0) : vec3(1.0, 0.0, 0.0);',
    '      T = a - n * dot(n, a);',
    '    }',
    '    vec3 t = normalize(T);',
    '    vec3 b = cross(n, t);',
    '    if (u_kind == 2) {',
    '      vec3 vw2 = normalize(u_eye - v_pos);',
    '      vec3 vl2 = vec3(dot(vw2, t), dot(vw2, b), dot(vw2, n));',
    '      L = max((1.0 - fx) * (1.0 - fy) * view_radiance_at(t00, vl2) + fx * (1.0 - fy) * view_radiance_at(t10, vl2)',
    '        + (1.0 - fx) * fy * view_radiance_at(t01, vl2) + fx * fy * view_radiance_at(t11, vl2), vec3(0.0));',
    '    } else {',
    '    // incident_light',
    '    vec3 l; vec3 E;',
    '    if (u_lkind == 0) { vec3 d = u_lpd - v_pos; float r2 = dot(d, d); l = d / sqrt(r2); E = u_lI / r2; }',
    '    else { l = -normalize(u_lpd); E = u_lI; }',
    '    float cosi = dot(n, l);',
    '    if (cosi > 0.0) {',
    '      vec3 vw = normalize(u_eye - v_pos);',
    '      vec3 ul = vec3(dot(l, t), dot(l, b), dot(l, n));',
    '      vec3 vl = vec3(dot(vw, t), dot(vw, b), dot(vw, n));',
    '      int part = (u_mode == 1) ? 1 : ((u_mode == 2) ? 2 : 0);',
    '      vec3 f = (1.0 - fx) * (1.0 - fy) * brdf(t00, ul, vl, part) + fx * (1.0 - fy) * brdf(t10, ul, vl, part)',
    '             + (1.0 - fx) * fy * brdf(t01, ul, vl, part) + fx * fy * brdf(t11, ul, vl, part);',
    '      L = f * E * cosi;',
    '    }',
    '    }',
    '  }',
    '  vec3 pix = u_exposure * L;',
    '  vec3 outc = srgb(pix);',
    '  vec2 q = vec2(gl_FragCoord.x / u_size.x, 1.0 - gl_FragCoord.y / u_size.y);  // photo UV, row 0 at top',
    '  if (u_mode == 3) {  // error: |render - photo| (linear) times gain',
    '    outc = u_hasphoto != 0 ? srgb(u_gain * abs(pix - linear(texture(u_photo, q).rgb))) : vec3(0.5, 0.0, 0.5);',
    '  } else if (u_mode == 4) {  // the photo itself',
    '    outc = u_hasphoto != 0 ? texture(u_photo, q).rgb : vec3(0.5, 0.0, 0.5);',
    '  } else if (u_mode == 5) {  // texels no photo saw (nearest texel), magenta',
    '    ivec2 nx = ivec2(clamp(int(floor(x + 0.5)), 0, u_W - 1), clamp(int(floor(y + 0.5)), 0, u_H - 1));',
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
    gl.attachShader(prog, compile(gl, gl.FRAGMENT_SHADER, FS));
    gl.bindAttribLocation(prog, 0, 'a_pos');
    gl.bindAttribLocation(prog, 1, 'a_nrm');
    gl.bindAttribLocation(prog, 2, 'a_uv');
    gl.bindAttribLocation(prog, 3, 'a_tan');
    gl.linkProgram(prog);
    if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error('shader link: ' + gl.getProgramInfoLog(prog));
    V.prog = prog;
    var U = {};
    ['u_R', 'u_t', 'u_K', 'u_size', 'u_nf', 'u_params', 'u_photo', 'u_seen', 'u_W', 'u_H', 'u_kind', 'u_nlobes',
      'u_aniso', 'u_lkind', 'u_lpd', 'u_lI', 'u_eye', 'u_exposure', 'u_mode', 'u_gain', 'u_hasphoto',
      'u_views', 'u_vframe', 'u_terms', 'u_vres', 'u_vmap', 'u_vlookup', 'u_vinterp', 'u_vcols', 'u_fcols', 'u_slookup'
    ].forEach(function (k) { U[k] = gl.getUniformLocation(prog, k); });
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

    // light field mapping: view maps (unit 3) and vertex frames (unit 4); 1-texel stand-ins otherwise, so
    // every sampler has a texture of its own type
    var LF = M.lfm;
    var views = gl.createTexture();
    gl.activeTexture(gl.TEXTURE3);
    gl.bindTexture(gl.TEXTURE_2D_ARRAY, views);
    if (LF) gl.texImage3D(gl.TEXTURE_2D_ARRAY, 0, gl.RGBA32F, LF.views.width, LF.views.height, LF.views.layers, 0,
      gl.RGBA, gl.FLOAT, f32(LF.views.data));
    else gl.texImage3D(gl.TEXTURE_2D_ARRAY, 0, gl.RGBA32F, 1, 1, 1, 0, gl.RGBA, gl.FLOAT, new Float32Array(4));
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    var vframe = gl.createTexture();
    gl.activeTexture(gl.TEXTURE4);
    gl.bindTexture(gl.TEXTURE_2D, vframe);
    if (LF) gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, LF.frames.width, LF.frames.height, 0, gl.RGBA, gl.FLOAT,
      f32(LF.frames.data));
    else gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, 1, 1, 0, gl.RGBA, gl.FLOAT, new Float32Array(4));
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);

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
    gl.uniform1i(U.u_kind, { radiance: 1, view_radiance: 2, lfm: 3 }[M.kind] || 0);
    gl.uniform1i(U.u_views, 3);
    gl.uniform1i(U.u_vframe, 4);
    var LF = M.lfm || { terms: 0, view_res: 1, tile_columns: 1, frames: { columns: 1 } };
    gl.uniform1i(U.u_terms, LF.terms);
    gl.uniform1i(U.u_vres, LF.view_res);
    gl.uniform1i(U.u_vmap, LF.view_map === 'hemioct' ? 1 : 0);
    gl.uniform1i(U.u_vlookup, LF.lookup === 'nearest' ? 0 : 1);
    gl.uniform1i(U.u_vinterp, LF.render_view === 'vertex' ? 0 : 1);
    gl.uniform1i(U.u_vcols, LF.tile_columns);
    gl.uniform1i(U.u_fcols, LF.frames.columns);
    gl.uniform1i(U.u_slookup, LF.surface_lookup === 'nearest' ? 0 : 1);
    gl.uniform1i(U.u_nlobes, M.n_lobes);
    gl.uniform1i(U.u_aniso, M.anisotropic ? 1 : 0);
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
