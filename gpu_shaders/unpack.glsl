/* Read-back gather: nodes n0 .. n0+count-1 of a level, in node order, into a
 * compact single-layer texture of width `width` (twin: x[n0:n0+count]).
 * Only this small texture is read back.  The node -> texel map is the block
 * layout of gpu_shaders/pack.py (Layout.texel), with r = BLOCK. */
void main()
{
  ivec3 p = ivec3(gl_GlobalInvocationID);
  int k = p.y * width + p.x;
  if (k >= count) {
    return;
  }
  int n = n0 + k;
  int local_n = n < n_inner ? n : n - n_inner;
  int row0 = n < n_inner ? 0 : rows_inner;
  int b = local_n / (BLOCK * BLOCK);
  int o = local_n - b * (BLOCK * BLOCK);
  int bx = b % per_row;
  int by = b / per_row + row0;
  int x = bx * BLOCK + o % BLOCK;
  int row = by * BLOCK + o / BLOCK;
  ivec3 t = ivec3(x, row % layer_h, row / layer_h);
  imageStore(dst, p, texelFetch(src, t, 0));
}
