#!/usr/bin/env bash
# One entry point for a fresh Debian machine with Python 3.11:
#   ./run.sh demo   install everything, then run the levitation demo in Meshcat
#   ./run.sh test   install everything, then run the test suite
# Anything after the first word is passed on (to `maglev run` or to pytest).
set -euo pipefail
cd "$(dirname "$0")"
what="${1:-demo}"; shift || true

as_root() { if [ "$(id -u)" = 0 ]; then "$@"; else sudo "$@"; fi; }
apt_updated=0
apt_install() {  # install Debian packages that are missing
  local missing=()
  for pkg in "$@"; do
    # Removed packages keep a dpkg entry ("deinstall ok config-files"): check the status.
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" \
      || missing+=("$pkg")
  done
  [ ${#missing[@]} -eq 0 ] && return 0
  [ $apt_updated = 1 ] || { as_root apt-get update -qq; apt_updated=1; }
  DEBIAN_FRONTEND=noninteractive as_root apt-get install -y -qq "${missing[@]}" >/dev/null
}

python=$(command -v python3.11 || command -v python3)
"$python" -c 'import sys; assert sys.version_info[:2] == (3, 11), sys.version' \
  || { echo "run.sh: needs Python 3.11 (drake 1.51.1 wheels); found $("$python" --version)"; exit 1; }
# graphviz draws `maglev diagram`; python3-venv is not in Debian's base python3.
apt_install graphviz
# Drake's VTK renderer draws the stereo display headless through EGL (Mesa llvmpipe).
apt_install libegl1 libgl1-mesa-dri
"$python" -m venv --help >/dev/null 2>&1 && "$python" -c 'import ensurepip' 2>/dev/null \
  || apt_install python3-venv
if [ ! -x .venv/bin/python ]; then "$python" -m venv .venv; fi
.venv/bin/python -m pip install -q --disable-pip-version-check -e '.[test]'

export MPLBACKEND=Agg
case "$what" in
  demo) exec .venv/bin/maglev run levitate "$@" ;;
  test) exec .venv/bin/python -m pytest -q "$@" ;;
  *) echo "usage: ./run.sh demo|test [args]"; exit 2 ;;
esac
