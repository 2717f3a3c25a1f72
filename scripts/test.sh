#!/usr/bin/env bash
# The whole test suite: installs what it needs (scripts/setup.sh), checks that the minimal
# build (no default features: replay, report, export) still builds, then runs every test of
# every crate of the workspace.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
export TAGDEFLECT_PYTHON="$PWD/target/test-venv/bin/python"
# The minimal binary: neither Aravis nor a database client, no simulator, no live page.
cargo build --locked --no-default-features --bin tagdeflect
cargo test --workspace --locked --no-fail-fast -- --test-threads 2
