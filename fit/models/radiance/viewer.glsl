// view-independent radiance: unlit, the radiance L (params 0:3) blended bilinearly at the four texels
vec3 radiance_at(ivec2 xy) { return vec3(P(xy, 0), P(xy, 1), P(xy, 2)); }
vec3 model_radiance(vec2 uv, vec3 pos, vec3 nrm, vec3 tng, vec3 eye, int part) {
  Taps a = texel_taps(uv);
  ivec2 t00 = ivec2(a.x0, a.y0), t10 = ivec2(a.x0 + 1, a.y0), t01 = ivec2(a.x0, a.y0 + 1), t11 = ivec2(a.x0 + 1, a.y0 + 1);
  float fx = a.fx, fy = a.fy;
  return (1.0 - fx) * (1.0 - fy) * radiance_at(t00) + fx * (1.0 - fy) * radiance_at(t10)
    + (1.0 - fx) * fy * radiance_at(t01) + fx * fy * radiance_at(t11);
}
