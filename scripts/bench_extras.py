"""Per-evaluation cost table, stability map and N-four-bar scaling into an output directory.

Companion of ``closedchain bench`` (run by scripts/make_bench_figures.sh):

* ``evaluation.csv`` / ``evaluation.md``: microseconds per forward-dynamics call of
  every registered method beside pinocchio.constraintDynamics and MuJoCo's mj_forward;
* ``stability.csv`` / ``stability.png`` / ``stability.md``: the stability map;
* ``scaling.csv`` / ``scaling.png`` / ``scaling.md``: cost per evaluation against size
  for the families of ``closedchain bench --scaling`` (chain, leg pair, N-four-bar), with
  growth exponents: a generated page of its own;
* ``percall.csv`` / ``percall.md``: microseconds per call of the public per-call functions
  (compiled core and numpy reference) on the chain family, beside the tuned
  pinocchio.constraintDynamics call and pinocchio.rnea: a generated page of its own;
* ``couplings.csv`` / ``couplings.md``: CPU seconds of 1 s of ``simulate`` under the
  default settings on mechanisms with couplings (URDF ``<mimic>``, coupling loops, MJCF
  joint equalities), compiled core and numpy reference, and the largest |phi| of every
  declared row along the run: a generated page of its own (local copies of shipped
  models, such as MuJoCo Menagerie's Robotiq 2F-85, through ``--coupled``);
* ``results.md`` (part ``report``): the documentation site's generated results page
  (docs/bench/results.md): every table above, the work-precision run's ratio table,
  reference agreements and charts, under a header with the command, machine, date, load
  and wall time of the run (scripts/make_bench_figures.sh is the single source of the
  benchmark numbers; no prose carries them).

BLAS runs on one thread (OPENBLAS_NUM_THREADS=1 unless set): the timers count the
process's CPU time, and after a numpy call on matrices large enough for OpenBLAS to
thread (the N-four-bar at N = 40) its idle worker threads spin, charging their CPU time to
whatever is timed next: the compiled kkt at N = 40 measured 1.4-1.6 ms per call right
after a numpy schur call against 0.49-0.59 ms of the calling thread (the 2.1 ms of the
scaling run of issue 10).

Run: python scripts/bench_extras.py --out docs/bench [--workers 2] [--parts evaluation ...]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy is imported

import argparse  # noqa: E402
import logging  # noqa: E402
from pathlib import Path  # noqa: E402

import bench_page  # noqa: E402  (scripts/bench_page.py: the generated pages' header)

from closedchain._io import atomic_write
from closedchain.benchmark import write_rows
from closedchain.benchmark.evaluation import (
    EVALUATION_COLUMNS,
    EvaluationSettings,
    evaluation_markdown,
    time_evaluations,
)
from closedchain.benchmark.plots import plot_stability_map
from closedchain.benchmark.runner import execute
from closedchain.benchmark.scaling import DEFAULT_CALL, SIMULATE_DT, run_scaling
from closedchain.benchmark.stability import (
    CASES,
    STABILITY_COLUMNS,
    make_stability_jobs,
    run_stability_job,
    stability_summary,
)

ROOT = Path(__file__).resolve().parent.parent
MODELS = ROOT / "models"
PARTS = ("evaluation", "stability", "scaling", "percall", "couplings")
#: Chain sizes of the per-call page.
PERCALL_SIZES = (10, 30, 100, 300)
#: Pinocchio's proximal settings of the per-call page's reference call (absolute and
#: relative accuracy, mu, iterations): the cheapest that still matches kkt on the chain
#: (the page gives the difference).
PERCALL_PROXIMAL = (0.0, 0.0, 1e-8, 3)
#: Size of the random move of the assembly's start off the closed configuration [rad].
PERCALL_ASSEMBLY_OFFSET = 1e-3
PERCALL_COLUMNS = ("n", "nv", "nc", "call", "backend", "us", "reference", "ratio")
#: Mechanisms with couplings of the couplings page (more through --coupled).
COUPLED_MODELS = (ROOT / "tests/data/mimic_gripper.urdf", ROOT / "tests/data/mimic_fourbar.urdf")
#: Simulated time of the couplings page [s].
COUPLED_T_FINAL = 1.0
COUPLED_COLUMNS = (
    "model",
    "nv",
    "nc",
    "couplings",
    "backend",
    "cpu_s",
    "steps",
    "max_phi",
)


def write_scaling_page(out: Path, quiet: bool = False) -> None:
    """Run the scaling study (``closedchain bench --scaling``: every family) into ``out``
    and turn its table into the generated page ``scaling.md`` (header, tables, chart)."""
    command = "python scripts/bench_extras.py --parts scaling"
    date = bench_page.today()
    load_before = bench_page.load_average()
    progress = None if quiet else (lambda name: logging.info("scaling: %s", name))
    run_scaling(out, progress=progress)
    tables = (out / "scaling.md").read_text()
    head = bench_page.run_header(
        "Cost per evaluation against size",
        command=command,
        date=date,
        load_before=load_before,
        about="What is measured and how: [Benchmark protocol](../benchmarks/protocol.md"
        "#cost-per-evaluation-and-scaling).",
    )
    text = "\n".join(
        [
            *head,
            "CPU microseconds per forward-dynamics evaluation (median of interleaved "
            "repeats, same process), against nv; p is the least-squares slope of "
            "log(us) against log(nv). *compiled* is the compiled core called from Python "
            "(one call), *compiled, in simulate* its cost per evaluation inside "
            f"`simulate` (rk4 at {SIMULATE_DT * 1e3:g} ms, the difference of a short and a "
            f"long run); *{DEFAULT_CALL}* is `simulate` under its default settings (the "
            "same difference, its own steps, error estimates and projections counted in "
            "the cost of its evaluations), the marginal cost of an evaluation a user "
            "gets without tuning; *refused* a method that raised at that size.",
            "",
            tables,
            "![scaling](scaling.png)",
            "",
        ]
    )
    with atomic_write(out / "scaling.md", "w") as f:
        f.write(text)


def percall_entries(n: int) -> tuple[list[tuple], dict]:
    """The timed calls on the n-link chain: ``(call, backend, reference, fn)``, the
    references first (``reference`` None), and facts for the page (sizes, the reference
    call's agreement with kkt)."""
    import tempfile

    import numpy as np
    import pinocchio as pin

    import closedchain as cc
    from closedchain.benchmark.families import FAMILIES
    from closedchain.benchmark.scaling import _start
    from closedchain.dynamics.base import METHOD_CAPABILITIES

    family = FAMILIES["chain"]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"chain{n}.urdf"
        path.write_text(family.urdf(n))
        mech = cc.load(path)
    q, v = _start(mech, family.start)
    tau = np.zeros(mech.nv)
    a_P = np.ones(mech.mobility)
    guess = pin.integrate(
        mech.model, q, PERCALL_ASSEMBLY_OFFSET * np.random.default_rng(0).standard_normal(mech.nv)
    )
    cms, cds, _, data = mech.pinocchio_constraints()
    prox = pin.ProximalSettings(*PERCALL_PROXIMAL)
    rnea_data = pin.Data(mech.model)
    pin_call = "pin.constraintDynamics"
    entries = [
        (
            pin_call,
            "C++",
            None,
            lambda: pin.constraintDynamics(mech.model, data, q, v, tau, cms, cds, prox),
        ),
        ("pin.rnea", "C++", None, lambda: pin.rnea(mech.model, rnea_data, q, v, tau)),
    ]
    methods = sorted(m for m, c in METHOD_CAPABILITIES.items() if c.compiled)
    for backend in ("compiled", "numpy"):
        for m in methods:
            entries.append(
                (
                    f"forward_dynamics {m}",
                    backend,
                    pin_call,
                    lambda m=m, b=backend: cc.forward_dynamics(
                        mech, q, v, tau, method=m, backend=b
                    ),
                )
            )
        b = backend
        entries += [
            (
                "inverse_dynamics",
                b,
                pin_call,
                lambda b=b: cc.inverse_dynamics(mech, q, v, a_P, actuated="independent", backend=b),
            ),
            ("compute_phi", b, pin_call, lambda b=b: cc.compute_phi(mech, q, backend=b)),
            ("compute_jacobian", b, pin_call, lambda b=b: cc.compute_jacobian(mech, q, backend=b)),
            ("compute_gamma", b, pin_call, lambda b=b: cc.compute_gamma(mech, q, v, backend=b)),
            (
                "project_velocity",
                b,
                pin_call,
                lambda b=b: cc.project_velocity(mech, q, v, backend=b),
            ),
            (
                "assemble",
                b,
                pin_call,
                lambda b=b: cc.assemble(mech, guess, fixed="independent", backend=b),
            ),
        ]
    a_pin = pin.constraintDynamics(mech.model, data, q, v, tau, cms, cds, prox)
    a_kkt = cc.forward_dynamics(mech, q, v, tau, method="kkt", backend="numpy").a
    facts = dict(nv=mech.nv, nc=mech.nc, pin_error=float(np.max(np.abs(a_pin - a_kkt))))
    return entries, facts


def run_percall(repeats: int = 5) -> tuple[list[dict], dict]:
    """Time :func:`percall_entries` at every size of :data:`PERCALL_SIZES`, interleaved
    (every call of every size once per repeat; median of the repeats), CPU time of this
    process, BLAS on one thread. Returns tidy rows and the facts of each size."""
    import numpy as np
    from threadpoolctl import threadpool_limits

    from closedchain.benchmark.scaling import _time_entries

    entries, facts = [], {}
    for n in PERCALL_SIZES:
        mine, facts[n] = percall_entries(n)
        entries += [(n, call, backend, ref, fn, False, []) for call, backend, ref, fn in mine]
    with threadpool_limits(limits=1, user_api="blas"):
        _time_entries(entries, repeats)
    us = {(n, call, backend): float(np.median(runs)) for n, call, backend, *_, runs in entries}
    return [
        dict(
            n=n,
            nv=facts[n]["nv"],
            nc=facts[n]["nc"],
            call=call,
            backend=backend,
            us=us[n, call, backend],
            reference=ref or "",
            ratio=us[n, call, backend] / us[n, ref, "C++"] if ref else float("nan"),
        )
        for n, call, backend, ref, *_ in entries
    ], facts


def percall_markdown(rows: list[dict], facts: dict) -> str:
    """The per-call tables: one per backend, a row per call, a column per size."""
    sizes = sorted(facts)
    head = " | ".join(f"n = {n} (nv {facts[n]['nv']})" for n in sizes)
    cell = {(r["n"], r["call"], r["backend"]): r for r in rows}

    def fmt(r: dict) -> str:
        us = r["us"]
        text = "failed" if us != us else (f"{us:.1f}" if us < 1000 else f"{us:.0f}")
        return text + (f" ({r['ratio']:.2f}x)" if r["reference"] and us == us else "")

    parts = []
    for backend, title in (
        ("C++", "References"),
        ("compiled", "Compiled core"),
        ("numpy", "numpy reference"),
    ):
        calls = list(dict.fromkeys(r["call"] for r in rows if r["backend"] == backend))
        lines = [
            f"### {title}",
            "",
            f"| call | reference | {head} |",
            "| --- | --- |" + " --- |" * len(sizes),
        ]
        for call in calls:
            first = cell[sizes[0], call, backend]
            cells = " | ".join(fmt(cell[n, call, backend]) for n in sizes)
            lines.append(f"| {call} | {first['reference'] or '-'} | {cells} |")
        parts.append("\n".join(lines))
    agree = ", ".join(f"{facts[n]['pin_error']:.1e} (n = {n})" for n in sizes)
    parts.append(
        "max |a_pin - a_kkt| of the reference call against closedchain's numpy kkt: " + agree + "."
    )
    return "\n\n".join(parts) + "\n"


def write_percall_page(out: Path) -> None:
    """Time the per-call functions (:func:`run_percall`) and write ``percall.csv`` and
    the generated page ``percall.md`` into ``out``."""
    command = "python scripts/bench_extras.py --parts percall"
    date = bench_page.today()
    load_before = bench_page.load_average()
    rows, facts = run_percall()
    write_rows(rows, out / "percall.csv", PERCALL_COLUMNS)
    head = bench_page.run_header(
        "Per-call cost of the public API",
        command=command,
        date=date,
        load_before=load_before,
        about="What runs where: [Backends of the per-call functions]"
        "(../guide/dynamics-methods.md#backends-of-the-per-call-functions).",
    )
    text = "\n".join(
        [
            *head,
            "CPU microseconds per call from Python (median of 5 interleaved repeats, same "
            "process, BLAS on one thread) on the n-link chain of the scaling page at its "
            "assembled start, moving; in brackets the ratio to the reference call: "
            "`pin.constraintDynamics` with one CONTACT_3D at the tip and ProximalSettings"
            f"{PERCALL_PROXIMAL} (containers, its own Data), for every call; `pin.rnea` (tree "
            "inverse dynamics) is listed beside it. `inverse_dynamics` prescribes and "
            "actuates the independent coordinates. "
            "`assemble` starts "
            f"{PERCALL_ASSEMBLY_OFFSET:g} rad (random directions) off the closure, holding "
            "the independent coordinates.",
            "",
            percall_markdown(rows, facts),
        ]
    )
    with atomic_write(out / "percall.md", "w") as f:
        f.write(text)


def run_couplings(paths: list[Path]) -> list[dict]:
    """Simulate every mechanism of ``paths`` for :data:`COUPLED_T_FINAL` from its
    ``q_ref`` at rest under the default settings (``closedchain simulate``'s), on the
    compiled core and on the numpy reference: CPU time of this process (BLAS on one
    thread), steps, and the largest |phi| over every declared row at the samples."""
    import time

    import numpy as np
    from threadpoolctl import threadpool_limits

    import closedchain as cc
    from closedchain.closure import max_declared_residual

    rows = []
    for path in paths:
        mech = cc.load(path)
        v0 = np.zeros(mech.nv)
        for backend in ("compiled", "numpy"):
            with threadpool_limits(limits=1, user_api="blas"):
                cpu = time.process_time()
                traj = cc.simulate(mech, mech.q_ref, v0, COUPLED_T_FINAL, backend=backend)
                cpu = time.process_time() - cpu
            max_phi = max_declared_residual(mech, traj.q)
            rows.append(
                dict(
                    model=path.name,
                    nv=mech.nv,
                    nc=mech.nc,
                    couplings=len(mech.declared.couplings),
                    backend=traj.info.backend,
                    cpu_s=cpu,
                    steps=traj.info.steps,
                    max_phi=max_phi,
                )
            )
    return rows


def write_couplings_page(out: Path, extra: list[Path]) -> None:
    """Run :func:`run_couplings` on :data:`COUPLED_MODELS` and ``extra`` and write
    ``couplings.csv`` and the generated page ``couplings.md`` into ``out``."""
    command = "python scripts/bench_extras.py --parts couplings" + "".join(
        f" --coupled {p}" for p in extra
    )
    date = bench_page.today()
    load_before = bench_page.load_average()
    rows = run_couplings([*COUPLED_MODELS, *extra])
    write_rows(rows, out / "couplings.csv", COUPLED_COLUMNS)
    head = bench_page.run_header(
        "Mechanisms with couplings: 1 s of simulate",
        command=command,
        date=date,
        load_before=load_before,
        about="Coupling rows: [Coupling loops and mimic joints]"
        "(../guide/mechanisms-and-loops.md#coupling-loops-and-mimic-joints).",
    )
    lines = [
        "| model | nv | rows (couplings) | backend | CPU [s] | steps | max abs phi |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        lines.append(
            f"| {r['model']} | {r['nv']} | {r['nc']} ({r['couplings']}) | {r['backend']} | "
            f"{r['cpu_s']:.3f} | {r['steps']} | {r['max_phi']:.1e} |"
        )
    text = "\n".join(
        [
            *head,
            f"CPU seconds of `closedchain.simulate(mech, mech.q_ref, 0, {COUPLED_T_FINAL:g})` "
            "under the default settings (one run each, this process, BLAS on one thread), "
            "on the compiled core and on the numpy reference, with the largest |phi| over "
            "every declared row (the couplings q_j - m q_i - c included) at the samples. "
            "The first two models are tests/data's; the others are local copies named "
            "by --coupled (shipped models, not in the repository).",
            "",
            *lines,
            "",
        ]
    )
    with atomic_write(out / "couplings.md", "w") as f:
        f.write(text)


def _read(path: Path) -> str:
    return path.read_text().strip() if path.exists() else f"({path.name} missing: part not run)"


def write_report(
    out: Path,
    wall: float | None,
    load: str | None,
    *,
    command: str = "bash scripts/make_bench_figures.sh",
    date: str | None = None,
) -> None:
    """Write ``results.md``, the generated results page, from the run's outputs in ``out``.

    Args:
        out: the output directory of the run (docs/bench): machine.txt, wp/, the tables.
        wall: wall time of the whole run [s], if recorded.
        load: load averages before / after the run, if recorded.
        command: the command that made the run, for the page header.
        date: the date of the run, for the page header (default: machine.txt's).
    """
    import csv

    wp = out / "wp"
    refs = (
        list(csv.DictReader(open(wp / "reference.csv"))) if (wp / "reference.csv").exists() else []
    )
    machine = [ln for ln in _read(out / "machine.txt").splitlines() if ln.strip()]
    code = [ln.removeprefix("commit ") for ln in machine if ln.startswith("commit ")]
    dates = [ln.removeprefix("date ") for ln in machine if ln.startswith("date ")]
    versions = [ln.removeprefix("version ") for ln in machine if ln.startswith("version ")]
    machine = [ln for ln in machine if not ln.startswith(("commit ", "date ", "version "))]
    lines = bench_page.header(
        "Benchmark results",
        command=command,
        date=date or (dates[0] if dates else ""),
        machine="; ".join(machine),
        code=code[0] if code else "",
        version=versions[0] if versions else "",
        extra={
            "load average (1, 5, 15 min) before / after": load or "",
            "wall time": f"{wall / 60:.1f} min" if wall else "",
        },
        about="What is measured and how: [Benchmark protocol](../benchmarks/protocol.md).",
    )
    lines += [
        "CPU times move with the machine's load; ratios from this one interleaved run carry "
        "over, single timings do not.",
        "",
        "## References",
        "",
        "Max coordinate difference of the confirmation from the reference over the horizon:",
        "",
        "| scenario | reference, confirmation | agreement [rad or m] |",
        "| --- | --- | --- |",
    ]
    lines += [f"| {r['scenario']} | {r['reference']} | {float(r['agreement']):.1e} |" for r in refs]
    rows = list(csv.DictReader(open(wp / "work_precision.csv"))) if refs else []
    lesson_backends = sorted({r["backend"] for r in rows if r["family"] == "lesson"})
    lines += [
        "",
        "## CPU at equal error",
        "",
        "closedchain CPU / peer CPU at equal error (< 1: closedchain cheaper; cheapest run "
        "of each family reaching the error; *interpolated on the fronts*: each side's CPU "
        "at exactly the error, log-log between the two runs of its Pareto front around it, "
        "which removes the luck of where a step or tolerance grid lands):",
        "",
        _read(wp / "ratios.md"),
        "",
        "The peer named lesson is the scheme of the lesson the project grew from "
        "([References](../references.md#lesson)): explicit Euler step, two Newton "
        "projections, no velocity projection (`closedchain.lesson_settings()` with kkt, "
        f"semi-implicit, projection), run by closedchain.simulate on the "
        f"{', '.join(lesson_backends) or '-'} backend, the core closedchain's own "
        "configurations use: not the lesson's Python program. Errors are taken on a 0.01 s "
        "grid, on the N-four-bar on a 0.05 s grid, "
        "so that fixed steps up to 0.05 s run there (a step runs where it divides the "
        "grid's spacing).",
        "",
        "## Stability map",
        "",
        "Largest step that stays ok (every declared row <= 1e-6, with every smaller step also ok):",
        "",
        _read(out / "stability.md"),
        "",
        "The N-four-bar case runs 20 s with steps up to 1 s: over a shorter horizon its "
        "parallelogram branch keeps every Euler step closed, and ok could not separate the "
        "configurations. The peer's limit there is the explicit-Euler bound dt < 2 / Kd of "
        "its Baumgarte velocity gain (Kd = 20). ok says nothing of accuracy: a 1 s step "
        "stays closed and finite, far from the motion.",
        "",
        "## Cost per evaluation",
        "",
        "CPU us per forward-dynamics call, median of repeats, same process:",
        "",
        _read(out / "evaluation.md"),
        "",
        "## Scaling",
        "",
        "Cost per evaluation against the size of a chain, a pair of legs and the "
        "N-four-bar, with fitted exponents: [Scaling](scaling.md) (generated by its own "
        "run).",
        "",
        "## Charts",
        "",
    ]
    charts = [(f"work-precision, {r['scenario']}", f"wp/wp_{r['scenario']}.png") for r in refs]
    charts += [("stability map", "stability.png")]
    for title, path in charts:
        if (out / path).exists():
            lines += [f"![{title}]({path})", ""]
    (out / "results.md").write_text("\n".join(lines).rstrip() + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs/bench")
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS))
    parser.add_argument("--number", type=int, default=500, help="calls per timing repeat")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument(
        "--report",
        action="store_true",
        help="only write results.md, the generated results page, from the outputs in --out",
    )
    parser.add_argument("--wall", type=float, help="wall time of the whole run [s] (report)")
    parser.add_argument("--load", help="load averages during the run (report)")
    parser.add_argument(
        "--command",
        default="bash scripts/make_bench_figures.sh",
        help="the command that made the run, for the page header (report)",
    )
    parser.add_argument("--date", help="date of the run, for the page header (report)")
    parser.add_argument(
        "--coupled",
        nargs="+",
        type=Path,
        default=[],
        help="more mechanisms with couplings for the couplings page (local copies)",
    )
    args = parser.parse_args()
    if args.workers < 1:
        parser.error(f"--workers must be at least 1, got {args.workers}")
    if args.number < 1:
        parser.error(f"--number must be at least 1, got {args.number}")
    if args.report:
        write_report(Path(args.out), args.wall, args.load, command=args.command, date=args.date)
        return
    logging.basicConfig(level=logging.INFO)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if "evaluation" in args.parts:
        rows = time_evaluations(
            [MODELS / "fourbar.urdf", MODELS / "agile_eye.urdf", MODELS / "nfourbar_2.urdf"],
            EvaluationSettings(number=args.number, repeats=5),
        )
        write_rows(rows, out / "evaluation.csv", EVALUATION_COLUMNS)
        with atomic_write(out / "evaluation.md", "w") as f:
            f.write(evaluation_markdown(rows))
    if "stability" in args.parts:
        from tqdm import tqdm

        jobs = make_stability_jobs(list(CASES), str(MODELS))
        # Costly jobs first so the pool's last minutes are not one long job.
        jobs.sort(key=lambda j: -CASES[j["case"]].t_final / j["step"])
        with tqdm(total=len(jobs), unit="run", desc="stability", disable=args.no_progress) as bar:
            rows = execute(jobs, fn=run_stability_job, workers=args.workers, progress=bar.update)
        write_rows(rows, out / "stability.csv", STABILITY_COLUMNS)
        plot_stability_map(rows, out / "stability.png")
        with atomic_write(out / "stability.md", "w") as f:
            f.write(stability_summary(rows))
    if "scaling" in args.parts:
        write_scaling_page(out, args.no_progress)
    if "percall" in args.parts:
        write_percall_page(out)
    if "couplings" in args.parts:
        write_couplings_page(out, args.coupled)


if __name__ == "__main__":
    main()
