#!/usr/bin/env bash
# `texstream fit` with its defaults on the GPU machine (issue 40): the code before (the checkout the device
# tool sends, BEFORE=its root) against the code after (a copy of the package folders, NEW/texstream/<folder>),
# in one session on one machine: the full ornament written as a folder of float EXRs, a cold run, warm runs
# alternating before and after (benchmarks/fit_cli_timeline.py: the wall time of each run, its phase lines,
# model.json), a cProfile of one run of each, and the dense ornament's held-out figures (scale 0.01, 1,760
# photos of 160x160, the fit's own 256 atlas, every 8th photo held out) before and after.
#   usage: NEW=DIR WHEELS=DIR bash benchmarks/fit_defaults_gpu.sh OUT     (warp in /root/site)
# VARIANT_ARGS: extra `texstream fit` arguments of a third code path measured beside ("after" with them);
# VARIANTS: several, separated by ';' (runs and dense fits named variant1, variant2, ...; VARIANT_ARGS alone: variant).
# PROFILE_OLD=0: no cProfile of the code before (its profile from an earlier call stands).
set -u
declare -a vnames=() vargs=()
if [ -n "${VARIANTS:-}" ]; then
  IFS=';' read -r -a vargs <<< "$VARIANTS"
  for i in "${!vargs[@]}"; do vnames+=("variant$((i + 1))"); done
elif [ -n "${VARIANT_ARGS:-}" ]; then
  vnames=(variant); vargs=("$VARIANT_ARGS")
fi
out=$1
before=${BEFORE:-$PWD}
work=/root/w
mkdir -p "$out" "$work" /root/bin /root/old/texstream
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
nproc
python3 -m pip install -q --no-index --no-deps --no-compile --target /root/oiio "$WHEELS"/*.whl || exit 1
for d in core render capture calib geometry fit pipelines; do ln -sfn "$before/$d" "/root/old/texstream/$d"; done
ln -sfn "$NEW" /root/new
for v in old new; do
  printf '#!/bin/sh\nexport PYTHONPATH=/root/%s:/root/site:/root/oiio\nexec python3 -c "from texstream.pipelines.cli import console_main; console_main()" "$@"\n' "$v" > /root/bin/ts-$v
  chmod +x /root/bin/ts-$v
done
export PYTHONPATH=/root/new:/root/site:/root/oiio
stamp() { python3 -c "import time; print(f'{time.time():.3f}')"; }
s=$(stamp)
python3 -c "from texstream.capture.synthetic.synth import SynthConfig, synthesize
synthesize('ornament', '/root/sd/capture', SynthConfig(scale=1.0, device='cuda:0', progress=False, preview=False))"
echo "capture written in $(python3 -c "print(round($(stamp) - $s, 1))") s"
cap=(--capture /root/sd/capture --mesh /root/sd/capture/ground_truth)
timeline() {  # name code [fit args...]
  local name=$1 code=$2; shift 2
  TEXSTREAM_COMMIT=$([ $code = old ] && echo "${OLD_COMMIT:-old}" || echo "${NEW_COMMIT:-new}") python3 "$before/benchmarks/fit_cli_timeline.py" "${cap[@]}" --out "$work/$name" --runs 1 \
      --texstream /root/bin/ts-$code -- "$@" | tail -n 1
  cp "$work/$name/fit_cli_timeline.json" "$work/json/$name.json"
  cp "$work/$name/model_0/model.json" "$work/json/$name.model.json" 2>/dev/null
  cp "$work/$name/model_0/trace.json" "$work/json/$name.trace.json" 2>/dev/null
}
mkdir -p "$work/json"
echo "== cold (fresh kernel cache): after, then before"
timeline cold_new new
timeline warmup_old old  # compiles what only the code before uses
echo "== warm, alternating"
for r in 1 2; do
  timeline warm_old_$r old
  timeline warm_new_$r new
  for i in "${!vnames[@]}"; do timeline "warm_${vnames[$i]}_$r" new ${vargs[$i]}; done
done
echo "== profiles"
for v in $([ "${PROFILE_OLD:-1}" = 0 ] || echo old) new; do
  PYTHONPATH=/root/$v:/root/site:/root/oiio python3 -c "
import cProfile, pstats, sys
sys.argv = ['texstream', 'fit', '/root/sd/capture', '--mesh', '/root/sd/capture/ground_truth', '-o', '$work/prof_$v']
from texstream.pipelines.cli import main
cProfile.run('main()', '$work/prof_$v.out')
pstats.Stats('$work/prof_$v.out').sort_stats('cumulative').print_stats(45)" > "$work/json/profile_$v.txt" 2>&1
  grep -m1 "function calls" "$work/json/profile_$v.txt"
done
echo "== dense ornament, held out"
/root/bin/ts-new synth ornament --scale 0.01 --photos 1760 --image-size 160 -o /root/dense --device cuda:0 > "$work/json/dense_synth.log" 2>&1
dense() {  # name code [fit args...]
  local name=$1 code=$2; shift 2
  local s=$(stamp)
  /root/bin/ts-$code fit /root/dense --mesh /root/dense/ground_truth/mesh.obj -o "$work/$name" --holdout-every 8 \
      --model lafortune "$@" > "$work/json/$name.log" 2>&1 || { echo "$name: fit failed"; tail -n 5 "$work/json/$name.log"; return; }
  echo "$name: fit $(python3 -c "print(round($(stamp) - $s, 1))") s"
  cp "$work/$name/model.json" "$work/json/$name.model.json"
  cp "$work/$name/trace.json" "$work/json/$name.trace.json"
  /root/bin/ts-$code eval "$work/$name" /root/dense --holdout-every 8 -o "$work/json/$name.eval.json" 2>&1 | tail -n 1
}
dense dense_new new
dense dense_old old
for i in "${!vnames[@]}"; do dense "dense_${vnames[$i]}" new ${vargs[$i]}; done
(cd "$work" && tar czf "$out/results.tgz" json)
python3 "$SUMMARY" "$work/json" > "$out/summary.txt" 2>&1
cat "$out/summary.txt"
