// The winner of a pixel from the 64-bit keys (see raster_key64.wgsl).
@group(0) @binding(6) var<storage, read> keys: array<vec2<u32>>;

// the winning logical index at pixel i and its depth bits; false = background
fn winner(i: u32, out_logical: ptr<function, u32>, out_depth: ptr<function, u32>) -> bool {
  let k = keys[i];
  if (k.x == 0u && k.y == 0u) { return false; }
  *out_logical = ~k.x;
  *out_depth = ~k.y;
  return true;
}

// the depth bits only (eye-dome lighting's neighbours); false = background
fn depth_at(i: u32, out_depth: ptr<function, u32>) -> bool {
  let k = keys[i];
  if (k.x == 0u && k.y == 0u) { return false; }
  *out_depth = ~k.y;
  return true;
}
