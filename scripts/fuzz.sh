#!/usr/bin/env bash
# Runs every cargo-fuzz target in fuzz/ for SECONDS each (default 60) and prints, per
# target, the executions done and whether it crashed. Not run by CI.
#
#   scripts/fuzz.sh [SECONDS] [TARGET...]
#
# Needs cargo-fuzz (`cargo install cargo-fuzz --locked`, done here when missing) and a
# nightly toolchain for the sanitizer flags; without one, the stable toolchain is used with
# RUSTC_BOOTSTRAP=1 (which cargo-fuzz supports). FUZZ_SANITIZER=none|address (default
# address). A crash leaves its input in fuzz/artifacts/<target>/; copy it into
# tests/fixtures/fuzz-regressions/<target>/ so the normal test suite replays it
# (tests/it/robustness.rs), then fix the code.
set -euo pipefail
secs=${1:-60}
shift || true
cd "$(dirname "$0")/.."
command -v cargo-fuzz >/dev/null || cargo install cargo-fuzz --locked
if rustup toolchain list 2>/dev/null | grep -q '^nightly'; then
    tc=(+nightly)
else
    tc=()
    export RUSTC_BOOTSTRAP=1
fi
san=${FUZZ_SANITIZER:-address}
# FUZZ_TARGET_DIR: where the fuzz build goes (default fuzz/target).
td=()
[ -n "${FUZZ_TARGET_DIR:-}" ] && td=(--target-dir "$FUZZ_TARGET_DIR")
cd fuzz
targets=("$@")
[ ${#targets[@]} -gt 0 ] || mapfile -t targets < <(cargo "${tc[@]}" fuzz list)
mkdir -p logs
# Integer overflow checks and debug assertions on (-a); memory limits catch allocations
# driven by input sizes.
# Only the targets asked for are built (each links the whole crate).
if [ $# -gt 0 ]; then
    for t in "${targets[@]}"; do cargo "${tc[@]}" fuzz build "${td[@]}" -a -s "$san" "$t"; done
else
    cargo "${tc[@]}" fuzz build "${td[@]}" -a -s "$san"
fi
status=0
printf '%-14s %12s %10s  %s\n' target execs exec/s result
for t in "${targets[@]}"; do
    mkdir -p "corpus/$t"
    seeds=()
    [ -d "../tests/fixtures/fuzz-regressions/$t" ] && seeds=("../tests/fixtures/fuzz-regressions/$t")
    if cargo "${tc[@]}" fuzz run "${td[@]}" -a -s "$san" "$t" "corpus/$t" "${seeds[@]}" -- \
        -max_total_time="$secs" -rss_limit_mb=2048 -malloc_limit_mb=1024 -timeout=10 -print_final_stats=1 \
        >"logs/$t.log" 2>&1; then
        result=ok
    else
        result="CRASH (see fuzz/logs/$t.log, input in fuzz/artifacts/$t/)"
        status=1
    fi
    execs=$(grep -o 'stat::number_of_executed_units: *[0-9]*' "logs/$t.log" | grep -o '[0-9]*$' | tail -1)
    rate=$(grep -o 'stat::average_exec_per_sec: *[0-9]*' "logs/$t.log" | grep -o '[0-9]*$' | tail -1)
    printf '%-14s %12s %10s  %s\n' "$t" "${execs:-?}" "${rate:-?}" "$result"
done
exit $status
