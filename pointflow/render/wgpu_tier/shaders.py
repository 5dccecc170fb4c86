"""WGSL sources of the wgpu tier (strings, so the package needs no data files).

Params is one uniform block, written per frame; word offsets are in ``renderer._P_*``.
"""
from __future__ import annotations

PARAMS = r"""
struct Params {
  vp: mat4x4<f32>,
  model: mat4x4<f32>,
  planes: array<vec4<f32>, 6>,
  fixed_color: vec4<f32>,
  vw: f32, vh: f32, point_size: f32, size_scale: f32,
  now_hi: f32, now_lo: f32, window_ms: f32, imp_lo: f32,
  imp_scale: f32, range_lo: f32, range_scale: f32, range_hi: f32,
  head: u32, size: u32, capacity: u32, lod_stride: u32,
  seed: u32, flags: u32, budget: u32, color_mode: u32,
  budget_seed: u32, groups_x: u32, n_slots: u32, groups_total: u32,
};
// flags
const F_WINDOW: u32 = 1u;
const F_IMPORTANCE: u32 = 2u;
const F_IMP_DEGENERATE: u32 = 4u;
const F_WORLD_SIZE: u32 = 16u;
const F_ROUND: u32 = 32u;
const F_RANGE_AUTO: u32 = 64u;
const F_RANGE_DEGENERATE: u32 = 128u;
const F_COLOUR_IN_VS: u32 = 256u;
// colour modes
const C_FIXED: u32 = 0u;
const C_RGB: u32 = 1u;
const C_SCALAR: u32 = 2u;
const C_Z: u32 = 3u;
const C_TIME: u32 = 4u;
// state words
const S_COUNT1: u32 = 8u;
const S_COUNT2: u32 = 9u;
const S_NONFINITE: u32 = 12u;
const S_OCCUPIED: u32 = 13u;

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
"""

SCAN = r"""
var<workgroup> sh: array<u32, 256>;

// exclusive prefix sum over the 256 lanes of a workgroup (call in uniform control flow)
fn wg_exclusive(lid: u32, v: u32) -> u32 {
  sh[lid] = v;
  workgroupBarrier();
  for (var off = 1u; off < 256u; off = off * 2u) {
    var t = 0u;
    if (lid >= off) { t = sh[lid - off]; }
    workgroupBarrier();
    sh[lid] = sh[lid] + t;
    workgroupBarrier();
  }
  return sh[lid] - v;
}

// one workgroup: per-workgroup counts wgc[0..n) -> exclusive offsets (in place); the total
// lands in st[total_at]. Offsets in workgroup order make the compaction deterministic.
fn scan_counts(lid: u32, n: u32, total_at: u32) {
  let chunk = (n + 255u) / 256u;
  let a = min(lid * chunk, n);
  let b = min(a + chunk, n);
  var sum = 0u;
  for (var i = a; i < b; i = i + 1u) { sum = sum + wgc[i]; }
  let base = wg_exclusive(lid, sum);
  var run = base;
  for (var i = a; i < b; i = i + 1u) {
    let c = wgc[i];
    wgc[i] = run;
    run = run + c;
  }
  if (lid == 255u) { atomicStore(&st[total_at], base + sum); }
}
"""

CULL = PARAMS + r"""
@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> pos: array<f32>;
@group(0) @binding(2) var<storage, read> tms: array<vec2<f32>>;
@group(0) @binding(3) var<storage, read> imp: array<f32>;
@group(0) @binding(4) var<storage, read> col: array<u32>;
@group(0) @binding(5) var<storage, read_write> idx_out: array<vec2<u32>>;
@group(0) @binding(6) var<storage, read_write> st: array<atomic<u32>, 16>;
@group(0) @binding(7) var<storage, read_write> rng: array<atomic<u32>, 2>;
@group(0) @binding(8) var<storage, read_write> dargs: array<u32, 4>;
@group(0) @binding(9) var<storage, read> lut: array<u32, 256>;
@group(0) @binding(10) var<storage, read_write> clip_out: array<vec4<f32>>;
@group(0) @binding(11) var<storage, read_write> flags: array<u32>;
@group(0) @binding(12) var<storage, read_write> wgc: array<u32>;
""" + SCAN + r"""
var<workgroup> wg_count: atomic<u32>;
var<workgroup> wg_bad: atomic<u32>;
var<workgroup> wg_occ: atomic<u32>;
var<workgroup> wg_min: atomic<u32>;
var<workgroup> wg_max: atomic<u32>;

fn colour_value(slot: u32, p: vec3<f32>) -> f32 {
  if (P.color_mode == C_Z) { return p.z; }
  if (P.color_mode == C_TIME) { return tms[slot].x; }
  return bitcast<f32>(col[slot]);
}

// colour of a survivor when the range is known before the draw (not F_COLOUR_IN_VS):
// computed once per point here instead of once per quad vertex in the vertex shader
fn cull_colour(slot: u32, p: vec3<f32>) -> u32 {
  if ((P.flags & F_COLOUR_IN_VS) != 0u) { return 0u; }
  if (P.color_mode == C_FIXED) { return pack4x8unorm(P.fixed_color); }
  if (P.color_mode == C_RGB) { return col[slot]; }
  let v = colour_value(slot, p);
  if (!is_finite(v)) { return pack4x8unorm(P.fixed_color); }
  var i = 255u;
  if ((P.flags & F_RANGE_DEGENERATE) == 0u && P.range_hi > P.range_lo) {
    let t = (v - P.range_lo) * P.range_scale;
    i = u32(floor(clamp(t, 0.0, 1.0) * 255.0 + 0.5));
  }
  return lut[i];
}

fn slot_of(logical: u32) -> u32 {
  // logical index -> ring slot (threads run in logical order: oldest first)
  return (P.head + logical) % P.capacity;
}

// pass 1: one thread per logical index; keep flag + per-workgroup count
@compute @workgroup_size(256)
fn cull(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>) {
  if (lid == 0u) {
    atomicStore(&wg_count, 0u);
    atomicStore(&wg_bad, 0u);
    atomicStore(&wg_occ, 0u);
    atomicStore(&wg_min, 0xffffffffu);
    atomicStore(&wg_max, 0u);
  }
  workgroupBarrier();
  let g = wid.y * P.groups_x + wid.x;
  let logical = g * 256u + lid;
  var keep = false;
  if (logical < P.size) {
    let slot = slot_of(logical);
    if (slot < P.n_slots) {
      let p = vec3<f32>(pos[3u * slot], pos[3u * slot + 1u], pos[3u * slot + 2u]);
      keep = is_finite(p.x) && is_finite(p.y) && is_finite(p.z);
      atomicAdd(&wg_occ, 1u);
      if (!keep) { atomicAdd(&wg_bad, 1u); }
      if ((P.flags & F_RANGE_AUTO) != 0u) {
        let v = colour_value(slot, p);
        if (keep && is_finite(v)) {
          atomicMin(&wg_min, ord_f(v));
          atomicMax(&wg_max, ord_f(v));
        }
      }
      if (keep && (P.flags & F_WINDOW) != 0u) {
        let t = tms[slot];
        let dt = (P.now_hi - t.x) + (P.now_lo - t.y);
        keep = dt <= P.window_ms;
      }
      if (keep) {
        for (var i = 0u; i < 6u; i = i + 1u) {
          let pl = P.planes[i];
          keep = keep && (dot(pl.xyz, p) + pl.w >= 0.0);
        }
      }
      if (keep && P.lod_stride > 1u) {
        keep = (logical % P.lod_stride) == 0u;
      }
      if (keep && (P.flags & F_IMPORTANCE) != 0u) {
        var n = 1.0;
        if ((P.flags & F_IMP_DEGENERATE) == 0u) {
          let x = imp[slot];
          n = clamp((x - P.imp_lo) * P.imp_scale, 0.0, 1.0);
          if (!is_finite(x)) { n = 0.0; }
        }
        keep = u01(slot, P.seed) <= n;
      }
    }
  }
  if (logical < P.groups_total * 256u) { flags[logical] = select(0u, 1u, keep); }
  if (keep) { atomicAdd(&wg_count, 1u); }
  workgroupBarrier();
  if (lid == 0u) {
    if (g < P.groups_total) { wgc[g] = atomicLoad(&wg_count); }
    let bad = atomicLoad(&wg_bad);
    if (bad > 0u) { atomicAdd(&st[S_NONFINITE], bad); }
    let occ = atomicLoad(&wg_occ);
    if (occ > 0u) { atomicAdd(&st[S_OCCUPIED], occ); }
    if ((P.flags & F_RANGE_AUTO) != 0u) {
      let mn = atomicLoad(&wg_min);
      let mx = atomicLoad(&wg_max);
      if (mn <= mx) { atomicMin(&rng[0], mn); atomicMax(&rng[1], mx); }
    }
  }
}

// pass 2: one workgroup scans the per-workgroup counts
@compute @workgroup_size(256)
fn scan(@builtin(local_invocation_index) lid: u32) {
  scan_counts(lid, P.groups_total, S_COUNT1);
}

// pass 3: survivors written in logical order, projected and coloured once per point.
// Each thread walks EMIT_K consecutive logical indices, so one 256-lane prefix sum (the
// barrier-heavy part on CPU adapters) covers 256 * EMIT_K points.
const EMIT_K: u32 = 8u;

@compute @workgroup_size(256)
fn emit(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>) {
  let G = wid.x;                       // emit group: cull groups G*EMIT_K .. G*EMIT_K+EMIT_K-1
  let first = G * 256u * EMIT_K + lid * EMIT_K;
  let limit = P.groups_total * 256u;
  var c = 0u;
  for (var j = 0u; j < EMIT_K; j = j + 1u) {
    let l = first + j;
    if (l < limit) { c = c + flags[l]; }
  }
  let local = wg_exclusive(lid, c);
  if (c > 0u) {
    var o = wgc[G * EMIT_K] + local;
    for (var j = 0u; j < EMIT_K; j = j + 1u) {
      let l = first + j;
      if (l < limit && flags[l] == 1u) {
        let slot = slot_of(l);
        let p = vec3<f32>(pos[3u * slot], pos[3u * slot + 1u], pos[3u * slot + 2u]);
        idx_out[o] = vec2<u32>(slot, cull_colour(slot, p));
        clip_out[o] = {CLIP};
        o = o + 1u;
      }
    }
  }
}

// one thread: draw args (no budget) or the thinning dispatch (budget)
@compute @workgroup_size(1)
fn finalize() {
  let c1 = atomicLoad(&st[S_COUNT1]);
  atomicStore(&st[0], 6u);
  atomicStore(&st[2], 0u);
  atomicStore(&st[3], 0u);
  if (P.budget == 0xffffffffu) {
    atomicStore(&st[1], c1);
  } else {
    atomicStore(&st[1], 0u);
    var frac = 2.0;
    if (c1 > P.budget) {
      // aim 3 sigma under the budget so the hard cap rarely bites: the drawn set then
      // depends only on the hash
      let b = f32(P.budget);
      frac = max(b - 3.0 * sqrt(b), 0.5 * b) / f32(c1);
    }
    atomicStore(&st[10], bitcast<u32>(frac));
    let groups = (c1 + 255u) / 256u;
    let gx = max(min(groups, 65535u), 1u);
    dargs[0] = gx;
    dargs[1] = (groups + gx - 1u) / gx;
    dargs[2] = 1u;
    atomicStore(&st[11], gx);
  }
}

@compute @workgroup_size(1)
fn finalize_budget() {
  atomicStore(&st[1], min(atomicLoad(&st[S_COUNT2]), P.budget));
}
"""

THIN = PARAMS + r"""
@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> idx_in: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read_write> idx_out: array<vec2<u32>>;
@group(0) @binding(3) var<storage, read_write> st: array<atomic<u32>, 16>;
@group(0) @binding(4) var<storage, read> clip_in: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read_write> clip_out: array<vec4<f32>>;
@group(0) @binding(6) var<storage, read_write> flags: array<u32>;
@group(0) @binding(7) var<storage, read_write> wgc: array<u32>;
""" + SCAN + r"""
var<workgroup> wg_count: atomic<u32>;

fn thin_groups() -> u32 {
  return (atomicLoad(&st[S_COUNT1]) + 255u) / 256u;
}

// budget pass 1 (indirect, one thread per survivor in logical order): hashed keep flag
@compute @workgroup_size(256)
fn thin(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>) {
  if (lid == 0u) { atomicStore(&wg_count, 0u); }
  workgroupBarrier();
  let g = wid.y * atomicLoad(&st[11]) + wid.x;
  let i = g * 256u + lid;
  let c1 = atomicLoad(&st[S_COUNT1]);
  let frac = bitcast<f32>(atomicLoad(&st[10]));
  var keep = false;
  if (i < c1) { keep = u01(idx_in[i].x, P.budget_seed) < frac; }
  if (i < thin_groups() * 256u) { flags[i] = select(0u, 1u, keep); }
  if (keep) { atomicAdd(&wg_count, 1u); }
  workgroupBarrier();
  if (lid == 0u && g < thin_groups()) { wgc[g] = atomicLoad(&wg_count); }
}

@compute @workgroup_size(256)
fn thin_scan(@builtin(local_invocation_index) lid: u32) {
  scan_counts(lid, thin_groups(), S_COUNT2);
}

// budget pass 3: kept survivors in logical order; beyond the budget: the newest dropped
@compute @workgroup_size(256)
fn thin_emit(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>) {
  let g = wid.y * atomicLoad(&st[11]) + wid.x;
  let i = g * 256u + lid;
  var k = 0u;
  if (i < thin_groups() * 256u) { k = flags[i]; }
  let local = wg_exclusive(lid, k);
  if (k == 1u) {
    let o = wgc[g] + local;
    if (o < P.budget) {
      idx_out[o] = idx_in[i];
      clip_out[o] = clip_in[i];
    }
  }
}
"""

#: A scalar through the colormap LUT; ``{RANGE_AUTO}`` is the test for an auto range (a
#: uniform flag here, a pipeline constant in the compute resolve pass).
LUT_COLOUR = r"""fn lut_colour(v: f32) -> u32 {
  if (!is_finite(v)) { return pack4x8unorm(P.fixed_color); }
  var lo = P.range_lo;
  var hi = P.range_hi;
  var scale = P.range_scale;
  if ({RANGE_AUTO}) {
    lo = unord_f(rng[0]);
    hi = unord_f(rng[1]);
    scale = 1.0 / (hi - lo);
  }
  var i = 255u;
  if ((P.flags & F_RANGE_DEGENERATE) == 0u && hi > lo) {
    let t = (v - lo) * scale;
    i = u32(floor(clamp(t, 0.0, 1.0) * 255.0 + 0.5));
  }
  return lut[i];
}
"""


DRAW_HEAD = PARAMS + r"""
@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> pos: array<f32>;
@group(0) @binding(2) var<storage, read> tms: array<vec2<f32>>;
@group(0) @binding(3) var<storage, read> imp: array<f32>;
@group(0) @binding(4) var<storage, read> col: array<u32>;
@group(0) @binding(5) var<storage, read> idx: array<vec2<u32>>;
@group(0) @binding(6) var<storage, read> lut: array<u32, 256>;
@group(0) @binding(7) var<storage, read> rng: array<u32, 2>;
@group(0) @binding(8) var<storage, read> clipb: array<vec4<f32>>;

""" + LUT_COLOUR.replace("{RANGE_AUTO}", "(P.flags & F_RANGE_AUTO) != 0u") + r"""
fn point_colour(slot: u32, p: vec3<f32>) -> u32 {
  if (P.color_mode == C_RGB) { return col[slot]; }
  if (P.color_mode == C_SCALAR) { return lut_colour(bitcast<f32>(col[slot])); }
  if (P.color_mode == C_Z) { return lut_colour(p.z); }
  if (P.color_mode == C_TIME) { return lut_colour(tms[slot].x); }
  return pack4x8unorm(P.fixed_color);
}
"""

#: The vertex/fragment stage is generated per variant (shape, size space, where the colour
#: is computed, pick) so each carries only the code and varyings it needs: on software
#: rasterisers (llvmpipe runs the vertex shader 6x per point) a generic shader with
#: uniform branches drew 1M points about 1.8x slower than the specialised one.
_VS = r"""
struct VOut {
  @builtin(position) position: vec4<f32>,
  {FIELDS}
};

@vertex
fn vs(@builtin(vertex_index) vi: u32, @builtin(instance_index) ii: u32) -> VOut {
  let e = idx[ii];
  let slot = e.x;
  let clip = clipb[ii];
  {SIZE}
  var corners = array<vec2<f32>, 6>(vec2<f32>(-1.0, -1.0), vec2<f32>(1.0, -1.0), vec2<f32>(-1.0, 1.0),
                                    vec2<f32>(-1.0, 1.0), vec2<f32>(1.0, -1.0), vec2<f32>(1.0, 1.0));
  let off = corners[vi] * ext * vec2<f32>(2.0 / P.vw, 2.0 / P.vh) * clip.w;
  var o: VOut;
  // a point exactly on the far plane (depth 1.0) must still pass 'less' against the cleared 1.0
  o.position = vec4<f32>(clip.xy + off, min(clip.z, clip.w * 0.99999994), clip.w);
  {ASSIGN}
  return o;
}
"""

_FS_DRAW = r"""
@fragment
fn fs(in: VOut) -> @location(0) vec4<f32> {
  {COVER}
  return unpack4x8unorm(in.color);
}
"""

_FS_PICK = r"""
struct PickOut {
  @location(0) slot: u32,
  @location(1) attrs: vec4<f32>,
};

@fragment
fn fs_pick(in: VOut) -> PickOut {
  {COVER}
  var o: PickOut;
  o.slot = in.slot + 1u;
  let t = tms[in.slot];
  o.attrs = vec4<f32>(in.position.z, imp[in.slot], t.x, t.y);
  return o;
}
"""

_COVER = r"""let d = in.position.xy - in.centre.xy;
  if (dot(d, d) > in.centre.z * in.centre.z) { discard; }"""

CLIP_RELATIVE = "P.vp * vec4<f32>(p, 1.0)"
#: test-only: absolute float32 model matrix (shows the large-coordinate error)
CLIP_NAIVE = "P.vp * (P.model * vec4<f32>(p, 1.0))"


def cull_source(naive: bool = False) -> str:
    """WGSL of the cull/finalize passes (projects survivors with the chosen transform)."""
    return CULL.replace("{CLIP}", CLIP_NAIVE if naive else CLIP_RELATIVE)


def draw_source(round_points: bool = False, pick: bool = False, world_size: bool = False,
                colour_in_vs: bool = False) -> str:
    """WGSL for one draw variant: ``vs`` + ``fs`` (colour) or ``fs_pick`` (slot + attributes).
    Survivors arrive projected (``clipb``) and, unless ``colour_in_vs``, coloured by the cull."""
    fields, assign = [], []
    if not pick:
        fields.append("@location(0) @interpolate(flat) color: u32,")
        if colour_in_vs:  # the colour range is reduced during this frame's cull
            assign.append("let p = vec3<f32>(pos[3u * slot], pos[3u * slot + 1u], pos[3u * slot + 2u]);\n"
                          "  o.color = point_colour(slot, p);")
        else:
            assign.append("o.color = e.y;")
    if round_points:
        fields.append("@location(1) @interpolate(flat) centre: vec3<f32>,")
        assign.append("let ndc = clip.xy / clip.w;\n  "
                      "o.centre = vec3<f32>((ndc.x * 0.5 + 0.5) * P.vw, (0.5 - ndc.y * 0.5) * P.vh, 0.5 * s);")
    if pick:
        fields.append("@location(2) @interpolate(flat) slot: u32,")
        assign.append("o.slot = slot;")
    size = ("let s = clamp(P.point_size * P.size_scale / clip.w, 1.0, 4096.0);" if world_size
            else "let s = P.point_size;")
    size += "\n  let ext = 0.5 * s + 1.0;" if round_points else "\n  let ext = 0.5 * s;"
    vs = (_VS.replace("{FIELDS}", "\n  ".join(fields)).replace("{ASSIGN}", "\n  ".join(assign))
          .replace("{SIZE}", size))
    fs = (_FS_PICK if pick else _FS_DRAW).replace("{COVER}", _COVER if round_points else "")
    return DRAW_HEAD + vs + fs
