# Sourced by the GPU benchmark scripts (cold_start_gpu.sh, env_fit_gpu.sh) with OUT set: records the machine and
# the commit under OUT, installs OpenImageIO's wheel (WHEELS, default .whl/) into /root/oiio and texstream itself
# (editable), with Warp from /root/site (the two-call recipe of ../shared/tools/device/README.md). The commit the
# device tool's checkout reports can be its base, not the tree sent: name the tree beside the results.
mkdir -p "$out"
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader | tee "$out/machine.txt"
nproc | tee -a "$out/machine.txt"
git rev-parse --short HEAD 2>/dev/null | tee "$out/commit.txt"
python3 -m pip install -q --no-index --no-deps --no-compile --target /root/oiio "${WHEELS:-.whl}"/*.whl || exit 1
export PYTHONPATH=/root/site:/root/oiio
python3 -m pip install -q --no-deps --no-build-isolation -e . >/dev/null 2>&1 || exit 1
