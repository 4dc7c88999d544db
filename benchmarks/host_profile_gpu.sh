#!/usr/bin/env bash
# Where a GPU run's time goes on the host (issue 40): Python's cProfile over a warm `texstream run` of a posed
# capture (TEMPLE_CAPTURE, e.g. the Middlebury temple's `posed/` of a CPU run: mesh, atlas, refine, fit, export,
# report on the GPU) and over a warm `texstream fit` with its defaults on the full ornament (1,760 float EXRs),
# each after one run that warms Warp's kernel cache; the profiles (*.prof) and their top functions by own and by
# cumulative time (*.txt) under OUT. Warp in /root/site, wheels as benchmarks/default_paths_gpu.sh says (pymeshlab,
# scipy, xatlas on EXTRA_PYTHONPATH; pymeshlab's GL libraries on LD_LIBRARY_PATH). PARTS: "temple fit" (default).
#   usage: TEMPLE_CAPTURE=POSED EXTRA_PYTHONPATH=SITE WHEELS=.whl bash benchmarks/host_profile_gpu.sh OUT
set -u
out=$1
here=$(cd "$(dirname "$0")/.." && pwd)
(out="$out/setup"; . "$here/benchmarks/gpu_setup.sh")
export PYTHONPATH="${EXTRA_PYTHONPATH:-}:/root/site:/root/oiio"
python3 -m compileall -q -j 16 /root/site/warp /root/oiio "$here" > /dev/null 2>&1  # as a pip install has them
summary() {  # the profile's top functions, own time and cumulative
  python3 - "$1" > "${1%.prof}.txt" <<'EOF'
import pstats, sys
for key in ("tottime", "cumtime"):
    pstats.Stats(sys.argv[1]).sort_stats(key).print_stats(45)
EOF
}
parts=" ${PARTS:-temple fit} "
if [[ $parts == *" temple "* ]]; then
  texstream run "$TEMPLE_CAPTURE" -o /root/t_warmup --no-progress > "$out/temple_warmup.log" 2>&1
  s=$(date +%s.%N)
  python3 -m cProfile -o "$out/temple.prof" -m texstream.pipelines.cli run "$TEMPLE_CAPTURE" -o /root/t_prof \
    --no-progress > "$out/temple.log" 2>&1
  echo "temple profiled rc=$? $(python3 -c "print(round($(date +%s.%N) - $s, 1))") s" | tee -a "$out/temple.log"
  tail -n 14 "$out/temple.log"
  summary "$out/temple.prof"
fi
if [[ $parts == *" fit "* ]]; then
  python3 -c "from texstream.capture.synthetic.synth import SynthConfig, synthesize
synthesize('ornament', '/root/sd/capture', SynthConfig(scale=1.0, device='cuda:0', progress=False, preview=False))"
  texstream fit /root/sd/capture --mesh /root/sd/capture/ground_truth -o /root/f_warmup > "$out/fit_warmup.log" 2>&1
  s=$(date +%s.%N)
  python3 -m cProfile -o "$out/fit.prof" -m texstream.pipelines.cli fit /root/sd/capture \
    --mesh /root/sd/capture/ground_truth -o /root/f_prof > "$out/fit.log" 2>&1
  echo "fit profiled rc=$? $(python3 -c "print(round($(date +%s.%N) - $s, 1))") s" | tee -a "$out/fit.log"
  summary "$out/fit.prof"
fi
