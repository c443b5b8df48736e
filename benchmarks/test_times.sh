#!/usr/bin/env bash
# How long the README's test command takes a user: its pytest part run twice in this checkout's
# environment, first cold (an empty JAX compilation cache, as on a fresh machine) and then warm (the cache
# the first run filled), each timed end to end; the table goes to benchmarks/results/test_times.md.
#
#   bash benchmarks/test_times.sh            # uses .venv when the checkout has one, else `python` on PATH
#
# The install part of the command (apt, venv, pip) is not timed here: `.ci/run` times it. A run with
# other work on the machine gives upper bounds; the results file says what else was running (the load
# average before each phase).
set -euo pipefail
cd "$(dirname "$0")/.."
[ -d .venv ] && export PATH="$PWD/.venv/bin:$PATH"
test_part=$(.ci/test_command pytest)
cache=$(mktemp -d)
logs=$(mktemp -d)
trap 'rm -rf "$cache"' EXIT
rows=""
for phase in cold warm; do
  load=$(cut -d' ' -f1-3 /proc/loadavg)
  t0=$(date +%s)
  rc=0
  CFGS_JAX_CACHE="$cache" bash -c "$test_part" >"$logs/$phase.log" 2>&1 || rc=$?
  took=$(( $(date +%s) - t0 ))
  summary=$(grep -E "^(=+ )?[0-9]+ (passed|failed)" "$logs/$phase.log" | tail -1 | sed 's/=//g; s/^ *//; s/ *$//')
  echo "$phase: $took s, exit code $rc ($summary; log $logs/$phase.log)"
  rows+="| $phase | $took | $rc | $summary | $load |"$'\n'
  [ "$rc" -eq 0 ] || { echo "test_times: the $phase run failed; see $logs/$phase.log" >&2; exit "$rc"; }
done
machine=$(python -c "import sys; sys.path.insert(0, 'benchmarks'); import common; print(common.machine())")
out=benchmarks/results/test_times.md
tmp=$(mktemp "$out.XXXX")
cat >"$tmp" <<MD
# The README's test command: cold and warm (benchmarks/test_times.sh)

Command: \`bash benchmarks/test_times.sh\` (the pytest part of the README's test command, \`$test_part\`,
run twice: with an empty JAX compilation cache, then with the cache that run filled). Machine: $machine.
Date: $(date -u +%F). Code: $(git rev-parse --short HEAD)$(git diff --quiet HEAD -- src tests || echo ' with uncommitted changes').

| run | seconds | exit code | pytest's summary | load average before (1 / 5 / 15 min) |
|---|---:|---:|---|---|
$rows
MD
mv "$tmp" "$out"
echo "wrote $out"
