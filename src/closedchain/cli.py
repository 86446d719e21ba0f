"""The ``closedchain`` command line: the only module that prints.

Subcommands are built in :func:`build_parser`; each has a ``_cmd_<name>``
handler that returns the process exit status.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from .exceptions import ClosedChainError

#: Options that must be finite and positive, by argparse attribute.
POSITIVE_OPTIONS = {
    "t_final": "--t-final",
    "fps": "--fps",
    "dt": "--dt",
    "rtol": "--rtol",
    "atol": "--atol",
}

#: Suffixes ``simulate --out`` can write (Trajectory.save).
TRAJECTORY_SUFFIXES = (".npz", ".csv")


def _fmt(x: float) -> str:
    return f"{x:.3e}"


def _print_table(rows: list[tuple[str, ...]], header: tuple[str, ...]) -> None:
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]
    line = "  ".join(h.ljust(w) for h, w in zip(header, widths, strict=True))
    print(line)
    print("  ".join("-" * w for w in widths))
    for r in rows:
        print("  ".join(str(c).ljust(w) for c, w in zip(r, widths, strict=True)))


def _load(args, path=None):
    from .mechanism import load

    path = args.file if path is None else path
    gravity = getattr(args, "gravity", None)
    return load(path) if gravity is None else load(path, gravity=gravity)


def _coordinate(token: str) -> str | int:
    """A ``--coordinates`` token: an integer is a velocity index, anything else a name."""
    try:
        return int(token)
    except ValueError:
        return token


def check_args(args: argparse.Namespace) -> None:
    """Check the values argparse cannot (ranges, output files) before any work is done.

    Raises:
        ClosedChainError: an option is out of range, an output file has an
            unsupported suffix, or its directory does not exist.
    """
    for attr, flag in POSITIVE_OPTIONS.items():
        value = getattr(args, attr, None)
        if value is not None and not (np.isfinite(value) and value > 0):
            raise ClosedChainError(f"{flag} must be a positive number, got {value:g}")
    samples = getattr(args, "samples", None)
    if samples is not None and samples < 1:
        raise ClosedChainError(f"--samples must be at least 1, got {samples}")
    out = getattr(args, "out", None)
    if out is not None and Path(out).suffix not in TRAJECTORY_SUFFIXES:
        raise ClosedChainError(
            f"cannot save a trajectory as {Path(out).name!r}; valid suffixes: "
            + ", ".join(TRAJECTORY_SUFFIXES)
        )
    for path in (out, getattr(args, "output", None)):
        if path is not None and not Path(path).parent.is_dir():
            raise ClosedChainError(f"{path}: directory {Path(path).parent} does not exist")
    if args.command == "plot":
        from .plotting import image_formats

        suffix = Path(args.output).suffix.lower().removeprefix(".")
        if suffix not in image_formats():
            raise ClosedChainError(
                f"cannot write an image as {Path(args.output).name!r}; supported suffixes: "
                + ", ".join("." + f for f in image_formats())
            )
        if args.urdf is not None and Path(args.file).suffix != ".npz":
            raise ClosedChainError("--urdf is for a .npz trajectory; FILE is already a URDF")


def _cmd_info(args) -> int:
    mech = _load(args)
    s = mech.summary()
    if args.json:
        print(json.dumps(s, indent=2))
        return 0
    print(f"mechanism {s['name']}  ({s['path']})")
    print(f"  nq = {s['nq']}, nv = {s['nv']}, gravity = {s['gravity']} m/s^2")
    print("\ntree")
    _print_table(
        [(t["joint"], t["type"], t["parent"], str(t["idx_q"]), str(t["idx_v"])) for t in s["tree"]],
        ("joint", "type", "parent", "idx_q", "idx_v"),
    )
    print("\nloops")
    _print_table(
        [
            (
                lp["name"],
                lp["type"],
                lp["predecessor"],
                lp["successor"],
                f"{len(lp['declared_rows'])} ({' '.join(lp['declared_rows'])})",
                f"{len(lp['independent_rows'])} ({' '.join(lp['independent_rows'])})",
            )
            for lp in s["loops"]
        ],
        ("loop", "type", "predecessor", "successor", "declared rows", "independent rows"),
    )
    print(
        f"\nconstraint rows: {s['declared_rows']} declared, {s['independent_rows']} independent;"
        f" mobility {s['mobility']}"
    )
    print(f"actuated coordinates:    {', '.join(s['actuated']) or 'none'}")
    print(f"independent coordinates: {', '.join(s['independent'])} ({s['independent_source']})")
    print(f"dependent coordinates:   {', '.join(s['dependent'])}")
    print(
        "assembled configuration q_ref = "
        + np.array2string(np.array(s["q_ref"]), precision=6, max_line_width=100)
    )
    if not s["pinocchio_reference"]:
        print("note: no Pinocchio reference for this mechanism's loop types (prismatic)")
    return 0


def _cmd_validate(args) -> int:
    from .validation import validate

    mech = _load(args)
    rep = validate(mech, n_samples=args.samples, seed=args.seed, method=args.method)
    if args.json:
        print(json.dumps(rep.as_dict(), indent=2))
    else:
        print(
            f"{mech.name}: method {rep.method!r} vs pinocchio.constraintDynamics at "
            f"{rep.n_samples} random consistent states (seed {rep.seed})"
        )
        _print_table(
            [
                (
                    "max |a - a_pin|",
                    _fmt(rep.max_da),
                    _fmt(rep.tol_a),
                    "ok" if rep.max_da <= rep.tol_a else "FAIL",
                ),
                (
                    "max |J^T lam - J^T lam_pin| (rel. above 1)",
                    _fmt(rep.max_dforce),
                    _fmt(rep.tol_force),
                    "ok" if rep.max_dforce <= rep.tol_force else "FAIL",
                ),
                ("max |J a + gamma| (ours)", _fmt(rep.max_constraint_residual), "", ""),
                (
                    "max |J a_pin + gamma| (Pinocchio)",
                    _fmt(rep.max_pin_constraint_residual),
                    "",
                    "",
                ),
            ],
            ("quantity", "value", "tolerance", "status"),
        )
        if rep.n_singular:
            print(f"{rep.n_singular} states refused as singular")
        print("PASSED" if rep.passed else "FAILED")
    return 0 if rep.passed else 1


def _cmd_animate(args) -> int:
    from .visualize import write_html

    mech = _load(args)
    traj = simulate_from_args(args, mech)
    out = write_html(mech, traj, args.output, fps=args.fps)
    print(
        f"wrote {out.path} ({out.size / 1e6:.2f} MB; {out.duration:.3g} s at {out.fps:g} fps, "
        f"{out.n_keyframes} keyframes x {out.n_tracks} tracks)"
    )
    return 0


def _cmd_plot(args) -> int:
    from .plotting import plot_trajectory
    from .trajectory import Trajectory

    if Path(args.file).suffix == ".npz":
        traj = Trajectory.load(args.file)
        mech = None if args.urdf is None else _load(args, args.urdf)
    else:
        mech = _load(args)
        traj = simulate_from_args(args, mech)
    fig = plot_trajectory(traj, mech=mech, coordinates=args.coordinates)
    fig.savefig(args.output)
    print(f"wrote {args.output}")
    return 0


def add_simulation_arguments(p: argparse.ArgumentParser) -> None:
    """Add the options of ``closedchain simulate`` (shared by ``animate`` and ``plot``)."""
    from .dynamics import METHODS
    from .simulate import INTEGRATORS, STABILIZATIONS

    p.add_argument("--t-final", type=float, default=5.0, help="duration [s] (default 5)")
    p.add_argument("--method", default="kkt", choices=sorted(METHODS), help="dynamics method")
    p.add_argument(
        "--integrator", default="DOP853", choices=sorted(INTEGRATORS), help="time integrator"
    )
    step = p.add_mutually_exclusive_group()
    step.add_argument("--dt", type=float, help="fixed step [s] (fixed-step integrators)")
    step.add_argument("--rtol", type=float, help="relative tolerance (adaptive integrators)")
    p.add_argument("--atol", type=float, help="absolute tolerance (adaptive integrators)")
    p.add_argument(
        "--stabilization",
        default=None,
        choices=sorted(STABILIZATIONS),
        help="drift control (default: projection for fixed-step, none for adaptive)",
    )
    p.add_argument(
        "--q0",
        type=float,
        nargs="+",
        metavar="Q",
        help="initial configuration (nq numbers, assembled before the run; default: q_ref)",
    )
    p.add_argument("--fps", type=float, default=30.0, help="output samples per second")


def simulate_from_args(args, mech):
    """Run the simulation the shared options describe; return the Trajectory."""
    from .kinematics import assemble
    from .simulate import simulate

    q0 = mech.q_ref if args.q0 is None else assemble(mech, np.array(args.q0), fixed="independent")
    v0 = np.zeros(mech.nv)
    n = int(round(args.t_final * args.fps)) + 1
    bar = None
    if not getattr(args, "json", False) and sys.stderr.isatty():
        from tqdm import tqdm

        bar = tqdm(
            total=args.t_final,
            unit="s sim",
            leave=False,
            file=sys.stderr,
            bar_format="{l_bar}{bar}| {n:.2f}/{total:.2f} s [{elapsed}<{remaining}]",
        )

    def progress(t: float) -> None:
        bar.update(t - bar.n)

    try:
        return simulate(
            mech,
            q0,
            v0,
            args.t_final,
            method=args.method,
            integrator=args.integrator,
            dt=args.dt,
            rtol=args.rtol,
            atol=args.atol,
            stabilization=args.stabilization,
            t_eval=np.linspace(0.0, args.t_final, n),
            progress=progress if bar else None,
        )
    finally:
        if bar is not None:
            bar.close()


def _cmd_simulate(args) -> int:
    from .plotting import coordinate_series

    mech = _load(args)
    traj = simulate_from_args(args, mech)
    info = traj.info
    summary = {
        "mechanism": mech.name,
        "method": info["method"],
        "integrator": info["integrator"],
        "stabilization": info["stabilization"],
        "t_final": info["t_final"],
        "steps": info["steps"],
        "evaluations": info["evaluations"],
        "cpu_time_s": info["cpu_time"],
        "max_constraint_residual": traj.max_constraint_residual,
        "max_velocity_residual": float(np.max(traj.velocity_residual)),
        "energy_drift": traj.energy_drift,
        "repartitions": len(info["repartitions"]),
        "final_independent": {
            mech.coordinate_names[i]: float(coordinate_series(mech, traj.q[-1], i))
            for i in mech.independent_idx_v
        },
    }
    if args.out:
        summary["out"] = str(traj.save(args.out))
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    print(
        f"{mech.name}: {summary['t_final']:g} s with method {summary['method']!r}, "
        f"integrator {summary['integrator']!r}, stabilization {summary['stabilization']!r}"
    )
    _print_table(
        [
            ("steps", str(summary["steps"])),
            ("dynamics evaluations", str(summary["evaluations"])),
            ("CPU time", f"{summary['cpu_time_s']:.3f} s"),
            ("max constraint residual |phi|", _fmt(summary["max_constraint_residual"])),
            ("max velocity residual |J v|", _fmt(summary["max_velocity_residual"])),
            ("relative energy drift", _fmt(summary["energy_drift"])),
            ("re-partitions", str(summary["repartitions"])),
        ],
        ("quantity", "value"),
    )
    if args.out:
        print(f"trajectory written to {summary['out']}")
    return 0


def _cmd_export_mjcf(args) -> int:
    from .export.mjcf import STIFF, MjcfSettings, export_mjcf

    mech = _load(args)
    settings = STIFF if args.stiff else MjcfSettings()
    export_mjcf(mech, args.output, settings=settings)
    print(f"wrote {args.output}")
    return 0


def _cmd_bench(args) -> int:
    from tqdm import tqdm

    from .benchmark import QUICK, BenchSettings, run_work_precision

    if args.workers < 1:
        raise ClosedChainError(f"--workers must be at least 1, got {args.workers}")
    settings = QUICK if args.quick else BenchSettings()
    if args.repeats is not None:
        if args.repeats < 1:
            raise ClosedChainError(f"--repeats must be at least 1, got {args.repeats}")
        settings = replace(settings, repeats=args.repeats)
    bar = tqdm(total=1, unit="run", disable=args.no_progress)

    def progress(done: int, total: int) -> None:
        bar.total = total
        bar.n = done
        bar.refresh()

    rows, checks = run_work_precision(
        args.out_dir,
        settings=settings,
        scenarios=args.scenarios,
        models_dir=args.models,
        workers=args.workers,
        scheduler=args.scheduler,
        progress=progress,
    )
    bar.close()
    for c in checks:
        print(f"reference {c.scenario}: confirmed to {c.agreement:.2e} (max coordinate difference)")
    print((Path(args.out_dir) / "ratios.md").read_text())
    print(f"wrote {len(rows)} rows to {Path(args.out_dir) / 'work_precision.csv'}")
    return 0


def _cmd_workspace(args) -> int:
    from .workspace import plot_workspace

    mech = _load(args)
    outputs = tuple(args.outputs) if args.outputs else None
    print(plot_workspace(mech, args.output, points=args.points, outputs=outputs, span=args.span))
    print(f"wrote {args.output}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser with every subcommand."""
    from .dynamics import METHODS

    parser = argparse.ArgumentParser(
        prog="closedchain",
        description="Dynamics of closed-chain mechanisms (URDF + <loop>) on top of Pinocchio.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress")
    sub = parser.add_subparsers(dest="command", required=True)

    def add(name: str, help_: str, handler) -> argparse.ArgumentParser:
        p = sub.add_parser(name, help=help_, description=help_)
        p.add_argument("file", help="URDF file with <loop> elements")
        p.add_argument(
            "--gravity",
            type=float,
            nargs=3,
            metavar=("GX", "GY", "GZ"),
            help="gravity in the world frame [m/s^2] (default 0 0 -9.81)",
        )
        p.set_defaults(handler=handler)
        return p

    p = add("info", "show the tree, loops, constraint rows, mobility and coordinates", _cmd_info)
    p.add_argument("--json", action="store_true", help="print JSON")

    p = add("validate", "compare forward dynamics with pinocchio.constraintDynamics", _cmd_validate)
    p.add_argument("--samples", type=int, default=100, help="random consistent states")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    # "pinocchio" is the reference itself: comparing it with itself checks nothing.
    p.add_argument(
        "--method",
        default="kkt",
        choices=sorted(set(METHODS) - {"pinocchio"}),
        help="method to check",
    )
    p.add_argument("--json", action="store_true", help="print the report as JSON")

    p = add(
        "simulate", "integrate the constrained dynamics and report accuracy and cost", _cmd_simulate
    )
    add_simulation_arguments(p)
    p.add_argument("--out", help="write the trajectory (.npz or .csv)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")

    p = add("animate", "simulate and write a self-contained HTML animation (meshcat)", _cmd_animate)
    add_simulation_arguments(p)
    p.add_argument("-o", "--output", required=True, help="HTML file to write")

    p = add(
        "export-mjcf",
        "write the mechanism as MuJoCo MJCF (loops as connect/weld equality constraints)",
        _cmd_export_mjcf,
    )
    p.add_argument("-o", "--output", required=True, help="MJCF file to write")
    p.add_argument(
        "--stiff",
        action="store_true",
        help="stiff equality solref/solimp (closer to exact closure, needs a smaller timestep)",
    )

    p = add(
        "workspace",
        "4-bar: Grashof class and crank range; otherwise a singularity map (type I / II)",
        _cmd_workspace,
    )
    p.add_argument("-o", "--output", required=True, help="image file to write")
    p.add_argument("--points", type=int, help="sweep / grid points per axis")
    p.add_argument("--outputs", nargs="+", metavar="JOINT", help="output coordinates (map)")
    p.add_argument(
        "--span", type=float, default=1.5, help="half-width of the map around q_ref [rad]"
    )

    help_ = "work-precision benchmark of closedchain beside its peers (CSV, ratio table, charts)"
    p = sub.add_parser("bench", help=help_, description=help_)
    p.add_argument("--quick", action="store_true", help="4-bar only, 2 s, few settings, 1 repeat")
    p.add_argument(
        "--out", dest="out_dir", default="bench-out", help="output directory (default bench-out)"
    )
    p.add_argument("--workers", type=int, default=1, help="local worker processes")
    p.add_argument(
        "--scheduler", metavar="ADDRESS", help="Dask distributed scheduler (tcp://host:port)"
    )
    p.add_argument("--models", default="models", help="directory of the scenarios' URDF files")
    p.add_argument("--scenarios", nargs="+", metavar="NAME", help="scenario names (default all)")
    p.add_argument("--repeats", type=int, help="runs per configuration (CPU is their median)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(handler=_cmd_bench)

    help_ = "plot coordinates, constraint residual and energy drift against time (PNG, PDF, SVG)"
    p = sub.add_parser("plot", help=help_, description=help_)
    p.add_argument("file", help="trajectory (.npz from Trajectory.save) or URDF file to simulate")
    p.add_argument(
        "--urdf",
        metavar="URDF",
        help="the mechanism of a .npz trajectory: gives joint types and units; needed"
        " when nq != nv (continuous joints)",
    )
    p.add_argument(
        "--gravity",
        type=float,
        nargs=3,
        metavar=("GX", "GY", "GZ"),
        help="gravity in the world frame [m/s^2] (URDF input; default 0 0 -9.81)",
    )
    add_simulation_arguments(p)
    p.add_argument(
        "--coordinates",
        nargs="+",
        type=_coordinate,
        metavar="COORD",
        help="joint names or velocity indices (0..nv-1) to plot (default: independent)",
    )
    p.add_argument(
        "-o",
        "--output",
        required=True,
        help="image file to write; its suffix gives the format (.png, .pdf, .svg, ...)",
    )
    p.set_defaults(handler=_cmd_plot)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; return the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING)
    try:
        check_args(args)
        return int(args.handler(args))
    except (ClosedChainError, OSError) as exc:
        # OSError: a file the command writes cannot be (no such directory, no permission).
        print(f"closedchain: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
