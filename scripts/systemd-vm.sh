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
#   - `systemctl stop` during the test ends the daemon cleanly (exit status 0, Result=success),
#     `systemctl start` resumes the test (same id), `systemctl restart` too;
#   - the lab user stops the test and copies its folder and report to her home;
#   - `systemd-analyze verify` on the installed unit is clean; the `systemd-analyze security`
#     exposure score is printed.
#
#   scripts/systemd-vm.sh [--deb PATH] [--bin PATH] [--tcg] [--fresh] [--test-s N] [--sim-cameras 1|3]
#
#   --deb PATH   the package to install (default: the newest target/debian/tagdeflect_*.deb,
#                else scripts/package.sh builds one)
#   --bin PATH   package this binary when no package is there (scripts/package.sh --bin)
#   --tcg        software emulation even when /dev/kvm is usable (slow)
#   --fresh      debootstrap the base system again
#   --test-s N   seconds the test runs before and after the restarts (default 20)
#   --sim-cameras 1|3  the installed simulated rig's cameras kept beside vivid (default 1, its
#                centre camera: under software emulation three render and detect too slowly)
#
# Needs root (debootstrap, chroot) and network the first time (deb.debian.org, or
# $SYSTEMD_VM_MIRROR). Installs qemu-system-x86, debootstrap, cpio and e2fsprogs with apt if
# missing; Debian's current kernel and busybox-static are downloaded (`apt-get download`) and
# unpacked into the work dir, never installed on the host. Cached under $SYSTEMD_VM_DIR
# (default target/systemd-vm): the base system (debootstrap minbase with systemd, udev, the
# package's dependencies), the kernel and the initramfs. Every run makes a new ext4 image from
# the base (sparse, 2 GiB apparent) so nothing of a previous run is left in it, boots it with
# KVM (TCG when KVM does not work), and reads the results out of the image after power-off
# (debugfs). Prints PASS/FAIL lines; exits 1 when a check fails, 2 on bad usage.
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
frames_s=240
while [ $# -gt 0 ]; do
  case "$1" in
    --deb) deb=$2; shift 2 ;;
    --bin) bin=$2; shift 2 ;;
    --tcg) accel=tcg; shift ;;
    --fresh) fresh=1; shift ;;
    --test-s) test_s=$2; shift 2 ;;
    --sim-cameras) sim_cameras=$2; shift 2 ;;
    -h|--help) sed -n '2,42p' "$0"; exit 0 ;;
    *) echo "systemd-vm: unknown argument $1" >&2; exit 2 ;;
  esac
done
case "$sim_cameras" in 1|3) ;; *) echo "systemd-vm: --sim-cameras wants 1 or 3" >&2; exit 2 ;; esac
case "$test_s" in ''|*[!0-9]*) echo "systemd-vm: --test-s wants a whole number of seconds" >&2; exit 2 ;; esac
[ "$(id -u)" = 0 ] || { echo "systemd-vm: run as root (debootstrap and chroot need it)" >&2; exit 2; }

say() { echo "systemd-vm: $*" >&2; }
suite=$(. /etc/os-release && echo "${VERSION_CODENAME:-bookworm}")
mkdir -p "$work"
t_begin=$(date +%s)

install_host_packages() {
  local missing=() p
  for p in qemu-system-x86 debootstrap cpio e2fsprogs; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
  done
  if [ ${#missing[@]} -gt 0 ]; then
    say "installing ${missing[*]}"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
  fi
}

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

# Debian's current kernel and busybox-static: the kernel's package kept (its modules are
# unpacked into the base system, a subset), the kernel image and busybox unpacked (not installed).
fetch_kernel() {
  [ -f "$work/kernel/.done" ] && return
  local pkg
  pkg=$(apt-cache depends linux-image-amd64 | awk '/Depends: linux-image-[0-9]/{print $2; exit}')
  [ -n "$pkg" ] || { say "cannot resolve linux-image-amd64 (apt-get update?)"; exit 1; }
  say "downloading $pkg and busybox-static"
  rm -rf "$work/dl" "$work/kernel"
  mkdir -p "$work/dl" "$work/kernel/busybox" "$work/kernel/boot"
  (cd "$work/dl" && apt-get download -qq -o APT::Sandbox::User=root "$pkg" busybox-static)
  dpkg-deb --fsys-tarfile "$work"/dl/linux-image-*.deb | tar -x -C "$work/kernel" ./boot
  dpkg-deb -x "$work"/dl/busybox-static_*.deb "$work/kernel/busybox"
  rm -f "$work"/dl/busybox-static_*.deb
  echo "${pkg#linux-image-}" >"$work/kernel/.done"
}
kver() { cat "$work/kernel/.done"; }

# The kernel's modules the VM needs (virtio, ext4, V4L2 and vivid, crypto, USB cameras' media
# drivers) into the base system: ~90 MB instead of ~400.
install_modules() {
  local kv=$1 base=$2 tmp="$work/modules.tmp"
  rm -rf "$tmp" "$base/usr/lib/modules/$kv"
  mkdir -p "$tmp" "$base/usr/lib/modules/$kv"
  dpkg-deb --fsys-tarfile "$work"/dl/linux-image-*.deb | tar -x -C "$tmp" "./lib/modules/$kv"
  (cd "$tmp/lib/modules/$kv" && tar -cf - modules.order modules.builtin* kernel/arch kernel/crypto kernel/lib kernel/block \
    kernel/mm kernel/fs kernel/drivers/media kernel/drivers/virtio kernel/drivers/block kernel/drivers/char) |
    tar -x -C "$base/usr/lib/modules/$kv"
  rm -rf "$tmp"
  chroot "$base" depmod "$kv"
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
  kv=$(kver)
  if [ ! -f "$base/usr/lib/modules/$kv/modules.dep" ]; then
    say "unpacking the kernel's modules ($kv) into the base system"
    install_modules "$kv" "$base"
  fi
}

# The initramfs: busybox and the modules to mount the ext4 root from a virtio disk, then
# systemd (the root's /sbin/init).
make_initrd() {
  local kv=$1 out="$work/initrd.img" dep="$work/base/usr/lib/modules/$1/modules.dep"
  [ -f "$out" ] && [ "$out" -nt "$dep" ] && return
  say "building the initramfs"
  local d="$work/initrd.tmp" m f line deps i order=()
  rm -rf "$d"
  mkdir -p "$d/bin" "$d/mods" "$d/proc" "$d/sys" "$d/dev" "$d/newroot"
  cp "$work/kernel/busybox/bin/busybox" "$d/bin/busybox"
  for m in virtio_pci virtio_blk crc32c_generic ext4; do
    line=$(grep -E "/$m\.ko(\.[a-z]+)?:" "$dep") || continue
    read -r -a deps <<<"${line#*:}"
    for ((i = ${#deps[@]} - 1; i >= 0; i--)); do order+=("${deps[$i]}"); done
    order+=("${line%%:*}")
  done
  : >"$d/mods/order"
  for f in "${order[@]}"; do
    grep -qx "$(basename "$f")" "$d/mods/order" && continue
    cp "$work/base/usr/lib/modules/$kv/$f" "$d/mods/"
    basename "$f" >>"$d/mods/order"
  done
  cat >"$d/init" <<'EOF'
#!/bin/busybox sh
/bin/busybox mount -t proc proc /proc
/bin/busybox mount -t sysfs sys /sys
/bin/busybox mount -t devtmpfs dev /dev
for pass in 1 2; do
  for m in $(/bin/busybox cat /mods/order); do /bin/busybox insmod /mods/$m 2>/dev/null; done
done
i=0
until /bin/busybox mount -t ext4 -o rw /dev/vda /newroot; do
  i=$((i + 1)); [ $i -lt 50 ] || { echo "initramfs: cannot mount /dev/vda"; /bin/busybox poweroff -f; }
  /bin/busybox sleep 0.2
done
/bin/busybox umount /dev /proc /sys
exec /bin/busybox switch_root /newroot /sbin/init
EOF
  chmod +x "$d/init"
  (cd "$d" && find . | cpio -o -H newc --quiet | gzip -1) >"$out.tmp"
  mv "$out.tmp" "$out"
  rm -rf "$d"
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
  printf 'TEST_S=%s\nSIM_CAMERAS=%s\nFRAMES_S=%s\n' "$test_s" "$sim_cameras" "$frames_s" >"$o/vm-test/params"
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

qpid=""
stop_vm() {
  if [ -n "$qpid" ] && kill -0 "$qpid" 2>/dev/null; then
    kill "$qpid" 2>/dev/null || true
    sleep 1
    kill -9 "$qpid" 2>/dev/null || true
    wait "$qpid" 2>/dev/null || true
  fi
  qpid=""
}
trap stop_vm EXIT INT TERM

# boot_vm SECONDS ACCEL-ARGS...: runs until the VM powers off (or SECONDS pass: killed). With
# $probe_s, gives up (status 3) when the kernel printed nothing by then (nested KVM hangs).
boot_vm() {
  local limit=$1 log="$work/console.log" t=0
  shift
  qemu-system-x86_64 "$@" -smp 2 -m 2048 -nographic -no-reboot -nic none \
    -kernel "$work/kernel/boot/vmlinuz-$kv" -initrd "$work/initrd.img" \
    -append "console=ttyS0 panic=-1 loglevel=6 systemd.show_status=auto" \
    -drive "file=$work/disk.img,if=virtio,format=raw,cache=unsafe" \
    -object rng-random,filename=/dev/urandom,id=rng0 -device virtio-rng-pci,rng=rng0 \
    </dev/null >"$log" 2>&1 &
  qpid=$!
  while kill -0 "$qpid" 2>/dev/null; do
    if [ -n "${probe_s:-}" ] && [ "$t" -ge "$probe_s" ] && ! grep -q "Linux version\|Welcome" "$log"; then
      stop_vm
      return 3
    fi
    if [ "$t" -ge "$limit" ]; then
      say "the VM ran longer than $limit s: killed"
      stop_vm
      return 1
    fi
    sleep 1
    t=$((t + 1))
  done
  wait "$qpid" || true
  qpid=""
}

run_vm() {
  local broken="$work/kvm-unusable"
  if [ "$accel" = auto ] && [ -c /dev/kvm ] && (exec 3<>/dev/kvm) 2>/dev/null && [ "$(cat "$broken" 2>/dev/null)" != "$(uname -r)" ]; then
    say "booting the VM (KVM, 2 vCPUs, 2 GiB)"
    if probe_s=60 boot_vm 900 -enable-kvm -cpu host; then return; fi
    say "KVM: the guest printed nothing within 60 s; noted in $broken, using TCG"
    uname -r >"$broken"
    make_image
  fi
  say "booting the VM (TCG software emulation, 2 vCPUs, 2 GiB; slow)"
  probe_s="" boot_vm 2400 -accel tcg
}

install_host_packages
pick_deb
fetch_kernel
kv=$(kver)
make_base
make_initrd "$kv"
write_overlay
make_image
say "image: $(du -h --apparent-size "$work/disk.img" | cut -f1) apparent, $(du -h "$work/disk.img" | cut -f1) on disk"
t_boot=$(date +%s)
run_vm
say "the VM ran $(($(date +%s) - t_boot)) s (console: $work/console.log)"
rm -rf "$work/out"
debugfs -R "rdump /vm-test/out $work" "$work/disk.img" >/dev/null 2>&1 || true
rm -f "$work/disk.img"
if [ ! -f "$work/out/results" ]; then
  say "no results from the VM; the console's end:"
  tail -40 "$work/console.log" >&2
  exit 1
fi
cat "$work/out/results"
fails=$(grep -c '^FAIL' "$work/out/results" || true)
passes=$(grep -c '^PASS' "$work/out/results" || true)
say "$passes passed, $fails failed; $(($(date +%s) - t_begin)) s in all (logs in $work/out)"
grep -q '^END' "$work/out/results" || { say "the checks did not finish"; exit 1; }
[ "$fails" = 0 ] || exit 1
