#!/usr/bin/env bash
# Runs the integration tests N times in a row (default 20) while `stress --cpu 2` loads the
# machine, and prints one line per run: a test that fails one run in five shows here. Builds
# first (scripts/setup.sh installs stress). Usage: scripts/stress-suite.sh [N]
set -euo pipefail
cd "$(dirname "$0")/.."
n=${1:-20}
export TAGDEFLECT_PYTHON="$PWD/target/test-venv/bin/python"
bin=$(cargo test --locked --test it --no-run --message-format=json 2>/dev/null \
  | sed -n 's/.*"executable":"\([^"]*\/it-[^"]*\)".*/\1/p' | tail -1)
[ -x "$bin" ] || { echo "stress-suite: cannot build the integration tests" >&2; exit 1; }
stress --cpu 2 >/dev/null 2>&1 &
load=$!
trap 'kill $load 2>/dev/null; wait $load 2>/dev/null || true' EXIT
failed=0
for i in $(seq 1 "$n"); do
  start=$(date +%s)
  if "$bin" --test-threads 2 >"target/stress-run-$i.log" 2>&1; then rc=0; else rc=$?; failed=$((failed + 1)); fi
  echo "run $i/$n: exit $rc in $(($(date +%s) - start)) s: $(grep 'test result' "target/stress-run-$i.log" | tail -1)"
done
echo "$failed of $n runs failed (logs: target/stress-run-*.log)"
[ "$failed" = 0 ]
