#!/usr/bin/env bash
# Create .venv if missing and install closedchain into it (editable), with the
# extras given as arguments, e.g.  scripts/setup_venv.sh test
# The extra `test` also builds closedchain._core_testing, the compiled helpers that only
# the tests call (CMake option CLOSEDCHAIN_TESTING; without it: OFF).
# The compiled core (C++, ~4 min the first time) is built in build/ with the
# build requirements installed in .venv (no build isolation), so a re-run
# recompiles only what changed.
set -euo pipefail
cd "$(dirname "$0")/.."
[ -x .venv/bin/python ] || python3 -m venv .venv
extras="${1:-}"
spec="."
[ -n "$extras" ] && spec=".[${extras}]"
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python - <<'PY' > .venv/build-requirements.txt
import tomllib

with open("pyproject.toml", "rb") as f:
    print("\n".join(tomllib.load(f)["build-system"]["requires"]))
PY
.venv/bin/python -m pip install --quiet -r .venv/build-requirements.txt ninja cmake
testing=OFF
[[ ",$extras," == *,test,* ]] && testing=ON
.venv/bin/python -m pip install --quiet --no-build-isolation \
  --config-settings=cmake.define.CLOSEDCHAIN_TESTING=$testing -e "$spec"
