#!/usr/bin/env bash
# Create .venv if missing and install closedchain into it (editable), with the
# extras given as arguments, e.g.  scripts/setup_venv.sh test
set -euo pipefail
cd "$(dirname "$0")/.."
[ -x .venv/bin/python ] || python3 -m venv .venv
extras="${1:-}"
spec="."
[ -n "$extras" ] && spec=".[${extras}]"
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip install --quiet -e "$spec"
