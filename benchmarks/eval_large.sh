#!/usr/bin/env bash
# The 320×240 evaluations (benchmarks/eval_large.toml) of flood, corals and quake, run so that they
# survive interruptions and use a 2-core machine fully, then published.
#
#   bash benchmarks/eval_large.sh WORK          # start or continue, in the background; logs in WORK/*.log
#   bash benchmarks/eval_large.sh WORK publish  # write results/eval_large_S.md for each finished scene
#   bash benchmarks/eval_large.sh WORK stop     # stop every scene's lanes; each checkpoints its step first
#   SCENES="quake" bash benchmarks/eval_large.sh WORK   # start or publish only these scenes (default: all three)
#   SET="refine.lr_o=0.05 refine.lr_alpha=0.1" NAME=eval_large_o bash benchmarks/eval_large.sh WORK [publish]
#                                               # every part run with these overrides (`--set`), published as
#                                               # results/NAME_S.md (default NAME: eval_large)
#
# Each scene is the command `python -m cfgs_jax.pipeline eval --scene S --config benchmarks/eval_large.toml
# --out WORK/S --resume --no-progress`, run as its parts (`--part`) so that both cores work: first
# `--part train` (the per-date models, on both cores), then two single-core processes side by side (on
# the 2-core CPU two processes give about 1.5× the throughput of one on both cores): core 0 runs
# `fusion`, core 1 the Individual +N of every date and `known_transforms`; then each lane takes the
# ablations (each a refinement as long as the fusion's, from its cross-init) one at a time, whichever
# lane is free first (`--part ablations --set eval.ablations=["KEY"]`; a claim is a folder
# WORK/S.claims/KEY, cleared when the scene starts again); then `--part all` writes the table, and
# WORK/S.finished records the SET it was written with (a start with other overrides, e.g. more
# ablations, runs the scene's parts again: each finds what is already done and adds the rest). Every part
# checkpoints, so running this again after the machine or the process stopped continues where each
# part stopped. The scenes run one after the other (flood, corals, quake); one already running (a
# process with its --out) is left alone. Publishing runs `benchmarks/bench_quality.py publish --scene S --out
# WORK/S --config benchmarks/eval_large.toml --name eval_large_S` for each scene whose table.md exists.
set -euo pipefail
cd "$(dirname "$0")/.."
work=$(realpath -m "${1:?usage: bash benchmarks/eval_large.sh WORK [publish]}")
mkdir -p "$work"
python=${PYTHON:-python}
all_scenes="flood corals quake"
scene_names=${SCENES:-$all_scenes}

read -r -a items <<<"${SET:-}"  # SET's overrides split at spaces, never globbed ("eval.ablations=[]")
sets=()
for item in "${items[@]}"; do sets+=(--set "$item"); done

if [ "${2:-}" = "publish" ]; then
  for s in $scene_names; do
    if [ -f "$work/$s/table.md" ]; then
      "$python" benchmarks/bench_quality.py publish --scene "$s" --out "$work/$s" --config benchmarks/eval_large.toml \
        --name "${NAME:-eval_large}_$s" "${sets[@]}"
    else
      echo "$s: not finished ($work/$s/table.md missing)"
    fi
  done
  exit 0
fi

if [ "${2:-}" = "stop" ]; then
  # the drivers first (so that none starts its next part), then SIGTERM to each scene's processes: the
  # loop in progress ends its step and saves a checkpoint (cfgs_jax.stopping) before the process exits
  pkill -f -- "^bash -c .*(scenes|part [a-z]+ )" || true
  for s in $all_scenes; do  # every scene: the line above stopped every scene's driver
    pkill -TERM -f -- "--out $work/$s( |$)" && echo "$s: asked to stop" || true
  done
  exit 0
fi

part() {  # part S PART [ARGS...]: one part of scene S's evaluation, logged to WORK/S.log
  local s=$1 rc=0
  shift
  local -a sets=() items
  read -r -a items <<<"${SET:-}"
  for item in "${items[@]}"; do sets+=(--set "$item"); done
  "$python" -m cfgs_jax.pipeline eval --scene "$s" --config benchmarks/eval_large.toml "${sets[@]}" --out "$work/$s" \
    --resume --no-progress --part "$@" >>"$work/$s.log" 2>&1 || rc=$?
  echo "$s part $* rc=$rc $(date -u +%FT%TZ) code $(git rev-parse --short HEAD)" >>"$work/done.log"
  return $rc
}
ablation_keys() {  # ablation_keys S: the ablations scene S's evaluation runs ([eval] ablations after SET)
  local -a items
  read -r -a items <<<"${SET:-}"
  "$python" -c 'import sys
from cfgs_jax.config import apply_overrides, load_config
from cfgs_jax.evaluation.protocol import EvalSetup
print(" ".join(EvalSetup.parse(apply_overrides(load_config(sys.argv[1]), sys.argv[2:])).ablation_keys))' \
    benchmarks/eval_large.toml "${items[@]}"
}
ablations() {  # ablations S KEY...: each ablation no other lane has claimed, one at a time, once the
  # fusion's cross-init (their start) is done or the fusion's part has ended; one that fails is given back
  local s=$1 key
  shift
  [ $# -gt 0 ] || return 0
  until [ -e "$work/$s.claims/.fusion_ended" ] || "$python" -c 'import sys
from cfgs_jax.io.run_dir import RunDir
sys.exit(not RunDir.open(sys.argv[1], finished=False).done("cross_init"))' "$work/$s/run" 2>/dev/null; do
    sleep 60
  done
  for key in "$@"; do
    mkdir "$work/$s.claims/$key" 2>/dev/null || continue  # mkdir is atomic: one lane gets each key
    part "$s" ablations --set "eval.ablations=[\"$key\"]" || rmdir "$work/$s.claims/$key"
  done
}
scenes() {  # each unfinished scene in turn: train, the two single-core lanes, then the table
  local s
  for s in $scene_names; do
    # finished with these overrides: WORK/S.finished holds the SET its table was written with
    [ -f "$work/$s/table.md" ] && [ -f "$work/$s.finished" ] && [ "$(cat "$work/$s.finished")" = "${SET:-}" ] && continue
    pgrep -f -- "--out $work/$s( |$)" >/dev/null && continue  # another start is running it
    part "$s" train || continue
    local keys
    keys=$(ablation_keys "$s" 2>>"$work/$s.log") || continue  # a bad SET: the error is in WORK/S.log
    rm -rf "$work/$s.claims" && mkdir -p "$work/$s.claims"
    (
      taskset -c 0 bash -c "part $s fusion; touch $work/$s.claims/.fusion_ended; ablations $s $keys" &
      taskset -c 1 bash -c "part $s individual; part $s known_transforms; ablations $s $keys" &
      wait
    )
    part "$s" all && printf '%s' "${SET:-}" >"$work/$s.finished"
  done
}
export -f part ablation_keys ablations scenes
export work python scene_names SET
# The compiled steps are kept on disk (JAX's persistent cache, shared with the tests' cache) so that a
# restarted scene does not compile again (a training step took 10 minutes to compile on one busy core).
export JAX_COMPILATION_CACHE_DIR=${JAX_COMPILATION_CACHE_DIR:-$HOME/.cache/cfgs_jax/xla}
# Each lane is a session of its own (setsid), so with Linux's autogroup scheduling `nice` alone does not
# yield to other sessions' work; the autogroup's own nice value makes the lanes yield to interactive work
# (tests, benchmarks) and use what is left.
background() { setsid nohup bash -c "echo 19 >/proc/self/autogroup 2>/dev/null; nice -n 19 bash -c scenes" \
  >/dev/null 2>&1 </dev/null & }
background
echo "started: $scene_names in turn, each on both cores (logs: $work/*.log, parts finished: $work/done.log)"
