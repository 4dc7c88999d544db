#!/usr/bin/env bash
# The env_diffuse fit of the ornament-sized capture on one GPU (issue 42: converges in under 10 s): the scene of
# benchmarks/env_light_gap.py (ornament --scale 0.1 re-rendered Lambertian under an SH light, made on the GPU:
# the GPU machine's Warp has no CPU compiler), then `texstream fit --model env_diffuse --device cuda` with an empty Warp kernel cache (cold), then again
# (warm), each fit's wall time and its phases from model.json (timings_s: setup, stream, transfer,
# light_and_albedo; the stream's passes and final row); then the whole relighting gap on the GPU
# (benchmarks/env_light_gap.py --device cuda, its JSON). Warp in /root/site, OpenImageIO's wheel in WHEELS
# (default .whl/), as benchmarks/cold_start_gpu.sh.
#   usage: bash benchmarks/env_fit_gpu.sh OUT
set -u
out=$1
. "$(dirname "$0")/gpu_setup.sh"
work=/root/env_gap
(cd benchmarks && python3 env_light_gap.py "$work" --scene-only --device cuda) > "$out/scene.log" 2>&1 || { tail "$out/scene.log"; exit 1; }
export WARP_CACHE_PATH=/root/warp-cache-env  # empty: the cold fit compiles every kernel it launches
rm -rf "$WARP_CACHE_PATH"
for run in cold warm; do
  s=$(date +%s.%N)
  texstream fit "$work/capture" --mesh "$work/capture/ground_truth" -o "/root/env_fit_$run" --model env_diffuse \
    --device cuda --holdout-every 8 --env.scale light_mean --env.scale-value 0.8 > "$out/fit_$run.log" 2>&1
  rc=$?
  e=$(date +%s.%N)
  python3 - "$run" "$rc" "$s" "$e" "/root/env_fit_$run/model.json" "$out/fit_$run.json" <<'PY'
import json, sys
run, rc, s, e, src, dst = sys.argv[1:]
m = json.load(open(src)) if rc == "0" else {}
row = {"run": run, "rc": int(rc), "wall_s": float(e) - float(s), "device": m.get("device"),
       "phases_s": m.get("timings_s"), "stream_passes": m.get("passes"), "stream_final": m.get("final"),
       "light_trace_rounds": len((m.get("light") or {}).get("trace") or []),
       "heldout_own_light": m.get("heldout"), "texels": (m.get("atlas") or {}).get("seen_texels")}
json.dump(row, open(dst, "w"), indent=1)
print(json.dumps(row))
PY
done
(cd benchmarks && python3 env_light_gap.py "$work" --reuse-scene --device cuda --out "$out/gap_cuda.json") \
  > "$out/gap_cuda.log" 2>&1
echo "gap rc=$?"; tail -n 20 "$out/gap_cuda.log"
