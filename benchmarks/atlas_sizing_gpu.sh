#!/usr/bin/env bash
# The temple at fixed atlas sides (1024 twice: the first builds the kernels; 512; 768), every 4th photo held out
# (three views), refine on; JSON-ish summary lines per side (model, held-out pooled and worst, stage seconds, the
# fit's resolution line). The evidence for atlas.min_texel_pixels (docs/scale.md): texels finer than the photos
# resolve cost time and no held-out PSNR.
#   usage: bash benchmarks/atlas_sizing_gpu.sh POSED_CAPTURE MESH.obj OUT   (warp, OpenImageIO, scipy, xatlas on
#          PYTHONPATH; the mesh an OBJ: the GPU machine's pymeshlab cannot load)
set -u
capture=$1; mesh=$2; out=$3; mkdir -p "$out"
python3 -m compileall -q -j 16 . > /dev/null 2>&1
for r in 1024 512 768 1024; do
  printf '[atlas]\nresolution = %s\nmin_texel_pixels = 0.0\n\n[refine]\nmode = "on"\nholdout_every = 4\n\n[fit]\nholdout_every = 4\n' \
    "$r" > "$out/r$r.toml"
  s=$(date +%s.%N)
  texstream run "$capture" -o "/tmp/atlas_sizing_$r" --no-progress --mesh-file "$mesh" --config "$out/r$r.toml" \
    > "$out/t_$r.log" 2>&1
  echo "r$r rc=$? $(python3 -c "print(round($(date +%s.%N) - $s, 1))") s" | tee -a "$out/t_$r.log"
  python3 - "$r" "/tmp/atlas_sizing_$r/run.json" >> "$out/summary.txt" <<'PY'
import json, sys
r, j = sys.argv[1], json.load(open(sys.argv[2]))
st = {s["name"]: round(s["seconds"], 1) for s in j["stages"]}
h = j["heldout"]
print(r, j["model"], "pooled", round(h["pooled_psnr_db"], 3), "worst", round(h["worst_psnr_db"], 3), "views",
      h["views"], st, j["resolutions"].get("fit"))
PY
done
cat "$out/summary.txt"
