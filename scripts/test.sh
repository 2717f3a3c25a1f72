#!/usr/bin/env bash
# The whole test suite: installs what it needs (scripts/setup.sh), then runs every test.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
export TAGDEFLECT_PYTHON="$PWD/target/test-venv/bin/python"
cargo test --locked --no-fail-fast -- --test-threads 2
