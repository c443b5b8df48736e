#!/usr/bin/env bash
# On a lent GPU, in one call: which Pallas kernel variants compile (gpu_probe.py), the kernel tests of
# both compositor backends, and the kernel against gsplat's CUDA rasteriser (bench_gsplat.py).
# Run in the repository root on the device:
#
#   bash benchmarks/gpu_kernel.sh
#
# Needs, carried beside the tree: .whl/ (cp312 wheels of colour-science, dm-pix, msgspec, OpenEXR, plyfile
# and gsplat==1.5.3, which the device image lacks). Writes under $OUT: log.txt, probe.txt, junit.xml,
# gsplat_build.txt, kernel_vs_gsplat_<chip>_gpu.{json,md}.
export PYTHONUNBUFFERED=1
exec > >(tee -a "$OUT/log.txt") 2>&1
t0=$(date +%s)
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD/src XLA_PYTHON_CLIENT_PREALLOCATE=false
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
# gsplat's CUDA extension compiles on its first import: build it in the background meanwhile
(MAX_JOBS=8 TORCH_CUDA_ARCH_LIST=9.0 python3 -c "from gsplat.cuda._backend import _C; print('gsplat built', _C is not None)" \
  >"$OUT/gsplat_build.txt" 2>&1 &)
timeout 60 python3 benchmarks/gpu_probe.py | tee "$OUT/probe.txt"
scatter=""
for v in "partials dotbehind dot_behind" "partials dot dot" "atomic dotbehind dot_behind" "atomic dot dot"; do
  set -- $v
  if grep -q "bwd_$1_$2_T1_k32: OK" "$OUT/probe.txt" && { [ "$1" = atomic ] || grep -q "bwd_$1_$2_T2_k16: OK" "$OUT/probe.txt"; }; then
    scatter="$1 $3"  # the device copy's defaults only
    sed -i "s/    scatter: str = \"atomic\"/    scatter: str = \"$1\"/" src/cfgs_jax/splat/config.py
    sed -i "s/    prefix: str = \"scan\"/    prefix: str = \"$3\"/" src/cfgs_jax/splat/pallas_composite.py
    break
  fi
done
grep -n "scatter: str\|prefix: str" src/cfgs_jax/splat/config.py src/cfgs_jax/splat/pallas_composite.py
echo "backward scatter: ${scatter:-none compiles} at $(( $(date +%s) - t0 )) s"
if [ -n "$scatter" ]; then
  timeout 90 python3 -m pytest -p no:cacheprovider -n 2 --dist loadfile -q -o addopts="" -rfE \
    --junitxml="$OUT/junit.xml" tests/test_pallas.py tests/test_splat.py 2>&1 | grep -v "Fatal\|^  File\|^Thread\|^$\|PytestBenchmark\|warner"
  echo "pytest at $(( $(date +%s) - t0 )) s"
  timeout 190 python3 benchmarks/bench_gsplat.py --out "$OUT" --no-sweep --reps 5
else
  timeout 150 python3 benchmarks/bench_gsplat.py --out "$OUT" --no-sweep --no-dates --backends xla --reps 5
fi
echo "bench_gsplat rc=$? at $(( $(date +%s) - t0 )) s"
