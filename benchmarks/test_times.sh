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
#   bash benchmarks/test_times.sh compare [TEST FILES]
#                                            # the tests' quick CPU compile against XLA's defaults, cold and
#                                            # warm, side by side: benchmarks/results/test_compile_modes.md
#   bash benchmarks/test_times.sh profile [--out F] [-- PYTEST ARGS]
#                                            # where a cold run's time goes: every XLA compilation by test
#                                            # file and program (benchmarks/compile_profile.py), to
#                                            # benchmarks/results/compile_profile.md
set -euo pipefail
cd "$(dirname "$0")/.."
[ -d .venv ] && export PATH="$PWD/.venv/bin:$PATH"
summary_of() {  # pytest's closing line in log $1, without its ===
  grep -E "^(=+ )?[0-9]+ (passed|failed)" "$1" | tail -1 | sed 's/=//g; s/^ *//; s/ *$//'
}
machine() { python -c "import sys; sys.path.insert(0, 'benchmarks'); import common; print(common.machine())"; }
if [ "${1:-}" = profile ]; then
  shift
  exec python -c 'import sys; sys.path.insert(0, "benchmarks"); import compile_profile; compile_profile.main()' "$@"
fi
if [ "${1:-}" = compare ]; then
  # The tests' quick CPU compile (tests/conftest.py) against XLA's defaults, side by side on one machine:
  # each setting cold (its own empty cache), then warm twice, alternating.
  shift
  files=${*:-tests/train tests/fusion/test_cross_init.py tests/fusion/test_refine.py tests/changes}
  logs=$(mktemp -d)
  trap 'rm -rf "$logs"' EXIT
  rows=""
  for run in cold warm warm; do
    for mode in default quick; do
      [ "$run" = cold ] && rm -rf "$logs/cache_$mode"
      t0=$(date +%s)
      rc=0
      CFGS_JAX_TEST_COMPILE=$mode CFGS_JAX_CACHE="$logs/cache_$mode" python -m pytest -q -n 2 --dist loadfile \
        -p no:cacheprovider $files >"$logs/$mode.log" 2>&1 || rc=$?
      took=$(( $(date +%s) - t0 ))
      summary=$(summary_of "$logs/$mode.log")
      echo "$run $mode: $took s, exit code $rc ($summary)"
      rows+="| $run | $mode | $took | $rc | $summary |"$'\n'
    done
  done
  out=benchmarks/results/test_compile_modes.md
  tmp=$(mktemp "$out.XXXX")
  cat >"$tmp" <<MD
# The tests' quick CPU compile against XLA's defaults (benchmarks/test_times.sh compare)

Command: \`bash benchmarks/test_times.sh compare${*:+ $*}\` (\`python -m pytest -q -n 2 --dist loadfile\` on $files;
\`CFGS_JAX_TEST_COMPILE=default\`: XLA's defaults; \`quick\`: tests/conftest.py's \`--xla_cpu_use_fusion_emitters=false\`;
each with its own compilation cache, emptied before its cold run; the runs alternate). Machine:
$(machine). Date: $(date -u +%F). Code: $(git rev-parse --short HEAD).

| run | compile setting | seconds | exit code | pytest's summary |
|---|---|---:|---:|---|
$rows
MD
  mv "$tmp" "$out"
  echo "wrote $out"
  exit 0
fi
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
  summary=$(summary_of "$logs/$phase.log")
  echo "$phase: $took s, exit code $rc ($summary; log $logs/$phase.log)"
  rows+="| $phase | $took | $rc | $summary | $load |"$'\n'
  [ "$rc" -eq 0 ] || { echo "test_times: the $phase run failed; see $logs/$phase.log" >&2; exit "$rc"; }
done
machine=$(machine)
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
