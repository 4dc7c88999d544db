#!/usr/bin/env bash
# The GPU kernel study behind benchmarks/results/<gpu>_kernels/README.md, run on the GPU machine
# from the repository root once warp is installed (../shared/tools/device/README.md):
#
#   OUT=$OUT/study bash benchmarks/gpu_kernel_study.sh profile    # ms per pass: block sizes, register caps
#   OLD_TREE=/root/old OUT=$OUT/study bash benchmarks/gpu_kernel_study.sh old   # the same passes of an older checkout
#   OUT=$OUT/study bash benchmarks/gpu_kernel_study.sh fit   # error against time, four optimizers (BLOCK= overrides)
#
# Full ornament (1,760 photos), filtered sampling, fp32, the automatic photo groups.
set -euo pipefail
OUT=${OUT:-out/gpu_kernel_study}
mkdir -p "$OUT"
OUT=$(cd "$OUT" && pwd)
nvidia-smi --query-gpu=name,memory.total,clocks.max.sm,clocks.max.mem --format=csv > "$OUT/gpu.csv" || true
case "${1:-}" in
  profile)
    python3 benchmarks/pass_profile.py --scene ornament --scale 1.0 --device cuda:0 --models lafortune,diffuse \
      --samplings filtered --kinds grad,dhd,lm --groups 0 --max-registers 0,168 --block-dims 256,128,64 \
      --passes 5 --bandwidth-probe --out "$OUT/profile" ;;
  old)
    (cd "$OLD_TREE" && python3 -m pip install -q --no-deps --no-build-isolation -e . >/dev/null 2>&1 &&
     python3 benchmarks/pass_profile.py --scene ornament --scale 1.0 --device cuda:0 --models lafortune,diffuse \
       --samplings filtered --kinds grad,lm --groups 0 --passes 5 --bandwidth-probe --out "$OUT/old_profile")
    python3 -m pip install -q --no-deps --no-build-isolation -e . >/dev/null 2>&1 ;;
  fit)
    python3 benchmarks/fit_error_vs_time.py --scene ornament --scale 1.0 --device cuda:0 --optimizers lm,lbfgs,cg,sd \
      --iterations 250 --sd-iterations 250 --bandwidth-probe ${BLOCK:+--block-dim $BLOCK} --out "$OUT/fit" ;;
  *)
    echo "usage: gpu_kernel_study.sh profile|old|fit" >&2; exit 2 ;;
esac
