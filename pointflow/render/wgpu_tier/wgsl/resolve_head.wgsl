// Bindings and colour of the compute method's per-pixel passes (resolve.wgsl, pick.wgsl);
// with common.wgsl, lut_colour.wgsl and resolve_key64.wgsl / resolve_key32.wgsl.
@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<uniform> C: CParams;
@group(0) @binding(2) var<storage, read> pos: array<f32>;
@group(0) @binding(3) var<storage, read> tms: array<vec2<f32>>;
@group(0) @binding(4) var<storage, read> imp: array<f32>;
@group(0) @binding(5) var<storage, read> col: array<u32>;
@group(0) @binding(7) var<storage, read> ikeys: array<u32>;
@group(0) @binding(8) var<storage, read> lut: array<u32, 256>;
@group(0) @binding(9) var<storage, read> rng: array<u32, 2>;

// the colour mode and whether the range is this frame's GPU reduction: pipeline constants
// (on CPU adapters branches are often flattened, and a generic colour function made the
// resolve pass 6x slower)
override CMODE: u32 = 0u;
override RANGE_AUTO: bool = false;

fn range_is_auto() -> bool { return RANGE_AUTO; }

fn point_colour(slot: u32) -> u32 {
  if (CMODE == C_RGB) { return col[slot]; }
  if (CMODE == C_SCALAR) { return lut_colour(bitcast<f32>(col[slot])); }
  if (CMODE == C_Z) { return lut_colour(pos[3u * slot + 2u]); }
  if (CMODE == C_TIME) { return lut_colour(tms[slot].x); }
  return pack4x8unorm(P.fixed_color);
}

fn slot_of(logical: u32) -> u32 {
  let s = P.head + logical;
  return select(s, s - P.capacity, s >= P.capacity);
}
