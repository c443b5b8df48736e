#!/usr/bin/env bash
# On a lent GPU, in one call: the kernel tests (both compositor backends), the kernel against gsplat's
# CUDA rasteriser (bench_gsplat.py) and the training step at 300k Gaussians, 960×540 (bench_train.py).
# Run in the repository root on the device:
#
#   bash benchmarks/gpu_kernel.sh
#
# Needs, carried beside the tree: .whl/ (cp312 wheels of colour-science, dm-pix, msgspec, OpenEXR, plyfile
# and gsplat==1.5.3, which the device image lacks) and .carry/train_960 (one 960×540 date of `corals`,
# rendered here with `bench_train.py --data .carry/train_960 --width 960 --height 540`). Writes under $OUT:
# log.txt, junit.xml, gsplat_build.txt, kernel_vs_gsplat_<chip>_gpu.{json,md}, train_*_gpu.{json,md}.
export PYTHONUNBUFFERED=1
exec > >(tee -a "$OUT/log.txt") 2>&1
t0=$(date +%s)
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD/src XLA_PYTHON_CLIENT_PREALLOCATE=false
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
# gsplat's CUDA extension compiles on its first import: build it in the background meanwhile
(MAX_JOBS=8 TORCH_CUDA_ARCH_LIST=9.0 python3 -c "from gsplat.cuda._backend import _C; print('gsplat built', _C is not None)" \
  >"$OUT/gsplat_build.txt" 2>&1 &)
# a smoke test first: the Pallas kernel compiles and agrees with the XLA one, else stop early
python3 - <<'PY' || { echo "smoke test failed after $(( $(date +%s) - t0 )) s"; exit 1; }
import sys; sys.path.insert(0, "tests")
import jax, jax.numpy as jnp
from test_splat import scene, camera
from cfgs_jax import splat
g, cam = scene(300, 3), camera(50, 37)
a = splat.render(g, cam, config=splat.RenderConfig(backend="xla"))
b = splat.render(g, cam, config=splat.RenderConfig(backend="pallas"))
print("smoke:", jax.devices()[0].device_kind, "image max |Δ|", float(jnp.max(jnp.abs(a.image - b.image))))
PY
echo "smoke at $(( $(date +%s) - t0 )) s"
timeout 150 python3 -m pytest -p no:cacheprovider -n 4 --dist loadfile -q -o addopts="" -rfE --durations=5 \
  --junitxml="$OUT/junit.xml" tests/test_pallas.py tests/test_splat.py
echo "pytest rc=$? at $(( $(date +%s) - t0 )) s"
timeout 300 python3 benchmarks/bench_gsplat.py --out "$OUT"
echo "bench_gsplat rc=$? at $(( $(date +%s) - t0 )) s"
rm -f benchmarks/results/train_960x540_300k_*_gpu.*
timeout 70 python3 benchmarks/bench_train.py --data .carry/train_960 --gaussians 300000 --width 960 --height 540 \
  --steps 20 --tag _960x540_300k
echo "bench_train rc=$? at $(( $(date +%s) - t0 )) s"
cp benchmarks/results/train_960x540_300k_*_gpu.* "$OUT/" 2>/dev/null
ls -la "$OUT"
