#!/usr/bin/env bash
# The 320×240 evaluations (benchmarks/eval_large.toml) of flood, corals and quake, run so that they
# survive interruptions and use a 2-core machine fully, then published.
#
#   bash benchmarks/eval_large.sh WORK          # start or continue, in the background; logs in WORK/*.log
#   bash benchmarks/eval_large.sh WORK publish  # write results/eval_large_S.md for each finished scene
#   bash benchmarks/eval_large.sh WORK stop     # stop the lanes; each scene checkpoints its step first
#
# Each scene is `python -m cfgs_jax.pipeline eval --scene S --config benchmarks/eval_large.toml
# --out WORK/S --resume --no-progress`: every stage checkpoints, so running this again after the machine
# or the process stopped continues where each scene stopped. Two single-core processes run side by side
# (flood on core 0, corals on core 1, quake on whichever is free first): on the 2-core CPU they give about 1.5× the throughput of
# one process on both cores (20k Gaussians, 320×240: forward + backward 0.43 s on two cores, 0.57–0.61 s
# each for two processes on one core each). A scene already running (a process with its --out) is left
# alone. Publishing runs `benchmarks/eval_publish.py --scene S --out WORK/S --config
# benchmarks/eval_large.toml --name eval_large_S` for each scene whose table.md exists.
set -euo pipefail
cd "$(dirname "$0")/.."
work=$(realpath -m "${1:?usage: bash benchmarks/eval_large.sh WORK [publish]}")
mkdir -p "$work"
python=${PYTHON:-python}

if [ "${2:-}" = "publish" ]; then
  for s in flood corals quake; do
    if [ -f "$work/$s/table.md" ]; then
      "$python" benchmarks/eval_publish.py --scene "$s" --out "$work/$s" --config benchmarks/eval_large.toml \
        --name "eval_large_$s"
    else
      echo "$s: not finished ($work/$s/table.md missing)"
    fi
  done
  exit 0
fi

if [ "${2:-}" = "stop" ]; then
  # the lanes first (so that no lane starts its next scene), then SIGTERM to each scene's process: the
  # loop in progress ends its step and saves a checkpoint (cfgs_jax.stopping) before the process exits
  pkill -f -- "lane [0-9]+ " || true
  for s in flood corals quake; do
    pkill -TERM -f -- "--out $work/$s( |$)" && echo "$s: asked to stop" || true
  done
  exit 0
fi

lane() {  # lane CORE SCENE...: on one core, each scene in this order that is unfinished and no lane has
  local core=$1 s
  shift
  for s in "$@"; do
    [ -f "$work/$s/table.md" ] && continue
    mkdir "$work/.$s.claimed" 2>/dev/null || continue  # another lane has it (or had it: it failed there)
    while pgrep -f -- "--out $work/$s( |$)" >/dev/null; do sleep 60; done  # one process per scene
    taskset -c "$core" "$python" -m cfgs_jax.pipeline eval --scene "$s" --config benchmarks/eval_large.toml \
      --out "$work/$s" --resume --no-progress >>"$work/$s.log" 2>&1
    echo "$s rc=$? $(date -u +%FT%TZ) code $(git rev-parse --short HEAD)" >>"$work/done.log"
  done
}
export -f lane
export work python
# The compiled steps are kept on disk (JAX's persistent cache, shared with the tests' cache) so that a
# restarted scene does not compile again (a training step took 10 minutes to compile on one busy core).
export JAX_COMPILATION_CACHE_DIR=${JAX_COMPILATION_CACHE_DIR:-$HOME/.cache/cfgs_jax/xla}
# Each lane is a session of its own (setsid), so with Linux's autogroup scheduling `nice` alone does not
# yield to other sessions' work; the autogroup's own nice value makes the lanes yield to interactive work
# (tests, benchmarks) and use what is left.
background() { setsid nohup bash -c "echo 19 >/proc/self/autogroup 2>/dev/null; nice -n 19 bash -c 'lane $1'" \
  >/dev/null 2>&1 </dev/null & }
# a scene is claimed by the first lane to reach it; the claims of an earlier start (its lanes gone) are cleared
pgrep -f -- "lane [0-9]+ " >/dev/null || rm -rf "$work"/.*.claimed
background "0 flood quake corals"
background "1 corals quake flood"
echo "started: flood on core 0, corals on core 1, then quake on the first core free (logs: $work/*.log, finished: $work/done.log)"
