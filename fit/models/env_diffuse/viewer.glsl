// env_diffuse: albedo (params 0:3) x (transfer (params 3:12) . L) per texel, clamped at 0, blended bilinearly at the
// four texels (as texstream's renderer blends the lit radiance). L: the estimated order-2 SH light (u_shlight texels
// 0..8; texel 9: the object's centre), turned about +z by the azimuth of the viewer's light around the centre (the
// default light, straight above, turns nothing) and scaled by its intensity: render/sh.py's basis order.
uniform highp sampler2D u_shlight;
vec3 sh_coef(int k) { return texelFetch(u_shlight, ivec2(k, 0), 0).rgb; }
vec3 lit_at(ivec2 xy, vec3 L[9]) {
  vec3 acc = vec3(0.0);
  for (int k = 0; k < 9; k++) acc += P(xy, 3 + k) * L[k];
  return max(vec3(P(xy, 0), P(xy, 1), P(xy, 2)) * acc, vec3(0.0));
}
vec3 model_radiance(vec2 uv, vec3 pos, vec3 nrm, vec3 tng, vec3 eye, int part) {
  vec3 c = texelFetch(u_shlight, ivec2(9, 0), 0).xyz;
  vec2 d = u_lpd.xy - c.xy;
  float a = length(d) > 1e-6 ? atan(d.y, d.x) : 0.0;  // turning the environment by a about +z
  float ca = cos(a), sa = sin(a), c2 = cos(2.0 * a), s2 = sin(2.0 * a);
  vec3 L[9];
  for (int k = 0; k < 9; k++) L[k] = sh_coef(k) * u_lI;
  vec3 y1 = L[1], x1 = L[3], yz = L[5], xz = L[7], xy = L[4], x2y2 = L[8];
  L[3] = ca * x1 - sa * y1; L[1] = sa * x1 + ca * y1;
  L[7] = ca * xz - sa * yz; L[5] = sa * xz + ca * yz;
  L[8] = c2 * x2y2 - s2 * xy; L[4] = s2 * x2y2 + c2 * xy;
  Taps t = texel_taps(uv);
  ivec2 t00 = ivec2(t.x0, t.y0), t10 = ivec2(t.x0 + 1, t.y0), t01 = ivec2(t.x0, t.y0 + 1), t11 = ivec2(t.x0 + 1, t.y0 + 1);
  return (1.0 - t.fx) * (1.0 - t.fy) * lit_at(t00, L) + t.fx * (1.0 - t.fy) * lit_at(t10, L)
    + (1.0 - t.fx) * t.fy * lit_at(t01, L) + t.fx * t.fy * lit_at(t11, L);
}
