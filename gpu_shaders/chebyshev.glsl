/* One fused step of Chebyshev semi-iteration with the Jacobi preconditioner
 * (twin: kernels.chebyshev_step; Saad, Alg. 12.1):
 *
 *   x' = x + d;   r' = r - A d;   d' = coef_d d + coef_r r' / a_ii
 *
 * coef_d, coef_r: per-channel scalars from the host (push constants).
 * x and r are updated in place (each invocation touches only its own texel);
 * d ping-pongs because A d needs the neighbours' d. */
void main()
{
  ivec3 p = ivec3(gl_GlobalInvocationID);
  vec4 ex = texelFetch(ext, p, 0);
  vec3 s;
  vec3 diag;
  LINKS(s, diag, d_in, p, ex);
  if (!all(greaterThan(diag, vec3(0.0)))) {
    imageStore(d_out, p, vec4(0.0));
    return;
  }
  vec3 d = texelFetch(d_in, p, 0).rgb;
  vec3 r = imageLoad(r_io, p).rgb - (diag * d - s);
  imageStore(x_io, p, vec4(imageLoad(x_io, p).rgb + d, 0.0));
  imageStore(r_io, p, vec4(r, 0.0));
  imageStore(d_out, p, vec4(coef_d * d + coef_r * r / diag, 0.0));
}
