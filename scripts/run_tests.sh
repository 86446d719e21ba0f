#!/usr/bin/env bash
# Install closedchain with its test extras, Debian's chromium for the browser
# test (never Playwright's own browser download), and run the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_venv.sh test
if [ ! -x /usr/bin/chromium ]; then
  if [ "$(id -u)" -eq 0 ]; then
    apt-get update -qq && apt-get install -y -qq chromium
  else
    sudo apt-get update -qq && sudo apt-get install -y -qq chromium
  fi
fi
exec .venv/bin/python -m pytest "$@"
