// The quads method's draw: instanced quads (6 vertices per survivor) pulled from the
// compacted survivors (raster/quads.py). One entry-point pair per shape and per target
// (colour / pick), so each carries only the varyings it needs: on software rasterisers
// (llvmpipe runs the vertex shader 6x per point) a generic shader drew 1M points about 1.8x
// slower. WORLD (size in world units) and COLOUR_IN_VS (the colour range is this frame's
// GPU reduction, so the colour is computed here, not in the cull) are pipeline constants.
@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> pos: array<f32>;
@group(0) @binding(2) var<storage, read> tms: array<vec2<f32>>;
@group(0) @binding(3) var<storage, read> imp: array<f32>;
@group(0) @binding(4) var<storage, read> col: array<u32>;
@group(0) @binding(5) var<storage, read> idx: array<vec2<u32>>;
@group(0) @binding(6) var<storage, read> lut: array<u32, 256>;
@group(0) @binding(7) var<storage, read> rng: array<u32, 2>;
@group(0) @binding(8) var<storage, read> clipb: array<vec4<f32>>;

override WORLD: bool = false;
override COLOUR_IN_VS: bool = false;

fn range_is_auto() -> bool { return (P.flags & F_RANGE_AUTO) != 0u; }

fn point_colour(slot: u32, p: vec3<f32>) -> u32 {
  if (P.color_mode == C_RGB) { return col[slot]; }
  if (P.color_mode == C_SCALAR) { return lut_colour(bitcast<f32>(col[slot])); }
  if (P.color_mode == C_Z) { return lut_colour(p.z); }
  if (P.color_mode == C_TIME) { return lut_colour(tms[slot].x); }
  return pack4x8unorm(P.fixed_color);
}

fn colour_of(ii: u32) -> u32 {
  let e = idx[ii];
  if (COLOUR_IN_VS) {
    let slot = e.x;
    let p = vec3<f32>(pos[3u * slot], pos[3u * slot + 1u], pos[3u * slot + 2u]);
    return point_colour(slot, p);
  }
  return e.y;
}

// the footprint in px (rules of render/base.py)
fn size_px(clip: vec4<f32>) -> f32 {
  if (WORLD) { return clamp(P.point_size * P.size_scale / clip.w, 1.0, 4096.0); }
  return P.point_size;
}

// The footprint's pixels are the rules of render/base.py computed as the compute method does
// (raster.wgsl, splat): the pixel box [x0, x1) x [y0, y1) of the float32 centre, and for round
// points the centre test in the fragment shader. The quad's corners lie on that box's pixel
// edges, half a pixel from every pixel centre, so the rasteriser's vertex snapping and edge
// rules cannot change which centres it covers (relying on them put ~0.1% of footprint edge
// pixels one pixel off the cpu rule). Depth is the linear view depth w times P.depth_scale (a
// power of two, so exact and < 1 inside the far plane) at clip w = 1: the depth test orders
// points by w with float32's full relative precision, as the compute keys do, not by z/w.

// the footprint's centre in px (x, y) and its half size h = s / 2 (z)
fn centre_of(clip: vec4<f32>, s: f32) -> vec3<f32> {
  let w = clip.w;
  return vec3<f32>((clip.x / w * 0.5 + 0.5) * P.vw, (0.5 - clip.y / w * 0.5) * P.vh, 0.5 * s);
}

// square: the pixels x in [ceil(px - h - 0.5), ceil(px + h - 0.5)), the same for y, i.e.
// centres in [p - s/2, p + s/2) (as floats: x0, x1, y0, y1)
fn box_square(c: vec3<f32>) -> vec4<f32> {
  return vec4<f32>(ceil(c.x - c.z - 0.5), ceil(c.x + c.z - 0.5), ceil(c.y - c.z - 0.5), ceil(c.y + c.z - 0.5));
}

// round: the box of the centres within s/2 (the fragment shader tests each centre)
fn box_round(c: vec3<f32>) -> vec4<f32> {
  return vec4<f32>(ceil(c.x - c.z - 0.5), floor(c.x + c.z - 0.5) + 1.0,
                   ceil(c.y - c.z - 0.5), floor(c.y + c.z - 0.5) + 1.0);
}

// corner vi of the quad on the pixel box b (an empty box draws nothing, as in the compute method)
fn corner(vi: u32, clip: vec4<f32>, b: vec4<f32>) -> vec4<f32> {
  var corners = array<vec2<f32>, 6>(vec2<f32>(0.0, 0.0), vec2<f32>(1.0, 0.0), vec2<f32>(0.0, 1.0),
                                    vec2<f32>(0.0, 1.0), vec2<f32>(1.0, 0.0), vec2<f32>(1.0, 1.0));
  let k = corners[vi];
  let x = select(b.x, b.y, k.x > 0.5);
  let y = select(b.z, b.w, k.y > 0.5);
  let depth = min(max(clip.w, 0.0) * P.depth_scale, 0.99999994);
  return vec4<f32>(x / P.vw * 2.0 - 1.0, 1.0 - y / P.vh * 2.0, depth, 1.0);
}

// round: centres within s/2 (<=)
fn outside(frag: vec4<f32>, centre: vec3<f32>) -> bool {
  let ex = frag.x - centre.x;
  let ey = frag.y - centre.y;
  return ex * ex + ey * ey > centre.z * centre.z;
}

struct VSquare {
  @builtin(position) position: vec4<f32>,
  @location(0) @interpolate(flat) color: u32,
};

@vertex
fn vs_square(@builtin(vertex_index) vi: u32, @builtin(instance_index) ii: u32) -> VSquare {
  let clip = clipb[ii];
  let s = size_px(clip);
  var o: VSquare;
  o.position = corner(vi, clip, box_square(centre_of(clip, s)));
  o.color = colour_of(ii);
  return o;
}

@fragment
fn fs_square(in: VSquare) -> @location(0) vec4<f32> {
  return unpack4x8unorm(in.color);
}

struct VRound {
  @builtin(position) position: vec4<f32>,
  @location(0) @interpolate(flat) color: u32,
  @location(1) @interpolate(flat) centre: vec3<f32>,
};

@vertex
fn vs_round(@builtin(vertex_index) vi: u32, @builtin(instance_index) ii: u32) -> VRound {
  let clip = clipb[ii];
  let s = size_px(clip);
  var o: VRound;
  let c = centre_of(clip, s);
  o.position = corner(vi, clip, box_round(c));
  o.color = colour_of(ii);
  o.centre = c;
  return o;
}

@fragment
fn fs_round(in: VRound) -> @location(0) vec4<f32> {
  if (outside(in.position, in.centre)) { discard; }
  return unpack4x8unorm(in.color);
}

// picking: slot + 1 and (depth, importance, t_hi, t_lo) of the front-most point per texel
struct PickOut {
  @location(0) slot: u32,
  @location(1) attrs: vec4<f32>,
};

fn pick_out(slot: u32, z: f32) -> PickOut {
  var o: PickOut;
  o.slot = P.slot_base + slot + 1u;  // (slot is the chunk's; the ring's slot + 1 goes out)
  let t = tms[slot];
  o.attrs = vec4<f32>(z, imp[slot], t.x, t.y);
  return o;
}

struct VPickSquare {
  @builtin(position) position: vec4<f32>,
  @location(2) @interpolate(flat) slot: u32,
};

@vertex
fn vs_pick_square(@builtin(vertex_index) vi: u32, @builtin(instance_index) ii: u32) -> VPickSquare {
  let clip = clipb[ii];
  let s = size_px(clip);
  var o: VPickSquare;
  o.position = corner(vi, clip, box_square(centre_of(clip, s)));
  o.slot = idx[ii].x;
  return o;
}

@fragment
fn fs_pick_square(in: VPickSquare) -> PickOut {
  return pick_out(in.slot, in.position.z);
}

struct VPickRound {
  @builtin(position) position: vec4<f32>,
  @location(1) @interpolate(flat) centre: vec3<f32>,
  @location(2) @interpolate(flat) slot: u32,
};

@vertex
fn vs_pick_round(@builtin(vertex_index) vi: u32, @builtin(instance_index) ii: u32) -> VPickRound {
  let clip = clipb[ii];
  let s = size_px(clip);
  var o: VPickRound;
  let c = centre_of(clip, s);
  o.position = corner(vi, clip, box_round(c));
  o.centre = c;
  o.slot = idx[ii].x;
  return o;
}

@fragment
fn fs_pick_round(in: VPickRound) -> PickOut {
  if (outside(in.position, in.centre)) { discard; }
  return pick_out(in.slot, in.position.z);
}

// eye-dome lighting (render.edl): the colour pass also writes the point's linear view depth
// (clip w, > 0) into an r32float target cleared to 0 (background); edl_post.wgsl shades
struct VSquareEdl {
  @builtin(position) position: vec4<f32>,
  @location(0) @interpolate(flat) color: u32,
  @location(3) @interpolate(flat) w: f32,
};

struct EdlOut {
  @location(0) color: vec4<f32>,
  @location(1) w: f32,
};

@vertex
fn vs_square_edl(@builtin(vertex_index) vi: u32, @builtin(instance_index) ii: u32) -> VSquareEdl {
  let clip = clipb[ii];
  let s = size_px(clip);
  var o: VSquareEdl;
  o.position = corner(vi, clip, box_square(centre_of(clip, s)));
  o.color = colour_of(ii);
  o.w = clip.w;
  return o;
}

@fragment
fn fs_square_edl(in: VSquareEdl) -> EdlOut {
  return EdlOut(unpack4x8unorm(in.color), in.w);
}

struct VRoundEdl {
  @builtin(position) position: vec4<f32>,
  @location(0) @interpolate(flat) color: u32,
  @location(1) @interpolate(flat) centre: vec3<f32>,
  @location(3) @interpolate(flat) w: f32,
};

@vertex
fn vs_round_edl(@builtin(vertex_index) vi: u32, @builtin(instance_index) ii: u32) -> VRoundEdl {
  let clip = clipb[ii];
  let s = size_px(clip);
  var o: VRoundEdl;
  let c = centre_of(clip, s);
  o.position = corner(vi, clip, box_round(c));
  o.color = colour_of(ii);
  o.centre = c;
  o.w = clip.w;
  return o;
}

@fragment
fn fs_round_edl(in: VRoundEdl) -> EdlOut {
  if (outside(in.position, in.centre)) { discard; }
  return EdlOut(unpack4x8unorm(in.color), in.w);
}
