/* Upload helper: Blender's Python API uploads float data only, so uint
 * addresses travel as two exact float halves (lo, hi < 65536) and are joined
 * here into the RGBA32UI texture the kernels read (once per bake). */
void main()
{
  ivec3 p = ivec3(gl_GlobalInvocationID);
  uvec4 lo = uvec4(texelFetch(lo_in, p, 0));
  uvec4 hi = uvec4(texelFetch(hi_in, p, 0));
  imageStore(dst, p, lo | (hi << 16u));
}
