/* One pass of the per-channel sum reduction (twin: kernels.squared_norms).
 *
 * Each invocation sums a TILE x TILE tile of every layer of `src` and writes
 * one texel of `dst` (a single-layer texture TILE times smaller per axis).
 * The first pass squares (SQUARE = 1), later passes add (SQUARE = 0); the
 * host repeats passes until one texel is left and reads back only that. */
void main()
{
  ivec2 o = ivec2(gl_GlobalInvocationID.xy);
  ivec3 dsz = imageSize(dst);
  if (o.x >= dsz.x || o.y >= dsz.y) {
    return;
  }
  ivec3 sz = textureSize(src, 0);
  int x0 = o.x * TILE, y0 = o.y * TILE;
  int x1 = min(x0 + TILE, sz.x), y1 = min(y0 + TILE, sz.y);
  vec4 acc = vec4(0.0);
  for (int l = 0; l < sz.z; l++) {
    for (int y = y0; y < y1; y++) {
      for (int x = x0; x < x1; x++) {
        vec4 v = texelFetch(src, ivec3(x, y, l), 0);
#if SQUARE
        acc += v * v;
#else
        acc += v;
#endif
      }
    }
  }
  imageStore(dst, ivec3(o, 0), acc);
}
