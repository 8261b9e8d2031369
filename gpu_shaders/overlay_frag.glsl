/* Viewport overlay: fragment stage.  Display mapping of the exposed radiance x = gain * L:
 * soft: 1 - exp(-x) (bright regions roll off towards white), else min(x, 1).
 * Its numpy twin is ops.overlay.tone_map. */
void main()
{
  vec3 x = max(v_radiance.rgb, vec3(0.0)) * gain;
  vec3 display = (soft > 0.5) ? (vec3(1.0) - exp(-x)) : min(x, vec3(1.0));
  FragColor = vec4(display, 1.0);
}
