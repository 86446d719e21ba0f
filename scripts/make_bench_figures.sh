#!/usr/bin/env bash
# Regenerate every benchmark figure and table into docs/bench/ and write the documentation
# site's generated results page, docs/bench/results.md: the single source of the
# benchmark numbers (no prose carries them). Run from the repository root:
#   bash scripts/make_bench_figures.sh [WORKERS]
# Steps: one `closedchain bench` run over all work-precision scenarios (references from
# the on-disk cache when the code that computes them is unchanged), then the
# per-evaluation table, the stability map, the scaling and per-call pages
# (scripts/bench_extras.py), the N-four-bar page (scripts/nfourbar_cost.py), the
# default on the accuracy-speed front (scripts/bench_front.py), then the
# report. Every page's header carries the version and the default configuration it
# measured (scripts/bench_page.py). The corpus page needs a checkout of
# example-parallel-robots: scripts/check_corpus.py says how. The couplings page adds the
# models listed in COUPLED (local copies of shipped models with couplings, e.g. MuJoCo
# Menagerie's robotiq_2f85/2f85.xml with its assets/ folder):
#   COUPLED="/path/to/robotiq_2f85/2f85.xml" bash scripts/make_bench_figures.sh
# The command, the machine, the date, the load average before and after, and the wall
# time go into the header of results.md.
set -euo pipefail
WORKERS=${1:-2}
PY=${PYTHON:-python}
OUT=docs/bench
mkdir -p "$OUT"
START=$(date +%s)
COMMAND="${COUPLED:+COUPLED=\"$COUPLED\" }bash scripts/make_bench_figures.sh $WORKERS"
LOAD_BEFORE=$(cut -d' ' -f1-3 /proc/loadavg)
$PY scripts/bench_page.py machine > "$OUT/machine.txt"  # CPU, versions, commit, date
$PY -m closedchain.cli bench --out "$OUT/wp" --workers "$WORKERS"
# shellcheck disable=SC2086  # COUPLED is a list of paths
$PY scripts/bench_extras.py --out "$OUT" --workers "$WORKERS" ${COUPLED:+--coupled $COUPLED}
$PY scripts/nfourbar_cost.py --n 1 2 5 10 20 40 --t 0.01 --page "$OUT/nfourbar.md"
$PY scripts/bench_front.py --repeat 3 --page "$OUT/front.md"
$PY -m closedchain.cli workspace models/fourbar.urdf -o "$OUT/workspace_fourbar.png"
$PY -m closedchain.cli workspace models/agile_eye.urdf -o "$OUT/workspace_agile_eye.png"
LOAD_AFTER=$(cut -d' ' -f1-3 /proc/loadavg)
$PY scripts/bench_extras.py --out "$OUT" --report --wall $(( $(date +%s) - START )) \
  --load "$LOAD_BEFORE / $LOAD_AFTER" --command "$COMMAND"
echo "wall time $(( $(date +%s) - START )) s; see $OUT/results.md"
