#!/usr/bin/env bash
# Injects each regression of scripts/regressions/NAME.patch into the product, runs the tests
# its header names, reverts it, and says which tests failed (docs/accuracy.md's table
# "Injected regressions" is made from this). A patch's header:
#   Regression: what it breaks, in words
#   Unit: arguments of `cargo test` for crate unit tests (may be empty; more than one filter
#         goes after `--`: `-p CRATE --lib -- FILTER FILTER`)
#   It: filters of the integration test binary (`cargo test --test it -- FILTERS`)
#
# Usage: scripts/inject_regressions.sh [NAME...]        each alone (default: every patch)
#        TOGETHER=1 scripts/inject_regressions.sh A B   A and B at once, the union of their
#            tests run once (one build: for patches whose tests cannot be failed by the other)
#        RUN_IT=0 ...                                   crate unit tests only
#        RUN_UNIT=0 ...                                 integration tests only (a crate's unit
#            tests build the crate's dependencies again with its own features: ~30 min here)
# Results: target/regressions/results.md (a table row per run) and one log per run.
# Needs a clean work tree where the patches apply; a patch is reverted even when interrupted.
set -u
cd "$(git rev-parse --show-toplevel)"
export CARGO_INCREMENTAL=0
dir=scripts/regressions
out=target/regressions
mkdir -p "$out"
names=("$@")
[ ${#names[@]} -eq 0 ] && names=($(ls "$dir" | sed -n 's/\.patch$//p'))

field() { sed -n "s/^$2: //p" "$dir/$1.patch" | head -1; }

applied=()
revert() {
    for n in "${applied[@]}"; do git apply -R "$dir/$n.patch" || echo "REVERT FAILED: $n" >&2; done
    applied=()
}
trap 'revert; exit 130' INT TERM

# Runs `cargo test ARGS`, appends the log, prints the names of failed tests (or BUILD FAILED).
run_tests() {
    local log=$1; shift
    cargo test "$@" >>"$log" 2>&1
    local rc=$?
    local failed
    failed=$(sed -n 's/^test \(.*\) \.\.\. FAILED$/\1/p' "$log" | sort -u)
    if [ $rc -ne 0 ] && [ -z "$failed" ] && grep -q "^error\(\[E[0-9]*\]\)\?:" "$log"; then
        echo "BUILD FAILED"
    else
        echo "$failed"
    fi
}

run_group() {
    local label=$1; shift
    local log="$out/$label.log" unit its=() desc=()
    : >"$log"
    for n in "$@"; do
        git apply "$dir/$n.patch" || { echo "$n: does not apply (the code moved on: remake the patch)"; revert; return; }
        applied+=("$n")
        desc+=("$(field "$n" Regression)")
        its+=($(field "$n" It))
    done
    local failed=""
    for n in "$@"; do
        unit=$(field "$n" Unit)
        [ -n "$unit" ] && [ "${RUN_UNIT:-1}" != 0 ] && failed+=$'\n'$(run_tests "$log" $unit)
    done
    if [ "${RUN_IT:-1}" != 0 ] && [ ${#its[@]} -gt 0 ]; then
        failed+=$'\n'$(run_tests "$log" --test it -- "${its[@]}")
    fi
    revert
    failed=$(echo "$failed" | sed '/^$/d' | sort -u)
    local count list
    count=$(echo "$failed" | sed '/^$/d' | wc -l)
    list=$(echo "$failed" | sed '/^$/d' | sed 's/.*/`&`/' | paste -sd, - | sed 's/,/, /g')
    local row="| $(IFS=';'; echo "${desc[*]}") | ${count}: ${list:-none} | $(date -u +%F) load $(cut -d' ' -f1 /proc/loadavg) |"
    echo "$row" | tee -a "$out/results.md"
}

if [ "${TOGETHER:-0}" = 1 ]; then
    run_group "$(IFS=+; echo "${names[*]}")" "${names[@]}"
else
    for n in "${names[@]}"; do run_group "$n" "$n"; done
fi
