#!/usr/bin/env bash
# The Debian package under a booted systemd, with a camera: boots a small Debian VM whose init
# is systemd, installs the package with `apt-get install ./tagdeflect_*.deb` (its postinst runs
# on the booted system), loads the kernel's virtual camera `vivid`, turns the installed
# configuration into a rig with that camera (a fourth camera `vivid` on /dev/video0 beside the
# simulated ones, the simulated UTM, the lab's tests folder and token as docs/operations.md
# says), starts tagdeflect.service under its installed unit (DynamicUser, UMask,
# DevicePolicy=closed with its DeviceAllow) and checks, one PASS/FAIL line each with figures:
#
#   - the postinst made the group `tagdeflect` and the folder /var/lib/tagdeflect-lab (2770);
#   - the service is active (Type=notify) as the dynamic user, and its feed lines carry the
#     vivid camera's frames: DevicePolicy=closed lets a V4L2 camera through;
#   - a lab user in the group (made as the guide says: usermod -aG tagdeflect) starts a test
#     with the CLI and the token file, without sudo; a user not in the group can read neither
#     the token nor the tests, and his start is refused;
#   - DevicePolicy=closed refuses what the unit does not allow: a root shell moved into the
#     unit's cgroup opens /dev/video0 and /dev/null but is refused /dev/vda and /dev/mem (which
#     it opens outside the unit);
#   - the simulated camera's frames join sets beside vivid's (at most 10 % dropped as late);
#   - `systemctl stop` during the test ends the daemon cleanly (exit status 0, Result=success),
#     `systemctl start` resumes the test (same id), `systemctl restart` too;
#   - the lab user stops the test (the report is made at stop), copies its folder and report to
#     her home and runs `tagdeflect report verify` on it;
#   - `systemd-analyze verify` on the installed unit is clean; the `systemd-analyze security`
#     exposure score is printed.
#
# Fitted to software emulation (TCG renders 20-50x slower than the host): the simulated rig
# beside vivid is cut to one camera at 1 fps without its optical blur. A simulated frame is
# stamped when due and handed over once rendered; rendered slower than the wait for a set's
# missing cameras (a frame period of the fastest camera), it comes after vivid's newer set has
# closed and is dropped as late, as the frame-set contract says (crates/io/src/sync.rs). The
# checks first run the previous settings (2 fps, blur) for --control-s seconds as a control
# and print both settings' render times and the simulated frames' age at arrival.
#
#   scripts/systemd-vm.sh [--deb PATH] [--bin PATH] [--tcg] [--fresh] [--test-s N] [--sim-cameras 1|3]
#                         [--sim-fps N] [--control-s N]
#
#   --deb PATH   the package to install (default: the newest target/debian/tagdeflect_*.deb,
#                else scripts/package.sh builds one)
#   --bin PATH   package this binary when no package is there (scripts/package.sh --bin)
#   --tcg        software emulation even when /dev/kvm is usable (slow)
#   --fresh      debootstrap the base system again
#   --test-s N   seconds the test runs before and after the restarts (default 20)
#   --sim-cameras 1|3  the installed simulated rig's cameras kept beside vivid (default 1, its
#                centre camera: under software emulation three render and detect too slowly)
#   --sim-fps N  the simulated camera's frame rate (default 1; vivid runs at 1 fps)
#   --control-s N  seconds of the control run with the previous settings (default 60; 0: none)
#
# Needs root (debootstrap, chroot) and network the first time (deb.debian.org, or
# $SYSTEMD_VM_MIRROR). Installs qemu-system-x86, debootstrap, cpio and e2fsprogs with apt if
# missing; Debian's current kernel and busybox-static are downloaded (`apt-get download`) and
# unpacked into the work dir, never installed on the host. Cached under $SYSTEMD_VM_DIR
# (default target/systemd-vm): the base system (debootstrap minbase with systemd, udev, the
# package's dependencies), the kernel and the initramfs. Every run makes a new ext4 image from
# the base (sparse, 2 GiB apparent) so nothing of a previous run is left in it, boots it with
# KVM (TCG when KVM does not work), and reads the results out of the image after power-off
# (debugfs; kept with the console log in $SYSTEMD_VM_DIR/runs/TIME). Prints PASS/FAIL lines;
# exits 1 when a check fails, 2 on bad usage. The boot loop is scripts/vm-common.sh's.
# CI does not run it: it needs root, network and a VM (docs/operations.md, "Checked on a booted
# systemd").
set -euo pipefail

repo=$(cd "$(dirname "$0")/.." && pwd)
work=${SYSTEMD_VM_DIR:-$repo/target/systemd-vm}
mirror=${SYSTEMD_VM_MIRROR:-http://deb.debian.org/debian}
deb=""
bin=""
accel=auto
fresh=0
test_s=20
sim_cameras=1
sim_fps=1
control_s=60
frames_s=240
while [ $# -gt 0 ]; do
  case "$1" in
    --deb) deb=$2; shift 2 ;;
    --bin) bin=$2; shift 2 ;;
    --tcg) accel=tcg; shift ;;
    --fresh) fresh=1; shift ;;
    --test-s) test_s=$2; shift 2 ;;
    --sim-cameras) sim_cameras=$2; shift 2 ;;
    --sim-fps) sim_fps=$2; shift 2 ;;
    --control-s) control_s=$2; shift 2 ;;
    -h|--help) sed -n '2,60p' "$0"; exit 0 ;;
    *) echo "systemd-vm: unknown argument $1" >&2; exit 2 ;;
  esac
done
case "$sim_cameras" in 1|3) ;; *) echo "systemd-vm: --sim-cameras wants 1 or 3" >&2; exit 2 ;; esac
case "$test_s" in ''|*[!0-9]*) echo "systemd-vm: --test-s wants a whole number of seconds" >&2; exit 2 ;; esac
case "$sim_fps" in ''|*[!0-9]*|0) echo "systemd-vm: --sim-fps wants a whole number of frames a second" >&2; exit 2 ;; esac
case "$control_s" in ''|*[!0-9]*) echo "systemd-vm: --control-s wants a whole number of seconds" >&2; exit 2 ;; esac
vm_name=systemd-vm
# shellcheck source=scripts/vm-common.sh
. "$repo/scripts/vm-common.sh"
t_begin=$(date +%s)

pick_deb() {
  if [ -z "$deb" ]; then
    deb=$(ls -t "$repo"/target/debian/tagdeflect_*.deb 2>/dev/null | head -1 || true)
    if [ -z "$deb" ]; then
      say "no package in target/debian: scripts/package.sh ${bin:+--bin $bin}"
      deb=$("$repo/scripts/package.sh" ${bin:+--bin "$bin"} | tail -1)
    fi
  fi
  [ -f "$deb" ] || { say "no package at $deb"; exit 2; }
  say "package: $deb ($(du -h "$deb" | cut -f1), $(date -r "$deb" -u +%FT%TZ))"
}

# The package's Depends as package names (alternatives: the first).
deb_depends() {
  dpkg-deb -f "$deb" Depends | tr ',' '\n' | sed -e 's/|.*//' -e 's/(.*)//' -e 's/[[:space:]]//g' | grep -v '^$'
}

# The base system: minbase with systemd as init, udev (the camera node's group), the NSS
# module DynamicUser needs, kmod and v4l-utils, and the package's dependencies (so that
# `apt-get install ./x.deb` in the VM, which has no network, finds them installed).
make_base() {
  local base="$work/base" pkgs missing=() p kv
  if [ "$fresh" = 1 ] || [ ! -f "$base/.done" ]; then
    rm -rf "$base" "$base.tmp"
    say "debootstrap $suite (minbase, systemd) into $base (a few minutes)"
    local t0
    t0=$(date +%s)
    debootstrap --variant=minbase --include=systemd,systemd-sysv,udev,dbus,libnss-systemd,kmod,v4l-utils \
      "$suite" "$base.tmp" "$mirror" >"$work/debootstrap.log" 2>&1 || { tail -20 "$work/debootstrap.log" >&2; exit 1; }
    mv "$base.tmp" "$base"
    touch "$base/.done"
    say "debootstrap took $(($(date +%s) - t0)) s"
  fi
  pkgs=$(deb_depends)
  for p in $pkgs; do
    chroot "$base" dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
  done
  if [ ${#missing[@]} -gt 0 ]; then
    say "adding the package's dependencies ${missing[*]}"
    cp /etc/resolv.conf "$base/etc/resolv.conf"
    chroot "$base" env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}" >"$work/deps.log" 2>&1 ||
      { tail -20 "$work/deps.log" >&2; exit 1; }
    chroot "$base" apt-get clean
  fi
  kv=$(vm_kver)
  if [ ! -f "$base/usr/lib/modules/$kv/modules.dep" ]; then
    # The modules the VM needs (virtio, ext4, V4L2 and vivid, crypto, USB cameras' media
    # drivers): ~90 MB instead of ~400.
    say "unpacking the kernel's modules ($kv) into the base system"
    vm_kernel_modules "$kv" "$base" kernel/arch kernel/crypto kernel/lib kernel/block kernel/mm kernel/fs \
      kernel/drivers/media kernel/drivers/virtio kernel/drivers/block kernel/drivers/char
  fi
}

# The initramfs: busybox and the modules to mount the ext4 root from a virtio disk, then
# systemd (the root's /sbin/init).
make_initrd() {
  local kv=$1 out="$work/initrd.img" dep="$work/base/usr/lib/modules/$1/modules.dep"
  [ -f "$out" ] && [ "$out" -nt "$dep" ] && return
  say "building the initramfs"
  vm_make_initrd "$out" "$work/base/usr/lib/modules/$kv" "-t ext4 -o rw /dev/vda" /sbin/init virtio_pci virtio_blk crc32c_generic ext4
}

# The run's files in the image: the package, the checks (a unit started once the system is
# up, powering off after), fstab, hostname.
write_overlay() {
  local o="$work/overlay"
  rm -rf "$o"
  mkdir -p "$o/vm-test/out" "$o/etc/systemd/system/multi-user.target.wants"
  cp "$deb" "$o/vm-test/"
  cp "$repo/scripts/systemd-vm-checks.sh" "$o/vm-test/checks.sh"
  chmod 0755 "$o/vm-test/checks.sh"
  printf 'TEST_S=%s\nSIM_CAMERAS=%s\nFRAMES_S=%s\nSIM_FPS=%s\nCONTROL_S=%s\n' "$test_s" "$sim_cameras" "$frames_s" "$sim_fps" "$control_s" \
    >"$o/vm-test/params"
  printf '/dev/vda / ext4 rw,errors=remount-ro 0 0\n' >"$o/etc/fstab"
  echo tagdeflect-vm >"$o/etc/hostname"
  cat >"$o/etc/systemd/system/vm-checks.service" <<'EOF'
[Unit]
Description=tagdeflect package checks under a booted systemd
After=multi-user.target
[Service]
Type=simple
ExecStart=/vm-test/checks.sh
StandardOutput=journal+console
StandardError=journal+console
ExecStopPost=/bin/systemctl poweroff --no-block
[Install]
WantedBy=multi-user.target
EOF
  ln -s /etc/systemd/system/vm-checks.service "$o/etc/systemd/system/multi-user.target.wants/vm-checks.service"
}

# A new ext4 image of the base and the overlay (mke2fs -d: no loop device, no mount).
make_image() {
  local img="$work/disk.img" tree="$work/tree"
  rm -f "$img"
  rm -rf "$tree"
  say "making the disk image (base $(du -sh "$work/base" | cut -f1))"
  cp -a --reflink=auto "$work/base" "$tree"
  rm -f "$tree/.done" "$tree/etc/machine-id"
  : >"$tree/etc/machine-id"
  cp -a "$work/overlay/." "$tree/"
  truncate -s 2G "$img"
  mkfs.ext4 -q -F -L root -d "$tree" "$img"
  rm -rf "$tree"
}

# Every boot gets a new image (a guest that hung under KVM may have written to the last one).
vm_prepare() {
  make_image
  say "image: $(du -h --apparent-size "$work/disk.img" | cut -f1) apparent, $(du -h "$work/disk.img" | cut -f1) on disk"
}
vm_started="Linux version\|Welcome"
vm_install_host_packages qemu-system-x86 debootstrap cpio e2fsprogs
pick_deb
vm_fetch_kernel
kv=$(vm_kver)
make_base
make_initrd "$kv"
write_overlay
vm_args=(-m 2048 -append "console=ttyS0 panic=-1 loglevel=6 systemd.show_status=auto"
  -drive "file=$work/disk.img,if=virtio,format=raw,cache=unsafe"
  -object rng-random,filename=/dev/urandom,id=rng0 -device virtio-rng-pci,rng=rng0)
t_boot=$(date +%s)
vm_run 900 2400 || say "the VM did not power off by itself"
say "the VM ran $(($(date +%s) - t_boot)) s (console: $work/console.log)"
rm -rf "$work/out"
debugfs -R "rdump /vm-test/out $work" "$work/disk.img" >/dev/null 2>&1 || true
rm -f "$work/disk.img"
cp "$work/console.log" "$work/out/" 2>/dev/null || true
run_dir="$work/runs/$(date -u +%Y%m%dT%H%M%SZ)"
mkdir -p "$work/runs" && cp -a "$work/out" "$run_dir" 2>/dev/null || true
if [ ! -f "$work/out/results" ]; then
  say "no results from the VM; the console's end:"
  tail -40 "$work/console.log" >&2
  exit 1
fi
cat "$work/out/results"
fails=$(grep -c '^FAIL' "$work/out/results" || true)
passes=$(grep -c '^PASS' "$work/out/results" || true)
say "$passes passed, $fails failed; $(($(date +%s) - t_begin)) s in all (logs in $run_dir)"
grep -q '^END' "$work/out/results" || { say "the checks did not finish"; exit 1; }
[ "$fails" = 0 ] || exit 1
