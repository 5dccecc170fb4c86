// The quads method's budget thinning passes (raster/quads.py); with common.wgsl and scan.wgsl.
@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> idx_in: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read_write> idx_out: array<vec2<u32>>;
@group(0) @binding(3) var<storage, read_write> st: array<atomic<u32>, 16>;
@group(0) @binding(4) var<storage, read> clip_in: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read_write> clip_out: array<vec4<f32>>;
@group(0) @binding(6) var<storage, read_write> flags: array<u32>;
@group(0) @binding(7) var<storage, read_write> wgc: array<u32>;
// the colour-range buffer: word 5 counts the survivors drawn by the segments before (cull.wgsl)
@group(0) @binding(8) var<storage, read_write> glob: array<atomic<u32>, 8>;

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
  if (i < c1) { keep = u01(idx_in[i].x + P.slot_base, P.budget_seed) < frac; }
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
    if (o + atomicLoad(&glob[5]) < P.budget) {
      idx_out[o] = idx_in[i];
      clip_out[o] = clip_in[i];
    }
  }
}
