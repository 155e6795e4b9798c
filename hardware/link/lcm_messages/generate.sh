#!/usr/bin/env bash
# Regenerate the Python message classes from the .lcm files here (lcm-gen comes with
# the `lcm` wheel): run from anywhere, then commit the result.
set -euo pipefail
cd "$(dirname "$0")"
lcm-gen --python --ppath .. ./*.lcm
