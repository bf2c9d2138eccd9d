#!/usr/bin/env bash
# robo3d's one entry point for a fresh machine (Debian/Ubuntu, Python 3.11+):
#
#   ./run.sh demo    set up, write the demo recordings into recordings/ if missing (about
#                    50 s each, once), then run the pipeline on the recordings there
#   ./run.sh test    set up, then run the test suite
#
# Set-up is idempotent and fast the second time: the system libraries Open3D needs
# (libusb-1.0, GL/EGL, OpenMP) and python3-venv are installed with apt-get only when
# missing; the environment lives in .venv/ and is reinstalled only when pyproject.toml
# changes. Extra arguments are passed on: `./run.sh demo --config recordings=/data`,
# `./run.sh test -k carving`.
set -euo pipefail
cd "$(dirname "$0")"

say() { printf '\033[1m[robo3d]\033[0m %s\n' "$*" >&2; }

as_root() {
  if [ "$(id -u)" = 0 ]; then "$@"
  elif command -v sudo >/dev/null 2>&1; then sudo "$@"
  else say "need root to run: $*  (run it once by hand, or run as root)"; exit 1
  fi
}

apt_updated=0
apt_install() {
  command -v apt-get >/dev/null 2>&1 || { say "missing system packages: $* (no apt-get here: install them with your package manager)"; exit 1; }
  if [ "$apt_updated" = 0 ]; then as_root apt-get update -qq; apt_updated=1; fi
  say "installing system packages: $*"
  as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "$@" >/dev/null
}

find_python() {
  for py in python3.13 python3.12 python3.11 python3; do
    if command -v "$py" >/dev/null 2>&1 &&
       "$py" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; then
      command -v "$py"; return 0
    fi
  done
  return 1
}

ensure_python() {
  PY=$(find_python) || { apt_install python3 python3-venv; PY=$(find_python) || {
    apt_install python3.11 python3.11-venv; PY=$(find_python); }; } || {
    say "Python 3.11 or newer is needed"; exit 1; }
  if ! "$PY" -c 'import ensurepip, venv' >/dev/null 2>&1; then
    ver=$("$PY" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")')
    apt_install "python${ver}-venv" || apt_install python3-venv
  fi
}

# Shared libraries the Open3D wheel links against, and the Debian package of each.
ensure_system_libs() {
  local pkgs=()
  local pairs=("libusb-1.0.so.0:libusb-1.0-0" "libGL.so.1:libgl1" "libEGL.so.1:libegl1"
               "libgomp.so.1:libgomp1" "libX11.so.6:libx11-6")
  for pair in "${pairs[@]}"; do
    ldconfig -p 2>/dev/null | grep -q "${pair%%:*}" || pkgs+=("${pair#*:}")
  done
  if [ ${#pkgs[@]} -gt 0 ]; then apt_install "${pkgs[@]}"; fi
}

ensure_venv() {
  local stamp=.venv/.robo3d-installed want
  want=$(cat pyproject.toml | sha256sum | cut -d' ' -f1)
  if [ -x .venv/bin/python ] && [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
    return 0
  fi
  ensure_python
  if [ ! -x .venv/bin/python ]; then
    say "creating .venv with $PY"
    "$PY" -m venv .venv
  fi
  say "installing robo3d and its dependencies into .venv (first run: a few minutes)"
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e '.[test]'
  echo "$want" > "$stamp"
}

ensure_system_libs
ensure_venv
# robo3d's own modules compiled to bytecode here, once: where PYTHONDONTWRITEBYTECODE is
# set (this CI image sets it) every workflow job compiled them from source again, 0.1 s
# of each job's 1.7 s on a tiny scan (stop 64); only changed modules are compiled again
.venv/bin/python -m compileall -q robo3d
export PATH="$PWD/.venv/bin:$PATH"

cmd=${1:-demo}
shift || true
case "$cmd" in
  demo)
    case " $* " in
      *recordings=*) ;;  # the user's own recordings: no demo needed
      *)
        # the demo recordings are generated, not kept in the repository (about 7 MB each,
        # deterministic: the same bytes on every machine); once, about a minute each
        .venv/bin/robo3d simulate --demo recordings/ --missing --threads 0
        ;;
    esac
    # the numba kernels compiled once (a fresh install), not once per job started side by
    # side; about a second when they are in the cache already
    .venv/bin/robo3d warm-up
    say "running the pipeline on the recordings in recordings/ (results in results/)"
    exec .venv/bin/snakemake --cores all --keep-going --rerun-incomplete "$@"
    ;;
  test)
    # two workers (the machine the suite is sized for has 2 cores), one file at a time each,
    # handed out longest first (tests/conftest.py; xdist's own reorder by test count off);
    # the kernels compiled once first, not by each of the end-to-end tests' jobs at once;
    # the 16-bit and float frames' too, which the stripe tests use, on the second core
    .venv/bin/robo3d warm-up --all-types
    exec .venv/bin/python -m pytest -n 2 --dist loadfile --no-loadscope-reorder "$@"
    ;;
  *)
    say "usage: ./run.sh demo|test [args...]"; exit 2
    ;;
esac
