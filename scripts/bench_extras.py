"""Per-evaluation cost table, stability map and N-four-bar scaling into an output directory.

Companion of ``closedchain bench`` (run by scripts/make_bench_figures.sh):

* ``evaluation.csv`` / ``evaluation.md``: microseconds per forward-dynamics call of
  every registered method beside pinocchio.constraintDynamics and MuJoCo's mj_forward;
* ``stability.csv`` / ``stability.png`` / ``stability.md``: the stability map;
* ``scaling.csv`` / ``scaling.png`` / ``scaling.md``: cost per evaluation against N for
  the N-four-bar (models written by scripts/make_nfourbar.py), with growth exponents.

Run: python scripts/bench_extras.py --out docs/bench [--workers 2] [--parts evaluation ...]
"""

from __future__ import annotations

import argparse
import logging
import math
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from closedchain.benchmark import write_rows
from closedchain.benchmark.evaluation import (
    EVALUATION_COLUMNS,
    EvaluationSettings,
    evaluation_markdown,
    time_evaluations,
)
from closedchain.benchmark.plots import plot_scaling, plot_stability_map
from closedchain.benchmark.runner import execute
from closedchain.benchmark.scaling import SCALING_COLUMNS, growth_exponents, time_scaling
from closedchain.benchmark.stability import (
    CASES,
    STABILITY_COLUMNS,
    make_stability_jobs,
    run_stability_job,
    stability_summary,
)

ROOT = Path(__file__).resolve().parent.parent
MODELS = ROOT / "models"
#: Sizes of the N-four-bar scaling study.
SIZES = (1, 2, 5, 10, 20, 40)
PARTS = ("evaluation", "stability", "scaling")


def nfourbar_start(mech) -> np.ndarray:
    """The N-four-bar's benchmark start (scripts/make_nfourbar.py): cranks vertical, couplers
    horizontal (crank_i = pi/2, coupler_i = -pi/2), a regular configuration."""
    q = mech.q_ref.copy()
    for i, name in enumerate(mech.coordinate_names):
        if name.startswith("crank"):
            q[i] = math.pi / 2
        elif name.startswith("coupler"):
            q[i] = -math.pi / 2
    return q


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs/bench")
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS))
    parser.add_argument("--number", type=int, default=500, help="calls per timing repeat")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if "evaluation" in args.parts:
        rows = time_evaluations(
            [MODELS / "fourbar.urdf", MODELS / "agile_eye.urdf", MODELS / "nfourbar_2.urdf"],
            EvaluationSettings(number=args.number, repeats=5),
        )
        write_rows(rows, out / "evaluation.csv", EVALUATION_COLUMNS)
        (out / "evaluation.md").write_text(evaluation_markdown(rows))
    if "stability" in args.parts:
        jobs = make_stability_jobs(list(CASES), str(MODELS))
        rows = execute(jobs, fn=run_stability_job, workers=args.workers)
        write_rows(rows, out / "stability.csv", STABILITY_COLUMNS)
        plot_stability_map(rows, out / "stability.png")
        (out / "stability.md").write_text(stability_summary(rows))
    if "scaling" in args.parts:
        with tempfile.TemporaryDirectory() as tmp:
            files = {}
            for n in SIZES:
                path = MODELS / f"nfourbar_{n}.urdf"
                if not path.exists():
                    path = Path(tmp) / f"nfourbar_{n}.urdf"
                    subprocess.run(
                        [
                            sys.executable,
                            str(ROOT / "scripts/make_nfourbar.py"),
                            str(n),
                            "--out",
                            str(path),
                        ],
                        check=True,
                    )
                files[n] = path
            rows = time_scaling(
                files, number=max(args.number // 10, 10), repeats=3, guess=nfourbar_start
            )
        write_rows(rows, out / "scaling.csv", SCALING_COLUMNS)
        plot_scaling(rows, out / "scaling.png")
        exps = growth_exponents(rows)
        (out / "scaling.md").write_text(
            "| method | growth exponent p (cost ~ N^p, N = "
            + ", ".join(map(str, SIZES))
            + ") |\n| --- | --- |\n"
            + "".join(f"| {m} | {p:.2f} |\n" for m, p in exps.items())
        )
        for m, p in exps.items():
            logging.info("growth exponent %s: %.2f", m, p)


if __name__ == "__main__":
    main()
