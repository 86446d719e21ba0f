"""Run the acceptance on a local copy of example-parallel-robots and print its table.

Every robot folder of PATH holding ``robot.urdf`` and ``robot.yaml`` is loaded
with ``closedchain.load(robot.urdf, loops=robot.yaml)`` (meshes are not read,
so ``package://`` paths need not resolve) and checked, each in a subprocess
with a time limit: loops, nv, mobility against the number of motors (where
they differ, the notes list the motions left with the motors held, by the
joints each moves), load CPU time, max |phi| at ``q_ref`` over every declared
row, ``validate`` against pinocchio.constraintDynamics (the judged deviation
in the mass-matrix norm, relative above 1, and max |a - a_pin| for
information: see closedchain.validation), the CPU time of a passive
simulation from ``q_ref`` (default integrator), or the error that stopped a
step, and the size of the HTML animation of that motion (``write_html`` into a
temporary directory, meshes embedded within the default budget; up to the stop
when a step failed). The table is Markdown; ``--out FILE`` also writes it as a
generated page (the run's command, date, machine and code in its header,
scripts/bench_page.py), atomically: FILE.tmp, then renamed.

Get the corpus (BSD-3) with::

    git clone https://github.com/Gepetto/example-parallel-robots
    python scripts/check_corpus.py example-parallel-robots/robots --out docs/bench/corpus.md
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_page  # noqa: E402  (scripts/bench_page.py: the generated pages' header)

#: Validation states per robot.
N_VALIDATE = 10
#: Seed of the validation states.
VALIDATE_SEED = 0
#: Default simulated time [s].
T_FINAL = 1.0
#: Default wall-clock limit per robot [s] (load, validation and simulation together).
TIMEOUT = 900.0
#: Longest error text kept in the table [characters].
MAX_NOTE = 160
#: Velocity entries below this (relative to the largest) are not part of a motion [-].
MOTION_TOL = 1e-9
#: Bytes per megabyte in the animation cell.
MEGABYTE = 1e6

COLUMNS = (
    "robot",
    "loops",
    "nv",
    "mobility / motors",
    "load CPU [s]",
    "max abs phi at q_ref",
    "validate da_M (judged)",
    "validate max abs da [rad/s^2]",
    "simulate CPU [s]",
    "animates",
    "notes",
)


def _short(exc: BaseException, folder: Path) -> str:
    """One line naming the error, the robot folder's path left out, at most MAX_NOTE long."""
    text = " ".join(str(exc).replace(f"{folder}/", "").split())
    text = f"{type(exc).__name__}: {text}"
    return text if len(text) <= MAX_NOTE else text[: MAX_NOTE - 3] + "..."


def _sparse_basis(N, tol: float):
    """Return a basis of the columns' span in reduced row-echelon form (few entries each).

    Args:
        N: a basis, shape (nv, k).
        tol: entries below ``tol`` times the largest are zero.

    Returns:
        Rows spanning the same space, shape (k, nv), each with a unit pivot.
    """
    import numpy as np

    B = np.array(N, dtype=float).T
    row = 0
    for col in range(B.shape[1]):
        if row == B.shape[0]:
            break
        pivot = row + int(np.argmax(np.abs(B[row:, col])))
        if abs(B[pivot, col]) <= tol:
            continue
        B[[row, pivot]] = B[[pivot, row]]
        B[row] /= B[row, col]
        for other in range(B.shape[0]):
            if other != row:
                B[other] -= B[other, col] * B[row]
        row += 1
    B[np.abs(B) <= tol * np.max(np.abs(B), initial=1.0)] = 0.0
    return B


def unactuated_motions(mech) -> list[list[str]]:
    """Return the motions the closed mechanism keeps with its motors held, as the joints each moves.

    A basis of the null space of the constraint Jacobian (every independent
    row) with the motor columns held, at ``q_ref``, made sparse
    (:func:`_sparse_basis`); each motion is named by the joints whose velocity
    it makes nonzero (``MOTION_TOL``), in tree order.
    """
    import numpy as np
    import scipy.linalg

    from closedchain.kinematics import compute_jacobian

    model = mech.model
    held = np.zeros((len(mech.actuated_joints), mech.nv))
    for i, name in enumerate(mech.actuated_joints):
        held[i, model.joints[model.getJointId(name)].idx_v] = 1.0
    J = compute_jacobian(mech, mech.q_ref)
    basis = _sparse_basis(scipy.linalg.null_space(np.vstack([J, held])), MOTION_TOL)
    joints = range(1, model.njoints)
    return [
        [
            model.names[j]
            for j in joints
            if np.any(v[model.joints[j].idx_v : model.joints[j].idx_v + model.joints[j].nv])
        ]
        for v in basis
    ]


def _mobility_note(mech) -> str:
    """Say why the mobility exceeds the motors: the motions left with the motors held."""
    motions = unactuated_motions(mech)
    listed = "; ".join("+".join(links) for links in motions)
    return (
        f"mobility {mech.mobility} = {len(mech.actuated_joints)} motors + {len(motions)} "
        f"motion{'s' if len(motions) != 1 else ''} with the motors held, moving only the "
        f"joints {listed}"
    )


def _animation_cell(mech, trajectory, stop: str | None) -> str:
    """Write the motion's HTML animation into a temporary directory; return its size and meshes."""
    import tempfile

    from closedchain import write_html

    with tempfile.TemporaryDirectory() as tmp:
        anim = write_html(mech, trajectory, Path(tmp) / "robot.html", stop=stop)
    meshes = anim.meshes
    cell = f"{anim.size / MEGABYTE:.2g} MB, {meshes.n_embedded} meshes"
    if meshes.primitive_links:
        cell += f", {len(meshes.primitive_links)} links as primitives"
    return cell


def check_robot(folder: Path, t_final: float, method: str | None = None) -> dict:
    """Load, check and simulate one robot; return its row (values, or errors in ``notes``).

    Errors of any type after the load are reported in ``notes``, not raised: one
    robot's failure (or a bug it finds) must not hide the others' rows.
    """
    import numpy as np

    import closedchain as cc
    from closedchain.closure import max_declared_residual
    from closedchain.yaml_loops import read_loops_yaml

    urdf, loops = folder / "robot.urdf", folder / "robot.yaml"
    row: dict = {"robot": folder.name, "notes": []}
    try:
        spec = read_loops_yaml(loops)
    except cc.ClosedChainError as exc:
        row["notes"].append(f"yaml: {_short(exc, folder)}")
        return row
    kinds = [k for _, _, k in spec.loops]
    row["loops"] = f"{len(kinds)} ({kinds.count('fixed')} 6d, {kinds.count('spherical')} 3d)"
    t0 = time.process_time()
    try:
        mech = cc.load(urdf, loops=loops)
    except cc.ClosedChainError as exc:
        row["load"] = time.process_time() - t0
        row["notes"].append(f"load: {_short(exc, folder)}")
        return row
    row["load"] = time.process_time() - t0
    row["nv"] = mech.nv
    row["mobility"] = f"{mech.mobility} / {len(mech.actuated_joints)}"
    if mech.mobility != len(mech.actuated_joints):
        try:
            row["notes"].append(_mobility_note(mech))
        except Exception as exc:
            row["notes"].append(f"mobility: {_short(exc, folder)}")
    row["phi"] = max_declared_residual(mech, np.atleast_2d(mech.q_ref))
    options = {} if method is None else {"method": method}
    try:
        rep = cc.validate(mech, n_samples=N_VALIDATE, seed=VALIDATE_SEED)
        row["da"] = rep.max_da
        row["da_M"] = rep.max_da_mass_norm
        if rep.n_singular:
            row["notes"].append(f"validate: {rep.n_singular} singular states")
    except Exception as exc:
        row["notes"].append(f"validate: {_short(exc, folder)}")
    t0 = time.process_time()
    stop = None
    try:
        trajectory = cc.simulate(mech, mech.q_ref, np.zeros(mech.nv), t_final, **options)
        row["simulate"] = time.process_time() - t0
    except Exception as exc:
        row["notes"].append(f"simulate: {_short(exc, folder)}")
        trajectory, stop = getattr(exc, "trajectory", None), str(exc)
    if trajectory is not None:
        try:
            row["animates"] = _animation_cell(mech, trajectory, stop)
        except Exception as exc:
            row["notes"].append(f"animate: {_short(exc, folder)}")
    return row


def _cell(row: dict, key: str, fmt: str) -> str:
    value = row.get(key)
    if value is None:
        return "-"
    return format(value, fmt) if fmt else str(value)


def table(rows: list[dict], t_final: float) -> str:
    """Return the Markdown table of the rows."""
    lines = [
        "| " + " | ".join(c.replace("simulate", f"simulate {t_final:g} s") for c in COLUMNS) + " |",
        "|" + "|".join("---" for _ in COLUMNS) + "|",
    ]
    for row in rows:
        cells = [
            row["robot"],
            _cell(row, "loops", ""),
            _cell(row, "nv", ""),
            _cell(row, "mobility", ""),
            _cell(row, "load", ".2f"),
            _cell(row, "phi", ".1e"),
            _cell(row, "da_M", ".1e"),
            _cell(row, "da", ".1e"),
            _cell(row, "simulate", ".2f"),
            _cell(row, "animates", ""),
            "; ".join(row["notes"]).replace("|", "\\|"),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("path", type=Path, help="a local copy of the corpus's robots/ folder")
    parser.add_argument("--out", type=Path, help="also write the table here (atomically)")
    parser.add_argument("--t-final", type=float, default=T_FINAL, help="simulated time [s]")
    parser.add_argument(
        "--timeout", type=float, default=TIMEOUT, help="wall-clock limit per robot [s]"
    )
    parser.add_argument("--method", help="forward-dynamics method of the run (default: simulate's)")
    parser.add_argument("--robot", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.robot:  # one robot, in the subprocess main() starts: its row as JSON
        print(json.dumps(check_robot(args.path, args.t_final, args.method)))
        return 0

    date, load = bench_page.today(), bench_page.load_average()
    rows, skipped = [], []
    for folder in sorted(p for p in args.path.iterdir() if p.is_dir()):
        missing = [f for f in ("robot.urdf", "robot.yaml") if not (folder / f).is_file()]
        if missing:
            skipped.append(f"{folder.name} (no {', '.join(missing)})")
            continue
        command = [sys.executable, __file__, str(folder), "--robot", "--t-final", str(args.t_final)]
        if args.method is not None:
            command += ["--method", args.method]
        try:
            run = subprocess.run(
                command, capture_output=True, text=True, timeout=args.timeout, check=False
            )
        except subprocess.TimeoutExpired:
            rows.append({"robot": folder.name, "notes": [f"timeout after {args.timeout:g} s"]})
            continue
        lines = run.stdout.strip().splitlines()
        if run.returncode != 0 or not lines:
            error = (run.stderr.strip().splitlines() or ["no output"])[-1]
            rows.append({"robot": folder.name, "notes": [f"crashed: {error[:MAX_NOTE]}"]})
            continue
        rows.append(json.loads(lines[-1]))
        print(f"checked {folder.name}", file=sys.stderr)

    text = table(rows, args.t_final) + "\n"
    if skipped:
        text += f"\nSkipped: {', '.join(skipped)}.\n"
    print(text, end="")
    if args.out is not None:
        command = "python scripts/check_corpus.py " + shlex.join(
            [args.path.name, *(argv if argv is not None else sys.argv[1:])[1:]]
        )
        head = bench_page.run_header(
            "example-parallel-robots: the acceptance",
            command=command,
            date=date,
            load_before=load,
            about="How the YAML is read: [Robots and moving bases]"
            "(../guide/robots-and-moving-bases.md#loops-in-yaml-example-parallel-robots).",
        )
        from closedchain._io import atomic_write

        with atomic_write(args.out, "w") as f:
            f.write("\n".join(head) + "\n" + text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
