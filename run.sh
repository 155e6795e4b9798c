#!/usr/bin/env bash
# One entry point for a fresh Debian or Ubuntu machine with Python 3.12 or newer:
#   ./run.sh demo   install everything, then run the levitation demo in Meshcat
#   ./run.sh test   install everything, then run the default test suite on both cores
#                   (-m slow: the long tests; .ci/run runs both)
# Anything after the first word is passed on (to `maglev run` or to pytest).
# MAGLEV_PYTHON=/path/to/python picks the interpreter; else the newest 3.12+ found.
set -euo pipefail
cd "$(dirname "$0")"
what="${1:-demo}"; shift || true
case "$what" in demo|test) ;; *) echo "usage: ./run.sh demo|test [args]"; exit 2 ;; esac

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

supported() { "$1" -c 'import sys; sys.exit(sys.version_info < (3, 12))' 2>/dev/null; }
find_python() {  # the newest Python >= 3.12: on PATH, then under pyenv
  local candidate
  if [ -n "${MAGLEV_PYTHON:-}" ]; then echo "$MAGLEV_PYTHON"; return; fi
  for candidate in python3.14 python3.13 python3.12 python3; do
    # A pyenv shim is on PATH even when its version is not selected: ask it to run.
    candidate=$(command -v "$candidate" 2>/dev/null) || continue
    supported "$candidate" && { echo "$candidate"; return; }
  done
  local root; root=$(pyenv root 2>/dev/null || echo "$HOME/.pyenv")
  for candidate in $(ls -d "$root"/versions/3.1[2-9]*/bin/python3 2>/dev/null | sort -rV); do
    supported "$candidate" && { echo "$candidate"; return; }
  done
}
python=$(find_python || true)
if [ -z "$python" ] || ! supported "$python"; then
  found=$(for p in python3 python3.11 python3.10; do
            if command -v "$p" >/dev/null; then "$p" --version 2>&1; fi
          done | sort -u | paste -sd, - | sed 's/,/, /g')
  echo "run.sh: needs Python 3.12 or newer (drake 1.58 wheels); found: ${found:-none}." \
       "Install one (Ubuntu 24.04 / Debian 13: apt install python3 python3-venv; else pyenv install 3.12)" \
       "or point MAGLEV_PYTHON at it."
  exit 1
fi
echo "run.sh: using $("$python" --version 2>&1) at $python"
# graphviz draws `maglev diagram`; Drake's VTK renderer draws the stereo display headless
# through EGL (Mesa llvmpipe).
apt_install graphviz libegl1 libgl1-mesa-dri
# The tests open Meshcat's page in a real browser: Debian's Chromium, driven by Playwright.
# Where it cannot be had (Ubuntu ships it as a snap) that test is skipped and says why.
if [ "$what" = test ]; then
  apt_install chromium || echo "run.sh: could not install chromium; the browser test will be skipped"
fi
if ! "$python" -c 'import ensurepip, venv' 2>/dev/null; then
  # Debian splits venv out of its python3: the package named after the interpreter's version.
  apt_install "python$("$python" -c 'import sys; print("%d.%d" % sys.version_info[:2])')-venv"
fi
# A venv of another interpreter (an older checkout's 3.11) is rebuilt.
if [ -x .venv/bin/python ] && [ "$(.venv/bin/python -c 'import sys; print(sys.version)')" != \
     "$("$python" -c 'import sys; print(sys.version)')" ]; then rm -rf .venv; fi
if [ ! -x .venv/bin/python ]; then "$python" -m venv .venv; fi
.venv/bin/python -m pip install -q --disable-pip-version-check -e '.[test]'

export MPLBACKEND=Agg
case "$what" in
  demo) exec .venv/bin/maglev run levitate "$@" ;;
  # The default suite on both cores (pytest-xdist: 6.5 against 10.5 minutes on a slow
  # 2-core host); a run that picks its tests (-m slow: paced and two-process tests that
  # need the cores to themselves; a file; -k) runs them one at a time.
  test) if [ $# -eq 0 ]; then set -- -n 2; fi
        exec .venv/bin/python -m pytest -q "$@" ;;
esac
