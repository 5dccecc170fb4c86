// Eye-dome lighting (rules.edl_shade; Potree's EDL): a covered pixel p is darkened by
// shade = exp(-300 * strength / 8 * sum_k max(0, log2 z(p) - log2 z(p + o_k))) over the 8
// integer offsets o_k in E (computed on the CPU); a background or outside neighbour adds 0,
// background pixels are never shaded. The including shader declares E: EdlParams and
// fn linear_depth(x: u32, y: u32, z: ptr<function, f32>) -> bool (false = background).

fn edl_offset(k: u32) -> vec2<i32> {
  let v = E.offsets[k >> 1u];
  if ((k & 1u) == 0u) { return v.xy; }
  return v.zw;
}

// sum_k max(0, log2 z - log2 z_k) = log2(prod over nearer neighbours of z / z_k): one log2
// per pixel instead of nine (the product can only overflow when the shade is 0 anyway;
// clamped so that strength 0 still gives exactly 1)
fn edl_shade(x: u32, y: u32, z: f32) -> f32 {
  var prod = 1.0;
  for (var k = 0u; k < 8u; k = k + 1u) {
    let q = vec2<i32>(i32(x), i32(y)) + edl_offset(k);
    if (q.x < 0 || q.y < 0 || q.x >= i32(E.width) || q.y >= i32(E.height)) { continue; }
    var zq = 0.0;
    if (linear_depth(u32(q.x), u32(q.y), &zq) && zq < z) { prod = prod * (z / zq); }
  }
  if (prod == 1.0) { return 1.0; }
  return exp(-E.k * log2(min(prod, 3.0e38)));
}

// RGB bytes times the shade, rounded to nearest as a unorm8 target stores them; alpha kept
fn shade_rgba8(c: u32, s: f32) -> u32 {
  let r = u32(floor(f32(c & 255u) * s + 0.5));
  let g = u32(floor(f32((c >> 8u) & 255u) * s + 0.5));
  let b = u32(floor(f32((c >> 16u) & 255u) * s + 0.5));
  return r | (g << 8u) | (b << 16u) | (c & 0xff000000u);
}
