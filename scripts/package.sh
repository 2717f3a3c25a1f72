#!/usr/bin/env bash
# Builds the Debian package target/debian/tagdeflect_<version>_<arch>.deb with dpkg-deb:
#
#   /usr/bin/tagdeflect                         the binary (stripped)
#   /lib/systemd/system/tagdeflect.service      the unit of systemd/ (ExecStart=/usr/bin/tagdeflect)
#   /etc/tagdeflect/tagdeflect.toml             config/tagdeflect.toml, a conffile: the simulated
#                                               rig, so `systemctl start tagdeflect` shows the
#                                               live page at once (its comments say what to
#                                               change for real cameras)
#   /usr/share/man/man1/tagdeflect*.1.gz        man pages  } generated from the command line
#   bash, zsh and fish completions              } (`tagdeflect assets`: clap_mangen, clap_complete)
#   /usr/share/doc/tagdeflect/                  README, CHANGELOG, docs/, example configs, copyright
#
# Runtime dependencies are computed by dpkg-shlibdeps from the binary's shared libraries (not
# listed by hand), plus a font for the report's plots (fonts-dejavu-core, or Liberation or
# Noto). The service is not enabled or started on install (postinst only reloads systemd);
# removing the package stops it.
#
#   scripts/package.sh [--bin PATH] [--out DIR]
#
#   --bin PATH   package this binary (default: cargo build --release, then
#                $CARGO_TARGET_DIR/release/tagdeflect, or target/release/tagdeflect)
#   --out DIR    where the .deb goes (default: target/debian)
#
# Needs dpkg-deb, dpkg-shlibdeps (dpkg-dev) and binutils (strip); scripts/setup.sh installs
# them. Prints the path of the package.
set -euo pipefail

repo=$(cd "$(dirname "$0")/.." && pwd)
bin=""
out="$repo/target/debian"
while [ $# -gt 0 ]; do
  case "$1" in
    --bin) bin=$2; shift 2 ;;
    --out) out=$2; shift 2 ;;
    -h|--help) sed -n '2,26p' "$0"; exit 0 ;;
    *) echo "package: unknown argument $1" >&2; exit 2 ;;
  esac
done
for t in dpkg-deb dpkg-shlibdeps strip gzip; do
  command -v "$t" >/dev/null || { echo "package: $t not found (scripts/setup.sh installs it)" >&2; exit 2; }
done

if [ -z "$bin" ]; then
  (cd "$repo" && nice -n 10 cargo build --release --locked --bin tagdeflect)
  bin="${CARGO_TARGET_DIR:-$repo/target}/release/tagdeflect"
fi
[ -x "$bin" ] || { echo "package: no executable at $bin" >&2; exit 2; }

version=$(sed -n 's/^version *= *"\(.*\)"/\1/p' "$repo/Cargo.toml" | head -1)
[ -n "$version" ] || { echo "package: no version in Cargo.toml" >&2; exit 2; }
arch=$(dpkg --print-architecture)
work=$(mktemp -d "${TMPDIR:-/tmp}/tagdeflect-deb.XXXXXX")
trap 'rm -rf "$work"' EXIT
root="$work/root"
doc="$root/usr/share/doc/tagdeflect"
mkdir -p "$root/DEBIAN" "$root/usr/bin" "$root/lib/systemd/system" "$root/etc/tagdeflect" "$doc/docs" "$doc/examples" \
  "$root/usr/share/man/man1" "$root/usr/share/bash-completion/completions" "$root/usr/share/zsh/vendor-completions" \
  "$root/usr/share/fish/vendor_completions.d"

# The binary.
install -m 0755 "$bin" "$root/usr/bin/tagdeflect"
strip --strip-unneeded "$root/usr/bin/tagdeflect"

# The unit: the installed binary's path, and install notes for the package.
sed -e 's|/usr/local/bin/tagdeflect|/usr/bin/tagdeflect|g' \
    -e '/^# Install:$/,/^#   systemctl daemon-reload/c\# Installed by the tagdeflect package (not enabled, not started):\n#   systemctl enable --now tagdeflect' \
    "$repo/systemd/tagdeflect.service" > "$root/lib/systemd/system/tagdeflect.service"
chmod 0644 "$root/lib/systemd/system/tagdeflect.service"
# The lab's group and folder (the unit's SupplementaryGroups=tagdeflect, ReadWritePaths=).
install -D -m 0644 "$repo/systemd/tagdeflect.sysusers" "$root/usr/lib/sysusers.d/tagdeflect.conf"
install -D -m 0644 "$repo/systemd/tagdeflect.tmpfiles" "$root/usr/lib/tmpfiles.d/tagdeflect.conf"
grep -q '^ExecStart=/usr/bin/tagdeflect run --config /etc/tagdeflect/tagdeflect.toml$' "$root/lib/systemd/system/tagdeflect.service" \
  || { echo "package: the unit's ExecStart is not as expected" >&2; exit 1; }

# The configuration (a conffile).
install -m 0644 "$repo/config/tagdeflect.toml" "$root/etc/tagdeflect/tagdeflect.toml"
echo /etc/tagdeflect/tagdeflect.toml > "$root/DEBIAN/conffiles"

# Man pages and completions, from the command line itself.
"$root/usr/bin/tagdeflect" assets --out "$work/assets"
for m in "$work"/assets/man/*.1; do gzip -9n -c "$m" > "$root/usr/share/man/man1/$(basename "$m").gz"; done
install -m 0644 "$work/assets/completions/tagdeflect.bash" "$root/usr/share/bash-completion/completions/tagdeflect"
install -m 0644 "$work/assets/completions/_tagdeflect" "$root/usr/share/zsh/vendor-completions/_tagdeflect"
install -m 0644 "$work/assets/completions/tagdeflect.fish" "$root/usr/share/fish/vendor_completions.d/tagdeflect.fish"

# Docs.
install -m 0644 "$repo/README.md" "$doc/README.md"
install -m 0644 "$repo/CHANGELOG.md" "$doc/CHANGELOG.md"
install -m 0644 "$repo"/docs/*.md "$repo"/docs/*.png "$doc/docs/"
install -m 0644 "$repo"/config/*.toml "$doc/examples/"
cat > "$doc/copyright" <<COPY
Format: https://www.debian.org/doc/packaging-manuals/copyright-format/1.0/
Upstream-Name: tagdeflect

Files: *
License: $(sed -n 's/^license *= *"\(.*\)"/\1/p' "$repo/Cargo.toml" | head -1)
COPY
printf 'tagdeflect (%s) unstable; urgency=medium\n\n  * Package of tagdeflect %s.\n\n -- tagdeflect <tagdeflect@localhost>  %s\n' \
  "$version" "$version" "$(date -R -u -d @"${SOURCE_DATE_EPOCH:-$(git -C "$repo" log -1 --format=%ct 2>/dev/null || date +%s)}")" \
  | gzip -9n > "$doc/changelog.Debian.gz"

# Runtime dependencies from the shared libraries the binary links.
mkdir -p "$work/shlibs/debian"
printf 'Source: tagdeflect\n\nPackage: tagdeflect\nArchitecture: any\n' > "$work/shlibs/debian/control"
depends=$(cd "$work/shlibs" && dpkg-shlibdeps -O "$root/usr/bin/tagdeflect" 2>/dev/null | sed -n 's/^shlibs:Depends=//p')
[ -n "$depends" ] || { echo "package: dpkg-shlibdeps found no dependencies" >&2; exit 1; }
# And a font for the report's plots, which the binary reads from a file, not a library
# (crates/report's FONT_PATHS: DejaVu Sans, else Liberation Sans or Noto Sans): without
# one, no report is made at a test's stop.
depends="$depends, fonts-dejavu-core | fonts-liberation | fonts-noto-core"

# Maintainer scripts: reload systemd, never start; stop on removal.
cat > "$root/DEBIAN/postinst" <<'SH'
#!/bin/sh
set -e
# The lab's group and folder before the unit can start (it names the group).
systemd-sysusers tagdeflect.conf >/dev/null 2>&1 || getent group tagdeflect >/dev/null || addgroup --system tagdeflect >/dev/null
systemd-tmpfiles --create tagdeflect.conf >/dev/null 2>&1 || true
if [ -d /run/systemd/system ]; then
  systemctl daemon-reload >/dev/null 2>&1 || true
fi
if [ "$1" = configure ] && [ -z "$2" ]; then
  echo "tagdeflect: installed (the service is not started). The configuration /etc/tagdeflect/tagdeflect.toml"
  echo "  is the simulated rig: 'systemctl start tagdeflect' serves the live page on http://127.0.0.1:8080/."
fi
exit 0
SH
cat > "$root/DEBIAN/prerm" <<'SH'
#!/bin/sh
set -e
if [ "$1" = remove ] && [ -d /run/systemd/system ]; then
  systemctl stop tagdeflect.service >/dev/null 2>&1 || true
  systemctl disable tagdeflect.service >/dev/null 2>&1 || true
fi
exit 0
SH
cat > "$root/DEBIAN/postrm" <<'SH'
#!/bin/sh
set -e
if [ -d /run/systemd/system ]; then
  systemctl daemon-reload >/dev/null 2>&1 || true
fi
exit 0
SH
chmod 0755 "$root/DEBIAN/postinst" "$root/DEBIAN/prerm" "$root/DEBIAN/postrm"

size=$(du -sk --exclude=DEBIAN "$root" | cut -f1)
cat > "$root/DEBIAN/control" <<CTRL
Package: tagdeflect
Version: $version
Architecture: $arch
Maintainer: tagdeflect <tagdeflect@localhost>
Installed-Size: $size
Depends: $depends
Recommends: systemd
Section: science
Priority: optional
Homepage: https://github.com/tagdeflect/tagdeflect
Description: non-contact beam deflection measurement with AprilTags
 tagdeflect measures the deflection of a beam in a four-point bending test
 from AprilTags seen by one to three calibrated cameras (V4L2, GigE/USB3
 Vision), reads the testing machine's load over Modbus TCP, and streams
 deflection with load as JSON lines, with a live page, virtual gauges and a
 test report. Installed with a simulated rig as its configuration.
CTRL

mkdir -p "$out"
deb="$out/tagdeflect_${version}_${arch}.deb"
dpkg-deb --root-owner-group -Zxz --build "$root" "$deb" >/dev/null
echo "$deb"
