/* Outgoing partial current at surface nodes (twin: kernels.outgoing_partial_current):
 *
 *   J+ = max(0, phi - 2 q) / (2 (1 + F_dr))
 *
 * Surface nodes are the texels from global texel row surf_y0 on (the paper's
 * split of the texture along v); inner and padding texels get zero. */
void main()
{
  ivec3 p = ivec3(gl_GlobalInvocationID);
  int row = p.z * layer_h + p.y;
  if (row < surf_y0) {
    imageStore(j_out, p, vec4(0.0));
    return;
  }
  vec3 phi = texelFetch(phi_in, p, 0).rgb;
  vec3 qq = texelFetch(q, p, 0).rgb;
  imageStore(j_out, p, vec4(max(phi - 2.0 * qq, vec3(0.0)) / (2.0 * (1.0 + fdr)), 0.0));
}
