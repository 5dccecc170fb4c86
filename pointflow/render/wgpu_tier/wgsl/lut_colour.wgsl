// A scalar through the colormap LUT (the including shader declares lut, rng and
// range_is_auto(): a uniform flag in the quads draw, a pipeline constant in the resolve pass).
fn lut_colour(v: f32) -> u32 {
  if (!is_finite(v)) { return pack4x8unorm(P.fixed_color); }
  var lo = P.range_lo;
  var hi = P.range_hi;
  var scale = P.range_scale;
  if (range_is_auto()) {
    lo = unord_f(rng[0]);
    hi = unord_f(rng[1]);
    scale = 1.0 / (hi - lo);
  }
  var i = 255u;
  if ((P.flags & F_RANGE_DEGENERATE) == 0u && hi > lo) {
    let t = (v - lo) * scale;
    i = u32(floor(clamp(t, 0.0, 1.0) * 255.0 + 0.5));
  }
  return lut[i];
}
