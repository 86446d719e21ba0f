#!/usr/bin/env bash
# Regenerate the benchmark figures and tables of the README into docs/bench/.
# Each work-precision scenario is its own run (so one finished scenario is kept
# if a later one is interrupted); then the per-evaluation table, the stability
# map and the workspace pictures. Run from the repository root on an idle machine:
#   bash scripts/make_bench_figures.sh [WORKERS]
set -euo pipefail
WORKERS=${1:-2}
PY=${PYTHON:-python}
OUT=docs/bench
mkdir -p "$OUT"
lscpu | grep -E "Model name|^CPU\(s\)" > "$OUT/machine.txt" || true
$PY -c "import platform, pinocchio, numpy, scipy; print(platform.platform(), 'python', platform.python_version(), 'pin', pinocchio.__version__, 'numpy', numpy.__version__, 'scipy', scipy.__version__)" >> "$OUT/machine.txt"
for sc in fourbar-passive fourbar-driven agile_eye-coasting; do
  $PY -m closedchain.cli bench --scenarios "$sc" --out "$OUT/$sc" --workers "$WORKERS" --no-progress
done
$PY scripts/bench_extras.py --out "$OUT" --workers "$WORKERS"
