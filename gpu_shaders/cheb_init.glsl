/* First Chebyshev direction d_0 = r_0 / (theta a_ii)  (as in
 * diffusion.solve_chebyshev: d = r / diag / theta; inv_theta = 1/theta). */
void main()
{
  ivec3 p = ivec3(gl_GlobalInvocationID);
  vec3 diag;
  DIAGONAL(diag, p, texelFetch(ext, p, 0));
  if (!all(greaterThan(diag, vec3(0.0)))) {
    imageStore(d_out, p, vec4(0.0));
    return;
  }
  imageStore(d_out, p, vec4(texelFetch(r_in, p, 0).rgb * inv_theta / diag, 0.0));
}
