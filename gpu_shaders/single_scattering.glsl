/* Single scattering per view ray (Bernabei et al. eq. 3).  Numpy twin:
 * translucency_addon.single_scattering.runtime.integrate_view_rays followed by
 * exit_factor (render_vertices).  One invocation per ray:
 *
 *   L_o = out_scale * F_t(cos_o, eta) * sum_i  coef_i * psi_i(-d) * g_i
 *
 *   g_i   = weight_i * integral over [max(0, m - hc), min(t_exit, m + hc)] of
 *           exp(-a_i |x(t) - b_i|^2) dt                 (closed form with erf)
 *         = weight_i * sqrt(pi) / (2 sqrt(a_i)) * exp(-a_i dp^2)
 *           * (erf(sqrt(a_i) (tb - m)) - erf(sqrt(a_i) (ta - m)))
 *   coef  = the per-sample light term (per_ray_psi = 1), or light term times
 *           the per-sample view term psi_i(to the camera) (per_ray_psi = 0)
 *   psi_i(-d) = clamp(sum_k Y_k(-d) sh_ik, 0, 1)        (per_ray_psi = 1 only)
 *   out_scale = mm_per_unit / eta^2
 *
 * Grid walk: 3D DDA over the uniform sample grid (CSR cell lists).  A pair
 * (ray, sample) is evaluated only in the visited cell whose parameter
 * interval holds m = (b - o) . d, the point of the ray's line closest to b.
 * The intervals of one ray partition the line (the first starts at -BIG, the
 * last ends at +BIG, consecutive ones share the very same float end point),
 * and m is computed by the same instructions in every cell, so each pair is
 * counted exactly once, without de-duplication.
 *
 * Textures (row-major 1D arrays in 2D array textures of width TEX_W, layer 0;
 * gpu_shaders/single_scattering.py packs them from kernel_arrays()):
 *   samp_a  RGBA32F  per sample: centre xyz (shifted by the host), a_i
 *   samp_b  RGBA32F  per sample: weight_i, support radius R_i, 0, 0
 *   sh      RGBA32F  per sample and SH coefficient (index i * sh_k + k): rgb
 *   coef    RGBA32F  per sample, per frame: rgb
 *   cell_start, cell_items  RGBA32UI  four uint per texel (index j -> texel j / 4, component j % 4)
 *   grid    RGBA32F  texel 0: origin xyz (shifted), cell size; texel 1: dims xyz (exact in fp32)
 *   ray_o   RGBA32F  per ray: origin xyz (shifted), t_exit
 *   ray_d   RGBA32F  per ray: unit direction into the object, cos_o = n . w_o
 *   out_l   RGBA32F  per ray: outgoing radiance rgb (texels past n_rays untouched)
 */

#define BIG 1.0e30
#define SQRT_PI 1.7724538509055159

ivec3 at(int i)
{
  return ivec3(i % TEX_W, i / TEX_W, 0);
}

#ifndef SS_ERF_TEST
uint cell_uint(int which, int j)
{
  uvec4 v = which == 0 ? texelFetch(cell_start, at(j >> 2), 0) : texelFetch(cell_items, at(j >> 2), 0);
  return v[j & 3];
}
#endif

/* erf(x) in float32: the Maclaurin series through x^13 for |x| < 0.5, and
 * 1 - erfc(x) with the Chebyshev-fitted erfc of Numerical Recipes (erfcc,
 * fractional error < 1.2e-7) above.  Relative error of erf in exact
 * arithmetic <= 1.2e-7 everywhere (the series' truncation is < 3e-8 at
 * 0.5); evaluated in float32 about 2.5e-7 (measured against scipy on 2e5
 * points, tests/test_gpu_single_scattering.py).  Odd, and exactly +-1 for
 * |x| > ~4 (exp underflows). */
float erf_approx(float x)
{
  float ax = abs(x);
  if (ax < 0.5) {
    float z = x * x;
    /* 2/sqrt(pi) * (x - x^3/3 + x^5/10 - x^7/42 + x^9/216 - x^11/1320 + x^13/9360) */
    float p = 1.0 / 9360.0;
    p = p * z - 1.0 / 1320.0;
    p = p * z + 1.0 / 216.0;
    p = p * z - 1.0 / 42.0;
    p = p * z + 1.0 / 10.0;
    p = p * z - 1.0 / 3.0;
    p = p * z + 1.0;
    return 1.1283791670955126 * x * p;
  }
  float t = 1.0 / (1.0 + 0.5 * ax);
  float poly = -1.26551223 +
               t * (1.00002368 +
               t * (0.37409196 +
               t * (0.09678418 +
               t * (-0.18628806 +
               t * (0.27886807 +
               t * (-1.13520398 +
               t * (1.48851587 +
               t * (-0.82215223 +
               t * 0.17087277))))))));
  float erfc = t * exp(-ax * ax + poly);
  float r = 1.0 - erfc;
  return x < 0.0 ? -r : r;
}

/* Real orthonormal SH without the Condon-Shortley phase, order <= 4, in the
 * order and signs of translucency_addon/scene/sh.py (sh_basis). */
void sh_basis(vec3 w, out float Y[25])
{
  float x = w.x, y = w.y, z = w.z;
  float z2 = z * z;
  Y[0] = 0.282094791773878;
  Y[1] = 0.488602511902920 * y;
  Y[2] = 0.488602511902920 * z;
  Y[3] = 0.488602511902920 * x;
  Y[4] = 1.092548430592079 * x * y;
  Y[5] = 1.092548430592079 * y * z;
  Y[6] = 0.315391565252520 * (3.0 * z2 - 1.0);
  Y[7] = 1.092548430592079 * x * z;
  Y[8] = 0.546274215296040 * (x * x - y * y);
  Y[9] = 0.590043589926644 * y * (3.0 * x * x - y * y);
  Y[10] = 2.890611442640554 * x * y * z;
  Y[11] = 0.457045799464466 * y * (5.0 * z2 - 1.0);
  Y[12] = 0.373176332590115 * z * (5.0 * z2 - 3.0);
  Y[13] = 0.457045799464466 * x * (5.0 * z2 - 1.0);
  Y[14] = 1.445305721320277 * z * (x * x - y * y);
  Y[15] = 0.590043589926644 * x * (x * x - 3.0 * y * y);
  Y[16] = 2.503342941796705 * x * y * (x * x - y * y);
  Y[17] = 1.770130769779931 * y * z * (3.0 * x * x - y * y);
  Y[18] = 0.946174695757560 * x * y * (7.0 * z2 - 1.0);
  Y[19] = 0.669046543557289 * y * z * (7.0 * z2 - 3.0);
  Y[20] = 0.105785546915204 * (35.0 * z2 * z2 - 30.0 * z2 + 3.0);
  Y[21] = 0.669046543557289 * x * z * (7.0 * z2 - 3.0);
  Y[22] = 0.473087347878780 * (x * x - y * y) * (7.0 * z2 - 1.0);
  Y[23] = 1.770130769779931 * x * z * (x * x - 3.0 * y * y);
  Y[24] = 0.625835735449176 * (x * x * (x * x - 3.0 * y * y) - y * y * (3.0 * x * x - y * y));
}

#ifdef SS_ERF_TEST
/* Test kernel: out_l.r = erf_approx(ray_o.r) for n_rays texels. */
void main()
{
  int r = int(gl_GlobalInvocationID.y) * TEX_W + int(gl_GlobalInvocationID.x);
  if (r >= n_rays) {
    return;
  }
  ivec3 p = at(r);
  float x = texelFetch(ray_o, p, 0).r;
  imageStore(out_l, p, vec4(erf_approx(x), 0.0, 0.0, 0.0));
}
#else
void main()
{
  int r = int(gl_GlobalInvocationID.y) * TEX_W + int(gl_GlobalInvocationID.x);
  if (r >= n_rays) {
    return;
  }
  ivec3 p = at(r);
  vec4 ro = texelFetch(ray_o, p, 0);
  vec4 rd = texelFetch(ray_d, p, 0);
  vec3 o = ro.xyz;
  vec3 d = rd.xyz;
  float t1 = ro.w;
  float cos_o = rd.w;

  vec4 g0 = texelFetch(grid, ivec3(0, 0, 0), 0);
  vec4 g1 = texelFetch(grid, ivec3(1, 0, 0), 0);
  vec3 lo = g0.xyz;
  float cs = g0.w;
  ivec3 dims = ivec3(g1.xyz + 0.5);
  vec3 hi = lo + vec3(dims) * cs;

  /* Slab test of the segment [0, t1] against the grid box (axis-parallel rays: BIG). */
  float tn = -BIG, tf = BIG;
  for (int a = 0; a < 3; a++) {
    if (d[a] != 0.0) {
      float ta = (lo[a] - o[a]) / d[a];
      float tb = (hi[a] - o[a]) / d[a];
      tn = max(tn, min(ta, tb));
      tf = min(tf, max(ta, tb));
    }
    else if (o[a] < lo[a] || o[a] > hi[a]) {
      tf = -BIG;
    }
  }
  float t_cur = max(0.0, tn);
  float t_end = min(t1, tf);
  vec3 acc = vec3(0.0);
  if (t_cur < t_end) {
    float Y[25];
    if (per_ray_psi != 0) {
      sh_basis(-d, Y);
    }
    vec3 q = o + t_cur * d;
    ivec3 cell = clamp(ivec3(floor((q - lo) / cs)), ivec3(0), dims - 1);
    ivec3 stp = ivec3(sign(d));
    vec3 tmax, tdelta;
    ivec3 left;
    for (int a = 0; a < 3; a++) {
      if (d[a] != 0.0) {
        tmax[a] = (lo[a] + float(cell[a] + (d[a] > 0.0 ? 1 : 0)) * cs - o[a]) / d[a];
        tdelta[a] = cs / abs(d[a]);
      }
      else {
        tmax[a] = BIG;
        tdelta[a] = BIG;
      }
      left[a] = d[a] > 0.0 ? dims[a] - 1 - cell[a] : (d[a] < 0.0 ? cell[a] : 0);
    }
    float ia = -BIG;
    int guard = dims.x + dims.y + dims.z + 3;
    for (int it = 0; it < guard; it++) {
      /* the axis of the next crossing (first minimum, as numpy's argmin) */
      int ax = 0;
      if (tmax.y < tmax[ax]) {
        ax = 1;
      }
      if (tmax.z < tmax[ax]) {
        ax = 2;
      }
      float tnext = tmax[ax];
      float t_next = min(tnext, t_end);
      bool more = tnext < t_end && left[ax] > 0;
      float ib = more ? t_next : BIG;

      int lin = (cell.x * dims.y + cell.y) * dims.z + cell.z;
      int j0 = int(cell_uint(0, lin));
      int j1 = int(cell_uint(0, lin + 1));
      for (int j = j0; j < j1; j++) {
        int s = int(cell_uint(1, j));
        vec4 sa = texelFetch(samp_a, at(s), 0);
        vec3 bo = sa.xyz - o;
        float m = dot(bo, d);
        if (m < ia || m >= ib) {
          continue; /* another cell of this ray owns the pair */
        }
        vec4 sb = texelFetch(samp_b, at(s), 0);
        vec3 perp = bo - m * d;
        float dp2 = dot(perp, perp);
        float R2 = sb.y * sb.y;
        if (dp2 >= R2) {
          continue;
        }
        float hc = sqrt(R2 - dp2);
        float t_a = max(0.0, m - hc);
        float t_b = min(t1, m + hc);
        if (t_b <= t_a) {
          continue;
        }
        float al = sa.w;
        float sq = sqrt(al);
        float g = sb.x * (0.5 * SQRT_PI / sq) * exp(-al * dp2) *
                  (erf_approx(sq * (t_b - m)) - erf_approx(sq * (t_a - m)));
        vec3 c = texelFetch(coef, at(s), 0).rgb;
        if (per_ray_psi != 0) {
          vec3 psi = vec3(0.0);
          int base = s * sh_k;
          for (int k = 0; k < sh_k; k++) {
            psi += Y[k] * texelFetch(sh, at(base + k), 0).rgb;
          }
          c *= clamp(psi, 0.0, 1.0);
        }
        acc += c * g;
      }

      if (!more) {
        break;
      }
      cell[ax] += stp[ax];
      left[ax] -= 1;
      tmax[ax] += tdelta[ax];
      ia = t_next;
    }
  }
  float ft = cos_o > 0.0 ? fresnel_transmittance(cos_o, eta) : 0.0;
  imageStore(out_l, p, vec4(acc * (out_scale * ft), 0.0));
}
#endif
