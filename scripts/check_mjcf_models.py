"""Run the MJCF acceptance on local copies of public models and print its table.

Each MJCF file given is loaded as shipped (``closedchain.load``: MuJoCo compiles
it; its mesh files present, or absent and then left out), closed from its first
keyframe (else its pose at qpos0), simulated for 1 s from there at rest under
the default settings (closedchain applies the model's joint springs, damping
and armature: :mod:`closedchain.passive`), animated (``write_html`` into a
temporary directory), and compared with MuJoCo on the same file
(closedchain.mjcf_reference): its mass matrix at random configurations, and at
random closed states, with contacts, limits, friction loss and actuation off,
its accelerations with the equalities in MuJoCo's rigid limit (solimp at its
cap and the regulariser scaled towards 0: ``mujoco_model(rigid_limit=True)``),
the rigid KKT solve built from MuJoCo's own M, bias forces and equality
Jacobian, and, for the record, MuJoCo's stiffest simulated equality (solref
2e-4 s, solimp 0.9999, its own regulariser) against that rigid solve. Every
column is with the model's passive terms: armature in both mass matrices,
joint springs and damping in both accelerations (MuJoCo's ``qfrc_passive``
without friction loss; closedchain applies them in every method).

The CPU time of the 1 s simulation is the median of :data:`TIMING_REPEATS`
runs, interleaved over the models (``time.process_time``; BLAS on one thread,
``OPENBLAS_NUM_THREADS=1`` unless set: its idle threads would charge their CPU
time to the process), with the backend that ran.

When a model's mesh files are absent and MuJoCo would infer a moving body's
inertia from one of them, the reader refuses it (the table says so); the
script then runs the rest on a temporary copy whose missing meshes are
stubbed by :data:`STUB_SIZE` cubes (MuJoCo and closedchain read the same
copy), and the table marks the row "stubbed".

Get the models (Menagerie is read file by file; MuJoCo's test models from
``test/engine/testdata``) into one folder per model, then::

    python scripts/check_mjcf_models.py /path/to/models/*/*.xml --out docs/bench/mjcf_models.md
"""

from __future__ import annotations

import argparse
import os
import shlex
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy is imported

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_page  # noqa: E402  (scripts/bench_page.py: the generated pages' header)

#: Simulated time [s].
T_FINAL = 1.0
#: Runs of the 1 s simulation per model whose CPU time's median is reported.
TIMING_REPEATS = 5
#: Random states compared with MuJoCo per model.
N_STATES = 5
#: Seed of those states.
SEED = 0
#: Edge [m] of the cubes that stand for missing meshes in a stubbed copy.
STUB_SIZE = 0.02
#: Bytes per megabyte in the animation cell.
MEGABYTE = 1e6
#: Longest error text kept in the table [characters].
MAX_NOTE = 160
#: MuJoCo's ``eq_data`` entry of a weld's torquescale.
TORQUESCALE = 10

COLUMNS = (
    "model",
    "meshes",
    "nv",
    "loops",
    "mobility",
    "start",
    "max abs phi at q_ref",
    "simulate 1 s: CPU [s] (backend), max abs phi",
    "animation [MB]",
    "M vs MuJoCo (rel.)",
    "a vs MuJoCo, rigid limit (rel.)",
    "a vs rigid KKT from MuJoCo (rel.)",
    "MuJoCo rigid limit vs its rigid KKT (rel.)",
    "MuJoCo solref 2e-4, solimp 0.9999 vs its rigid KKT (rel.)",
)


def _stubbed_copy(path: Path, folder: Path) -> Path:
    """Copy the model into ``folder`` with its missing mesh files replaced by small cubes."""
    import mujoco
    import trimesh

    spec = mujoco.MjSpec.from_file(str(path))
    copy = folder / path.name
    shutil.copy(path, copy)
    meshdir = Path(spec.meshdir or "")
    for mesh in spec.meshes:
        target = path.parent / meshdir / mesh.file
        if mesh.file and not target.is_file():
            stub = folder / meshdir / mesh.file
            stub.parent.mkdir(parents=True, exist_ok=True)
            scale = np.abs(np.asarray(mesh.scale, dtype=float))
            box = trimesh.creation.box(extents=STUB_SIZE / np.where(scale > 0, scale, 1.0))
            box.export(stub, file_type="stl" if stub.suffix.lower() == ".stl" else "obj")
    return copy


def _meshes(path: Path) -> str:
    """Return "present", "absent", "k of n present" or "none" for the model's mesh files."""
    import mujoco

    spec = mujoco.MjSpec.from_file(str(path))
    meshdir = Path(spec.meshdir or "")
    files = [path.parent / meshdir / m.file for m in spec.meshes if m.file]
    found = sum(f.is_file() for f in files)
    if not files:
        return "none"
    return {0: "absent", len(files): "present"}.get(found, f"{found} of {len(files)} present")


def _states(mech, rng) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    import closedchain as cc

    out = []
    for _ in range(N_STATES):
        q, v = cc.random_consistent_state(mech, rng)
        out.append((q, v, rng.standard_normal(mech.nv)))
    return out


def _relative(ref, q, v, a, expected) -> float:
    from closedchain.mjcf_reference import to_mujoco

    return float(np.linalg.norm(to_mujoco(ref, q, v, a)[2] - expected) / np.linalg.norm(expected))


def _compare(mech, path: Path, rng) -> dict[str, str]:
    """Return the comparison columns: M, and a against MuJoCo's rigid limit and its rigid
    KKT solve, and MuJoCo's own answers (rigid limit, stiffest simulated) against that
    solve, the largest relative differences over the states."""
    import pinocchio as pin

    import closedchain as cc
    from closedchain.mjcf_reference import mujoco_accelerations, mujoco_mass_matrix, mujoco_model

    limit = mujoco_model(path, mech.model, rigid=False)
    cap = mujoco_model(path, mech.model, rigid=False, rigid_limit=False)
    dM = 0.0
    for _ in range(N_STATES):
        q = pin.randomConfiguration(mech.model, -np.ones(mech.nq), np.ones(mech.nq))
        M = pin.crba(mech.model, mech.data, q)
        M = np.triu(M) + np.triu(M, 1).T
        dM = max(dM, np.linalg.norm(mujoco_mass_matrix(limit, q) - M) / np.linalg.norm(M))
    worst = dict.fromkeys(("limit", "rigid", "limit_own", "cap_own"), 0.0)
    for q, v, tau in _states(mech, rng):
        a = cc.forward_dynamics(mech, q, v, tau, method="kkt").a
        soft, rigid, _ = mujoco_accelerations(limit, q, v, tau)
        capped = mujoco_accelerations(cap, q, v, tau)[0]
        norm = np.linalg.norm(rigid)
        for key, value in (
            ("limit", _relative(limit, q, v, a, soft)),
            ("rigid", _relative(limit, q, v, a, rigid)),
            ("limit_own", np.linalg.norm(soft - rigid) / norm),
            ("cap_own", np.linalg.norm(capped - rigid) / norm),
        ):
            worst[key] = max(worst[key], float(value))
    return {
        "M vs MuJoCo (rel.)": f"{dM:.1e}",
        "a vs MuJoCo, rigid limit (rel.)": f"{worst['limit']:.1e}",
        "a vs rigid KKT from MuJoCo (rel.)": f"{worst['rigid']:.1e}",
        "MuJoCo rigid limit vs its rigid KKT (rel.)": f"{worst['limit_own']:.1e}",
        "MuJoCo solref 2e-4, solimp 0.9999 vs its rigid KKT (rel.)": f"{worst['cap_own']:.1e}",
    }


def _torquescale_note(mech, path: Path, label: str) -> str | None:
    """For a model with welds whose torquescale is neither 0 nor 1 (closedchain holds them
    as rigid welds: see closedchain.mjcf), the numbers that place the difference: MuJoCo's
    stiffest simulated weld against its rigid KKT solve with its approximate diagonal and
    with the exact one (``diagexact``), and closedchain against MuJoCo's rigid limit with
    the torquescale as shipped and set to 1."""
    import mujoco

    import closedchain as cc
    from closedchain.mjcf_reference import mujoco_accelerations, mujoco_model

    weld = int(mujoco.mjtEq.mjEQ_WELD)
    probe = mujoco_model(path, mech.model, rigid=False)
    scales = [
        float(probe.mj.eq_data[e][TORQUESCALE])
        for e in range(probe.mj.neq)
        if int(probe.mj.eq_type[e]) == weld
        and probe.mj.eq_active0[e]
        and float(probe.mj.eq_data[e][TORQUESCALE]) not in (0.0, 1.0)
    ]
    if not scales:
        return None
    cap = mujoco_model(path, mech.model, rigid=False, rigid_limit=False)
    exact = mujoco_model(path, mech.model, rigid=False, rigid_limit=False)
    exact.mj.opt.enableflags |= int(mujoco.mjtEnableBit.mjENBL_DIAGEXACT)
    unscaled = mujoco_model(path, mech.model, rigid=False)
    for e in range(unscaled.mj.neq):
        if int(unscaled.mj.eq_type[e]) == weld and unscaled.mj.eq_data[e][TORQUESCALE] != 0.0:
            unscaled.mj.eq_data[e][TORQUESCALE] = 1.0
    worst = dict.fromkeys(("cap", "exact", "limit", "unscaled"), 0.0)
    for q, v, tau in _states(mech, np.random.default_rng(SEED)):
        a = cc.forward_dynamics(mech, q, v, tau, method="kkt").a
        soft, rigid, _ = mujoco_accelerations(probe, q, v, tau)
        norm = np.linalg.norm(rigid)
        values = {
            "cap": np.linalg.norm(mujoco_accelerations(cap, q, v, tau)[0] - rigid) / norm,
            "exact": np.linalg.norm(mujoco_accelerations(exact, q, v, tau)[0] - rigid) / norm,
            "limit": _relative(probe, q, v, a, soft),
            "unscaled": _relative(unscaled, q, v, a, mujoco_accelerations(unscaled, q, v, tau)[0]),
        }
        for key, value in values.items():
            worst[key] = max(worst[key], float(value))
    listed = ", ".join(f"{x:g}" for x in sorted(set(scales)))
    return (
        f"- {label}: welds with torquescale {listed}. MuJoCo scales such a weld's rotation "
        "rows (Jacobian and residual) by the torquescale; in the rigid limit scaled rows hold "
        "the same constraint, and closedchain holds a rigid weld. MuJoCo's stiffest simulated "
        "weld is soft where its regulariser comes from its approximate diagonal, which does "
        "not see the scale: "
        f"{worst['cap']:.1e} from its rigid KKT solve, {worst['exact']:.1e} with the exact "
        f"diagonal (`diagexact`). closedchain against MuJoCo's rigid limit: {worst['limit']:.1e} "
        f"with the torquescale as shipped, {worst['unscaled']:.1e} with it set to 1."
    )


def _note(exc: Exception) -> str:
    text = " ".join(str(exc).split())
    return text if len(text) <= MAX_NOTE else text[: MAX_NOTE - 3] + "..."


def prepare(path: Path, tmp: Path) -> tuple[dict[str, str], object, Path]:
    """Load one model (stubbing its missing meshes if it must) and fill the columns up to
    the start; return the row, the mechanism (None when refused) and the file read."""
    import closedchain as cc
    from closedchain.exceptions import ModelFileError

    row = {"model": f"`{path.parent.name}/{path.name}`", "meshes": _meshes(path)}
    try:
        mech = cc.load(path)
    except ModelFileError as exc:
        if "is missing, and MuJoCo infers" not in str(exc):
            row["start"] = f"refused: {_note(exc)}"
            return row, None, path
        body = str(exc).split("infers body ", 1)[1].split("'s inertia", 1)[0].strip("'")
        row["meshes"] = f"stubbed ({row['meshes']}: refused, {body}'s inertia from its mesh)"
        path = _stubbed_copy(path, tmp)
        mech = cc.load(path)
    desc = mech.description.tree
    kinds = [s.type for s in mech.description.loops]
    row["nv"] = str(mech.nv)
    row["loops"] = ", ".join(f"{kinds.count(k)} {k}" for k in sorted(set(kinds))) or "0"
    if desc.inactive:
        row["loops"] += f" (+{len(desc.inactive)} inactive)"
    row["mobility"] = str(mech.mobility)
    row["start"] = f"key `{next(iter(desc.keyframes))}`" if desc.keyframes else "qpos0"
    phi = cc.compute_phi(mech, mech.q_ref)
    row["max abs phi at q_ref"] = f"{np.max(np.abs(phi), initial=0.0):.1e}"
    return row, mech, path


def simulate_once(mech):
    """Return (CPU seconds, trajectory) of 1 s from q_ref at rest under the defaults."""
    import closedchain as cc

    start = time.process_time()
    traj = cc.simulate(mech, mech.q_ref, np.zeros(mech.nv), T_FINAL)
    return time.process_time() - start, traj


def finish(row: dict[str, str], mech, path: Path, cpu: list[float], traj, tmp: Path) -> None:
    """Fill the simulation, animation and comparison columns of a loaded model's row."""
    import closedchain as cc

    info = traj.info
    row["simulate 1 s: CPU [s] (backend), max abs phi"] = (
        f"{statistics.median(cpu):.3f} ({info.backend}), {info.max_constraint_residual:.1e}"
    )
    page = tmp / "animation.html"
    cc.write_html(mech, traj, page)
    row["animation [MB]"] = f"{page.stat().st_size / MEGABYTE:.2f}"
    row.update(_compare(mech, path, np.random.default_rng(SEED)))


def table(rows: list[dict[str, str]]) -> list[str]:
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + " --- |" * len(COLUMNS)]
    return lines + ["| " + " | ".join(r.get(c, "") for c in COLUMNS) + " |" for r in rows]


def run(paths: list[Path]) -> tuple[list[dict[str, str]], list[str]]:
    """Return the rows and the torquescale notes of the models (timing interleaved)."""
    import closedchain as cc

    tmp = Path(tempfile.mkdtemp(prefix="mjcf_check_"))
    try:
        loaded = []
        for k, path in enumerate(paths):
            folder = tmp / str(k)
            folder.mkdir()
            loaded.append((*prepare(path, folder), folder))
        cpu: dict[int, list[float]] = {k: [] for k in range(len(loaded))}
        trajectories, stopped = {}, {}
        for _ in range(TIMING_REPEATS):
            for k, (_, mech, _, _) in enumerate(loaded):
                if mech is None or k in stopped:
                    continue
                try:
                    seconds, trajectories[k] = simulate_once(mech)
                except cc.ClosedChainError as exc:
                    stopped[k] = _note(exc)
                    continue
                cpu[k].append(seconds)
        notes = []
        for k, (row, mech, path, folder) in enumerate(loaded):
            if mech is None:
                continue
            if k in stopped:
                row["simulate 1 s: CPU [s] (backend), max abs phi"] = f"stopped: {stopped[k]}"
                row.update(_compare(mech, path, np.random.default_rng(SEED)))
            else:
                finish(row, mech, path, cpu[k], trajectories[k], folder)
            note = _torquescale_note(mech, path, row["model"])
            if note:
                notes.append(note)
        return [row for row, *_ in loaded], notes
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("models", nargs="+", type=Path, help="MJCF files")
    parser.add_argument("--out", type=Path, help="also write the table as a generated page")
    parser.add_argument(
        "--about",
        default="",
        help="a sentence on where the models and their meshes came from (the page's header)",
    )
    args = parser.parse_args(argv)
    date, load = bench_page.today(), bench_page.load_average()
    rows, notes = run(args.models)
    lines = table(rows)
    if notes:
        lines += ["", "Welds with a torquescale other than 0 and 1:", "", *notes]
    print("\n".join(lines))
    if args.out is not None:
        names = " ".join(shlex.quote(f"MODELS/{p.parent.name}/{p.name}") for p in args.models)
        about = f" --about {shlex.quote(args.about)}" if args.about else ""
        command = f"python scripts/check_mjcf_models.py {names}{about} --out {args.out}"
        head = bench_page.run_header(
            "MJCF models as shipped",
            command=command,
            date=date,
            load_before=load,
            about="MODELS: the local folder of the models (one folder per model). "
            + (args.about + " " if args.about else "")
            + COLUMNS_ABOUT,
        )
        tmp = args.out.with_name(args.out.name + ".tmp")
        tmp.write_text("\n".join(head + lines) + "\n")
        tmp.replace(args.out)
    return 0


#: What the page says about its columns (its header).
COLUMNS_ABOUT = (
    "Every column is with the models' passive terms (joint springs, damping, armature: "
    "closedchain applies them in every method; MuJoCo's copy keeps them). "
    "Simulate: median CPU time of "
    f"{TIMING_REPEATS} runs interleaved over the models, under the default settings, and "
    "the backend that ran. Accelerations: the largest relative difference at "
    f"{N_STATES} random closed states with random velocities and joint forces, contacts, "
    "limits, friction loss and actuation off. MuJoCo's rigid limit: solimp at its cap "
    "0.9999 and its regulariser scaled by 1e-8 (`closedchain.mjcf_reference.mujoco_model`"
    "), which brings MuJoCo's own answer to its rigid KKT solve (next-to-last column); "
    "the last column is MuJoCo's stiffest simulated equality, for the record. "
    "See scripts/check_mjcf_models.py."
)


if __name__ == "__main__":
    sys.exit(main())
