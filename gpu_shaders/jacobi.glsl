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
  vec4 o_r = texelFetch(off_r, p, 0);
  vec4 o_g = texelFetch(off_g, p, 0);
  vec4 o_b = texelFetch(off_b, p, 0);
  vec4 ex = texelFetch(ext, p, 0);
  vec3 diag = diagonal(o_r, o_g, o_b, ex);
  if (!all(greaterThan(diag, vec3(0.0)))) {
    imageStore(x_out, p, vec4(0.0));
    return;
  }
  uvec4 nb = texelFetch(nbr, p, 0);
  vec3 s;
  NEIGHBOUR_SUM(s, x_in, nb, o_r, o_g, o_b);
  vec3 b = ex.a * texelFetch(q, p, 0).rgb;
  imageStore(x_out, p, vec4((b + s) / diag, 0.0));
}
