// view-dependent radiance, unlit: view_radiance of render/shading.py, L + sum_k a_k phi_k(v) with
// phi = (vx, vy, vx^2, vx vy, vy^2) of the local view direction, blended bilinearly at the four texels and
// clamped at 0 like render/kernels.py
vec3 view_radiance_at(ivec2 xy, vec3 v) {
  float phi[5] = float[5](v.x, v.y, v.x * v.x, v.x * v.y, v.y * v.y);
  vec3 L = vec3(P(xy, 0), P(xy, 1), P(xy, 2));
  for (int k = 0; k < 5; k++) { int o = 3 + 3 * k; L += phi[k] * vec3(P(xy, o), P(xy, o + 1), P(xy, o + 2)); }
  return L;
}
vec3 model_radiance(vec2 uv, vec3 pos, vec3 nrm, vec3 tng, vec3 eye, int part) {
  Taps a = texel_taps(uv);
  ivec2 t00 = ivec2(a.x0, a.y0), t10 = ivec2(a.x0 + 1, a.y0), t01 = ivec2(a.x0, a.y0 + 1), t11 = ivec2(a.x0 + 1, a.y0 + 1);
  float fx = a.fx, fy = a.fy;
  mat3 F = surface_frame(nrm, tng);
  vec3 vw2 = normalize(eye - pos);
  vec3 vl2 = vec3(dot(vw2, F[0]), dot(vw2, F[1]), dot(vw2, F[2]));
  return max((1.0 - fx) * (1.0 - fy) * view_radiance_at(t00, vl2) + fx * (1.0 - fy) * view_radiance_at(t10, vl2)
    + (1.0 - fx) * fy * view_radiance_at(t01, vl2) + fx * fy * view_radiance_at(t11, vl2), vec3(0.0));
}
