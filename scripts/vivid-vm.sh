#!/usr/bin/env bash
# V4L2 against the kernel's virtual camera: boots a small VM with Debian's kernel, loads the
# `vivid` driver, runs `tagdeflect run` on its capture node, unplugs the camera (unbinds the
# vivid platform device from its driver, which is what the kernel does when a USB camera is
# pulled) and plugs it back, several times, then stops the daemon with SIGTERM and checks:
#
#   - the daemon kept running and exited 0 on SIGTERM;
#   - it logged each loss and each reopening;
#   - frames were captured before the first unplug and after every replug (the recording's
#     frames.jsonl and the feed), and the recorded images are the driver's picture (not blank);
#   - the capture node's file descriptors and buffer mappings were released while the camera
#     was away and are as many after each replug as before the first unplug (no leak);
#   - the camera came back on the same node (/dev/video0): the old one was fully released.
#
#   scripts/vivid-vm.sh [--bin PATH] [--cycles N] [--tcg] [--keep]
#
#   --bin PATH   the tagdeflect binary (default: $TAGDEFLECT_BIN, else the newest of
#                $CARGO_TARGET_DIR/{release,debug}/tagdeflect and target/{release,debug}/,
#                else `cargo build --release`)
#   --cycles N   unplug/replug cycles (default 3)
#   --fps F      the camera's frame rate (default 5; below 2 fps every frame outlasts one
#                500 ms wait for a buffer)
#   --tcg        software emulation even when /dev/kvm is usable
#   --keep       keep the VM's output folder (default: kept anyway under the work dir)
#
# Needs root (debootstrap, chroot) and network the first time. Installs qemu-system-x86, cpio and
# debootstrap with apt if missing; the kernel (linux-image-amd64's current package) and
# busybox-static are downloaded with `apt-get download` and unpacked into the work dir, never
# installed on the host. The boot loop is scripts/vm-common.sh's (shared with systemd-vm.sh).
# Everything is cached under $VIVID_VM_DIR (default target/vivid-vm):
# the first run takes a few minutes (debootstrap), later runs about 3 minutes (emulated).
# Prints one PASS/FAIL line per check with its figures; exits 1 when a check fails. CI does
# not run it.
set -euo pipefail

repo=$(cd "$(dirname "$0")/.." && pwd)
work=${VIVID_VM_DIR:-$repo/target/vivid-vm}
mirror=${VIVID_VM_MIRROR:-http://deb.debian.org/debian}
bin=${TAGDEFLECT_BIN:-}
cycles=3
fps=5
accel=auto
while [ $# -gt 0 ]; do
  case "$1" in
    --bin) bin=$2; shift 2 ;;
    --cycles) cycles=$2; shift 2 ;;
    --fps) fps=$2; shift 2 ;;
    --tcg) accel=tcg; shift ;;
    --keep) shift ;;
    -h|--help) sed -n '2,34p' "$0"; exit 0 ;;
    *) echo "vivid-vm: unknown argument $1" >&2; exit 2 ;;
  esac
done
case "$cycles" in ''|*[!0-9]*) echo "vivid-vm: --cycles wants a number" >&2; exit 2 ;; esac
case "$fps" in ''|*[!0-9.]*) echo "vivid-vm: --fps wants a number" >&2; exit 2 ;; esac
vm_name=vivid-vm
# shellcheck source=scripts/vm-common.sh
. "$repo/scripts/vm-common.sh"

# The tagdeflect binary to test.
pick_binary() {
  if [ -z "$bin" ]; then
    local c best=""
    for c in "${CARGO_TARGET_DIR:-/nonexistent}/release/tagdeflect" "${CARGO_TARGET_DIR:-/nonexistent}/debug/tagdeflect" \
      "$repo/target/release/tagdeflect" "$repo/target/debug/tagdeflect"; do
      [ -x "$c" ] || continue
      if [ -z "$best" ] || [ "$c" -nt "$best" ]; then best=$c; fi
    done
    if [ -z "$best" ]; then
      say "no tagdeflect binary found: cargo build --release"
      (cd "$repo" && cargo build --release --quiet)
      best="${CARGO_TARGET_DIR:-$repo/target}/release/tagdeflect"
    fi
    bin=$best
  fi
  [ -x "$bin" ] || { say "$bin is not an executable"; exit 2; }
  say "binary: $bin ($(date -r "$bin" -u +%FT%TZ))"
}

# The Debian packages holding the libraries the binary links.
runtime_packages() {
  local lib p
  for lib in $(ldd "$bin" | awk '/=> \//{print $3}'); do
    p=$(dpkg -S "$lib" 2>/dev/null || dpkg -S "$(readlink -f "$lib")" 2>/dev/null || dpkg -S "/usr$lib" 2>/dev/null || true)
    [ -n "$p" ] && echo "${p%%:*}"
  done | sort -u
}

# A minbase root filesystem of the host's suite with the binary's libraries, kmod,
# v4l-utils and the kernel's modules.
make_rootfs() {
  local pkgs want
  pkgs=$(runtime_packages | tr '\n' ' ')
  if [ ! -f "$work/rootfs/.done" ]; then
    say "debootstrap $suite (minbase) into $work/rootfs (a few minutes)"
    rm -rf "$work/rootfs.tmp"
    want=$(echo kmod v4l-utils $pkgs | tr ' ' ',' | sed 's/,$//')
    debootstrap --variant=minbase --include="$want" "$suite" "$work/rootfs.tmp" "$mirror" >"$work/debootstrap.log" 2>&1 ||
      { say "debootstrap failed, see $work/debootstrap.log"; exit 1; }
    mv "$work/rootfs.tmp" "$work/rootfs"
    touch "$work/rootfs/.done"
  fi
  # A binary linking a library the root filesystem lacks: add its package.
  local missing=() p
  for p in kmod v4l-utils $pkgs; do
    chroot "$work/rootfs" dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
  done
  if [ ${#missing[@]} -gt 0 ]; then
    say "adding ${missing[*]} to the root filesystem"
    chroot "$work/rootfs" apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
  fi
  local kv
  kv=$(vm_kver)
  if [ ! -f "$work/rootfs/usr/lib/modules/$kv/modules.dep" ]; then
    say "copying the kernel's modules ($kv) into the root filesystem"
    vm_kernel_modules "$kv" "$work/rootfs"
  fi
}

# The initramfs: busybox and the modules to mount the root filesystem over virtio-9p.
make_initrd() {
  local kv=$1 out="$work/initrd.img"
  [ -f "$out" ] && [ "$out" -nt "$work/rootfs/usr/lib/modules/$kv/modules.dep" ] && return
  say "building the initramfs"
  vm_make_initrd "$out" "$work/rootfs/usr/lib/modules/$kv" "-t 9p -o trans=virtio,version=9p2000.L,msize=524288 rootfs" /vivid-test/init.sh virtio_pci 9pnet_virtio 9p
}

# The test inside the VM (PID 1 of the root filesystem) and its one-camera config.
write_test() {
  local t="$work/rootfs/vivid-test"
  rm -rf "$t"
  mkdir -p "$t/out"
  strip -o "$t/tagdeflect" "$bin" 2>/dev/null || cp "$bin" "$t/tagdeflect"
  cat >"$t/config.toml" <<'EOF'
# One camera: vivid's capture node at 640x480. vivid shows a test pattern, so no tag
# is expected: the feed still gets one line per frame set (with "tags": []).
[world]
up = [0.0, 0.0, 1.0]

[sync]
tolerance_ms = 20.0

[[camera]]
name = "vivid"
source = "v4l2:/dev/video0"
fps = FPS
width = 640
height = 480
fx = 600.0
fy = 600.0
cx = 319.5
cy = 239.5

[background]
family = "tag25h9"
size_mm = 60.0
[[background.tag]]
id = 0
corners_mm = [[-350.0, 100.0, 200.0], [-290.0, 100.0, 200.0], [-290.0, 100.0, 260.0], [-350.0, 100.0, 260.0]]
[[background.tag]]
id = 1
corners_mm = [[290.0, 100.0, 200.0], [350.0, 100.0, 200.0], [350.0, 100.0, 260.0], [290.0, 100.0, 260.0]]
[[background.tag]]
id = 2
corners_mm = [[-30.0, 100.0, 240.0], [30.0, 100.0, 240.0], [30.0, 100.0, 300.0], [-30.0, 100.0, 300.0]]

[specimen]
family = "tag36h11"
size_mm = 30.0
[[specimen.tag]]
id = 0
role = "support"
[[specimen.tag]]
id = 1
role = "midspan"
[[specimen.tag]]
id = 2
role = "support"

[output]
feed = "/vivid-test/out/feed.jsonl"
record_format = "pgm"
EOF
  sed -i "s/^fps = FPS\$/fps = $fps/" "$t/config.toml"
  cat >"$t/init.sh" <<EOF
#!/bin/sh
CYCLES=$cycles
EOF
  cat >>"$t/init.sh" <<'EOF'
# Runs as PID 1 in the VM; everything it finds goes to /vivid-test/out (shared with the host).
export PATH=/usr/sbin:/usr/bin:/sbin:/bin
O=/vivid-test/out
mount -t proc proc /proc
mount -t sysfs sys /sys
mount -t tmpfs tmp /tmp
mount -t tmpfs run /run
finish() { sync; echo "=== vivid-test end ==="; echo o >/proc/sysrq-trigger; sleep 10; }
echo "=== vivid-test start $(uname -r) ==="
now() { date +%s%N; }
ev() { echo "$1 $(now) ${2:-}" >>$O/events; echo "event: $1 ${2:-}"; }
# Capture node and output node only (node_types bit 0 and bit 8), one instance.
if ! modprobe vivid n_devs=1 node_types=0x101; then echo "modprobe vivid failed"; finish; fi
i=0; while [ ! -e /dev/video0 ] && [ $i -lt 50 ]; do sleep 0.1; i=$((i + 1)); done
ls -l /dev/video* >$O/nodes-initial 2>&1
v4l2-ctl -d /dev/video0 --info --list-formats >$O/v4l2-info 2>&1 || true
cat /sys/class/video4linux/video0/name >>$O/v4l2-info 2>&1 || true
PDEV=$(basename "$(readlink -f /sys/class/video4linux/video0/device)")
DRV=/sys/bus/platform/drivers/vivid
echo "platform device: $PDEV" >>$O/v4l2-info

# fds and mappings of the capture node in the daemon (the node may show as "(deleted)").
sample() {
  fd=$(ls -l /proc/$PID/fd 2>/dev/null | grep -c '/dev/video')
  # The fewest of three looks 0.2 s apart: a recorded frame's file is open only while it is
  # written (one look may catch it), a leaked descriptor is there every time.
  fdall=$(for i in 1 2 3; do ls /proc/$PID/fd 2>/dev/null | wc -l; sleep 0.2; done | sort -n | head -1)
  maps=$(grep -c '/dev/video' /proc/$PID/maps 2>/dev/null)
  mapsall=$(wc -l </proc/$PID/maps 2>/dev/null)
  frames=$(nframes)
  ls -l /proc/$PID/fd >$O/fds-$1 2>&1
  grep '/dev/video' /proc/$PID/maps >$O/maps-$1 2>&1
  echo "$1 $(now) video_fds=$fd all_fds=$fdall video_maps=$maps all_maps=$mapsall recorded=$frames" >>$O/samples
  echo "sample: $1 video_fds=$fd video_maps=$maps all_fds=$fdall recorded=$frames"
}
count() { grep -c "$1" $O/daemon.log 2>/dev/null; }
wait_for() { # wait_for PATTERN COUNT SECONDS: until the log has COUNT lines matching PATTERN
  n=0; while [ $n -lt $(($3 * 10)) ]; do
    [ "$(grep -c "$1" $O/daemon.log 2>/dev/null)" -ge "$2" ] && return 0
    sleep 0.1; n=$((n + 1))
  done; return 1
}
nframes() { if [ -f $O/rec/frames.jsonl ]; then wc -l <$O/rec/frames.jsonl; else echo 0; fi; }
wait_frames() { # wait_frames COUNT SECONDS: until the recording has COUNT more frames
  base=$(nframes)
  n=0; while [ $n -lt $(($2 * 10)) ]; do
    [ "$(nframes)" -ge $((base + $1)) ] && return 0
    sleep 0.1; n=$((n + 1))
  done; return 1
}

TAGDEFLECT_LOG=info /vivid-test/tagdeflect run --config /vivid-test/config.toml --record $O/rec 2>$O/daemon.log &
PID=$!
ev started "pid=$PID"
if wait_frames 20 60; then ev streaming; else ev no-frames; fi
sleep 2
sample before
c=1
while [ $c -le $CYCLES ]; do
  n=$(count 'reopening camera=')
  echo "$PDEV" >$DRV/unbind && ev unplug "cycle=$c" || ev unplug-failed "cycle=$c"
  wait_for 'reopening camera=' $((n + 1)) 15 && ev lost-logged "cycle=$c" || ev lost-not-logged "cycle=$c"
  sleep 3
  sample "away$c"
  ls /dev/video* >$O/nodes-away$c 2>&1 || true
  n=$(count 'camera reopened')
  echo "$PDEV" >$DRV/bind && ev replug "cycle=$c" || ev replug-failed "cycle=$c"
  ls -l /dev/video* >$O/nodes-back$c 2>&1 || true
  wait_for 'camera reopened' $((n + 1)) 30 && ev reopened "cycle=$c" || ev not-reopened "cycle=$c"
  wait_frames 15 30 || true
  sample "back$c"
  c=$((c + 1))
done
kill -TERM $PID
ev sigterm
i=0; while kill -0 $PID 2>/dev/null && [ $i -lt 200 ]; do sleep 0.1; i=$((i + 1)); done
if kill -0 $PID 2>/dev/null; then ev no-exit; kill -KILL $PID; fi
wait $PID; ev exited "code=$?"
echo "--- daemon log (last 40 lines) ---"; tail -40 $O/daemon.log
finish
EOF
  chmod +x "$t/init.sh"
}

# Every boot starts with an empty out folder (shared with the guest over 9p).
vm_prepare() {
  rm -rf "$work/rootfs/vivid-test/out"
  mkdir -p "$work/rootfs/vivid-test/out"
}
vm_started="=== vivid-test start"
vm_args=(-m 1024 -append "console=ttyS0 panic=-1 loglevel=4"
  -fsdev "local,id=root,path=$work/rootfs,security_model=passthrough" -device virtio-9p-pci,fsdev=root,mount_tag=rootfs)

vm_install_host_packages qemu-system-x86 debootstrap cpio
pick_binary
vm_fetch_kernel
kv=$(vm_kver)
make_rootfs
make_initrd "$kv"
write_test
start=$(date +%s)
vm_run 600 1200 || say "the VM did not power off by itself"
say "console log: $work/console.log"
say "VM ran $(($(date +%s) - start)) s"
out="$work/rootfs/vivid-test/out"
cp "$work/console.log" "$out/console.log"
python3 "$repo/scripts/vivid-check.py" "$out" "$cycles"
