#!/usr/bin/env bash
# One entry point for developers and CI:
#   bash dev.sh demo    set up .venv if needed, register the built-in capsule pair -> out/demo
#   bash dev.sh test    set up .venv if needed, run the test suite (pytest)
#   bash dev.sh setup   only set up
# Set-up: checks Python >= 3.10, installs the system packages Open3D and venv need when
# missing (as root; otherwise prints the exact command), creates .venv and installs the
# package with its test extras. It is skipped when pyproject.toml has not changed.
set -euo pipefail
cd "$(dirname "$0")"

PY="${PYTHON:-python3}"
VENV="${VENV:-.venv}"

die() { echo "dev.sh: $*" >&2; exit 1; }

need_apt() {  # need_apt PACKAGE... : install with apt-get as root, else explain
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "dev.sh: installing system package(s): $*" >&2
    if ! DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" >/dev/null; then
      apt-get update -qq >/dev/null
      DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" >/dev/null
    fi
  else
    die "missing system package(s) $*; install them with: sudo apt-get install -y $*"
  fi
}

setup() {
  command -v "$PY" >/dev/null 2>&1 || die "python3 not found; install Python 3.10 or newer"
  "$PY" -c 'import sys; sys.exit(sys.version_info < (3, 10))' \
    || die "Python 3.10 or newer is needed, found $("$PY" --version 2>&1)"
  # Open3D's wheel links libusb-1.0 (it fails to import without it).
  # (ldconfig lives in /sbin, which is not on a normal user's PATH on Debian)
  if ! { /sbin/ldconfig -p 2>/dev/null || ldconfig -p 2>/dev/null; } | grep -q 'libusb-1\.0\.so\.0'; then
    need_apt libusb-1.0-0
  fi
  if [ ! -x "$VENV/bin/python" ]; then
    if ! "$PY" -c 'import ensurepip, venv' >/dev/null 2>&1; then
      ver=$("$PY" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")')
      need_apt "python${ver}-venv" || need_apt python3-venv
    fi
    "$PY" -m venv "$VENV"
  fi
  stamp="$VENV/.installed"
  if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
    "$VENV/bin/python" -m pip install -q --upgrade pip
    "$VENV/bin/python" -m pip install -q -e '.[test]'
    "$VENV/bin/python" -c 'import open3d, igl, trimesh, scipy' \
      || die "the installed packages do not import; see the error above"
    touch "$stamp"
  fi
}

cmd="${1:-}"
shift || true
case "$cmd" in
  setup) setup ;;
  demo) setup; exec "$VENV/bin/morphmodes-vol" demo "$@" ;;
  test) setup; exec "$VENV/bin/python" -m pytest "$@" ;;
  *) die "usage: bash dev.sh {demo|test|setup} [arguments passed on]" ;;
esac
