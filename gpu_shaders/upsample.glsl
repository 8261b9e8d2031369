/* Eq. 10, Shepard interpolation from the coarser level (twin: kernels.shepard_upsample):
 *
 *   x_fine(n_x) = sum_y w_xy x_coarse(n_y)   over b <= 8 coarse nodes
 *
 * idx_a/idx_b hold the 8 coarse addresses (NONE = unused slot), w_a/w_b the weights.
 * Fine padding texels have only NONE slots and get zero. */
void main()
{
  ivec3 p = ivec3(gl_GlobalInvocationID);
  uvec4 ia = texelFetch(idx_a, p, 0);
  uvec4 ib = texelFetch(idx_b, p, 0);
  vec4 wa = texelFetch(w_a, p, 0);
  vec4 wb = texelFetch(w_b, p, 0);
  vec3 s = vec3(0.0);
  for (int k = 0; k < 4; k++) {
    if (ia[k] != NONE) {
      s += wa[k] * texelFetch(x_coarse, node_texel(ia[k]), 0).rgb;
    }
    if (ib[k] != NONE) {
      s += wb[k] * texelFetch(x_coarse, node_texel(ib[k]), 0).rgb;
    }
  }
  imageStore(x_fine, p, vec4(s, 0.0));
}
