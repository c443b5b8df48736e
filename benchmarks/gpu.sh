#!/usr/bin/env bash
# The GPU runs, one command. Here, on the CPU machine, before a device call: what the device needs and
# cannot download (wheels, the LPIPS weights, the training benchmark's date); then on the lent device, in
# the repository root, one part per call (each writes under $OUT and fits the device's 10 minutes):
#
#   PYTHON=.venv/bin/python bash benchmarks/gpu.sh prepare   # here: .whl/ and .carry/ (git-ignored)
#   bash benchmarks/gpu.sh kernel                            # device: Pallas probes, kernel and training figures, gsplat
#   bash benchmarks/gpu.sh fusion                            # device: a fusion end to end (bench_fusion.py e2e)
#   bash benchmarks/gpu.sh tests [MODULE ...]                # device: the test modules that need no Mitsuba
#
# Each part is the script benchmarks/gpu_PART.sh; its header says what it carries, runs and writes, and
# which environment variables set its timeouts. The summaries are written here afterwards:
# `python benchmarks/bench_gpu.py summary`, `… tests-summary`.
set -euo pipefail
part=${1:-}
case "$part" in
  prepare | kernel | fusion | tests)
    shift
    exec bash "$(dirname "$0")/gpu_$part.sh" "$@"
    ;;
  *)
    echo "usage: bash benchmarks/gpu.sh prepare|kernel|fusion|tests [ARGS]" >&2
    exit 2
    ;;
esac
