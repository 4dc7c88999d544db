#!/usr/bin/env bash
# The README's main command on a fresh GPU machine (issue 40): `texstream run` on the built-in synthetic set
# with an empty Warp kernel cache (cold), then again (warm), each run's stage times and held-out figures from
# its run.json, the cold fit's parallel build of the Warp modules (fit/stages/prewarm.py: its log line) and the
# kernel cache's modules after each run (``rehashed``: modules built under more than one hash, each a compile
# the prewarm did not save); then the CUDA tests named in CUDA_TESTS (pytest -k cuda). Warp in /root/site (the two-call
# recipe of ../shared/tools/device/README.md), OpenImageIO's wheel in WHEELS (default .whl/).
#   usage: CUDA_TESTS="tests/a.py tests/b.py" bash benchmarks/cold_start_gpu.sh OUT
set -u
out=$1
. "$(dirname "$0")/gpu_setup.sh"
export WARP_CACHE_PATH=/root/warp-cache-cold  # empty: the cold run compiles every kernel it launches
rm -rf "$WARP_CACHE_PATH"
for run in cold warm; do
  s=$(date +%s.%N)
  texstream run --out "/root/demo_$run" > "$out/run_$run.log" 2>&1
  rc=$?
  e=$(date +%s.%N)
  python3 - "$run" "$rc" "$s" "$e" "/root/demo_$run/run.json" "$out/run_$run.json" "$out/run_$run.log" \
    "$WARP_CACHE_PATH" <<'EOF'
import collections, json, pathlib, re, sys
run, rc, s, e, src, dst, log, cache = sys.argv[1:]
r = json.load(open(src)) if rc == "0" else {}
built = re.search(r"kernels built: (\d+) Warp modules in ([\d.]+) s", open(log).read())
names = collections.Counter(p.name.rsplit("_", 1)[0] for p in pathlib.Path(cache).glob("*/wp_*"))
row = {"run": run, "rc": int(rc), "wall_s": float(e) - float(s), "device": r.get("device"),
       "total_s": r.get("total_s"), "heldout": r.get("heldout"),
       "stages": {st["name"]: st["seconds"] for st in r.get("stages", [])},
       "prewarm": {"modules": int(built[1]), "seconds": float(built[2])} if built else None,
       "cache_modules": sum(names.values()), "rehashed": sorted(n for n, k in names.items() if k > 1)}
json.dump(row, open(dst, "w"), indent=1)
print(json.dumps(row))
EOF
done
grep -h "compiling its Warp kernels\|kernels built:" "$out"/run_*.log | head -2
if [ -n "${CUDA_TESTS:-}" ]; then
  python3 -m pytest -q -p no:cacheprovider $CUDA_TESTS -k cuda > "$out/cuda_tests.log" 2>&1
  echo "cuda tests rc=$?"; tail -n 15 "$out/cuda_tests.log"
fi
