// The compute method's raster passes (raster/compute.py): every per-point test fused with the
// projection and an atomic write of a per-pixel depth key. With common.wgsl, scan.wgsl and
// one of raster_key64.wgsl / raster_key32.wgsl (the key layout, see raster/compute.py).
@group(0) @binding(1) var<uniform> C: CParams;
@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(2) var<storage, read> pos: array<f32>;
@group(0) @binding(3) var<storage, read> tms: array<vec2<f32>>;
@group(0) @binding(4) var<storage, read> imp: array<f32>;
@group(0) @binding(5) var<storage, read> col: array<u32>;
@group(0) @binding(7) var<storage, read_write> ikeys: array<atomic<u32>>;
@group(0) @binding(8) var<storage, read_write> st: array<atomic<u32>, 16>;
@group(0) @binding(9) var<storage, read_write> rng: array<atomic<u32>, 2>;
@group(0) @binding(10) var<storage, read_write> wgc: array<u32>;
@group(0) @binding(11) var<storage, read_write> dbg: array<u32>;
// compact positions (compact.py): the chunk's coarse, medium, fine words one array after the
// other; per batch (lo.xyz, level) and (ext / 2^10).xyz
@group(0) @binding(12) var<storage, read> qpos: array<u32>;
@group(0) @binding(13) var<storage, read> qtab: array<vec4<f32>>;
// the footprint LOD's mask per batch of slots of the whole ring (render/batches.py lod_masks)
@group(0) @binding(14) var<storage, read> blod: array<u32>;

// The variant of a pipeline: pipeline-overridable constants, so a test that is off is not
// in the compiled code at all (CPU adapters flatten branches).
override K: u32 = 16u;            // points per thread (a workgroup covers 256 * K logical indices)
override MODE: u32 = 2u;          // what this entry point does (MODE_*):
override ROUND: bool = false;
override WORLD: bool = false;
override HAS_WINDOW: bool = true;
override HAS_LOD: bool = true;
override HAS_BLOD: bool = false;
override HAS_IMP: bool = true;
override RANGE_AUTO: bool = true;
override CMODE: u32 = 2u;
override COMPACT: bool = false;   // read the compact words at the batch's level (level 0: pos)
override BATCH: u32 = 16384u;     // slots per batch of the compact table
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
var<workgroup> wg_tasks: u32;

fn slot_of(logical: u32) -> u32 {
  // head < capacity and logical < size <= capacity: one conditional subtract, no modulo
  let s = P.head + logical;
  return select(s, s - P.capacity, s >= P.capacity);
}

fn ten_bits(w: u32) -> vec3<f32> {
  return vec3<f32>(vec3<u32>(w, w >> 10u, w >> 20u) & vec3<u32>(1023u));
}

// the slot's position: the float32 positions, or its compact words at its batch's level
// (each term exact in float32; the +0.5 centres the point in its last step)
fn load_pos(slot: u32) -> vec3<f32> {
  if (COMPACT) {
    let b = 2u * ((slot + P.slot_base) / BATCH);
    let t0 = qtab[b];
    let level = bitcast<u32>(t0.w);
    if (level != 0u) {
      let c = qpos[slot];
      if ((c & 0x80000000u) != 0u) {
        let bad = bitcast<f32>(c | 0x7f800000u);
        return vec3<f32>(bad, bad, bad);
      }
      let s1 = qtab[b + 1u].xyz;
      if (level == 1u) { return t0.xyz + (ten_bits(c) + 0.5) * s1; }
      let n = arrayLength(&qpos) / 3u;
      let s2 = s1 * (1.0 / 1024.0);
      let m = ten_bits(qpos[n + slot]);
      if (level == 2u) { return t0.xyz + ten_bits(c) * s1 + (m + 0.5) * s2; }
      let f = ten_bits(qpos[2u * n + slot]);
      return t0.xyz + ten_bits(c) * s1 + m * s2 + (f + 0.5) * (s2 * (1.0 / 1024.0));
    }
  }
  return vec3<f32>(pos[3u * slot], pos[3u * slot + 1u], pos[3u * slot + 2u]);
}

fn colour_value(slot: u32, p: vec3<f32>) -> f32 {
  if (CMODE == C_Z && COMPACT) { return pos[3u * slot + 2u]; }  // the exact z the resolve colours by
  if (CMODE == C_Z) { return p.z; }
  if (CMODE == C_TIME) { return tms[slot].x; }
  return bitcast<f32>(col[slot]);
}

struct Pt {
  keep: bool,        // passed every test before the budget
  occupied: bool,    // an occupied slot the tier renders
  cpu: bool,         // its batch's non-finite count and colour range are the CPU's (culling.py CPU_COUNTED)
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
  var lod_mask = 0u;
  if (HAS_BLOD) {
    let gs = slot + P.slot_base;
    lod_mask = blod[gs >> 14u];
    r.cpu = (lod_mask & 0x80000000u) != 0u;
    if (r.cpu && (gs & lod_mask) != 0u) { r.occupied = false; return r; }  // (main walks kept slots only)
  }
  let p = load_pos(slot);
  var keep = is_finite(p.x) && is_finite(p.y) && is_finite(p.z);
  r.finite = keep;
  if (!keep) { return r; }
  if (count && RANGE_AUTO) { r.cval = colour_value(slot, p); }
  r.clip = clip_of(p);
  for (var i = 0u; i < 6u; i = i + 1u) {
    let pl = P.planes[i];
    keep = keep && (dot(pl.xyz, p) + pl.w >= 0.0);
  }
  if (HAS_WINDOW && keep) {
    let t = tms[slot];
    keep = (P.now_hi - t.x) + (P.now_lo - t.y) <= P.window_ms;
  }
  if (HAS_LOD && keep) {
    keep = ((logical + P.logical_base) % P.lod_stride) == 0u;
  }
  if (HAS_BLOD && keep) {
    keep = ((slot + P.slot_base) & lod_mask) == 0u;
  }
  if (HAS_IMP && keep) {
    var n = 1.0;
    if ((P.flags & F_IMP_DEGENERATE) == 0u) {
      let x = imp[slot];
      n = clamp((x - P.imp_lo) * P.imp_scale, 0.0, 1.0);
      if (!is_finite(x)) { n = 0.0; }
    }
    keep = u01(slot + P.slot_base, P.seed) <= n;
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
  let key = make_key(dbits, logical);
  for (var y = y0; y < y1; y = y + 1) {
    let ey = f32(y) + 0.5 - py;
    for (var x = x0; x < x1; x = x + 1) {
      if (round_pt) {
        let ex = f32(x) + 0.5 - px;
        if (ex * ex + ey * ey > h * h) { continue; }
      }
      let i = u32(y) * W + u32(x);
      write_key(i, key);
    }
  }
}

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>) {
  let count = (MODE == MODE_COUNT) || (MODE == MODE_RASTER && C.budget_on == 0u && !INDEX_PASS);
  if (lid == 0u) {
    atomicStore(&wg_count, 0u);
    atomicStore(&wg_drawn, 0u);
    atomicStore(&wg_bad, 0u);
    atomicStore(&wg_occ, 0u);
    atomicStore(&wg_min, 0xffffffffu);
    atomicStore(&wg_max, 0u);
  }
  // workgroups of this segment, numbered over the whole ring (budget offsets in wgc)
  let gl = wid.y * P.groups_x + wid.x;
  let g = P.group_base + gl;
  let first = gl * 256u * K;
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
  // Footprint LOD: the workgroup's logical range in at most three pieces (split where a batch
  // ends and where the segment's slots wrap); a piece of a batch the CPU counts (CPU_COUNTED)
  // is walked at its stride, kept slots only, so its dropped slots get no thread at all and
  // the kept ones share SIMD lanes. Tasks stay in ascending logical order (budget ranks).
  var pc = array<u32, 3>(0u, 0u, 0u);  // tasks per piece
  var pl = array<u32, 3>(0u, 0u, 0u);  // the piece's first task's logical index
  var ps = array<u32, 3>(1u, 1u, 1u);  // its step
  if (HAS_BLOD) {
    var lg = first;
    let end = min(first + 256u * K, P.size);
    for (var q = 0u; q < 3u; q = q + 1u) {
      if (lg >= end) { break; }
      let slot = slot_of(lg);
      let gs = slot + P.slot_base;
      let m = blod[gs >> 14u];
      let len = min(min(((gs >> 14u) + 1u) * 16384u - gs, P.capacity - slot), end - lg);
      var off = 0u;
      if ((m & 0x80000000u) != 0u) {
        ps[q] = (m & 0x7fffffffu) + 1u;
        off = (ps[q] - (gs & (ps[q] - 1u))) & (ps[q] - 1u);  // to the first kept slot
      }
      pl[q] = lg + off;
      if (off < len) { pc[q] = (len - off + ps[q] - 1u) / ps[q]; }
      lg = lg + len;
    }
  }
  var tasks = 256u * K;
  if (HAS_BLOD) {  // rows past the tasks are skipped whole (the same count in every thread)
    if (lid == 0u) { wg_tasks = pc[0] + pc[1] + pc[2]; }
    tasks = workgroupUniformLoad(&wg_tasks);
  }
  for (var j = 0u; j < K; j = j + 1u) {
    if (j * 256u >= tasks) { break; }
    var logical = first + j * 256u + lid;
    if (HAS_BLOD) {
      var t = j * 256u + lid;
      logical = 0xffffffffu;  // no task: tested as unoccupied
      for (var q = 0u; q < 3u; q = q + 1u) {
        if (t < pc[q]) { logical = pl[q] + t * ps[q]; break; }
        t = t - pc[q];
      }
    }
    var pt = test_point(logical, count);
    var keep = pt.keep;
    if (count) {
      if (pt.occupied) { n_occ = n_occ + 1u; }
      if (pt.occupied && !pt.finite && !pt.cpu) { n_bad = n_bad + 1u; }
      if (RANGE_AUTO && pt.finite && !pt.cpu && is_finite(pt.cval)) {
        vmin = min(vmin, ord_f(pt.cval));
        vmax = max(vmax, ord_f(pt.cval));
      }
      if (keep) { n_keep = n_keep + 1u; }
    }
    if (C.budget_on != 0u && MODE != MODE_COUNT && keep) { keep = u01(pt.slot + P.slot_base, P.budget_seed) < frac; }
    if (MODE == MODE_THIN_COUNT && keep) { n_keep = n_keep + 1u; }
    if (MODE == MODE_DEBUG && logical < P.size) { dbg[P.logical_base + logical] = select(0u, 1u, keep); }
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
        splat(P.logical_base + logical, pt.clip);
      }
    }
  }
  if (n_keep > 0u) { atomicAdd(&wg_count, n_keep); }
  if (!INDEX_PASS && n_drawn > 0u) { atomicAdd(&wg_drawn, n_drawn); }
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

@compute @workgroup_size(256)
fn scan(@builtin(local_invocation_index) lid: u32) {
  scan_counts(lid, P.groups_total, S_COUNT2);
}
