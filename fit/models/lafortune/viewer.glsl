// Lafortune SBRDF (render/shading.py lafortune_brdf), lit by the viewer's light: the BRDF at the
// four texels around the hit blended with the bilinear weights, times the irradiance and cos(theta_i)
uniform int u_nlobes; uniform int u_aniso;
// first column of the ambient radiance (render/layout.py ModelLayout.ambient), -1: none; added lit or not
uniform int u_ambient;
vec3 ambient_at(ivec2 xy) { return vec3(P(xy, u_ambient), P(xy, u_ambient + 1), P(xy, u_ambient + 2)); }
// part 0 = all, 1 = diffuse only, 2 = lobes only
vec3 brdf(ivec2 xy, vec3 u, vec3 v, int part) {
  vec3 f = vec3(0.0);
  if (part != 2) f = vec3(P(xy, 0), P(xy, 1), P(xy, 2));
  if (part == 1) return f;
  int stride = 6 + u_aniso;
  for (int j = 0; j < u_nlobes; j++) {
    int o = 3 + j * stride;
    vec3 c = vec3(P(xy, o + 3), P(xy, o + 3), P(xy, o + 4));
    if (u_aniso != 0) c = vec3(P(xy, o + 3), P(xy, o + 4), P(xy, o + 5));
    float n = P(xy, o + stride - 1);
    float s = c.x * u.x * v.x + c.y * u.y * v.y + c.z * u.z * v.z;
    float lobe = s <= 0.0 ? 0.0 : exp(min(n * log(s), 30.0));
    f += lobe * vec3(P(xy, o), P(xy, o + 1), P(xy, o + 2));
  }
  return f;
}
vec3 model_radiance(vec2 uv, vec3 pos, vec3 nrm, vec3 tng, vec3 eye, int part) {
  Taps a = texel_taps(uv);
  ivec2 t00 = ivec2(a.x0, a.y0), t10 = ivec2(a.x0 + 1, a.y0), t01 = ivec2(a.x0, a.y0 + 1), t11 = ivec2(a.x0 + 1, a.y0 + 1);
  float fx = a.fx, fy = a.fy;
  mat3 F = surface_frame(nrm, tng);
  vec3 t = F[0], b = F[1], n = F[2];
  vec3 amb = vec3(0.0);
  if (u_ambient >= 0 && part != 2)
    amb = (1.0 - fx) * (1.0 - fy) * ambient_at(t00) + fx * (1.0 - fy) * ambient_at(t10)
        + (1.0 - fx) * fy * ambient_at(t01) + fx * fy * ambient_at(t11);
  // incident_light
  vec3 l; vec3 E;
  if (u_lkind == 0) { vec3 d = u_lpd - pos; float r2 = dot(d, d); l = d / sqrt(r2); E = u_lI / r2; }
  else { l = -normalize(u_lpd); E = u_lI; }
  float cosi = dot(n, l);
  if (cosi <= 0.0) return amb;
  vec3 vw = normalize(eye - pos);
  vec3 ul = vec3(dot(l, t), dot(l, b), dot(l, n));
  vec3 vl = vec3(dot(vw, t), dot(vw, b), dot(vw, n));
  vec3 f = (1.0 - fx) * (1.0 - fy) * brdf(t00, ul, vl, part) + fx * (1.0 - fy) * brdf(t10, ul, vl, part)
         + (1.0 - fx) * fy * brdf(t01, ul, vl, part) + fx * fy * brdf(t11, ul, vl, part);
  return amb + f * E * cosi;
}
