/* Residual r = b - A x = b - (a_ii x_i - sum_j c_ij x_j)  (twin: kernels.residual).
 * Padding texels get r = 0 so that the reduction can sum the whole texture. */
void main()
{
  ivec3 p = ivec3(gl_GlobalInvocationID);
  vec4 ex = texelFetch(ext, p, 0);
  vec3 s;
  vec3 diag;
  LINKS(s, diag, x_in, p, ex);
  if (!all(greaterThan(diag, vec3(0.0)))) {
    imageStore(r_out, p, vec4(0.0));
    return;
  }
  vec3 b = ex.a * texelFetch(q, p, 0).rgb;
  vec3 x = texelFetch(x_in, p, 0).rgb;
  imageStore(r_out, p, vec4(b - (diag * x - s), 0.0));
}
