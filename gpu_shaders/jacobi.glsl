/* One Jacobi relaxation sweep (twin: translucency_addon.diffusion.kernels.jacobi_sweep):
 *
 *   x'_i = (b_i + sum_j c_ij x_j) / a_ii,     b_i = b_scale_i q_i
 *
 * With the paper's coefficients (diffusion.assemble(scheme="paper")) this is
 * eq. 8 at inner nodes and eq. 9 at surface nodes.  Padding texels (a_ii = 0)
 * are written as zero.  Ping-pong: x_in and x_out are different textures. */
void main()
{
  ivec3 p = ivec3(gl_GlobalInvocationID);
  vec4 ex = texelFetch(ext, p, 0);
  vec3 s;
  vec3 diag;
  LINKS(s, diag, x_in, p, ex);
  if (!all(greaterThan(diag, vec3(0.0)))) {
    imageStore(x_out, p, vec4(0.0));
    return;
  }
  vec3 b = ex.a * texelFetch(q, p, 0).rgb;
  imageStore(x_out, p, vec4((b + s) / diag, 0.0));
}
