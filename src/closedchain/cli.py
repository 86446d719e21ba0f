"""The ``closedchain`` command line: the only module that prints.

Subcommands are built in :func:`build_parser`; each has a ``_cmd_<name>``
handler that returns the process exit status.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import re
import signal
import sys
import threading
import traceback
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from ._io import STDERR_LOCK
from .exceptions import (
    MESSAGE_MAX,
    ClosedChainError,
    NonFiniteError,
    SingularConfigurationError,
    UnknownChoiceError,
    format_upper_bound,
    resolve_choice,
    shorten,
)
from .simulate.settings import DEFAULT_ENERGY_TOL
from .visualize.settings import DEFAULT_SETTINGS as DEFAULT_ANIMATION
from .visualize.settings import MEGABYTE

#: Exit statuses of the ``closedchain`` command (documented in ``--help`` and the README).
EXIT_OK = 0
#: A check ran and FAILED (``validate`` beyond its tolerances).
EXIT_FAILED = 1
#: Bad input: an option, a file or a value refused before or during the work.
EXIT_BAD_INPUT = 2
#: A simulation stopped at a singular configuration or a non-finite or drifting state.
EXIT_STOPPED = 3
#: An internal error (a bug): the traceback is printed with ``--debug``.
EXIT_INTERNAL = 4
#: Interrupted by SIGINT (Ctrl-C): 128 + 2, as shells report it.
EXIT_INTERRUPTED = 130
#: Terminated by SIGTERM: 128 + 15, as shells report it.
EXIT_TERMINATED = 143

EXIT_STATUS_HELP = f"""exit status:
  {EXIT_OK}  success
  {EXIT_FAILED}  a check ran and FAILED (validate beyond its tolerances)
  {EXIT_BAD_INPUT}  bad input (options, files, values); one-line message
  {EXIT_STOPPED}  a simulation stopped: singular configuration, non-finite state or
     drift beyond the limit (animate still writes the animation up to the stop)
  {EXIT_INTERNAL}  internal error (a bug; add --debug for the traceback)
  {EXIT_INTERRUPTED}  interrupted (SIGINT, Ctrl-C); a file being written is left as it was
  {EXIT_TERMINATED}  terminated (SIGTERM); likewise"""

#: Options that must be finite and positive, by argparse attribute.
POSITIVE_OPTIONS = {
    "t_final": "--t-final",
    "fps": "--fps",
    "dt": "--dt",
    "rtol": "--rtol",
    "atol": "--atol",
    "span": "--span",
    "energy_tol": "--energy-tol",
    "closure_tol": "--closure-tol",
}

#: A Dask scheduler address: [protocol://]host:port.
SCHEDULER_ADDRESS = re.compile(
    r"(?:[a-z][a-z0-9+.-]*://)?(?:\[[0-9a-fA-F:]+\]|[^\s:/\[\]]+):\d{1,5}"
)

#: Default of ``--closure-tol`` [m or rad]: SimulationSettings.drift_limit on the command line.
DEFAULT_CLOSURE_TOL = 1e-6

#: Named choices of ``--torque`` (numbers, one per actuated joint, are accepted too).
TORQUES = ("zero", "gravity")

#: Suffixes ``simulate --out`` can write (Trajectory.save).
TRAJECTORY_SUFFIXES = (".npz", ".csv")

#: What each command writes and its valid suffixes (None: the image formats
#: matplotlib writes, :func:`closedchain.plotting.image_formats`).
OUTPUT_SUFFIXES = {
    "simulate": ("save a trajectory", TRAJECTORY_SUFFIXES),
    "animate": ("write an HTML animation", (".html",)),
    "export-mjcf": ("write MJCF", (".xml",)),
    "plot": ("write an image", None),
    "workspace": ("write an image", None),
}

#: Options naming input files, by argparse attribute (an output must not be one of them).
INPUT_OPTIONS = {"file": "FILE", "loops": "--loops", "urdf": "--urdf"}

#: Options naming output files, by argparse attribute.
OUTPUT_OPTIONS = {"out": "--out", "output": "-o/--output"}


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
    options = {"root_joint": getattr(args, "root", None), "loops": getattr(args, "loops", None)}
    gravity = getattr(args, "gravity", None)
    if gravity is not None:
        options["gravity"] = gravity
    keyframe = getattr(args, "keyframe", None)
    if keyframe is not None:
        options["keyframe"] = keyframe
    return load(path, **options)


def add_model_arguments(p: argparse.ArgumentParser, gravity_note: str = "") -> None:
    """Add ``--root``, ``--loops``, ``--gravity`` and ``--keyframe``, options of
    :func:`closedchain.load`."""
    p.add_argument(
        "--root",
        choices=("free", "planar"),
        help="joint between the world and the URDF's root link (default: fixed)",
    )
    p.add_argument(
        "--loops",
        metavar="FILE",
        help="URDF+ overlay whose links, joints, <loop> and <transmission> elements are"
        " merged into the tree, or a .yaml/.yml file of example-parallel-robots"
        " (closed_loop, type, name_mot, joint_name/joint_type)",
    )
    p.add_argument(
        "--gravity",
        type=float,
        nargs=3,
        metavar=("GX", "GY", "GZ"),
        help=f"gravity in the world frame [m/s^2] ({gravity_note}default 0 0 -9.81)",
    )
    p.add_argument(
        "--keyframe",
        metavar="NAME",
        help="MJCF models: the <key> the assembly starts from (default: the first keyframe)",
    )


def _choice(choices):
    """Return an argparse ``type`` that maps a name in any case to its registered spelling.

    An unknown name is passed through unchanged, so that argparse's ``choices``
    check refuses it with the list of valid choices (exit status 2).
    """

    def convert(value: str) -> str:
        try:
            return resolve_choice("choice", value, choices)
        except UnknownChoiceError:
            return value

    return convert


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
    for attr, (flag, low, high) in _count_options().items():
        value = getattr(args, attr, None)
        if value is not None and value < low:
            raise ClosedChainError(f"{flag} must be at least {low}, got {value}")
        if value is not None and high is not None and value > high:
            raise ClosedChainError(f"{flag} must be at most {high}, got {value}")
    if getattr(args, "fps", None) is not None and getattr(args, "t_final", None) is not None:
        if args.command == "animate":  # the tighter bound first
            _check_sample_count(
                args.t_final,
                args.fps,
                DEFAULT_ANIMATION.max_keyframes,
                "keyframes",
                "AnimationSettings.max_keyframes",
            )
        output_times(args.t_final, args.fps)  # checks the sample count before any work
    budget = getattr(args, "mesh_budget", None)
    if budget is not None and not (np.isfinite(budget) and budget >= 0):
        raise ClosedChainError(f"--mesh-budget must be a number of MB >= 0, got {budget:g}")
    if getattr(args, "torque", None) is not None:
        torque_values(args.torque)
    outputs = _check_output_suffix(args)
    for path in outputs.values():
        if not Path(path).parent.is_dir():
            raise ClosedChainError(f"{path}: directory {Path(path).parent} does not exist")
    _check_outputs_are_not_inputs(args, outputs)
    outputs_option = getattr(args, "outputs", None) or ()
    repeated = sorted({name for name in outputs_option if outputs_option.count(name) > 1})
    if repeated:
        raise ClosedChainError(
            f"--outputs names {', '.join(repeated)} more than once; valid: distinct joints"
        )
    scheduler = getattr(args, "scheduler", None)
    if scheduler is not None and not SCHEDULER_ADDRESS.fullmatch(scheduler):
        raise ClosedChainError(
            f"--scheduler {scheduler!r} is not a scheduler address; valid: "
            "[protocol://]host:port, e.g. tcp://127.0.0.1:8786"
        )
    if args.command == "plot":
        if Path(args.file).suffix.lower() == ".csv":
            raise ClosedChainError(
                f"{args.file}: plot reads a .npz trajectory or a URDF file to simulate; "
                "a .csv trajectory is for spreadsheets (save it as .npz to plot it)"
            )
        if args.urdf is not None and Path(args.file).suffix != ".npz":
            raise ClosedChainError("--urdf is for a .npz trajectory; FILE is already a URDF")


def _count_options() -> dict[str, tuple[str, int, int | None]]:
    """Integer options by argparse attribute: (flag, smallest, largest or None)."""
    from .benchmark.runner import MAX_REPEATS, MAX_WORKERS
    from .validation import MAX_VALIDATION_SAMPLES

    return {
        "samples": ("--samples", 1, MAX_VALIDATION_SAMPLES),
        "seed": ("--seed", 0, None),  # numpy's generators take no negative seed
        "workers": ("--workers", 1, MAX_WORKERS),
        "repeats": ("--repeats", 1, MAX_REPEATS),
    }


def _check_output_suffix(args: argparse.Namespace) -> dict[str, str]:
    """Refuse an output file whose suffix the command cannot write; return the outputs by flag.

    Raises:
        ClosedChainError: the suffix is not one the command writes (lists the valid ones).
    """
    outputs = {
        flag: getattr(args, attr)
        for attr, flag in OUTPUT_OPTIONS.items()
        if getattr(args, attr, None) is not None
    }
    for path in outputs.values():
        action, valid = OUTPUT_SUFFIXES[args.command]
        suffix = Path(path).suffix
        if valid is None:
            from .plotting import image_formats

            valid = tuple("." + f for f in image_formats())
            suffix = suffix.lower()
        if suffix not in valid:
            raise ClosedChainError(
                f"cannot {action} as {Path(path).name!r}; valid suffixes: {', '.join(valid)}"
            )
    return outputs


def _check_outputs_are_not_inputs(args: argparse.Namespace, outputs: dict[str, str]) -> None:
    """Refuse an output file that is one of the command's input files (same file on disk).

    Raises:
        ClosedChainError: an output and an input are the same file.
    """
    for out_flag, out in outputs.items():
        if not os.path.exists(out):
            continue
        for attr, in_flag in INPUT_OPTIONS.items():
            path = getattr(args, attr, None)
            if path is None or not os.path.exists(path):
                continue  # erd:<name>, or a missing file (reported when it is read)
            if os.path.samefile(out, path):
                raise ClosedChainError(
                    f"{out_flag} {out} is the input file {in_flag} {path}; writing it would "
                    "destroy the input: give another output file"
                )


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
    rs = s["row_selection"]
    print(
        f"row selection: rank {rs['rank']} of J over {rs['n_samples']} configurations along the "
        f"motion ({rs['n_singular']} singular, set aside); worst sigma_min(J_kept)/|J| "
        f"{rs['margin']:.3g}; dropped: {' '.join(rs['dropped']) or 'none'}"
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
        how = (
            "Pinocchio's answer refined by one step of iterative refinement of its own system"
            if rep.reference == "pinocchio.constraintDynamics"
            else "the couplings as Pinocchio mimic joints, compared on the primary joints"
        )
        print(
            f"{mech.name}: method {rep.method!r} vs {rep.reference} at "
            f"{rep.n_samples} random consistent states (seed {rep.seed}); {how}"
        )
        _print_table(
            [
                (
                    "max |a - a_pin|_M (mass-matrix norm, rel. above 1)",
                    _fmt(rep.max_da_mass_norm),
                    _fmt(rep.tol_a),
                    "ok" if rep.max_da_mass_norm <= rep.tol_a else "FAIL",
                ),
                ("max |a - a_pin|", _fmt(rep.max_da), "", ""),
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
                (
                    "max |a - a_pin| (single unrefined call)",
                    _fmt(rep.max_da_unrefined),
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


def run_or_stop(args, mech, *, min_samples: int = 1):
    """Run :func:`simulate_from_args`; return ``(trajectory, None)``, or the motion up to a
    stop and the error that stopped it (singular configuration, drift, inaccurate energy).

    Nothing is lost: the commands write what was computed, then exit with
    :data:`EXIT_STOPPED`. A stop with fewer than ``min_samples`` samples is raised.
    """
    from .simulate import SimulationError

    try:
        return simulate_from_args(args, mech), None
    except (SingularConfigurationError, SimulationError) as exc:
        if exc.trajectory is None or len(exc.trajectory.t) < min_samples:
            raise
        return exc.trajectory, exc


def report_stop(stopped, traj, what: str) -> int:
    """Print the one-line error of a stopped run after its output ``what`` was written
    from ``traj``; return the exit status (:data:`EXIT_OK` when ``stopped`` is None)."""
    if stopped is None:
        return EXIT_OK
    message = str(stopped).replace("\n", " ")
    print_error(f"closedchain: error: {message} ({what} up to t = {traj.t[-1]:.6g} s)")
    return EXIT_STOPPED


def _cmd_animate(args) -> int:
    from .visualize import write_html

    mech = _load(args)
    traj, stopped = run_or_stop(args, mech, min_samples=2)
    stop = None if stopped is None else f"Simulation stopped at t = {stopped.t:.6g} s: {stopped}"
    settings = replace(DEFAULT_ANIMATION, mesh_budget_bytes=round(args.mesh_budget * MEGABYTE))
    out = write_html(mech, traj, args.output, fps=args.fps, stop=stop, settings=settings)
    meshes = f"; {out.meshes.describe()}" if out.meshes.has_meshes else ""
    print(
        f"wrote {out.path} ({out.size / MEGABYTE:.2f} MB; {out.duration:.3g} s at {out.fps:g} "
        f"fps, {out.n_keyframes} keyframes x {out.n_tracks} tracks{meshes})"
    )
    return report_stop(stopped, traj, "animation written")


def _cmd_plot(args) -> int:
    from ._io import save_figure
    from .plotting import plot_trajectory
    from .trajectory import Trajectory

    if Path(args.file).suffix == ".npz":
        traj = Trajectory.load(args.file)
        mech = None if args.urdf is None else _load(args, args.urdf)
        stopped = None
    else:
        mech = _load(args)
        traj, stopped = run_or_stop(args, mech)
    fig = plot_trajectory(traj, mech=mech, coordinates=args.coordinates)
    save_figure(fig, args.output)
    print(f"wrote {args.output}")
    return report_stop(stopped, traj, "plot written")


def add_simulation_arguments(p: argparse.ArgumentParser) -> None:
    """Add the options of ``closedchain simulate`` (shared by ``animate`` and ``plot``)."""
    from .dynamics import DEFAULT_METHOD, METHODS
    from .simulate import INTEGRATORS, STABILIZATIONS

    p.add_argument("--t-final", type=float, default=5.0, help="duration [s] (default 5)")
    p.add_argument(
        "--method",
        default=DEFAULT_METHOD,
        type=_choice(METHODS),
        choices=sorted(METHODS),
        help="dynamics method, any case (default augmented-lagrangian: passes singular positions)",
    )
    p.add_argument(
        "--integrator",
        default=None,
        type=_choice(INTEGRATORS),
        choices=sorted(INTEGRATORS),
        help="time integrator, any case (default dop853-rk43: DOP853 where J is regular, "
        "rk43 near singular positions, error control under --rtol/--atol; rk4 when --dt "
        "is given)",
    )
    step = p.add_mutually_exclusive_group()
    step.add_argument("--dt", type=float, help="fixed step [s] (fixed-step integrators)")
    step.add_argument("--rtol", type=float, help="relative tolerance (adaptive integrators)")
    p.add_argument("--atol", type=float, help="absolute tolerance (adaptive integrators)")
    p.add_argument(
        "--stabilization",
        default=None,
        type=_choice(STABILIZATIONS),
        choices=sorted(STABILIZATIONS),
        help="drift control, any case (default: stage-projection for rk43/euler/"
        "semi-implicit/rk4, mass-orthogonal for ali3p, none for the other adaptive ones)",
    )
    p.add_argument(
        "--q0",
        type=float,
        nargs="+",
        metavar="Q",
        help="initial configuration (nq numbers, assembled before the run, released from rest;"
        " default: the URDF's <scene>, else rest at q_ref)",
    )
    p.add_argument(
        "--torque",
        nargs="+",
        default=["zero"],
        metavar="TAU",
        help="actuator torque: zero; gravity, the constant torque that holds q0 at rest against"
        " gravity (closed-chain inverse dynamics; needs actuators for every degree of freedom);"
        " or constant torques [N m or N], one number per actuated joint (as `info` lists them)",
    )
    p.add_argument(
        "--energy-tol",
        type=float,
        default=DEFAULT_ENERGY_TOL,
        help="largest relative energy balance (the energy drift, less the work of the torque)"
        f" before a run is reported as inaccurate (exit {EXIT_STOPPED}; default %(default)g)",
    )
    p.add_argument(
        "--closure-tol",
        type=float,
        default=DEFAULT_CLOSURE_TOL,
        help="largest max |phi| [m or rad] over the run before it stops "
        f"(exit {EXIT_STOPPED}; default %(default)g)",
    )
    p.add_argument(
        "--ignore-limits",
        action="store_true",
        help="start even where q0 is outside the URDF joint limits",
    )
    p.add_argument("--fps", type=float, default=30.0, help="output samples per second")


def output_times(t_final: float, fps: float) -> np.ndarray:
    """Return the output times of a run of ``t_final`` seconds at ``fps`` samples per second.

    At least the start and the end are kept (``--fps`` below 1 / t_final keeps
    those two); the count is checked against ``SimulationSettings.max_outputs``
    before the array is made.

    Raises:
        ClosedChainError: more samples than ``SimulationSettings.max_outputs``.
    """
    from .simulate.settings import DEFAULT_SIMULATION_SETTINGS

    n = _check_sample_count(
        t_final,
        fps,
        DEFAULT_SIMULATION_SETTINGS.max_outputs,
        "output samples",
        "SimulationSettings.max_outputs",
    )
    return np.linspace(0.0, t_final, max(n, 2))


def _check_sample_count(t_final: float, fps: float, limit: int, what: str, setting: str) -> int:
    """Return the samples of ``t_final`` s at ``fps`` (start and end included), at most ``limit``.

    Raises:
        ClosedChainError: more than ``limit`` samples (the message names
            ``setting`` and the valid ``--fps``).
    """
    frames = t_final * fps  # a float: inf when it overflows
    n = math.ceil(frames - 1e-9) + 1 if math.isfinite(frames) else math.inf
    if n > limit:
        raise ClosedChainError(
            f"--fps {fps:g} over --t-final {t_final:g} s is {shorten(n, 20)} {what}, more than "
            f"the limit {limit} ({setting}); "
            f"valid --fps: (0, {format_upper_bound((limit - 1) / t_final)}]"
        )
    return n


def torque_values(tokens: Sequence[str]) -> np.ndarray | None:
    """Return the numbers of ``--torque`` [N m or N], or None for a name in :data:`TORQUES`.

    Raises:
        ClosedChainError: neither one name of :data:`TORQUES` nor finite numbers.
    """
    if len(tokens) == 1 and tokens[0] in TORQUES:
        return None
    try:
        values = np.array([float(x) for x in tokens])
    except ValueError:
        values = np.array([np.nan])
    if not np.all(np.isfinite(values)):
        raise ClosedChainError(
            f"--torque {' '.join(tokens)}: valid: {' or '.join(TORQUES)}, or finite numbers "
            "[N m or N], one per actuated joint"
        )
    return values


def actuator_torque(mech, values: np.ndarray) -> np.ndarray:
    """Return the generalized force tau, shape (nv,), of constant actuator torques.

    Args:
        mech: the mechanism.
        values: one torque [N m or N] per actuated coordinate, in the order of
            ``Mechanism.actuated_idx_v``.

    Raises:
        ClosedChainError: not one value per actuated coordinate (names them).
    """
    idx = mech.actuated_idx_v
    if len(values) != len(idx):
        names = ", ".join(mech.coordinate_names[i] for i in idx) or "none"
        raise ClosedChainError(
            f"--torque takes {len(idx)} number(s) for {mech.name}, got {len(values)}; "
            f"actuated joints (<transmission>): {names}"
        )
    tau = np.zeros(mech.nv)
    tau[idx] = values
    return tau


def simulate_from_args(args, mech):
    """Run the simulation the shared options describe; return the Trajectory."""
    from .control import default_scene
    from .kinematics import assemble
    from .simulate import SimulationSettings, simulate

    torque = getattr(args, "torque", ["zero"])
    values = torque_values(torque)
    constant = None if values is None else actuator_torque(mech, values)  # before any work
    if args.q0 is None:
        scene = default_scene(mech)  # the <scene> element of the URDF, or rest at q_ref
        q0, v0, tau = scene.q0, scene.v0, scene.tau
        logging.getLogger(__name__).info("%s: default scene: %s", mech.name, scene.description)
    else:
        q0 = assemble(mech, mech.check_q(args.q0, "--q0"), fixed="independent")
        v0, tau = np.zeros(mech.nv), None
    if torque == ["gravity"]:
        from .control import gravity_torque

        if mech.mobility == 0:
            raise ClosedChainError(
                f"--torque gravity: {mech.name} has no degree of freedom (mobility 0): nothing "
                "to hold, the loops carry the load; valid: --torque zero"
            )

        tau = gravity_torque(mech, q0)
    elif constant is not None:
        tau = constant
    t_eval = output_times(args.t_final, args.fps)
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
            t_eval=t_eval,
            tau=tau,
            settings=SimulationSettings(
                check_limits=not args.ignore_limits,
                energy_tol=args.energy_tol,
                drift_limit=args.closure_tol,
            ),
            progress=progress if bar else None,
        )
    finally:
        if bar is not None:
            bar.close()


def _cmd_simulate(args) -> int:
    from .plotting import coordinate_series

    mech = _load(args)
    traj, stopped = run_or_stop(args, mech)
    info = traj.info
    summary = {
        "mechanism": mech.name,
        "method": info.method,
        "integrator": info.integrator,
        "stabilization": info.stabilization,
        "t_final": info.t_final,
        "steps": info.steps,
        "evaluations": info.evaluations,
        "cpu_time_s": info.cpu_time,
        "rejected_steps": info.get("rejected_steps"),
        "error_estimate_max": info.get("error_estimate_max"),
        "error_estimate_sum": info.get("error_estimate_sum"),
        "max_constraint_residual": traj.max_constraint_residual,
        "max_velocity_residual": float(np.max(traj.velocity_residual)),
        "energy_drift": traj.energy_drift,
        "energy_balance": traj.energy_balance,
        "repartitions": len(info.repartitions),
        "limit_violations": [list(v) for v in info.limit_violations],
        "final_independent": {
            mech.coordinate_names[i]: float(coordinate_series(mech, traj.q[-1], i))
            for i in mech.independent_idx_v
        },
    }
    if stopped is not None:
        summary["stopped"] = {"t": stopped.t, "reason": str(stopped)}
    if args.out:
        summary["out"] = str(traj.save(args.out))
    written = "trajectory written" if args.out else "summary printed"
    if args.json:
        print(json.dumps(summary, indent=2))
        return report_stop(stopped, traj, written)
    print(
        f"{mech.name}: {summary['t_final']:g} s with method {summary['method']!r}, "
        f"integrator {summary['integrator']!r}, stabilization {summary['stabilization']!r}"
    )
    _print_table(
        [
            ("steps", str(summary["steps"])),
            ("dynamics evaluations", str(summary["evaluations"])),
            ("CPU time", f"{summary['cpu_time_s']:.3f} s"),
            *(
                ()
                if summary["rejected_steps"] is None
                else (
                    ("rejected steps", str(summary["rejected_steps"])),
                    (
                        "largest local error estimate / tolerance",
                        _fmt(summary["error_estimate_max"]),
                    ),
                    (
                        "sum of local position error estimates [m or rad]",
                        _fmt(summary["error_estimate_sum"]),
                    ),
                )
            ),
            ("max constraint residual |phi|", _fmt(summary["max_constraint_residual"])),
            ("max velocity residual |J v|", _fmt(summary["max_velocity_residual"])),
            ("relative energy drift", _fmt(summary["energy_drift"])),
            ("relative energy balance (E - E0 - work of tau)", _fmt(summary["energy_balance"])),
            ("re-partitions", str(summary["repartitions"])),
            *(
                (f"left its <limit>: {joint}", f"t = {t:.6g} s, q = {value:.6g}")
                for joint, t, value, _ in summary["limit_violations"]
            ),
        ],
        ("quantity", "value"),
    )
    if args.out:
        print(f"trajectory written to {summary['out']}")
    return report_stop(stopped, traj, written)


def _add_debug(p: argparse.ArgumentParser) -> None:
    """Accept ``--debug`` after the subcommand too (it never resets a ``--debug`` before it)."""
    p.add_argument(
        "--debug", action="store_true", default=argparse.SUPPRESS, help=argparse.SUPPRESS
    )


def _cmd_export_mjcf(args) -> int:
    from .export.mjcf import STIFF, MjcfSettings, export_mjcf

    mech = _load(args)
    settings = STIFF if args.stiff else MjcfSettings()
    export_mjcf(mech, args.output, settings=settings)
    print(f"wrote {args.output}")
    return 0


def _default_cache() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "closedchain" / "bench-references"


def _cmd_bench(args) -> int:
    from tqdm import tqdm

    from .benchmark import QUICK, BenchSettings, run_work_precision

    if args.scaling is not None:
        return _bench_scaling(args)
    settings = QUICK if args.quick else BenchSettings()
    if args.repeats is not None:
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
        cache_dir=None if args.no_cache else args.cache,
    )
    bar.close()
    for c in checks:
        print(
            f"reference {c.scenario}: {c.reference}: agreement {c.agreement:.2e} "
            "(max coordinate difference over the horizon)"
        )
    print((Path(args.out_dir) / "ratios.md").read_text())
    print(f"wrote {len(rows)} rows to {Path(args.out_dir) / 'work_precision.csv'}")
    return 0


def _bench_scaling(args) -> int:
    from .benchmark.scaling import run_scaling

    families = args.scaling or None

    def progress(name: str) -> None:
        if not args.no_progress:
            print_error(f"scaling: timing the {name} family")

    rows = run_scaling(args.out_dir, families, repeats=args.repeats or 3, progress=progress)
    print((Path(args.out_dir) / "scaling.md").read_text())
    print(f"wrote {len(rows)} rows to {Path(args.out_dir) / 'scaling.csv'}")
    return 0


def _cmd_workspace(args) -> int:
    from .workspace import plot_workspace

    mech = _load(args)
    outputs = tuple(args.outputs) if args.outputs else None
    print(plot_workspace(mech, args.output, points=args.points, outputs=outputs, span=args.span))
    print(f"wrote {args.output}")
    return 0


#: Longest argparse error message [characters] (it quotes the value it could not read).
ARGPARSE_MESSAGE_MAX = 500


class _Parser(argparse.ArgumentParser):
    """argparse's parser, its error messages (which quote the bad value) bounded."""

    def error(self, message: str):
        super().error(shorten(message, ARGPARSE_MESSAGE_MAX))


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser with every subcommand."""
    from .benchmark.families import FAMILIES
    from .dynamics import METHODS

    parser = _Parser(
        prog="closedchain",
        description="Dynamics of closed-chain mechanisms (URDF + <loop>) on top of Pinocchio.",
        epilog=EXIT_STATUS_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress")
    parser.add_argument(
        "--debug",
        action="store_true",
        help="print the traceback of an internal error (exit status 4)",
    )
    sub = parser.add_subparsers(dest="command", required=True)

    def add(name: str, help_: str, handler) -> argparse.ArgumentParser:
        p = sub.add_parser(name, help=help_, description=help_)
        p.add_argument(
            "file", help="URDF file with <loop> elements, MJCF file (<mujoco>), or erd:<name>"
        )
        add_model_arguments(p)
        _add_debug(p)
        p.set_defaults(handler=handler)
        return p

    p = add("info", "show the tree, loops, constraint rows, mobility and coordinates", _cmd_info)
    p.add_argument("--json", action="store_true", help="print JSON")

    p = add("validate", "compare forward dynamics with Pinocchio's", _cmd_validate)
    p.add_argument("--samples", type=int, default=100, help="random consistent states")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    # "pinocchio" is the reference itself: comparing it with itself checks nothing.
    p.add_argument(
        "--method",
        default="kkt",
        type=_choice(METHODS),
        choices=sorted(set(METHODS) - {"pinocchio"}),
        help="method to check (any case)",
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
    budget_mb = DEFAULT_ANIMATION.mesh_budget_bytes / MEGABYTE
    p.add_argument(
        "--mesh-budget",
        type=float,
        default=budget_mb,
        metavar="MB",
        help="mesh data the page may embed [MB]; links over it are drawn as stick figures "
        f"(default: {budget_mb:g}; 0: no meshes)",
    )

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
    p.add_argument(
        "--outputs",
        nargs="+",
        metavar="JOINT",
        help="output coordinates of the map (default: the joints of the link every loop closes"
        " on, e.g. a platform; else the independent coordinates)",
    )
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
    p.add_argument(
        "--cache",
        default=str(_default_cache()),
        help="directory of cached references, keyed by scenario, models and code version"
        " (default %(default)s)",
    )
    p.add_argument("--no-cache", action="store_true", help="recompute the references")
    p.add_argument(
        "--scaling",
        nargs="*",
        metavar="FAMILY",
        choices=sorted(FAMILIES),
        help="instead of the work-precision run: cost per evaluation against size for these "
        f"families of mechanisms (default all: {', '.join(FAMILIES)}), with fitted exponents",
    )
    _add_debug(p)
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
    add_model_arguments(p, gravity_note="URDF input; ")
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
    _add_debug(p)
    p.set_defaults(handler=_cmd_plot)
    return parser


def print_error(text: str) -> None:
    """Print one line to standard error, holding :data:`closedchain._io.STDERR_LOCK` (a
    thread capturing fd 2 meanwhile would swallow it)."""
    with STDERR_LOCK:
        print(text, file=sys.stderr, flush=True)


def exit_status(exc: BaseException) -> int:
    """Return the exit status for an exception that ended a command.

    A simulation stopped by a singular configuration or a non-finite or
    drifting state is :data:`EXIT_STOPPED`; any other closedchain error, a
    file that cannot be written (OSError) and a problem too large for the
    memory (MemoryError) is bad input, :data:`EXIT_BAD_INPUT`; anything else
    is a bug, :data:`EXIT_INTERNAL`.
    """
    from .simulate import SimulationError

    if isinstance(exc, SingularConfigurationError | SimulationError | NonFiniteError):
        return EXIT_STOPPED
    if isinstance(exc, ClosedChainError | OSError | MemoryError):
        return EXIT_BAD_INPUT
    return EXIT_INTERNAL


def error_message(exc: BaseException, args: argparse.Namespace | None = None) -> str:
    """Return the one-line message of a bad-input or stopped-run error.

    An OSError names its file first (``"/x/y.html: Permission denied"``), as
    closedchain's own errors do, instead of Python's ``[Errno 13] ...`` form.
    A MemoryError names the command and its input (``args``) as what was too
    large. Line breaks (a numpy array printed over several lines) become spaces.
    """
    if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        message = f"{exc.filename}: {exc.strerror}"
    elif isinstance(exc, MemoryError):
        what = " ".join(
            str(x) for x in (getattr(args, "command", None), getattr(args, "file", None)) if x
        )
        message = (
            f"not enough memory for {what or 'the command'}"
            + (f" ({exc})" if str(exc) else "")
            + ": the problem is too large for this machine (lower --t-final, --fps, "
            "--samples, --points or the model's size)"
        )
    else:
        message = str(exc)
    message = " ".join(line.strip() for line in message.splitlines() if line.strip())
    return shorten(message, MESSAGE_MAX)


class _Terminated(BaseException):
    """SIGTERM, raised in the main thread so that files being written are cleaned up.

    A BaseException, like KeyboardInterrupt: ``except Exception`` blocks let it pass.
    """


def _raise_terminated(signum, frame) -> None:
    raise _Terminated


def _handle_sigterm():
    """Make SIGTERM raise :class:`_Terminated` (main thread only); return the previous handler."""
    if threading.current_thread() is not threading.main_thread():
        return None
    return signal.signal(signal.SIGTERM, _raise_terminated)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; return the exit status (see :data:`EXIT_STATUS_HELP`)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING)
    previous = _handle_sigterm()
    try:
        check_args(args)
        return int(args.handler(args))
    except KeyboardInterrupt:
        print_error("closedchain: interrupted")
        return EXIT_INTERRUPTED
    except _Terminated:
        print_error("closedchain: terminated")
        return EXIT_TERMINATED
    except Exception as exc:  # MemoryError included: exit_status makes it bad input
        status = exit_status(exc)
        if status == EXIT_INTERNAL:
            if args.debug:
                traceback.print_exc()
            print_error(
                f"closedchain: internal error: {type(exc).__name__}: {error_message(exc)}"
                + ("" if args.debug else " (run with --debug for the traceback)")
            )
        else:
            print_error(f"closedchain: error: {error_message(exc, args)}")
        return status
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
