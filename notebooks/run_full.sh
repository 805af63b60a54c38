#!/usr/bin/env bash
# Execute every notebook at full size and save its outputs in place (what is committed).
# About 3 minutes on 2 cores. CI runs the same notebooks at quick sizes without saving.
set -euo pipefail
cd "$(dirname "$0")"
SPACEGRASP_NOTEBOOK_QUICK=0 python3 -m pytest --nbmake --overwrite --nbmake-timeout=3600 -p no:cacheprovider "${@:-.}"
