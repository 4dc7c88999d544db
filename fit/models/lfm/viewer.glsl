// light field mapping (fit/kernels/lfm.py render_lfm_kernel), unlit: per atlas texel d (params 0:3), its
// slots' welded vertices (3:6, -1: no texel) and surface maps G[slot j, term k] at 6 + 3 (j K + k); view
// maps tiled per vertex in layer k of u_views; vertex frames (position, tangent, bitangent, normal) in u_vframe
uniform highp sampler2DArray u_views; uniform highp sampler2D u_vframe;
uniform int u_terms; uniform int u_vres; uniform int u_vmap; uniform int u_vlookup; uniform int u_vinterp;
uniform int u_vcols; uniform int u_fcols; uniform int u_slookup;
vec3 VF(int v, int i) { return texelFetch(u_vframe, ivec2(4 * (v % u_fcols) + i, v / u_fcols), 0).xyz; }
vec3 HV(int k, int v, int ix, int iy) {
  return texelFetch(u_views, ivec3((v % u_vcols) * u_vres + ix, (v / u_vcols) * u_vres + iy, k), 0).xyz;
}
// view_map_coords: continuous view-map coordinates of a local direction (texel centres at i + 0.5)
vec2 view_map_coords(vec3 w) {
  vec3 q = vec3(w.x, w.y, max(w.z, 0.0));
  float len = length(q);
  if (len <= 0.0) return vec2(0.5 * float(u_vres));
  q /= len;
  vec2 uv = q.xy;
  if (u_vmap == 1) { float s = abs(q.x) + abs(q.y) + q.z; vec2 pp = q.xy / s; uv = vec2(pp.x + pp.y, pp.x - pp.y); }
  return (uv + 1.0) * 0.5 * float(u_vres);
}
// texel_radiance: d + sum over the three slots and K terms of g h(view direction in the vertex frame);
// part 1 = d only, 2 = the view-dependent terms only
vec3 lfm_texel(ivec2 xy, vec3 p, vec3 eye, int part) {
  vec3 L = part == 2 ? vec3(0.0) : vec3(P(xy, 0), P(xy, 1), P(xy, 2));
  if (part == 1) return L;
  int hi = u_vres - 1;
  for (int j = 0; j < 3; j++) {
    int v = int(P(xy, 3 + j));
    vec3 src = u_vinterp != 0 ? p : VF(v, 0);
    vec3 d = normalize(eye - src);
    vec2 c = view_map_coords(vec3(dot(d, VF(v, 1)), dot(d, VF(v, 2)), dot(d, VF(v, 3))));
    ivec2 i0; ivec2 i1; float ax = 0.0, ay = 0.0;
    if (u_vlookup == 0) {
      i0 = clamp(ivec2(floor(c)), 0, hi); i1 = i0;
    } else {
      vec2 f = c - 0.5; vec2 f0 = floor(f);
      ax = f.x - f0.x; ay = f.y - f0.y;
      ivec2 b = ivec2(f0);
      i1 = clamp(b + 1, 0, hi); i0 = clamp(b, 0, hi);
    }
    for (int k = 0; k < u_terms; k++) {
      vec3 h = (1.0 - ax) * (1.0 - ay) * HV(k, v, i0.x, i0.y);
      if (u_vlookup != 0) h += ax * (1.0 - ay) * HV(k, v, i1.x, i0.y) + (1.0 - ax) * ay * HV(k, v, i0.x, i1.y)
                             + ax * ay * HV(k, v, i1.x, i1.y);
      int o = 6 + 3 * (j * u_terms + k);
      L += vec3(P(xy, o), P(xy, o + 1), P(xy, o + 2)) * h;
    }
  }
  return L;
}
// the nearest texel, or the four texels' models blended bilinearly (texels with no model skipped, the
// weights renormalised); negative radiance clamped to 0
vec3 model_radiance(vec2 uv, vec3 pos, vec3 nrm, vec3 tng, vec3 eye, int part) {
  Taps a = texel_taps(uv);
  vec3 acc = vec3(0.0); float ws = 0.0;
  if (u_slookup == 0) {
    ivec2 nx = ivec2(clamp(int(floor(a.x + 0.5)), 0, u_W - 1), clamp(int(floor(a.y + 0.5)), 0, u_H - 1));
    if (P(nx, 3) >= 0.0) { acc = lfm_texel(nx, pos, eye, part); ws = 1.0; }
  } else {
    for (int q = 0; q < 4; q++) {
      ivec2 tq = ivec2(a.x0 + q % 2, a.y0 + q / 2);
      float w = (q % 2 == 0 ? 1.0 - a.fx : a.fx) * (q / 2 == 0 ? 1.0 - a.fy : a.fy);
      if (w > 0.0 && P(tq, 3) >= 0.0) { acc += w * lfm_texel(tq, pos, eye, part); ws += w; }
    }
  }
  return ws > 0.0 ? max(acc / ws, vec3(0.0)) : vec3(0.0);
}
