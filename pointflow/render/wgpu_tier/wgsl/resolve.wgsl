// The compute method's resolve pass: each pixel's winning key -> its colour or the
// background, into the RGBA8 image (rows at the readback pitch, C.pick_x0 pixels).
@group(0) @binding(10) var<storage, read_write> img: array<u32>;

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
    c = point_colour(slot_of(logical));
  }
  img[gid.y * C.pick_x0 + x] = c;  // pick_x0 holds the row pitch in pixels here
}
