// The winner of a pixel from the two 32-bit key buffers (see raster_key32.wgsl).
@group(0) @binding(6) var<storage, read> keys: array<u32>;

// the winning logical index at pixel i and its depth bits; false = background
fn winner(i: u32, out_logical: ptr<function, u32>, out_depth: ptr<function, u32>) -> bool {
  let ik = ikeys[i];
  if (ik == 0u) { return false; }
  *out_logical = ~ik;
  *out_depth = ~keys[i];
  return true;
}

// the depth bits only (eye-dome lighting's neighbours); false = background
fn depth_at(i: u32, out_depth: ptr<function, u32>) -> bool {
  let k = keys[i];
  if (k == 0u) { return false; }
  *out_depth = ~k;
  return true;
}
