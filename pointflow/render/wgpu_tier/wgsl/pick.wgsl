// The compute method's pick gather: one thread per texel of the (2r+1)^2 block under the
// cursor writes the winner's slot + 1 and its attributes, as the quads method's pick
// textures hold them (no re-render).
struct PickTexel { slot1: u32, depth: f32, imp: f32, t_hi: f32, t_lo: f32, pad0: u32, pad1: u32, pad2: u32 };
@group(0) @binding(10) var<storage, read_write> pick_out: array<PickTexel>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
  let n = C.pick_w * C.pick_h;
  if (gid.x >= n) { return; }
  let x = C.pick_x0 + gid.x % C.pick_w;
  let y = C.pick_y0 + gid.x / C.pick_w;
  var t: PickTexel;
  t.slot1 = 0u;
  t.depth = 1.0;
  var logical = 0u;
  var depth = 0u;
  if (winner(y * u32(P.vw) + x, &logical, &depth)) {
    // once per segment, as the resolve pass (the first also writes the empty texels)
    let l = logical - P.logical_base;
    if (l >= P.size) { return; }
    let slot = slot_of(l);
    t.slot1 = P.slot_base + slot + 1u;
    t.depth = bitcast<f32>(depth);
    t.imp = imp[slot];
    let tt = tms[slot];
    t.t_hi = tt.x;
    t.t_lo = tt.y;
  } else if (P.logical_base != 0u) {
    return;
  }
  pick_out[gid.x] = t;
}
