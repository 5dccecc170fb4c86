// Workgroup prefix sums (the including shader declares wgc: array<u32> and st: array<atomic<u32>, 16>).
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
