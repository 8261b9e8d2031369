/* Residual r = b - A x = b - (a_ii x_i - sum_j c_ij x_j)  (twin: kernels.residual).
 * Padding texels get r = 0 so that the reduction can sum the whole texture. */
void main()
{
  ivec3 p = ivec3(gl_GlobalInvocationID);
  vec4 o_r = texelFetch(off_r, p, 0);
  vec4 o_g = texelFetch(off_g, p, 0);
  vec4 o_b = texelFetch(off_b, p, 0);
  vec4 ex = texelFetch(ext, p, 0);
  vec3 diag = diagonal(o_r, o_g, o_b, ex);
  if (!all(greaterThan(diag, vec3(0.0)))) {
    imageStore(r_out, p, vec4(0.0));
    return;
  }
  uvec4 nb = texelFetch(nbr, p, 0);
  vec3 s;
  NEIGHBOUR_SUM(s, x_in, nb, o_r, o_g, o_b);
  vec3 b = ex.a * texelFetch(q, p, 0).rgb;
  vec3 x = texelFetch(x_in, p, 0).rgb;
  imageStore(r_out, p, vec4(b - (diag * x - s), 0.0));
}
