/* x <- s x in place (re-scales a resident warm start when the host changes the
 * power-of-two scale of q in fp16 mode; twin: x * s). */
void main()
{
  ivec3 p = ivec3(gl_GlobalInvocationID);
  imageStore(x_io, p, vec4(imageLoad(x_io, p).rgb * s, 0.0));
}
