#!/usr/bin/env bash
# On a lent GPU, in one call: a whole fusion end to end (benchmarks/bench_fusion.py e2e, data made by the
# kernel, so neither Mitsuba nor pycolmap is needed), first with the arguments of the CPU's committed
# result (results/fusion_e2e.md, made by `python benchmarks/bench_fusion.py e2e` on the CPU: stage times side
# by side), then at the paper's cross-init and refinement
# schedule (3 000 steps per pair, 6 000) at 320×240 with 3 000 training steps per date, the refinement at
# the rates the dates were trained with (as benchmarks/eval_large.toml: at the paper's refinement rates an
# opaque surface, its α halved at the start, is still semi-transparent after 1 000 steps), within
# GPU_FUSION_TIMEOUT (default 360 s; the whole call fits the device's 10 minutes; a run cut short writes
# nothing).
# Run in the repository root on the device, carrying .whl and .carry (made by benchmarks/gpu_prepare.sh):
#
#   [BACKEND=pallas] bash benchmarks/gpu.sh fusion
#
# BACKEND=pallas makes the Pallas compositor the device copy's default (only once gpu_kernel.sh has shown
# that it compiles and agrees there). Writes under $OUT: log.txt and fusion_e2e*_<chip>_gpu.{json,md}.
source benchmarks/gpu_setup.sh
if [ "${BACKEND:-xla}" = "pallas" ]; then
  sed -i 's/    backend: str = "auto"/    backend: str = "pallas"/' src/cfgs_jax/splat/config.py
fi
grep -n "backend: str" src/cfgs_jax/splat/config.py
timeout "${CPU_ARGS_TIMEOUT:-200}" python3 benchmarks/bench_fusion.py e2e
echo "bench_fusion_e2e (the CPU's arguments) rc=$? at $(( $(date +%s) - t0 )) s"
timeout "${GPU_FUSION_TIMEOUT:-360}" python3 benchmarks/bench_fusion.py e2e --size 320x240 --gaussians 50000 \
  --train-steps 3000 --cross-steps 3000 --refine-steps 6000 --tag _paper_320x240 \
  --set refine.lr_alpha=0.05 --set refine.lr_color=0.0025 --set refine.lr_other=0.001
echo "bench_fusion_e2e (the paper's schedule) rc=$? at $(( $(date +%s) - t0 )) s"
cp benchmarks/results/fusion_e2e*_gpu.* "$OUT/" 2>/dev/null
