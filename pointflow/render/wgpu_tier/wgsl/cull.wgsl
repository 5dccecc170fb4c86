// The quads method's cull, compaction and draw-argument passes (raster/quads.py); with
// common.wgsl and scan.wgsl. They run once per segment of the ring (render/wgpu_tier/chunks.py)
// with that segment's Params and state words; rng[G_KEPT] and rng[G_USED] count over all
// segments (survivors, and those drawn under the budget by the segments before).
@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> pos: array<f32>;
@group(0) @binding(2) var<storage, read> tms: array<vec2<f32>>;
@group(0) @binding(3) var<storage, read> imp: array<f32>;
@group(0) @binding(4) var<storage, read> col: array<u32>;
@group(0) @binding(5) var<storage, read_write> idx_out: array<vec2<u32>>;
@group(0) @binding(6) var<storage, read_write> st: array<atomic<u32>, 16>;
@group(0) @binding(7) var<storage, read_write> rng: array<atomic<u32>, 8>;
const G_KEPT: u32 = 4u;
const G_USED: u32 = 5u;
@group(0) @binding(8) var<storage, read_write> dargs: array<u32, 4>;
@group(0) @binding(9) var<storage, read> lut: array<u32, 256>;
@group(0) @binding(10) var<storage, read_write> clip_out: array<vec4<f32>>;
@group(0) @binding(11) var<storage, read_write> flags: array<u32>;
@group(0) @binding(12) var<storage, read_write> wgc: array<u32>;
// the footprint LOD's mask per batch of slots of the whole ring (render/batches.py lod_masks)
@group(0) @binding(13) var<storage, read> blod: array<u32>;

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
    var lod_mask = 0u;
    var cpu = false;  // the batch's non-finite count and colour range are the CPU's (culling.py CPU_COUNTED)
    if (slot < P.n_slots && (P.flags & F_BATCH_LOD) != 0u) {
      lod_mask = blod[(slot + P.slot_base) >> 14u];
      cpu = (lod_mask & 0x80000000u) != 0u;
    }
    // a dropped slot of a batch the CPU counts is never read (nor counted: the CPU counts it)
    if (slot < P.n_slots && !(cpu && ((slot + P.slot_base) & lod_mask) != 0u)) {
      atomicAdd(&wg_occ, 1u);
      let p = vec3<f32>(pos[3u * slot], pos[3u * slot + 1u], pos[3u * slot + 2u]);
      keep = is_finite(p.x) && is_finite(p.y) && is_finite(p.z);
      if (!keep && !cpu) { atomicAdd(&wg_bad, 1u); }
      if ((P.flags & F_RANGE_AUTO) != 0u && !cpu) {
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
        keep = ((logical + P.logical_base) % P.lod_stride) == 0u;
      }
      if (keep && (P.flags & F_BATCH_LOD) != 0u) {
        keep = ((slot + P.slot_base) & lod_mask) == 0u;
      }
      if (keep && (P.flags & F_IMPORTANCE) != 0u) {
        var n = 1.0;
        if ((P.flags & F_IMP_DEGENERATE) == 0u) {
          let x = imp[slot];
          n = clamp((x - P.imp_lo) * P.imp_scale, 0.0, 1.0);
          if (!is_finite(x)) { n = 0.0; }
        }
        keep = u01(slot + P.slot_base, P.seed) <= n;
      }
    }
  }
  if (logical < P.groups_total * 256u) { flags[logical] = select(0u, 1u, keep); }
  if (keep) { atomicAdd(&wg_count, 1u); }
  workgroupBarrier();
  if (lid == 0u) {
    let kc = atomicLoad(&wg_count);
    if (g < P.groups_total) { wgc[g] = kc; }
    if (kc > 0u) { atomicAdd(&rng[G_KEPT], kc); }
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
        clip_out[o] = clip_of(p);
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
    let all = atomicLoad(&rng[G_KEPT]);  // survivors of every segment (all culled by now)
    if (all > P.budget) {
      // aim 3 sigma under the budget so the hard cap rarely bites: the drawn set then
      // depends only on the hash
      let b = f32(P.budget);
      frac = max(b - 3.0 * sqrt(b), 0.5 * b) / f32(all);
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
  // the hard cap over the whole ring: the first `budget` in logical order, segment by segment
  let used = atomicLoad(&rng[G_USED]);
  let d = min(atomicLoad(&st[S_COUNT2]), P.budget - used);
  atomicStore(&st[1], d);
  atomicStore(&rng[G_USED], used + d);
}
