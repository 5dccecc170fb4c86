// The quads method's eye-dome lighting pass (render.edl): one thread per pixel reads the
// colour target and the linear-depth target of the draw and writes the shaded RGBA8 image
// (rows at E.row_pitch pixels) that read_image copies. With edl.wgsl.
@group(0) @binding(0) var colour: texture_2d<f32>;
@group(0) @binding(1) var depth: texture_2d<f32>;
@group(0) @binding(2) var<storage, read_write> img: array<u32>;
@group(0) @binding(3) var<uniform> E: EdlParams;

fn linear_depth(x: u32, y: u32, z: ptr<function, f32>) -> bool {
  let w = textureLoad(depth, vec2<u32>(x, y), 0).x;
  *z = w;
  return w > 0.0;
}

@compute @workgroup_size(256, 1)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
  let x = gid.x;
  let y = gid.y;
  if (x >= E.width) { return; }
  var c = pack4x8unorm(textureLoad(colour, vec2<u32>(x, y), 0));
  var z = 0.0;
  if (linear_depth(x, y, &z)) { c = shade_rgba8(c, edl_shade(x, y, z)); }
  img[y * E.row_pitch + x] = c;
}
