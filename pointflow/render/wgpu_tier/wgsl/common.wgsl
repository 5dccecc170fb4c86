// Shared helpers of every wgpu pass (the Params/CParams structs and the F_*/C_*/S_* constants
// are generated from layout.py and prepended by wgsl.py).

// PCG RXS-M-XS 32-bit hash (reference.pcg_hash)
fn pcg(v: u32) -> u32 {
  let state = v * 747796405u + 2891336453u;
  let word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
  return (word >> 22u) ^ word;
}
fn u01(slot: u32, seed: u32) -> f32 {
  return f32(pcg(slot ^ seed) >> 8u) * (1.0 / 16777216.0);
}
fn is_finite(x: f32) -> bool {
  return (bitcast<u32>(x) & 0x7f800000u) != 0x7f800000u;
}
// order-preserving float -> u32 (for atomic min/max)
fn ord_f(x: f32) -> u32 {
  let b = bitcast<u32>(x);
  if ((b & 0x80000000u) != 0u) { return ~b; }
  return b | 0x80000000u;
}
fn unord_f(u: u32) -> f32 {
  if ((u & 0x80000000u) != 0u) { return bitcast<f32>(u & 0x7fffffffu); }
  return bitcast<f32>(~u);
}
// clip position of an origin-relative point; NAIVE (tests only): absolute float32 model
// matrix, which shows the large-coordinate error the origin-relative transform avoids
override NAIVE: bool = false;
fn clip_of(p: vec3<f32>) -> vec4<f32> {
  if (NAIVE) { return P.vp * (P.model * vec4<f32>(p, 1.0)); }
  return P.vp * vec4<f32>(p, 1.0);
}
