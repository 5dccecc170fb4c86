// The compute method's resolve pass: each pixel's winning key -> its colour or the
// background, into the RGBA8 image (rows at the readback pitch, C.pick_x0 pixels); with
// EDL (a pipeline constant) the colour is shaded by eye-dome lighting over the key
// buffer's depths (edl.wgsl).
@group(0) @binding(10) var<storage, read_write> img: array<u32>;
@group(0) @binding(11) var<uniform> E: EdlParams;

override EDL: bool = false;

// the winner's linear view depth (clip w) at pixel (x, y); false = background
fn linear_depth(x: u32, y: u32, z: ptr<function, f32>) -> bool {
  var bits = 0u;
  if (!depth_at(y * u32(P.vw) + x, &bits)) { return false; }
  *z = bitcast<f32>(bits);
  return true;
}

// one thread per pixel, a workgroup along a row (one row of threads: cheapest on lavapipe)
@compute @workgroup_size(256, 1)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
  let W = u32(P.vw);
  let x = gid.x;
  if (x >= W) { return; }
  var c = C.background;
  var logical = 0u;
  var depth = 0u;
  if (winner(gid.y * W + x, &logical, &depth)) {
    // a ring in several chunks resolves once per segment: each writes the pixels its own
    // points won (the first also the background)
    let l = logical - P.logical_base;  // wraps to a huge value before this segment
    if (l >= P.size) { return; }
    c = point_colour(slot_of(l));
    if (EDL) { c = shade_rgba8(c, edl_shade(x, gid.y, bitcast<f32>(depth))); }
  } else if (P.logical_base != 0u) {
    return;
  }
  img[gid.y * C.pick_x0 + x] = c;  // pick_x0 holds the row pitch in pixels here
}
