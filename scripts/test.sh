#!/usr/bin/env bash
# The whole test suite: installs what it needs (scripts/setup.sh), checks that the minimal
# build (no default features: replay, report, export) still builds, then runs every test of
# every crate of the workspace.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
export TAGDEFLECT_PYTHON="$PWD/target/test-venv/bin/python"
# The minimal binary: neither Aravis nor a database client, no simulator, no live page. It
# replays a recording of the simulated rig, exports its feed, and names the feature a missing
# command needs.
cargo build --locked --no-default-features --bin tagdeflect
min=target/debug/tagdeflect
if ldd "$min" | grep -qiE 'aravis|libpq'; then echo "minimal build links Aravis or a database client" >&2; exit 1; fi
"$min" replay replay/one-cam > target/minimal-feed.jsonl 2> /dev/null
"$min" export target/minimal-feed.jsonl --csv target/minimal-feed.csv
[ "$(wc -l < target/minimal-feed.jsonl)" -gt 0 ] && [ -s target/minimal-feed.csv ]
if "$min" demo --duration-s 1 2> target/minimal-demo.err; then echo "minimal build ran demo" >&2; exit 1; fi
grep -q 'needs the `sim` feature' target/minimal-demo.err
cargo test --workspace --locked --no-fail-fast -- --test-threads 2
