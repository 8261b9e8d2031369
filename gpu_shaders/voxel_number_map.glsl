/* Voxel Number Map transport (Mochida et al.; kernel derived in
 * translucency_addon/voxel_number_map/transport.py, eq. 6).  Numpy twin:
 * translucency_addon.voxel_number_map.transport.pair_kernel + PreparedKernel.product
 * (the packed kernel S times x with BLAS sspmv).  One invocation per exit voxel o:
 *
 *   J_o = sum_{i != o, not blocked} S_io x_i
 *   S_io = cos_i cos_o tau_s exp(-tau) / (4 pi R^2)
 *   tau   = sum_c sig_t[c] l_c(i, o),   tau_s = sum_c sig_s[c] l_c(i, o)   (per RGB channel)
 *   cos_i = max(0, -n_i . d),  cos_o = max(0, n_o . d),  d = (p_o - p_i) / R
 *
 * The LUT is read as stored (packed upper triangle with the diagonal, row by
 * row: pair (a, b), a <= b, at k = a n - a (a - 1) / 2 + (b - a)), fp16
 * lengths in voxel units; the coefficients arrive multiplied by the voxel
 * edge in mm, so tau is dimensionless.
 *
 * Textures (row-major 1D arrays in 2D array textures of width TEX_W, layer 0;
 * gpu_shaders/voxel_number_map.py packs them):
 *   lut     RGBA16F  per pair k: lengths of components 0..2, blocked flag (0 or 1)
 *   geom_a  RGBA32F  per surface voxel: position xyz (object units, centred by the host), 0
 *   geom_b  RGBA32F  per surface voxel: outward normal xyz, 0
 *   src     RGBA32F  per surface voxel, per frame: x = A Phi (rgb)
 *   coef    RGBA32F  texel c: h_mm sigma_t of component c (rgb); texel 4 + c: h_mm sigma_s
 *   out_j   RGBA32F  per surface voxel: J (rgb)
 */

#define FOUR_PI 12.566370614359172

ivec3 at(int i)
{
  return ivec3(i % TEX_W, i / TEX_W, 0);
}

void main()
{
  int o = int(gl_GlobalInvocationID.y) * TEX_W + int(gl_GlobalInvocationID.x);
  if (o >= n_vox) {
    return;
  }
  vec3 po = texelFetch(geom_a, at(o), 0).xyz;
  vec3 no = texelFetch(geom_b, at(o), 0).xyz;
  vec3 st0 = texelFetch(coef, ivec3(0, 0, 0), 0).rgb;
  vec3 st1 = texelFetch(coef, ivec3(1, 0, 0), 0).rgb;
  vec3 st2 = texelFetch(coef, ivec3(2, 0, 0), 0).rgb;
  vec3 ss0 = texelFetch(coef, ivec3(4, 0, 0), 0).rgb;
  vec3 ss1 = texelFetch(coef, ivec3(5, 0, 0), 0).rgb;
  vec3 ss2 = texelFetch(coef, ivec3(6, 0, 0), 0).rgb;
  vec3 acc = vec3(0.0);
  for (int i = 0; i < n_vox; i++) {
    if (i == o) {
      continue;
    }
    int a = min(i, o);
    int b = max(i, o);
    int k = a * n_vox - (a * (a - 1)) / 2 + (b - a);
    vec4 l = texelFetch(lut, at(k), 0);
    if (l.w > 0.5) {
      continue; /* blocked by an opaque part */
    }
    vec3 d = po - texelFetch(geom_a, at(i), 0).xyz;
    float r2 = dot(d, d);
    if (r2 <= 0.0) {
      continue;
    }
    float r = sqrt(r2);
    vec3 ni = texelFetch(geom_b, at(i), 0).xyz;
    float ci = max(-dot(ni, d) / r, 0.0);
    float co = max(dot(no, d) / r, 0.0);
    float g = ci * co / (FOUR_PI * r2);
    if (g <= 0.0) {
      continue;
    }
    vec3 tau = l.x * st0 + l.y * st1 + l.z * st2;
    vec3 tau_s = l.x * ss0 + l.y * ss1 + l.z * ss2;
    acc += g * tau_s * exp(-tau) * texelFetch(src, at(i), 0).rgb;
  }
  imageStore(out_j, ivec3(at(o)), vec4(acc, 0.0));
}
