#!/usr/bin/env bash
# One entry point for developers and CI:
#   bash dev.sh demo    set up .venv if needed, register the built-in capsule pair -> out/demo
#   bash dev.sh test    set up .venv if needed, run the test suite (pytest)
#   bash dev.sh setup   only set up
#   bash dev.sh vdb-env set up .venv-vdb: the OpenVDB-capable environment (see vdb_env below)
#   bash dev.sh test-vdb set up .venv-vdb if needed, run the OpenVDB tests (pytest -m vdb)
#   bash dev.sh lock    refresh requirements.lock and requirements-vdb.lock (uv pip compile)
# Set-up: checks Python >= 3.10, installs the system packages Open3D and venv need when
# missing (as root; otherwise prints the exact command), creates .venv and installs the
# package with its test extras, every package at the version of requirements.lock (a
# universal lock: one pinned set per Python version, 3.10 and newer). It is redone when
# pyproject.toml or the lock changes. LOCK= (empty) installs the newest versions instead:
#   VENV=.venv-newest LOCK= bash dev.sh test
set -euo pipefail
cd "$(dirname "$0")"

PY="${PYTHON:-python3}"
VENV="${VENV:-.venv}"
LOCK="${LOCK-requirements.lock}"
VDB_LOCK=requirements-vdb.lock

die() { echo "dev.sh: $*" >&2; exit 1; }

# what an installed venv was made from: the project's requirements and the lock's pins
install_key() { cat pyproject.toml "$@" 2>/dev/null | sha256sum | cut -d' ' -f1; }

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

need_libusb() {
  # Open3D's wheel links libusb-1.0 (it fails to import without it).
  # (ldconfig lives in /sbin, which is not on a normal user's PATH on Debian)
  if ! { /sbin/ldconfig -p 2>/dev/null || ldconfig -p 2>/dev/null; } | grep -q 'libusb-1\.0\.so\.0'; then
    need_apt libusb-1.0-0
  fi
}

setup() {
  command -v "$PY" >/dev/null 2>&1 || die "python3 not found; install Python 3.10 or newer"
  "$PY" -c 'import sys; sys.exit(sys.version_info < (3, 10))' \
    || die "Python 3.10 or newer is needed, found $("$PY" --version 2>&1)"
  need_libusb
  if [ ! -x "$VENV/bin/python" ]; then
    if ! "$PY" -c 'import ensurepip, venv' >/dev/null 2>&1; then
      ver=$("$PY" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")')
      need_apt "python${ver}-venv" || need_apt python3-venv
    fi
    "$PY" -m venv "$VENV"
  fi
  stamp="$VENV/.installed"
  if [ -n "$LOCK" ]; then
    [ -f "$LOCK" ] || die "$LOCK not found (LOCK= installs the newest versions instead)"
    key=$(install_key "$LOCK"); pins=(-c "$LOCK")
  else
    key="newest $(date +%F)"; pins=(--upgrade --upgrade-strategy eager)
  fi
  if [ "$(cat "$stamp" 2>/dev/null)" != "$key" ]; then
    "$VENV/bin/python" -m pip install -q --upgrade pip
    "$VENV/bin/python" -m pip install -q "${pins[@]}" -e '.[test]'
    "$VENV/bin/python" -c 'import open3d, igl, trimesh, scipy' \
      || die "the installed packages do not import; see the error above"
    echo "$key" > "$stamp"
  fi
}

# Refresh the locks from pyproject.toml with uv (installed into .venv for the purpose):
# requirements.lock for every Python from 3.10, requirements-vdb.lock for the OpenVDB venv
# (Debian's Python 3.11, NumPy < 2). Run the suite on the new lock before committing it.
lock() {
  [ -f "$LOCK" ] || LOCK=  # a first lock: set up with the newest versions
  setup
  "$VENV/bin/python" -m pip install -q uv
  uv=("$VENV/bin/uv" pip compile pyproject.toml --extra test --extra plot --quiet)
  "${uv[@]}" --universal --python-version 3.10 --custom-compile-command "bash dev.sh lock" -o requirements.lock
  echo "numpy<2" > "$VENV/vdb-numpy.txt"
  "${uv[@]}" --universal --python-version 3.11 -c "$VENV/vdb-numpy.txt" \
    --custom-compile-command "bash dev.sh lock" -o "$VDB_LOCK"
}

# The OpenVDB backend needs Debian's python3-openvdb (PyPI's pyopenvdb has no wheel for
# Python 3.11), whose extension is built against NumPy 1.x: with NumPy 2 it crashes the
# process. So a second venv, $VDB_VENV, pinned by requirements-vdb.lock (NumPy < 2), sees
# the system pyopenvdb module through a .pth file. Fails loudly when any step is impossible.
VDB_VENV="${VDB_VENV:-.venv-vdb}"
VDB_DIST=/usr/lib/python3/dist-packages
vdb_env() {
  need_libusb
  if ! ls "$VDB_DIST"/pyopenvdb*.so >/dev/null 2>&1; then
    need_apt python3-openvdb
  fi
  so=$(ls "$VDB_DIST"/pyopenvdb*.so | head -n 1)
  [ -n "$so" ] || die "python3-openvdb installed no pyopenvdb module in $VDB_DIST"
  # the extension is built for Debian's python3; the venv must use the same minor version
  tag=$(basename "$so" | sed -n 's/^pyopenvdb\.cpython-\([0-9]*\)-.*/\1/p')
  vpy="${VDB_PYTHON:-python3.${tag#3}}"
  command -v "$vpy" >/dev/null 2>&1 || vpy=/usr/bin/python3
  [ "$("$vpy" -c 'import sys; print(f"{sys.version_info[0]}{sys.version_info[1]}")')" = "$tag" ] \
    || die "$so is built for CPython $tag; set VDB_PYTHON to a Python of that version"
  if [ ! -x "$VDB_VENV/bin/python" ]; then
    if ! "$vpy" -c 'import ensurepip, venv' >/dev/null 2>&1; then
      ver=$("$vpy" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")')
      need_apt "python${ver}-venv" || need_apt python3-venv
    fi
    "$vpy" -m venv "$VDB_VENV"
  fi
  site=$("$VDB_VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
  # only the one module, not all of dist-packages (which would shadow the venv's packages)
  mkdir -p "$VDB_VENV/system-openvdb"
  ln -sf "$so" "$VDB_VENV/system-openvdb/"
  echo "$(cd "$VDB_VENV/system-openvdb" && pwd)" > "$site/system-openvdb.pth"
  stamp="$VDB_VENV/.installed"
  key=$(install_key "$VDB_LOCK")
  if [ "$(cat "$stamp" 2>/dev/null)" != "$key" ]; then
    "$VDB_VENV/bin/python" -m pip install -q --upgrade pip
    "$VDB_VENV/bin/python" -m pip install -q -c "$VDB_LOCK" -e '.[test,plot]'
    echo "$key" > "$stamp"
  fi
  "$VDB_VENV/bin/python" -c 'from morphmodes_vol.sdf.vdb import check_openvdb; check_openvdb(); import open3d, igl, trimesh, scipy' \
    || die "the OpenVDB environment $VDB_VENV does not work; see the error above"
}

cmd="${1:-}"
shift || true
case "$cmd" in
  setup) setup ;;
  demo) setup; exec "$VENV/bin/morphmodes-vol" demo "$@" ;;
  test) setup; exec "$VENV/bin/python" -m pytest "$@" ;;
  lock) lock ;;
  vdb-env) vdb_env ;;
  test-vdb) vdb_env; MORPHMODES_REQUIRE_VDB=1 exec "$VDB_VENV/bin/python" -m pytest -m vdb "$@" ;;
  *) die "usage: bash dev.sh {demo|test|setup|lock|vdb-env|test-vdb} [arguments passed on]" ;;
esac
