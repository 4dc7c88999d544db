#!/usr/bin/env bash
# The dense ornament on the fit's own 256x256 atlas (issue 17's worst held-out view) with the photo-sampling
# models of StreamConfig: the default (texel lookup, plane taps), mesh-traced taps, and the renderer's bilinear
# texture lookup with mesh-traced taps, and the materials step on traced taps (tracedmat: --traced-materials).
# Usage: benchmarks/dense_lookup_study.sh OUT DEVICE [VARIANTS...]
set -euo pipefail
out=$1; dev=$2; shift 2
variants=${*:-default tapmesh lookup}
mkdir -p "$out"
synth_args=${SYNTH_ARGS:---scale 0.01 --photos 1760 --image-size 160}
[ -d "$out/dense" ] || texstream synth ornament $synth_args -o "$out/dense" \
    --device "$dev" --no-progress > "$out/synth.log" 2>&1
for v in $variants; do
  case $v in
    default) extra=() ;;
    tapmesh) extra=(--stream.tap-geometry mesh) ;;
    lookup) extra=(--stream.tap-geometry mesh --stream.model-lookup bilinear) ;;
    tracedmat) extra=(--traced-materials) ;;
    *) echo "unknown variant $v"; exit 2 ;;
  esac
  start=$(date +%s.%N)
  texstream fit "$out/dense" --mesh "$out/dense/ground_truth/${MESH:-mesh.obj}" -o "$out/model_$v" --holdout-every 8 \
      --device "$dev" ${FIT_ARGS:-} "${extra[@]}" > "$out/fit_$v.log" 2>&1 || { echo "$v: fit failed"; tail -n 5 "$out/fit_$v.log"; continue; }
  end=$(date +%s.%N)
  texstream eval "$out/model_$v" "$out/dense" --holdout-every 8 --device "$dev" -o "$out/eval_$v.json" 2>&1 | tail -n 1
  echo "$v: fit $(python3 -c "print(round($end - $start, 1))") s"
done
