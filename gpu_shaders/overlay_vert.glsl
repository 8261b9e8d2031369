/* Viewport overlay of the radiance attribute (ops/overlay.py): vertex stage.
 * pos, radiance: per-vertex inputs; depth_bias pulls the overlay towards the camera
 * by a fraction of clip-space w so it wins the depth test against the object itself. */
void main()
{
  gl_Position = ModelViewProjectionMatrix * vec4(pos, 1.0);
  gl_Position.z -= depth_bias * gl_Position.w;
  v_radiance = radiance;
}
