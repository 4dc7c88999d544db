#!/usr/bin/env bash
# The default paths on one GPU (issue 40), in one call: Python's bytecode compiled first, as `pip install` does
# (the device's Warp comes from a tarball: without it every process compiles Warp's sources again; the import time
# of Warp is recorded before and after), then the README's `texstream run` cold and warm
# (benchmarks/cold_start_gpu.sh, with the CUDA tests in CUDA_TESTS), then `texstream fit` with its defaults on the
# full ornament (1,760 float EXRs of 430x430; benchmarks/fit_cli_timeline.py, RUNS runs, the first one warming the
# default kernel cache), Warp's CUDA activity over one more run (benchmarks/fit_gpu_activity.py), and the dense
# ornament's held-out figures (scale 0.01, 1,760 photos of 160x160, every 8th held out). With TEMPLE_CAPTURE (a posed
# capture folder, e.g. a CPU run's `posed/` of the Middlebury temple) first `texstream run` of it on the GPU: the mesh,
# atlas, refine and fit stages (pymeshlab, scipy and xatlas on EXTRA_PYTHONPATH: the machine has none of them; its
# pymeshlab needs libGL and X11's client libraries, which the machine lacks: copy them from a Debian box (ldd of
# pymeshlab's .so files lists them) onto LD_LIBRARY_PATH, or TEMPLE_ARGS="--mesh-file MESH" gives a CPU run's mesh).
# PARTS (default "readme temple fit"): which of the three to run (a device call lasts at most 10 minutes).
#   usage: CUDA_TESTS="tests/a.py ..." WHEELS=.whl bash benchmarks/default_paths_gpu.sh OUT   (warp in /root/site)
set -u
out=$1
mkdir -p "$out"
here=$(cd "$(dirname "$0")/.." && pwd)
(out="$out/setup"; . "$here/benchmarks/gpu_setup.sh")  # OpenImageIO's wheel and texstream, whatever PARTS
export PYTHONPATH=/root/site:/root/oiio
echo "PYTHONDONTWRITEBYTECODE=${PYTHONDONTWRITEBYTECODE:-unset}" | tee "$out/bytecode.txt"
import_warp() { python3 -c "import time; t = time.perf_counter(); import warp; print(f'{time.perf_counter() - t:.3f}')"; }
echo "import warp before compileall: $(import_warp) $(import_warp) s" | tee -a "$out/bytecode.txt"
python3 -m compileall -q -j 16 /root/site/warp "$here" > /dev/null 2>&1
echo "import warp after compileall: $(import_warp) $(import_warp) s" | tee -a "$out/bytecode.txt"
parts=" ${PARTS:-readme temple fit} "
[[ $parts == *" readme "* ]] && bash "$here/benchmarks/cold_start_gpu.sh" "$out/readme"
if [[ $parts == *" temple "* ]] && [ -n "${TEMPLE_CAPTURE:-}" ]; then  # twice: the first builds the kernels the radiance models need
  for t in cold warm; do
    s=$(date +%s.%N)
    PYTHONPATH="${EXTRA_PYTHONPATH:-}:$PYTHONPATH" texstream run "$TEMPLE_CAPTURE" -o "/root/temple_$t" --no-progress ${TEMPLE_ARGS:-} \
      > "$out/temple_$t.log" 2>&1
    echo "temple $t rc=$? $(python3 -c "print(round($(date +%s.%N) - $s, 1))") s" | tee -a "$out/temple_$t.log"
    cp "/root/temple_$t/run.json" "$out/temple_$t.json" 2>/dev/null
  done
  tail -n 16 "$out/temple_warm.log"
fi
[[ $parts == *" fit "* ]] || exit 0
python3 -m compileall -q -j 16 /root/oiio "$here" > /dev/null 2>&1  # the wheel cold_start installed
python3 -c "from texstream.capture.synthetic.synth import SynthConfig, synthesize
synthesize('ornament', '/root/sd/capture', SynthConfig(scale=1.0, device='cuda:0', progress=False, preview=False))"
python3 "$here/benchmarks/fit_cli_timeline.py" --capture /root/sd/capture --mesh /root/sd/capture/ground_truth \
  --out /root/fd --runs "${RUNS:-4}" | tee "$out/fit_timeline.txt"
cp /root/fd/fit_cli_timeline.json "$out/"
cp /root/fd/model_1/model.json "$out/fit_model_1.json"
python3 "$here/benchmarks/fit_gpu_activity.py" --capture /root/sd/capture --mesh /root/sd/capture/ground_truth \
  --out /root/act > "$out/fit_gpu_activity.txt" 2>&1
cp /root/act/fit_gpu_activity.json "$out/"
texstream synth ornament --scale 0.01 --photos 1760 --image-size 160 -o /root/dense --device cuda:0 > /dev/null 2>&1
s=$(date +%s.%N)
texstream fit /root/dense --mesh /root/dense/ground_truth/mesh.obj -o /root/dense_fit --holdout-every 8 \
  --model lafortune > "$out/dense_fit.log" 2>&1
echo "dense fit $(python3 -c "print(round($(date +%s.%N) - $s, 1))") s" | tee -a "$out/dense_fit.log"
texstream eval /root/dense_fit /root/dense --holdout-every 8 -o "$out/dense_eval.json" 2>&1 | tail -n 1 \
  | tee -a "$out/dense_fit.log"
cp /root/dense_fit/model.json "$out/dense_model.json"
