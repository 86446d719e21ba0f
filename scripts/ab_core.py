"""Paired timing of two builds of the compiled core (closedchain._core) per evaluation.

Each build is run in fresh processes, alternately (A, B, A, B, ...), from a
temporary copy of the package with that build's ``_core*.so`` in it; each
process times ``Core.repeat`` (one whole evaluation per repetition, as in
``scripts/bench_core.py``) on the 4-bar for the methods kkt and
augmented-lagrangian, CPU process time, the minimum of three runs of
``--number`` evaluations. Prints every process's figures and the medians and
the ratio B/A. Instruction counts (callgrind) are the load-independent check.

Run: python scripts/ab_core.py A.so B.so [--rounds 4] [--number 40000]
(e.g. A = a copy of main's src/closedchain/_core*.so, B = build/dev/_core*.so).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
CHILD = """
import sys, time
sys.path.insert(0, sys.argv[1])
from pathlib import Path
import numpy as np
import closedchain as cc
from closedchain import compiled
assert Path(compiled._core.__file__).parent.parent == Path(sys.argv[1]), compiled._core.__file__
n = int(sys.argv[2])
mech = cc.load(Path(sys.argv[3]) / "fourbar.urdf")
q, v = cc.random_consistent_state(mech, np.random.default_rng(0))
tau = np.zeros(mech.nv)
out = []
for method in ("kkt", "augmented-lagrangian"):
    core = compiled.compiled_dynamics(mech, method).core
    core.repeat(q, v, tau, 1000)
    best = float("inf")
    for _ in range(3):
        t0 = time.process_time()
        core.repeat(q, v, tau, n)
        best = min(best, time.process_time() - t0)
    out.append(best / n * 1e6)
print(" ".join(repr(x) for x in out))
"""


def package_with(so: Path, where: Path) -> Path:
    dest = where / "closedchain"
    shutil.copytree(ROOT / "src" / "closedchain", dest, ignore=shutil.ignore_patterns("_core*.so"))
    shutil.copy(so, dest / "_core.cpython-311-x86_64-linux-gnu.so")
    return where


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("a", type=Path)
    parser.add_argument("b", type=Path)
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--number", type=int, default=40000)
    args = parser.parse_args()
    res: dict[str, list[list[float]]] = {"A": [], "B": []}
    with tempfile.TemporaryDirectory() as tmp:
        dirs = {k: package_with(so, Path(tmp) / k) for k, so in (("A", args.a), ("B", args.b))}
        for _ in range(args.rounds):
            for k, d in dirs.items():
                cmd = [sys.executable, "-c", CHILD, str(d), str(args.number), str(ROOT / "models")]
                line = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
                res[k].append([float(x) for x in line.split()])
                print(k, " ".join(f"{x:.3f}" for x in res[k][-1]), flush=True)
    med = {k: np.median(np.array(r), axis=0) for k, r in res.items()}
    for i, method in enumerate(("kkt", "augmented-lagrangian")):
        print(
            f"4-bar {method:22s} A {med['A'][i]:.3f} us  B {med['B'][i]:.3f} us  "
            f"B/A {med['B'][i] / med['A'][i]:.3f}"
        )


if __name__ == "__main__":
    main()
