#!/usr/bin/env bash
# Soak test: run `tagdeflect demo` for a long time and sample its resident memory.
#
#   scripts/soak.sh [SECONDS] [BINARY]      (default 3600 s, target/release/tagdeflect)
#
# Prints one line per minute (elapsed s, VmRSS kB, feed lines so far) and, at the end, RSS at
# the first minute and at the end with the relative change. The feed goes to a temporary file
# that is counted and removed; the live page is served on a free port so that the HTTP sink's
# state is part of what is measured. Not part of CI (it runs for an hour by design).
set -euo pipefail
secs=${1:-3600}
bin=${2:-target/release/tagdeflect}
work=$(mktemp -d)
trap 'kill "$pid" 2>/dev/null || true; wait "$pid" 2>/dev/null || true; rm -rf "$work"' EXIT
"$bin" demo --duration-s "$secs" --http 127.0.0.1:0 >"$work/feed.jsonl" 2>"$work/log" &
pid=$!
first=""
start=$(date +%s)
while kill -0 "$pid" 2>/dev/null; do
  sleep 60
  rss=$(awk '/^VmRSS/ {print $2}' "/proc/$pid/status" 2>/dev/null || true)
  [ -n "$rss" ] || break
  lines=$(wc -l <"$work/feed.jsonl")
  now=$(( $(date +%s) - start ))
  echo "t=${now}s rss_kb=$rss feed_lines=$lines"
  [ -n "$first" ] || first=$rss
  last=$rss
done
wait "$pid" || { echo "demo exited with $?; log:"; tail -20 "$work/log"; exit 1; }
echo "rss_kb first_minute=$first end=$last change=$(awk -v a="$first" -v b="$last" 'BEGIN{printf "%+.1f%%", (b-a)*100/a}')"
echo "feed lines: $(wc -l <"$work/feed.jsonl")"
