/* Shared by every kernel (prepended by gpu_shaders/runtime.py; Blender adds the
 * #version line, the sampler/image/push-constant declarations and the defines).
 *
 * Node addressing (gpu_shaders/pack.py, Layout): every node of a QuadGraph
 * level is one texel (x, y, layer) of a set of 2D array textures, in the
 * bake's block order (r x r blocks, inner nodes first, surface nodes from a
 * new block row on).  A neighbour reference is the texel address packed into
 * one uint:  x | y << 14 | layer << 28  (x, y < 16384, layer < 15);
 * NONE (all bits set) means "no neighbour".
 */
const uint NONE = 0xFFFFFFFFu;

ivec3 node_texel(uint a)
{
  return ivec3(int(a & 0x3FFFu), int((a >> 14u) & 0x3FFFu), int(a >> 28u));
}

/* Exact unpolarised Fresnel transmittance F_t = 1 - F_r for light leaving
 * through the surface at cos_i (twin: translucency_addon.scene.fresnel; used by
 * radiance.glsl and single_scattering.glsl).  eta = 1: no interface, F_t = 1. */
float fresnel_transmittance(float cos_i, float n)
{
  if (n == 1.0) {
    return 1.0;
  }
  float c = clamp(cos_i, 0.0, 1.0);
  float sin_t2 = (1.0 - c * c) / (n * n);
  float cos_t = sqrt(max(0.0, 1.0 - sin_t2));
  float r_par = (n * c - cos_t) / (n * c + cos_t);
  float r_perp = (c - n * cos_t) / (c + n * cos_t);
  return 1.0 - 0.5 * (r_par * r_par + r_perp * r_perp);
}

/* The links of node texel p, over its link pages (gpu_shaders/pack.py: 4 links per page, page g in
 * layer p.z + g * page_layers of nbr and off_*; push constants pages and page_layers):
 *
 *   s = sum_j c_ij v_j,   dg = a_ii = e_i + sum_j c_ij   (per channel; e = ex.rgb)
 *
 * (c_ij per channel in off_r, off_g, off_b; v the sampler holding the vector).  Forming the diagonal
 * here in fp32 keeps the small absorption term e exact when the coefficients are stored in fp16.
 * Shared by the Jacobi, residual and Chebyshev kernels.  Macros, not functions: samplers as function
 * arguments are not portable across Blender's GPU backends. */
#define DIAGONAL(dg, p, ex) \
  dg = ex.rgb; \
  for (int g_ = 0; g_ < pages; g_++) { \
    ivec3 t_ = ivec3(p.xy, p.z + g_ * page_layers); \
    dg += vec3(dot(texelFetch(off_r, t_, 0), vec4(1.0)), dot(texelFetch(off_g, t_, 0), vec4(1.0)), \
               dot(texelFetch(off_b, t_, 0), vec4(1.0))); \
  }

#define LINKS(s, dg, v, p, ex) \
  s = vec3(0.0); \
  dg = ex.rgb; \
  for (int g_ = 0; g_ < pages; g_++) { \
    ivec3 t_ = ivec3(p.xy, p.z + g_ * page_layers); \
    vec4 o_r_ = texelFetch(off_r, t_, 0); \
    vec4 o_g_ = texelFetch(off_g, t_, 0); \
    vec4 o_b_ = texelFetch(off_b, t_, 0); \
    dg += vec3(dot(o_r_, vec4(1.0)), dot(o_g_, vec4(1.0)), dot(o_b_, vec4(1.0))); \
    uvec4 nb_ = texelFetch(nbr, t_, 0); \
    for (int k_ = 0; k_ < 4; k_++) { \
      if (nb_[k_] != NONE) { \
        s += vec3(o_r_[k_], o_g_[k_], o_b_[k_]) * texelFetch(v, node_texel(nb_[k_]), 0).rgb; \
      } \
    } \
  }
