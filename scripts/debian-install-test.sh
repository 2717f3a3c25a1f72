#!/usr/bin/env bash
# Installs the Debian package into a fresh Debian (debootstrap --variant=minbase of the host's
# suite, in a folder under target/; chroot) with `apt-get install ./tagdeflect_*.deb`, and
# checks what a lab would see:
#
#   - apt resolves the package's computed dependencies from the Debian mirror and installs it;
#   - the binary runs (--version), the man pages and the bash/zsh/fish completions are there;
#   - /etc/tagdeflect/tagdeflect.toml is a conffile, and the service is neither enabled nor
#     started; `systemd-analyze verify` accepts the installed unit;
#   - the installed config (the simulated rig) runs: `tagdeflect run --config
#     /etc/tagdeflect/tagdeflect.toml` writes feed lines with a net deflection to
#     /var/lib/tagdeflect/feed.jsonl, and the installed `tagdeflect demo` serves the live page
#     (read with curl; on a free port, so nothing else on the host is disturbed);
#   - `apt-get remove` removes it and keeps the conffile (purge removes it).
#
#   scripts/debian-install-test.sh [--deb PATH] [--fresh]
#
#   --deb PATH   the package (default: the newest target/debian/tagdeflect_*.deb, else
#                scripts/package.sh builds one)
#   --fresh      debootstrap again instead of reusing the cached base system
#
# Needs root (debootstrap, chroot) and network (the mirror, $DEBIAN_MIRROR, default
# deb.debian.org). The base system is cached in $DEBIAN_TEST_DIR (default
# target/debian-install); every run installs into a new copy of it. First run: a few minutes
# (debootstrap); later runs about a minute. Prints PASS/FAIL per check; exit 1 on a failure.
# CI does not run it (network and root); the deb build itself is checked by scripts/package.sh.
set -euo pipefail

repo=$(cd "$(dirname "$0")/.." && pwd)
work=${DEBIAN_TEST_DIR:-$repo/target/debian-install}
mirror=${DEBIAN_MIRROR:-http://deb.debian.org/debian}
deb=""
fresh=0
while [ $# -gt 0 ]; do
  case "$1" in
    --deb) deb=$2; shift 2 ;;
    --fresh) fresh=1; shift ;;
    -h|--help) sed -n '2,27p' "$0"; exit 0 ;;
    *) echo "debian-install-test: unknown argument $1" >&2; exit 2 ;;
  esac
done
[ "$(id -u)" = 0 ] || { echo "debian-install-test: run as root (debootstrap and chroot need it)" >&2; exit 2; }
command -v debootstrap >/dev/null || { echo "debian-install-test: debootstrap missing (scripts/setup.sh installs it)" >&2; exit 2; }
say() { echo "debian-install-test: $*" >&2; }
failures=0
check() { # check NAME CONDITION-EXIT-STATUS DETAIL
  if [ "$2" = 0 ]; then echo "PASS $1${3:+: $3}"; else echo "FAIL $1${3:+: $3}"; failures=$((failures + 1)); fi
}

if [ -z "$deb" ]; then
  deb=$(ls -t "$repo"/target/debian/tagdeflect_*.deb 2>/dev/null | head -1 || true)
  [ -n "$deb" ] || deb=$("$repo/scripts/package.sh" | tail -1)
fi
[ -f "$deb" ] || { echo "debian-install-test: no package at $deb" >&2; exit 2; }
suite=$(. /etc/os-release && echo "${VERSION_CODENAME:-bookworm}")
base="$work/base-$suite"
root="$work/root"
mkdir -p "$work"

if [ "$fresh" = 1 ] || [ ! -f "$base/.debootstrapped" ]; then
  rm -rf "$base"
  say "debootstrap $suite (minbase) into $base"
  t0=$(date +%s)
  debootstrap --variant=minbase "$suite" "$base" "$mirror" >"$work/debootstrap.log" 2>&1 \
    || { tail -20 "$work/debootstrap.log" >&2; exit 1; }
  touch "$base/.debootstrapped"
  say "debootstrap took $(( $(date +%s) - t0 )) s"
fi

# From here on every check runs and reports, whatever failed before it.
set +e
mounted=()
cleanup() {
  local m
  for m in "${mounted[@]}"; do umount -l "$m" 2>/dev/null || true; done
  [ -n "${demo_pid:-}" ] && kill "$demo_pid" 2>/dev/null || true
}
trap cleanup EXIT
rm -rf "$root"
cp -a "$base" "$root"
for m in proc sys dev; do
  mount --bind "/$m" "$root/$m"; mounted=("$root/$m" "${mounted[@]}")
done
cp /etc/resolv.conf "$root/etc/resolv.conf"
in_root() { chroot "$root" env -i PATH=/usr/sbin:/usr/bin:/sbin:/bin HOME=/root LANG=C.UTF-8 DEBIAN_FRONTEND=noninteractive "$@"; }

cp "$deb" "$root/tmp/"
name=$(basename "$deb")
t0=$(date +%s)
in_root apt-get update -qq >"$work/apt.log" 2>&1 || true
in_root apt-get install -y -q --no-install-recommends "./tmp/$name" >>"$work/apt.log" 2>&1 </dev/null
st=$?
# apt-get install ./x.deb wants a path: run it from / inside the chroot.
check "apt-get install ./$name" $st "$(( $(date +%s) - t0 )) s, $(grep -c '^Setting up' "$work/apt.log") packages set up"
in_root dpkg-query -W -f='${Status} ${Version}\n' tagdeflect | grep -q "install ok installed"; check "dpkg status installed" $?
v=$(in_root /usr/bin/tagdeflect --version 2>&1); check "tagdeflect --version" $? "$v"
[ -s "$root/usr/share/man/man1/tagdeflect.1.gz" ] && [ -s "$root/usr/share/man/man1/tagdeflect-calibrate.1.gz" ]; check "man pages" $? "$(ls "$root/usr/share/man/man1" | grep -c tagdeflect) pages"
[ -s "$root/usr/share/bash-completion/completions/tagdeflect" ] && [ -s "$root/usr/share/zsh/vendor-completions/_tagdeflect" ] \
  && [ -s "$root/usr/share/fish/vendor_completions.d/tagdeflect.fish" ]; check "completions (bash, zsh, fish)" $?
in_root dpkg-query -W -f='${Conffiles}\n' tagdeflect | grep -q /etc/tagdeflect/tagdeflect.toml; check "conffile /etc/tagdeflect/tagdeflect.toml" $?
! ls "$root"/etc/systemd/system/*.wants/tagdeflect.service >/dev/null 2>&1; check "service not enabled" $?
# The base system has no systemd: the host's verifies the installed file, its ExecStart pointed
# at the installed binary inside the root (verify wants it to exist).
mkdir -p "$work/unit"
sed "s|^ExecStart=/usr/bin/tagdeflect |ExecStart=$root/usr/bin/tagdeflect |" "$root/lib/systemd/system/tagdeflect.service" > "$work/unit/tagdeflect.service"
out=$(systemd-analyze verify --man=no "$work/unit/tagdeflect.service" 2>&1); st=$?
[ "$st" = 0 ] && [ -z "$out" ]; check "systemd-analyze verify (installed unit)" $? "${out:-no complaints}"

# The installed configuration runs (as the service would, minus systemd: its state folder made here).
mkdir -p "$root/var/lib/tagdeflect"
sed 's|^http = .*|http = "127.0.0.1:0"|' "$root/etc/tagdeflect/tagdeflect.toml" > "$root/tmp/rig.toml"
in_root /usr/bin/tagdeflect check --config /tmp/rig.toml >"$work/check.log" 2>&1; check "tagdeflect check on the installed config" $? "$(grep -c 'reproj' "$work/check.log") tags/cameras reported"
in_root /usr/bin/tagdeflect run --config /tmp/rig.toml --duration-s 12 >"$work/run.log" 2>&1; st=$?
lines=$(wc -l < "$root/var/lib/tagdeflect/feed.jsonl" 2>/dev/null || echo 0)
last=$(tail -1 "$root/var/lib/tagdeflect/feed.jsonl" 2>/dev/null | grep -o '"net_deflection_mm":[^,]*' || true)
[ "$st" = 0 ] && [ "$lines" -ge 5 ] && [ -n "$last" ]; check "run --config (installed) writes the feed" $? "exit $st, $lines lines, last $last"

# The installed demo serves the live page (port chosen by the kernel, read from its stderr).
in_root /usr/bin/tagdeflect demo --duration-s 30 --http 127.0.0.1:0 >"$work/demo.out" 2>"$work/demo.err" &
demo_pid=$!
url=""
for _ in $(seq 1 300); do
  url=$(grep -o 'http://127\.0\.0\.1:[0-9]*/' "$work/demo.err" | head -1 || true)
  [ -n "$url" ] && break
  kill -0 "$demo_pid" 2>/dev/null || break
  sleep 0.1
done
page=""; status=""
if [ -n "$url" ]; then
  page=$(curl -fsS --retry 5 --retry-connrefused "$url" || true)
  for _ in $(seq 1 100); do
    status=$(curl -fsS "${url}api/status" || true)
    echo "$status" | grep -q '"seq"' && break
    sleep 0.2
  done
fi
echo "$page" | grep -qi "<html"; check "demo serves the live page" $? "$url"
echo "$status" | grep -q '"seq"'; check "demo's /api/status has feed lines" $? "$(echo "$status" | head -c 120)"
kill "$demo_pid" 2>/dev/null || true; wait "$demo_pid" 2>/dev/null || true; demo_pid=""

# Remove keeps the conffile, purge removes it.
in_root apt-get remove -y -q tagdeflect >>"$work/apt.log" 2>&1
[ ! -e "$root/usr/bin/tagdeflect" ] && [ -e "$root/etc/tagdeflect/tagdeflect.toml" ]; check "remove keeps the conffile" $?
in_root dpkg --purge tagdeflect >>"$work/apt.log" 2>&1
[ ! -e "$root/etc/tagdeflect/tagdeflect.toml" ]; check "purge removes it" $?

if [ "$failures" -gt 0 ]; then say "$failures check(s) failed (logs in $work)"; exit 1; fi
say "all checks passed (logs in $work)"
