"""WGSL of the compute raster method (``render.raster: compute``), see compute_raster.py.

One pass over the occupied slots fuses every per-point test of the tier with the projection
and an atomic write of a per-pixel key; a second pass per pixel resolves the key to a colour.

Key encoding (the buffer is cleared to 0 and written with atomicMax, so keys are stored
inverted: the largest stored value is the smallest key):

* ``key = (bits(w) << 32) | logical`` with ``w`` the clip w of the point, i.e. its linear
  view depth in world units (perspective camera: ``w = -z_view > 0`` after the near test),
  as a float32 whose bit pattern orders like the number for positive values. The relative
  precision is 2^-24 whatever near/far are (0.03 mm at 500 m), unlike the hyperbolic
  ``z/w`` of a depth buffer; a smaller w always gives a smaller key, so quantisation can
  never let a farther point win, and equal depths fall back to the lower logical index.
* 64-bit atomics (``shader-int64-atomic-min-max``): the whole key in one ``atomicMax``.
* otherwise two passes of 32-bit atomics: ``atomicMax(~bits(w))`` per pixel, then the same
  pass again writes ``atomicMax(~logical)`` where its depth equals the pixel's winner.
"""
from __future__ import annotations

from .shaders import LUT_COLOUR, PARAMS, SCAN

#: points per thread (a workgroup of 256 covers 256 * K consecutive logical indices; row j
#: of a workgroup is 256 consecutive indices, so rows in order are logical order)
K = 16
POINTS_PER_GROUP = 256 * K

CPARAMS = r"""
struct CParams {
  background: u32, groups_x: u32, budget_on: u32, first_group: u32,
  pick_x0: u32, pick_y0: u32, pick_w: u32, pick_h: u32,
};
@group(0) @binding(1) var<uniform> C: CParams;
"""

_RASTER_HEAD = PARAMS + CPARAMS + r"""
@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(2) var<storage, read> pos: array<f32>;
@group(0) @binding(3) var<storage, read> tms: array<vec2<f32>>;
@group(0) @binding(4) var<storage, read> imp: array<f32>;
@group(0) @binding(5) var<storage, read> col: array<u32>;
@group(0) @binding(6) var<storage, read_write> keys: array<{KEYTYPE}>;
@group(0) @binding(7) var<storage, read_write> ikeys: array<atomic<u32>>;
@group(0) @binding(8) var<storage, read_write> st: array<atomic<u32>, 16>;
@group(0) @binding(9) var<storage, read_write> rng: array<atomic<u32>, 2>;
@group(0) @binding(10) var<storage, read_write> wgc: array<u32>;
@group(0) @binding(11) var<storage, read_write> dbg: array<u32>;
""" + SCAN + r"""
const K: u32 = {K}u;
// what this entry point does (specialised per pipeline)
const MODE_COUNT: u32 = 0u;       // budget: survivors only (counters)
const MODE_THIN_COUNT: u32 = 1u;  // budget: thinned survivors per workgroup
const MODE_RASTER: u32 = 2u;      // tests + atomic write
const MODE_DEBUG: u32 = 3u;       // tests only: keep flag per logical index (tests)

var<workgroup> wg_count: atomic<u32>;
var<workgroup> wg_drawn: atomic<u32>;
var<workgroup> wg_bad: atomic<u32>;
var<workgroup> wg_occ: atomic<u32>;
var<workgroup> wg_min: atomic<u32>;
var<workgroup> wg_max: atomic<u32>;
var<workgroup> wg_mode: u32;
var<workgroup> wg_base: u32;

fn slot_of(logical: u32) -> u32 {
  // head < capacity and logical < size <= capacity: one conditional subtract, no modulo
  let s = P.head + logical;
  return select(s, s - P.capacity, s >= P.capacity);
}

fn colour_value(slot: u32, p: vec3<f32>) -> f32 {
  if (CMODE == C_Z) { return p.z; }
  if (CMODE == C_TIME) { return tms[slot].x; }
  return bitcast<f32>(col[slot]);
}

struct Pt {
  keep: bool,        // passed every test before the budget
  occupied: bool,    // an occupied slot the tier renders
  finite: bool,      // ... with a finite position
  slot: u32,
  cval: f32,         // colour value for the auto range (NaN-free only when finite)
  clip: vec4<f32>,
};

// every per-point test of the tier (see reference.py), fused with the projection.
// count: update the occupancy / non-finite / colour-range counters
fn test_point(logical: u32, count: bool) -> Pt {
  var r: Pt;
  r.keep = false;
  if (logical >= P.size) { return r; }
  let slot = slot_of(logical);
  r.slot = slot;
  if (slot >= P.n_slots) { return r; }
  r.occupied = true;
  let p = vec3<f32>(pos[3u * slot], pos[3u * slot + 1u], pos[3u * slot + 2u]);
  var keep = is_finite(p.x) && is_finite(p.y) && is_finite(p.z);
  r.finite = keep;
  if (!keep) { return r; }
  if (count && RANGE_AUTO) { r.cval = colour_value(slot, p); }
  r.clip = {CLIP};
  for (var i = 0u; i < 6u; i = i + 1u) {
    let pl = P.planes[i];
    keep = keep && (dot(pl.xyz, p) + pl.w >= 0.0);
  }
  if (HAS_WINDOW && keep) {
    let t = tms[slot];
    keep = (P.now_hi - t.x) + (P.now_lo - t.y) <= P.window_ms;
  }
  if (HAS_LOD && keep) {
    keep = (logical % P.lod_stride) == 0u;
  }
  if (HAS_IMP && keep) {
    var n = 1.0;
    if ((P.flags & F_IMP_DEGENERATE) == 0u) {
      let x = imp[slot];
      n = clamp((x - P.imp_lo) * P.imp_scale, 0.0, 1.0);
      if (!is_finite(x)) { n = 0.0; }
    }
    keep = u01(slot, P.seed) <= n;
  }
  r.keep = keep;
  return r;
}

// budget thinning (only when the survivors exceed the budget; frac > 1 keeps all)
fn thin_frac() -> f32 {
  let c1 = atomicLoad(&st[S_COUNT1]);
  if (c1 <= P.budget) { return 2.0; }
  let b = f32(P.budget);
  return max(b - 3.0 * sqrt(b), 0.5 * b) / f32(c1);
}

// the atomic write of one point's footprint (rules of render/base.py)
fn splat(logical: u32, clip: vec4<f32>) {
  let w = clip.w;
  let px = (clip.x / w * 0.5 + 0.5) * P.vw;
  let py = (0.5 - clip.y / w * 0.5) * P.vh;
  var s = P.point_size;
  if (WORLD) { s = clamp(P.point_size * P.size_scale / w, 1.0, 4096.0); }
  let h = 0.5 * s;
  let round_pt = ROUND;
  // square: centres in [p - s/2, p + s/2); round: |centre - p| <= s/2
  let x0 = i32(clamp(ceil(px - h - 0.5), 0.0, P.vw));
  let y0 = i32(clamp(ceil(py - h - 0.5), 0.0, P.vh));
  var x1: i32;
  var y1: i32;
  if (round_pt) {
    x1 = i32(clamp(floor(px + h - 0.5) + 1.0, 0.0, P.vw));
    y1 = i32(clamp(floor(py + h - 0.5) + 1.0, 0.0, P.vh));
  } else {
    x1 = i32(clamp(ceil(px + h - 0.5), 0.0, P.vw));
    y1 = i32(clamp(ceil(py + h - 0.5), 0.0, P.vh));
  }
  let W = u32(P.vw);
  let dbits = bitcast<u32>(max(w, 0.0));
  {KEYDEF}
  for (var y = y0; y < y1; y = y + 1) {
    let ey = f32(y) + 0.5 - py;
    for (var x = x0; x < x1; x = x + 1) {
      if (round_pt) {
        let ex = f32(x) + 0.5 - px;
        if (ex * ex + ey * ey > h * h) { continue; }
      }
      let i = u32(y) * W + u32(x);
      {WRITE}
    }
  }
}

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>) {
  let count = (MODE == MODE_COUNT) || (MODE == MODE_RASTER && C.budget_on == 0u && PASS_COUNTS);
  if (lid == 0u) {
    atomicStore(&wg_count, 0u);
    atomicStore(&wg_drawn, 0u);
    atomicStore(&wg_bad, 0u);
    atomicStore(&wg_occ, 0u);
    atomicStore(&wg_min, 0xffffffffu);
    atomicStore(&wg_max, 0u);
  }
  let g = C.first_group + wid.y * C.groups_x + wid.x;
  let first = g * 256u * K;
  var frac = 2.0;
  // budget raster: 0 = all thinned survivors of this workgroup are under the budget,
  // 1 = none is, 2 = the budget ends inside it (rank each one in logical order)
  if (lid == 0u) {
    wg_mode = 0u;
    wg_base = 0u;
    if (MODE == MODE_RASTER && C.budget_on != 0u && g < P.groups_total) {
      let total = atomicLoad(&st[S_COUNT2]);
      let off = wgc[g];
      var end = total;
      if (g + 1u < P.groups_total) { end = wgc[g + 1u]; }
      wg_base = off;
      if (off >= P.budget) { wg_mode = 1u; } else if (end > P.budget) { wg_mode = 2u; }
    }
  }
  let mode = workgroupUniformLoad(&wg_mode);
  let base = workgroupUniformLoad(&wg_base);
  if (C.budget_on != 0u && MODE != MODE_COUNT) { frac = thin_frac(); }
  var run = base;
  // per-thread counters: one workgroup atomic per thread, not per point
  var n_keep = 0u;
  var n_drawn = 0u;
  var n_occ = 0u;
  var n_bad = 0u;
  var vmin = 0xffffffffu;
  var vmax = 0u;
  for (var j = 0u; j < K; j = j + 1u) {
    let logical = first + j * 256u + lid;
    var pt = test_point(logical, count);
    var keep = pt.keep;
    if (count) {
      if (pt.occupied) { n_occ = n_occ + 1u; }
      if (pt.occupied && !pt.finite) { n_bad = n_bad + 1u; }
      if (RANGE_AUTO && pt.finite && is_finite(pt.cval)) {
        vmin = min(vmin, ord_f(pt.cval));
        vmax = max(vmax, ord_f(pt.cval));
      }
      if (keep) { n_keep = n_keep + 1u; }
    }
    if (C.budget_on != 0u && MODE != MODE_COUNT && keep) { keep = u01(pt.slot, P.budget_seed) < frac; }
    if (MODE == MODE_THIN_COUNT && keep) { n_keep = n_keep + 1u; }
    if (MODE == MODE_DEBUG && logical < P.size) { dbg[logical] = select(0u, 1u, keep); }
    if (MODE == MODE_RASTER) {
      if (mode == 1u) {
        keep = false;
      } else if (mode == 2u) {
        let local = wg_exclusive(lid, select(0u, 1u, keep));
        let row = sh[255u];
        workgroupBarrier();
        keep = keep && (run + local < P.budget);
        run = run + row;
      }
      if (keep) {
        n_drawn = n_drawn + 1u;
        splat(logical, pt.clip);
      }
    }
  }
  if (n_keep > 0u) { atomicAdd(&wg_count, n_keep); }
  if (PASS_COUNTS && n_drawn > 0u) { atomicAdd(&wg_drawn, n_drawn); }
  if (n_occ > 0u) { atomicAdd(&wg_occ, n_occ); }
  if (n_bad > 0u) { atomicAdd(&wg_bad, n_bad); }
  if (vmin <= vmax) { atomicMin(&wg_min, vmin); atomicMax(&wg_max, vmax); }
  workgroupBarrier();
  if (lid == 0u) {
    if (MODE == MODE_THIN_COUNT) {
      if (g < P.groups_total) { wgc[g] = atomicLoad(&wg_count); }
    }
    if (count) {
      let c = atomicLoad(&wg_count);
      if (c > 0u) { atomicAdd(&st[S_COUNT1], c); }
      let bad = atomicLoad(&wg_bad);
      if (bad > 0u) { atomicAdd(&st[S_NONFINITE], bad); }
      let occ = atomicLoad(&wg_occ);
      if (occ > 0u) { atomicAdd(&st[S_OCCUPIED], occ); }
      if (RANGE_AUTO) {
        let mn = atomicLoad(&wg_min);
        let mx = atomicLoad(&wg_max);
        if (mn <= mx) { atomicMin(&rng[0], mn); atomicMax(&rng[1], mx); }
      }
    }
    let d = atomicLoad(&wg_drawn);
    if (d > 0u) { atomicAdd(&st[1], d); }
  }
}
"""

SCAN_ENTRY = r"""
@compute @workgroup_size(256)
fn scan(@builtin(local_invocation_index) lid: u32) {
  scan_counts(lid, P.groups_total, S_COUNT2);
}
"""

#: key write per key layout: 64-bit one atomic; 32-bit pass 0 depth, pass 1 index
_KEY64 = ("let key = ~((u64(dbits) << 32u) | u64(logical));", "atomicMax(&keys[i], key);")
_KEY32_DEPTH = ("let key = ~dbits;", "atomicMax(&keys[i], key);")
#: read the key before the atomic (skips the atomic where a nearer point is already there)
READ_FIRST = True
_KEY32_INDEX = ("let key = ~dbits;\n  let ikey = ~logical;",
                "if (atomicLoad(&keys[i]) == key) { atomicMax(&ikeys[i], ikey); }")


def raster_source(mode: int, key64: bool, index_pass: bool = False, naive: bool = False,
                  round_points: bool = False, world_size: bool = False, window: bool = True,
                  lod: bool = True, importance: bool = True, range_auto: bool = True, cmode: int = 2,
                  k: int = K) -> str:
    """One specialised entry point ``main``: mode 0 count, 1 thin count, 2 raster, 3 debug.
    ``index_pass``: the second of the two 32-bit passes (writes indices, counts nothing).
    The other flags are constants of the variant (which tests run, the colour mode): CPU
    adapters flatten branches, so a test that is off must not be in the code at all."""
    from .shaders import CLIP_NAIVE, CLIP_RELATIVE
    if key64:
        kdef, write = _KEY64
        ktype = "atomic<u64>"
    else:
        kdef, write = _KEY32_INDEX if index_pass else _KEY32_DEPTH
        ktype = "atomic<u32>"
    if READ_FIRST and not index_pass:
        write = "if (atomicLoad(&keys[i]) < key) { " + write + " }"
    src = (_RASTER_HEAD.replace("{KEYTYPE}", ktype).replace("{K}", str(int(k)))
           .replace("{CLIP}", CLIP_NAIVE if naive else CLIP_RELATIVE)
           .replace("{KEYDEF}", kdef).replace("{WRITE}", write))
    consts = (f"const MODE: u32 = {int(mode)}u;\nconst PASS_COUNTS: bool = {'false' if index_pass else 'true'};\n"
              f"const ROUND: bool = {'true' if round_points else 'false'};\n"
              f"const WORLD: bool = {'true' if world_size else 'false'};\n"
              f"const HAS_WINDOW: bool = {'true' if window else 'false'};\n"
              f"const HAS_LOD: bool = {'true' if lod else 'false'};\n"
              f"const HAS_IMP: bool = {'true' if importance else 'false'};\n"
              f"const RANGE_AUTO: bool = {'true' if range_auto else 'false'};\n"
              f"const CMODE: u32 = {int(cmode)}u;\n")
    return consts + src + (SCAN_ENTRY if mode == 1 else "")


_RESOLVE_HEAD = PARAMS + CPARAMS + r"""
@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(2) var<storage, read> pos: array<f32>;
@group(0) @binding(3) var<storage, read> tms: array<vec2<f32>>;
@group(0) @binding(4) var<storage, read> imp: array<f32>;
@group(0) @binding(5) var<storage, read> col: array<u32>;
@group(0) @binding(6) var<storage, read> keys: array<{KEYTYPE}>;
@group(0) @binding(7) var<storage, read> ikeys: array<u32>;
@group(0) @binding(8) var<storage, read> lut: array<u32, 256>;
@group(0) @binding(9) var<storage, read> rng: array<u32, 2>;

// the winning logical index at pixel i and its depth bits; false = background
fn winner(i: u32, out_logical: ptr<function, u32>, out_depth: ptr<function, u32>) -> bool {
  {WINNER}
}

""" + LUT_COLOUR.replace("{RANGE_AUTO}", "RANGE_AUTO") + r"""
// CMODE / RANGE_AUTO are constants of the pipeline variant: on CPU adapters branches are
// often flattened, and a generic colour function made the resolve pass 6x slower
fn point_colour(slot: u32) -> u32 {
  if (CMODE == C_RGB) { return col[slot]; }
  if (CMODE == C_SCALAR) { return lut_colour(bitcast<f32>(col[slot])); }
  if (CMODE == C_Z) { return lut_colour(pos[3u * slot + 2u]); }
  if (CMODE == C_TIME) { return lut_colour(tms[slot].x); }
  return pack4x8unorm(P.fixed_color);
}
"""

_RESOLVE64 = r"""let k = keys[gid.y * W + x];
  if (k.x != 0u || k.y != 0u) {
    let s = P.head + ~k.x;
    c = point_colour(select(s, s - P.capacity, s >= P.capacity));
  }"""
_RESOLVE32 = r"""let ik = ikeys[gid.y * W + x];
  if (ik != 0u) {
    let s = P.head + ~ik;
    c = point_colour(select(s, s - P.capacity, s >= P.capacity));
  }"""
_WINNER64 = r"""let k = keys[i];
  if (k.x == 0u && k.y == 0u) { return false; }
  *out_logical = ~k.x;
  *out_depth = ~k.y;
  return true;"""
_WINNER32 = r"""let ik = ikeys[i];
  if (ik == 0u) { return false; }
  *out_logical = ~ik;
  *out_depth = ~keys[i];
  return true;"""

_RESOLVE = r"""
@group(0) @binding(10) var<storage, read_write> img: array<u32>;

// one thread per pixel, a workgroup along a row (one row of threads: cheapest on lavapipe)
@compute @workgroup_size(256, 1)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
  let W = u32(P.vw);
  let x = gid.x;
  if (x >= W) { return; }
  var c = C.background;
  {RESOLVE_PIXEL}
  img[gid.y * C.pick_x0 + x] = c;  // pick_x0 holds the row pitch in pixels here
}
"""

_PICK = r"""
struct PickTexel { slot1: u32, depth: f32, imp: f32, t_hi: f32, t_lo: f32, pad0: u32, pad1: u32, pad2: u32 };
@group(0) @binding(10) var<storage, read_write> pick_out: array<PickTexel>;

// one thread per texel of the pick block: the winner's slot + 1 and its attributes
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
    let slot = (P.head + logical) % P.capacity;
    t.slot1 = slot + 1u;
    t.depth = bitcast<f32>(depth);
    t.imp = imp[slot];
    let tt = tms[slot];
    t.t_hi = tt.x;
    t.t_lo = tt.y;
  }
  pick_out[gid.x] = t;
}
"""


def resolve_source(key64: bool, pick: bool = False, cmode: int = 0, range_auto: bool = False) -> str:
    """The per-pixel resolve into the RGBA8 target for colour mode ``cmode`` (renderer.C_*)
    and a range reduced on the GPU (``range_auto``), or (``pick``) the pick-block gather."""
    consts = f"const CMODE: u32 = {int(cmode)}u;\nconst RANGE_AUTO: bool = {'true' if range_auto else 'false'};\n"
    head = consts + (_RESOLVE_HEAD.replace("{KEYTYPE}", "vec2<u32>" if key64 else "u32")
            .replace("{WINNER}", _WINNER64 if key64 else _WINNER32))
    return head + (_PICK if pick else _RESOLVE.replace("{RESOLVE_PIXEL}", _RESOLVE64 if key64 else _RESOLVE32))
