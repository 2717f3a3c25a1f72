# The boot loop scripts/systemd-vm.sh and scripts/vivid-vm.sh share: host tools, Debian's
# kernel and busybox, the initramfs's modules, and one VM booted with KVM when it works (else
# software emulation) until it powers off. Sourced, not run. The sourcing script sets:
#
#   work        its cache and work folder (the kernel, the initramfs, the console log)
#   vm_name     the prefix of its messages
#   accel       auto or tcg (--tcg)
#   vm_started  a pattern the console shows once the guest runs (the KVM probe)
#   vm_args     its own qemu arguments (memory, the root disk, the kernel's command line)
#
# On sourcing: exits 2 unless root; sets $suite (the host's Debian suite), makes $work, and
# defines say. The script may define vm_prepare, run before every boot (a fresh disk image,
# an empty out folder).
# Never leaves qemu running: vm_stop is trapped on EXIT, INT and TERM.

vm_say() { echo "$vm_name: $*" >&2; }
say() { vm_say "$@"; }
[ "$(id -u)" = 0 ] || { vm_say "run as root (debootstrap and chroot need it)"; exit 2; }
suite=$(. /etc/os-release && echo "${VERSION_CODENAME:-bookworm}")
mkdir -p "$work"

# vm_install_host_packages PKG...: the host tools, with apt when missing (quiet when present).
vm_install_host_packages() {
  local missing=() p
  for p in "$@"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
  done
  if [ ${#missing[@]} -gt 0 ]; then
    vm_say "installing ${missing[*]}"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
  fi
}

# vm_fetch_kernel: Debian's current kernel package (kept in $work/dl for its modules) with its
# image unpacked into $work/kernel/boot, and busybox-static unpacked into $work/kernel/busybox;
# never installed on the host. The kernel's version goes into $work/kernel/.done.
vm_fetch_kernel() {
  [ -f "$work/kernel/.done" ] && [ -n "$(ls "$work"/dl/linux-image-*.deb 2>/dev/null)" ] && return
  local pkg
  pkg=$(apt-cache depends linux-image-amd64 | awk '/Depends: linux-image-[0-9]/{print $2; exit}')
  [ -n "$pkg" ] || { vm_say "cannot resolve linux-image-amd64 (apt-get update?)"; exit 1; }
  vm_say "downloading $pkg and busybox-static"
  rm -rf "$work/dl" "$work/kernel"
  mkdir -p "$work/dl" "$work/kernel/busybox" "$work/kernel/boot"
  (cd "$work/dl" && apt-get download -qq -o APT::Sandbox::User=root "$pkg" busybox-static)
  dpkg-deb --fsys-tarfile "$work"/dl/linux-image-*.deb | tar -x -C "$work/kernel" ./boot
  dpkg-deb -x "$work"/dl/busybox-static_*.deb "$work/kernel/busybox"
  rm -f "$work"/dl/busybox-static_*.deb
  echo "${pkg#linux-image-}" >"$work/kernel/.done"
}
vm_kver() { sed 's/^linux-image-//' "$work/kernel/.done"; }

# vm_kernel_modules KVER ROOT [DIR...]: the kernel's modules (all, or only those under the
# given folders of lib/modules/KVER) into ROOT/usr/lib/modules/KVER, then depmod.
vm_kernel_modules() {
  local kv=$1 root=$2 tmp="$work/modules.tmp"
  shift 2
  rm -rf "$tmp" "$root/usr/lib/modules/$kv"
  mkdir -p "$tmp" "$root/usr/lib/modules/$kv"
  dpkg-deb --fsys-tarfile "$work"/dl/linux-image-*.deb | tar -x -C "$tmp" "./lib/modules/$kv"
  if [ $# -gt 0 ]; then
    (cd "$tmp/lib/modules/$kv" && tar -cf - modules.order modules.builtin* "$@") | tar -x -C "$root/usr/lib/modules/$kv"
  else
    cp -a "$tmp/lib/modules/$kv/." "$root/usr/lib/modules/$kv/"
  fi
  rm -rf "$tmp"
  chroot "$root" depmod "$kv"
}

# vm_initrd_modules MODULES_DIR DEST MODULE...: the modules and what they depend on (from
# MODULES_DIR/modules.dep) into DEST/mods, their load order in DEST/mods/order.
vm_initrd_modules() {
  local mdir=$1 dest=$2 m f line deps i order=()
  shift 2
  mkdir -p "$dest/mods"
  for m in "$@"; do
    # modules.dep: "path: dep1 dep2 ..." — the dependencies (last first), then the module.
    line=$(grep -E "/$m\.ko(\.[a-z]+)?:" "$mdir/modules.dep") || continue
    read -r -a deps <<<"${line#*:}"
    for ((i = ${#deps[@]} - 1; i >= 0; i--)); do order+=("${deps[$i]}"); done
    order+=("${line%%:*}")
  done
  : >"$dest/mods/order"
  for f in "${order[@]}"; do
    grep -qx "$(basename "$f")" "$dest/mods/order" && continue
    cp "$mdir/$f" "$dest/mods/"
    basename "$f" >>"$dest/mods/order"
  done
}

# vm_make_initrd OUT MODULES_DIR MOUNT INIT MODULE...: an initramfs at OUT of busybox and the
# modules (with what they depend on) that mounts the root with `mount MOUNT /newroot`
# (retried for 10 s), moves /dev into it and switches to INIT there.
vm_make_initrd() {
  local out=$1 mdir=$2 mnt=$3 init=$4 d="$work/initrd.tmp"
  shift 4
  rm -rf "$d"
  mkdir -p "$d/bin" "$d/proc" "$d/sys" "$d/dev" "$d/newroot"
  cp "$work/kernel/busybox/bin/busybox" "$d/bin/busybox"
  vm_initrd_modules "$mdir" "$d" "$@"
  cat >"$d/init" <<EOF
#!/bin/busybox sh
/bin/busybox mount -t proc proc /proc
/bin/busybox mount -t sysfs sys /sys
/bin/busybox mount -t devtmpfs dev /dev
# Modules in dependency order; a second pass for any that raced their dependency.
for pass in 1 2; do
  for m in \$(/bin/busybox cat /mods/order); do /bin/busybox insmod /mods/\$m 2>/dev/null; done
done
i=0
until /bin/busybox mount $mnt /newroot; do
  i=\$((i + 1)); [ \$i -lt 50 ] || { echo "initramfs: cannot mount the root ($mnt)"; /bin/busybox poweroff -f; }
  /bin/busybox sleep 0.2
done
/bin/busybox mount --move /dev /newroot/dev
/bin/busybox umount /proc /sys
exec /bin/busybox switch_root /newroot $init
EOF
  chmod +x "$d/init"
  (cd "$d" && find . | cpio -o -H newc --quiet | gzip -1) >"$out.tmp"
  mv "$out.tmp" "$out"
  rm -rf "$d"
}

vm_qpid=""
vm_stop() {
  if [ -n "$vm_qpid" ] && kill -0 "$vm_qpid" 2>/dev/null; then
    kill "$vm_qpid" 2>/dev/null || true
    sleep 1
    kill -9 "$vm_qpid" 2>/dev/null || true
    wait "$vm_qpid" 2>/dev/null || true
  fi
  vm_qpid=""
}
trap vm_stop EXIT INT TERM

# vm_boot SECONDS ACCEL-ARGS...: runs the VM until it powers off (or SECONDS pass: killed,
# status 1). With $probe_s, gives up (status 3) when the console has not shown $vm_started
# by then (nested KVM may hang before the kernel prints anything).
vm_boot() {
  local limit=$1 log="$work/console.log" t=0
  shift
  qemu-system-x86_64 "$@" -smp 2 -nographic -no-reboot -nic none \
    -kernel "$work/kernel/boot/vmlinuz-$(vm_kver)" -initrd "$work/initrd.img" "${vm_args[@]}" </dev/null >"$log" 2>&1 &
  vm_qpid=$!
  while kill -0 "$vm_qpid" 2>/dev/null; do
    if [ -n "${probe_s:-}" ] && [ "$t" -ge "$probe_s" ] && ! grep -q "$vm_started" "$log"; then
      vm_stop
      return 3
    fi
    if [ "$t" -ge "$limit" ]; then
      vm_say "the VM ran longer than $limit s: killed"
      vm_stop
      return 1
    fi
    sleep 1
    t=$((t + 1))
  done
  wait "$vm_qpid" || true
  vm_qpid=""
}

# vm_run KVM_SECONDS TCG_SECONDS: KVM when /dev/kvm works for this host kernel (a guest that
# shows nothing within 60 s is noted in $work/kvm-unusable, per host kernel, and not tried
# again), else — and with accel=tcg — software emulation (slow).
vm_run() {
  local broken="$work/kvm-unusable"
  if [ "$accel" = auto ] && [ -c /dev/kvm ] && (exec 3<>/dev/kvm) 2>/dev/null && [ "$(cat "$broken" 2>/dev/null)" != "$(uname -r)" ]; then
    vm_say "booting the VM (KVM, 2 vCPUs)"
    if declare -F vm_prepare >/dev/null; then vm_prepare; fi
    if probe_s=60 vm_boot "$1" -enable-kvm -cpu host; then return; fi
    vm_say "KVM: the guest showed nothing within 60 s (nested KVM?); noted in $broken, using TCG"
    uname -r >"$broken"
  fi
  vm_say "booting the VM (TCG software emulation, 2 vCPUs; slow)"
  if declare -F vm_prepare >/dev/null; then vm_prepare; fi
  probe_s="" vm_boot "$2" -accel tcg
}
