#!/usr/bin/env bash
# Installs what tagdeflect needs to build and test on Debian (idempotent, quiet when
# everything is already there): the C libraries of the -sys crates, Aravis's fake GigE
# camera, systemd-analyze, and a Python venv with pymodbus (the real Modbus peer of the
# tests). Run as root or with sudo available.
set -euo pipefail
cd "$(dirname "$0")/.."

pkgs=(pkg-config libclang-dev clang libaravis-dev aravis-tools libusb-1.0-0-dev systemd python3 python3-venv
  mosquitto postgresql)  # the MQTT broker and the database of the archive tests (started by the tests)
# The live page's browser test: Debian's Chromium and its WebDriver (driven by selenium).
pkgs+=(chromium chromium-driver)
# The test report: a TrueType font for the plots' text (PNG).
pkgs+=(fonts-dejavu-core)
# The Debian package (scripts/package.sh: dpkg-deb, dpkg-shlibdeps, strip) and its install test
# in a fresh Debian (scripts/debian-install-test.sh: debootstrap; curl reads the live page).
pkgs+=(dpkg-dev binutils debootstrap curl)
# The report printed to PDF by headless Chromium, and its pages looked at (pdftoppm).
pkgs+=(poppler-utils)
# The suite run again and again on a loaded machine (scripts/stress-suite.sh: stress --cpu 2).
pkgs+=(stress)
missing=()
for p in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
# A python3 outside Debian's packages (e.g. pyenv) is fine: only ask apt for it if none runs.
if command -v python3 >/dev/null 2>&1 && python3 -c 'import venv, ensurepip' >/dev/null 2>&1; then
  missing=("${missing[@]/python3}"); missing=("${missing[@]/python3-venv}")
fi
missing=($(printf '%s\n' "${missing[@]}" | sed '/^$/d'))
if [ ${#missing[@]} -gt 0 ]; then
  SUDO=""; [ "$(id -u)" = 0 ] || SUDO="sudo"
  echo "setup: installing ${missing[*]}" >&2
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${missing[@]}" >/dev/null
fi

venv=target/test-venv
if [ ! -x "$venv/bin/python" ] || ! "$venv/bin/python" -c 'import pymodbus' >/dev/null 2>&1; then
  echo "setup: creating $venv with pymodbus" >&2
  python3 -m venv "$venv"
  "$venv/bin/python" -m pip install --quiet --disable-pip-version-check 'pymodbus>=3.16,<3.17'
fi
# The live page's tests: selenium (drives Debian's chromium-driver) and the Prometheus
# text parser of the official Python client; matplotlib for scripts/plot_control_loop.py.
if ! "$venv/bin/python" -c 'import selenium, prometheus_client, matplotlib' >/dev/null 2>&1; then
  echo "setup: adding selenium, prometheus_client and matplotlib to $venv" >&2
  "$venv/bin/python" -m pip install --quiet --disable-pip-version-check 'selenium>=4.10,<5' 'prometheus_client>=0.17' 'matplotlib>=3.6,<4'
fi
