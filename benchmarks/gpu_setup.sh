# Sourced by the GPU scripts (gpu_kernel.sh, gpu_fusion.sh, gpu_tests.sh) in the repository root on a lent device: logs to
# $OUT/log.txt, installs the carried wheels (.whl/) beside the device image's packages, puts .carry/site (the
# LPIPS weights package) and src/ on the path (both made by benchmarks/gpu_prepare.sh on the CPU machine),
# names the card, and starts the clock t0.
export PYTHONUNBUFFERED=1
exec > >(tee -a "$OUT/log.txt") 2>&1
t0=$(date +%s)
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
if [ -f .warp_1/piece_0 ] && [ -f .warp_2/piece_1 ] && [ -f .warp_3/piece_2 ]; then  # NVIDIA Warp, carried in three calls
  mkdir -p /tmp/warp_whl && name=$(awk '{print $2}' .warp_3/wheel.sha256)
  cat .warp_1/piece_0 .warp_2/piece_1 .warp_3/piece_2 >"/tmp/warp_whl/$name"
  (cd /tmp/warp_whl && sha256sum -c "$OLDPWD/.warp_3/wheel.sha256") &&
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site "/tmp/warp_whl/$name"
else
  echo "warp-lang not carried (.warp_1..3): the warp backend is left out"
fi
export PYTHONPATH=/tmp/site:$PWD/.carry/site:$PWD/src XLA_PYTHON_CLIENT_PREALLOCATE=false
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
