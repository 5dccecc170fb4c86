#!/usr/bin/env bash
# The GPU check in one call (issue 29): on a machine with a real GPU, in under 8 minutes,
#   1. `pointflow info` (the adapters and what auto picks),
#   2. the GPU tests (tests/render_wgpu, tests/render_tiers; a missing adapter fails them),
#   3. the render benchmark at 1M, 4M and 16M points for every method -- wgpu compute, wgpu
#      quads, the cpu tier's compiled raster -- against the bare quad floor, interleaved,
#   4. compact positions against float32 in the compute method (bench/bench_wgpu_compact.py,
#      GPU_CHECK_COMPACT_POINTS, default 16M; 0 skips it),
#   5. the footprint LOD against none, both wgpu methods (bench/bench_lod_fill.py,
#      GPU_CHECK_LOD_POINTS, default 4M; 0 skips it),
# and writes ONE JSON (bench/results/gpu_check.json) plus a short table on stdout: frame
# times and G points/s per method and size (``gpoints_per_s`` in the JSON), and per size and
# method the GPU passes by timestamp queries, the CPU side, G points/s of GPU time and the
# ``streamed`` wall time per frame without readback (frames back to back, as a window draws:
# the figure for "a 1M frame <= 1 ms excluding readback" and "10 G points/s at 16M") (``by_pass``).
#
#   bench/gpu_check.sh                                  # the real check
#   GPU_CHECK_SIZES="100000 1000000" GPU_CHECK_TESTS=tests/render_tiers/test_agreement.py \
#       bench/gpu_check.sh                              # a dry run on a software adapter
#
# Env: PYTHON (default .venv/bin/python, else python3), GPU_CHECK_SIZES, GPU_CHECK_TESTS, GPU_CHECK_LOD_POINTS,
# GPU_CHECK_OUT (the JSON), GPU_CHECK_REQUIRE_GPU (default 1: tests fail without an adapter).
set -u
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
PY="${PYTHON:-}"
if [ -z "$PY" ]; then
  if [ -x "$ROOT/.venv/bin/python" ]; then PY="$ROOT/.venv/bin/python"; else PY="$(command -v python3)"; fi
fi
SIZES="${GPU_CHECK_SIZES:-1000000 4000000 16000000}"
TESTS="${GPU_CHECK_TESTS:-tests/render_wgpu tests/render_tiers}"
OUT="${GPU_CHECK_OUT:-$ROOT/bench/results/gpu_check.json}"
export PYTHONPATH="$ROOT${PYTHONPATH:+:$PYTHONPATH}"
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp/pointflow-xdg-$(id -u)}"
mkdir -p -m 700 "$XDG_RUNTIME_DIR"
export POINTFLOW_REQUIRE_GPU="${GPU_CHECK_REQUIRE_GPU:-1}"
WORK="$(mktemp -d "${TMPDIR:-/tmp}/gpu_check.XXXXXX")"
trap 'rm -rf "$WORK"' EXIT
T0=$(date +%s)

echo "== pointflow info" >&2
"$PY" -m pointflow.cli info >"$WORK/info.txt" 2>&1
INFO_RC=$?
cat "$WORK/info.txt" >&2
command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader \
  >"$WORK/nvidia.txt" 2>&1 || true

echo "== GPU tests: $TESTS" >&2
T1=$(date +%s)
# shellcheck disable=SC2086
"$PY" -m pytest $TESTS -q -p no:cacheprovider --junitxml="$WORK/tests.xml" >"$WORK/tests.txt" 2>&1
TEST_RC=$?
tail -n 5 "$WORK/tests.txt" >&2
T2=$(date +%s)

echo "== render benchmark: $SIZES points" >&2
# shellcheck disable=SC2086
"$PY" bench/bench_render.py --sizes $SIZES --cpu-max 0 --with-cpu-compute --out "$WORK/render.json" \
  >"$WORK/bench.txt" 2>&1
BENCH_RC=$?
tail -n 8 "$WORK/bench.txt" >&2
COMPACT_N="${GPU_CHECK_COMPACT_POINTS:-16000000}"
if [ "$COMPACT_N" != "0" ]; then
  echo "== compact positions against float32: $COMPACT_N points" >&2
  "$PY" bench/bench_wgpu_compact.py --points "$COMPACT_N" --rounds 7 --out "$WORK/compact.json" \
    >"$WORK/compact.txt" 2>&1 || echo "compact bench failed (rc $?)" >>"$WORK/compact.txt"
  tail -n 6 "$WORK/compact.txt" >&2
fi
LOD_N="${GPU_CHECK_LOD_POINTS:-4000000}"
if [ "$LOD_N" != "0" ]; then
  echo "== footprint LOD (render.lod_fill) against none: $LOD_N points" >&2
  "$PY" bench/bench_lod_fill.py --points "$LOD_N" --rounds 5 --tiers wgpu-compute,wgpu-quads --out "$WORK/lod.json" \
    >"$WORK/lod.txt" 2>&1 || echo "lod bench failed (rc $?)" >>"$WORK/lod.txt"
  tail -n 4 "$WORK/lod.txt" >&2
fi
T3=$(date +%s)

"$PY" - "$WORK" "$OUT" "$INFO_RC" "$TEST_RC" "$BENCH_RC" "$T0" "$T1" "$T2" "$T3" <<'EOF'
import json, os, platform, subprocess, sys, time
import xml.etree.ElementTree as ET
work, out, info_rc, test_rc, bench_rc = sys.argv[1], sys.argv[2], *map(int, sys.argv[3:6])
t0, t1, t2, t3 = map(int, sys.argv[6:10])
read = lambda n: open(os.path.join(work, n)).read() if os.path.exists(os.path.join(work, n)) else ""
tests = {}
try:
    s = ET.parse(os.path.join(work, "tests.xml")).getroot()
    s = s if s.tag == "testsuite" else s[0]
    tests = {k: int(s.get(k, 0)) for k in ("tests", "failures", "errors", "skipped")}
except Exception as e:  # noqa: BLE001
    tests = {"error": f"no junit report ({type(e).__name__})"}
bench = json.loads(read("render.json")) if read("render.json") else None
res = {"measured_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "host": platform.node(),
       "platform": platform.platform(), "cpu_count": os.cpu_count(),
       "gpu": read("nvidia.txt").strip() or None, "info": read("info.txt"), "info_rc": info_rc,
       "tests": {"rc": test_rc, **tests, "tail": read("tests.txt")[-3000:]},
       "bench_rc": bench_rc, "bench": bench,
       "compact": json.loads(read("compact.json")) if read("compact.json") else read("compact.txt")[-2000:] or None,
       "lod": json.loads(read("lod.json")) if read("lod.json") else read("lod.txt")[-2000:] or None,
       "bench_tail": None if bench else read("bench.txt")[-3000:],
       "seconds": {"info": t1 - t0, "tests": t2 - t1, "bench": t3 - t2, "total": t3 - t0},
       "load": subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()}
# G points/s per method and size (issue 41): points over the median frame time
METHODS = (("floor", "floor_ms"), ("quads", "quads_ms"), ("compute", "compute_ms"), ("cpu_compute", "cpu_compute_ms"))
res["gpoints_per_s"] = [{"points": r["points"], **{m: round(r["points"] / r[k] / 1e6, 3) for m, k in METHODS
                                                   if r.get(k)}} for r in (bench or {}).get("rows", [])]
# by pass (issue 41, item 4): the GPU's passes by timestamp queries (the key clear and the
# readback copy lie outside them), the CPU side (planning, culling, compact positions, upload,
# encode, submit: ``cpu_total``), and G points/s of GPU time
res["by_pass"] = []
for r in (bench or {}).get("rows", []):
    for m in ("quads", "compute"):
        g = r.get(f"{m}_gpu_ms") or {}
        gpu = sum(g.values()) if g else None
        st = r.get(f"{m}_streamed_ms")
        res["by_pass"].append({"points": r["points"], "method": m, "gpu_passes_ms": gpu, "gpu": g,
                               "cpu_side_ms": r.get(f"{m}_cpu_ms"), "frame_ms": r.get(f"{m}_ms"),
                               "streamed_ms": st,
                               "gpoints_per_s_gpu_time": round(r["points"] / gpu / 1e6, 3) if gpu else None,
                               "gpoints_per_s_streamed": round(r["points"] / st / 1e6, 3) if st else None})
os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
with open(out, "w") as f:
    json.dump(res, f, indent=1)
print(f"gpu check -- {bench['adapter'] if bench else 'no benchmark'} -- {res['gpu'] or 'no nvidia-smi'}")
print(f"tests: rc {test_rc}, {tests}; info rc {info_rc}; bench rc {bench_rc}; {res['seconds']['total']} s")
if bench:
    print(f"{'points':>11} {'floor ms':>9} {'quads ms':>9} {'compute ms':>10} {'cpu comp ms':>11} "
          f"{'floor/comp':>10} {'floor/quads':>11}")
    for r in bench["rows"]:
        cc = r.get("cpu_compute_ms", float("nan"))
        print(f"{r['points']:>11,} {r['floor_ms']:>9.1f} {r['quads_ms']:>9.1f} {r['compute_ms']:>10.1f} {cc:>11.1f} "
              f"{r['floor_over_compute_per_frame_median']:>10.2f} {r['floor_ms'] / r['quads_ms']:>11.2f}")
    print(f"{'points':>11} " + " ".join(f"{m + ' Gpt/s':>16}" for m, _ in METHODS))
    for g in res["gpoints_per_s"]:
        print(f"{g['points']:>11,} " + " ".join(f"{g.get(m, float('nan')):>16.3f}" for m, _ in METHODS))
    print(f"{'points':>11} {'method':>8} {'GPU passes ms':>13} {'CPU side ms':>11} {'frame ms':>9} "
          f"{'streamed ms':>11} {'Gpt/s GPU time':>14} {'Gpt/s streamed':>14}")
    for b in res["by_pass"]:
        na = float("nan")
        print(f"{b['points']:>11,} {b['method']:>8} {b['gpu_passes_ms'] or na:>13.3f} {b['cpu_side_ms'] or na:>11.2f} "
              f"{b['frame_ms'] or na:>9.1f} {b['streamed_ms'] or na:>11.2f} {b['gpoints_per_s_gpu_time'] or na:>14.3f} "
              f"{b['gpoints_per_s_streamed'] or na:>14.3f}")
if isinstance(res["lod"], dict):  # frame time over the same method without LOD, per view and fill
    print(f"footprint LOD at {res['lod']['points']:,} points: frame / without LOD (lod_fill 8, 2, 0.5)")
    for tier, views in res["lod"]["tiers"].items():
        for v, rows in views.items():
            print(f"  {tier:13} {v:8} {rows['0.0']['median_ms']:8.2f} ms  " +
                  "  ".join(f"{rows[k]['over_off']:.2f}" for k in ("8.0", "2.0", "0.5") if k in rows))
print(f"wrote {out}")
sys.exit(1 if (test_rc or bench_rc) else 0)
EOF
