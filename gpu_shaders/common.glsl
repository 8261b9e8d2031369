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

/* Per-channel diagonal a_ii = e_i + sum_k c_ik (e = ext.rgb, the part of the
 * diagonal that is not the sum of the off-diagonal coefficients: absorption
 * and boundary terms).  Forming it here in fp32 keeps the small absorption
 * term exact when the coefficients are stored in fp16. */
vec3 diagonal(vec4 o_r, vec4 o_g, vec4 o_b, vec4 ext)
{
  const vec4 one = vec4(1.0);
  return ext.rgb + vec3(dot(o_r, one), dot(o_g, one), dot(o_b, one));
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

/* s = sum_j c_ij v_j over the links nb of one node (c_ij per channel in
 * o_r, o_g, o_b; v the sampler holding the vector).  Shared by the Jacobi,
 * residual and Chebyshev kernels.  A macro, not a function: samplers as
 * function arguments are not portable across Blender's GPU backends. */
#define NEIGHBOUR_SUM(s, v, nb, o_r, o_g, o_b) \
  s = vec3(0.0); \
  for (int k_ = 0; k_ < 4; k_++) { \
    if (nb[k_] != NONE) { \
      s += vec3(o_r[k_], o_g[k_], o_b[k_]) * texelFetch(v, node_texel(nb[k_]), 0).rgb; \
    } \
  }
