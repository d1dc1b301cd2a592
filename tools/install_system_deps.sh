#!/usr/bin/env bash
# Install what the LWA Software Library (LSL) builds against, then LSL itself.
#
#   tools/install_system_deps.sh            # apt packages if missing, then `pip install lsl` if missing
#   PYTHON=python3.11 tools/install_system_deps.sh
#   tools/install_system_deps.sh --browser  # also the distribution's Chromium and its driver (the
#                                           # service page's browser test; `make test` asks for them)
#
# Idempotent: each step checks first and says what it does. apt-get runs only when a package is
# missing and only as root or through passwordless sudo; otherwise it prints the command to run.
set -euo pipefail

PYTHON="${PYTHON:-python3}"
APT_PACKAGES=(libgsl-dev libfftw3-dev pkg-config)
BROWSER_PACKAGES=(chromium chromium-driver)

say() { echo "[install_system_deps] $*"; }

missing=()
for pkg in "${APT_PACKAGES[@]}"; do
    if dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed"; then
        say "apt package $pkg: already installed"
    else
        missing+=("$pkg")
    fi
done

if [ "${#missing[@]}" -gt 0 ]; then
    if ! command -v apt-get >/dev/null 2>&1; then
        say "missing ${missing[*]} and no apt-get here: install GSL, FFTW3 and pkg-config with your package manager"
        exit 1
    fi
    if [ "$(id -u)" -eq 0 ]; then
        SUDO=()
    elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
        SUDO=(sudo -n)
    else
        say "missing ${missing[*]}; run as root: apt-get update && apt-get install -y ${missing[*]}"
        exit 1
    fi
    say "installing ${missing[*]} with apt-get"
    export DEBIAN_FRONTEND=noninteractive
    if ! "${SUDO[@]}" apt-get install -y "${missing[@]}"; then
        say "apt-get install failed; refreshing the package index and retrying"
        "${SUDO[@]}" apt-get update
        "${SUDO[@]}" apt-get install -y "${missing[@]}"
    fi
fi

if [ "${1:-}" = "--browser" ]; then
    # optional: without them the browser test of the service page is skipped, nothing fails
    want=()
    for pkg in "${BROWSER_PACKAGES[@]}"; do
        dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || want+=("$pkg")
    done
    if [ "${#want[@]}" -eq 0 ]; then
        say "browser packages ${BROWSER_PACKAGES[*]}: already installed"
    elif command -v apt-get >/dev/null 2>&1 && { [ "$(id -u)" -eq 0 ] || { command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; }; }; then
        say "installing ${want[*]} with apt-get (the service page's browser test)"
        SUDO=(); [ "$(id -u)" -eq 0 ] || SUDO=(sudo -n)
        export DEBIAN_FRONTEND=noninteractive
        "${SUDO[@]}" apt-get install -y -q "${want[@]}" >/dev/null \
            || { "${SUDO[@]}" apt-get update -q >/dev/null && "${SUDO[@]}" apt-get install -y -q "${want[@]}" >/dev/null; } \
            || say "could not install ${want[*]}: the browser test will be skipped"
    else
        say "not installing ${want[*]} (needs root): the browser test will be skipped"
    fi
fi

if "$PYTHON" -c "import importlib.util, sys; sys.exit(importlib.util.find_spec('lsl') is None)" 2>/dev/null; then
    say "lsl: already installed ($("$PYTHON" -c "from importlib.metadata import version; print(version('lsl'))"))"
else
    say "installing lsl with pip (builds C extensions against GSL/FFTW, about a minute)"
    "$PYTHON" -m pip install lsl
fi
say "done"
