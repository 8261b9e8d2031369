/* Outgoing radiance at the user's vertices (twin: the last part of
 * DiffusionSolver.vertex_radiance and diffusion.outgoing_radiance):
 *
 *   J+_v = sum_k w_vk J+(n_k)          (vertex map, k <= 8 finest surface nodes)
 *   L_o  = F_t(cos_v, eta) J+_v / (pi eta^2)       (out_scale = 1 / (pi eta^2 q_scale))
 *
 * F_t = 1 - F_r, the exact unpolarised Fresnel transmittance of fresnel.py;
 * F_t = 0 for cos <= 0.  Vertices are stored row-major in a texture of width
 * `width`; texels past `count` are left untouched. */
void main()
{
  ivec3 p = ivec3(gl_GlobalInvocationID);
  if (p.y * width + p.x >= count) {
    return;
  }
  uvec4 ia = texelFetch(idx_a, p, 0);
  uvec4 ib = texelFetch(idx_b, p, 0);
  vec4 wa = texelFetch(w_a, p, 0);
  vec4 wb = texelFetch(w_b, p, 0);
  vec3 j = vec3(0.0);
  for (int k = 0; k < 4; k++) {
    if (ia[k] != NONE) {
      j += wa[k] * texelFetch(jplus, node_texel(ia[k]), 0).rgb;
    }
    if (ib[k] != NONE) {
      j += wb[k] * texelFetch(jplus, node_texel(ib[k]), 0).rgb;
    }
  }
  float c = texelFetch(cos_o, p, 0).r;
  float ft = c > 0.0 ? fresnel_transmittance(c, eta) : 0.0;
  imageStore(l_out, p, vec4(j * (ft * out_scale), 0.0));
}
