"""Run the MJCF acceptance on local copies of public models and print its table.

Each MJCF file given is loaded as shipped (``closedchain.load``: MuJoCo compiles
it; mesh files may be absent), closed from its first keyframe (else its pose at
qpos0), simulated passively for 1 s from there (default integrator),
animated (``write_html`` into a temporary directory), and compared with
MuJoCo on the same file (closedchain.mjcf_reference): its mass matrix at
random configurations, and at random closed states its accelerations with
stiff equalities, contacts, limits, friction loss and actuation off (the
velocities scaled by :data:`SOFT_SPEED`; what remains is MuJoCo's softness)
and the rigid KKT solve built from MuJoCo's own M, bias forces and equality
Jacobian. Passive terms (armature, damping, springs) are zeroed in MuJoCo's
copy (the comparison of the rigid mechanism), unless ``--passive`` is given
(for closedchain's dynamics that apply them).

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
import shlex
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_page  # noqa: E402  (scripts/bench_page.py: the generated pages' header)

#: Simulated time [s].
T_FINAL = 1.0
#: Random states compared with MuJoCo per model.
N_STATES = 5
#: Seed of those states.
SEED = 0
#: Scale of the random consistent velocities compared with MuJoCo's soft solution.
SOFT_SPEED = 0.3
#: Edge [m] of the cubes that stand for missing meshes in a stubbed copy.
STUB_SIZE = 0.02
#: Bytes per megabyte in the animation cell.
MEGABYTE = 1e6
#: Longest error text kept in the table [characters].
MAX_NOTE = 160

COLUMNS = (
    "model",
    "meshes",
    "nv",
    "loops",
    "mobility",
    "start",
    "max abs phi at q_ref",
    "simulate 1 s: CPU [s], max abs phi",
    "animation [MB]",
    "M vs MuJoCo (rel.)",
    "a vs stiff MuJoCo (rel.)",
    "a vs rigid KKT from MuJoCo (rel.)",
    "stiff MuJoCo vs its rigid KKT (rel.)",
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


def _compare(mech, path: Path, rng, *, passive: bool) -> tuple[float, float, float, float]:
    """Return the largest relative differences: M, a against MuJoCo's stiff solution and
    against the rigid KKT solve from MuJoCo's arrays, and MuJoCo's stiff solution against
    that rigid solve (MuJoCo's own softness, at the same states)."""
    import pinocchio as pin

    import closedchain as cc
    from closedchain.mjcf_reference import (
        mujoco_accelerations,
        mujoco_mass_matrix,
        mujoco_model,
        to_mujoco,
    )

    ref = mujoco_model(path, mech.model, rigid=not passive)
    dM = soft = rigid = softness = 0.0
    for _ in range(N_STATES):
        q = pin.randomConfiguration(mech.model, -np.ones(mech.nq), np.ones(mech.nq))
        M = pin.crba(mech.model, mech.data, q)
        M = np.triu(M) + np.triu(M, 1).T
        dM = max(dM, np.linalg.norm(mujoco_mass_matrix(ref, q) - M) / np.linalg.norm(M))
        q, v = cc.random_consistent_state(mech, rng)
        tau = rng.standard_normal(mech.nv)
        for speed, which in ((SOFT_SPEED, 0), (1.0, 1)):
            a = cc.forward_dynamics(mech, q, speed * v, tau, method="kkt").a
            accelerations = mujoco_accelerations(ref, q, speed * v, tau)
            expected = accelerations[which]
            err = np.linalg.norm(to_mujoco(ref, q, speed * v, a)[2] - expected)
            err /= np.linalg.norm(expected)
            if which == 0:
                soft = max(soft, err)
                own = np.linalg.norm(accelerations[0] - accelerations[1])
                softness = max(softness, own / np.linalg.norm(accelerations[1]))
            else:
                rigid = max(rigid, err)
    return dM, soft, rigid, softness


def _note(exc: Exception) -> str:
    text = " ".join(str(exc).split())
    return text if len(text) <= MAX_NOTE else text[: MAX_NOTE - 3] + "..."


def check(path: Path, *, passive: bool = False) -> dict[str, str]:
    """Return one row of the table for one model file."""
    import closedchain as cc
    from closedchain.exceptions import URDFError

    row = {"model": f"`{path.parent.name}/{path.name}`", "meshes": "absent"}
    tmp = Path(tempfile.mkdtemp(prefix="mjcf_check_"))
    try:
        try:
            mech = cc.load(path)
        except URDFError as exc:
            if "is missing, and MuJoCo infers" not in str(exc):
                row["start"] = f"refused: {_note(exc)}"
                return row
            body = str(exc).split("infers body ", 1)[1].split("'s inertia", 1)[0].strip("'")
            row["meshes"] = f"stubbed (absent: refused, {body}'s inertia from its mesh)"
            path = _stubbed_copy(path, tmp)
            mech = cc.load(path)
        desc = mech.urdf.description
        kinds = [s.type for s in mech.urdf.loops]
        row["nv"] = str(mech.nv)
        row["loops"] = ", ".join(f"{kinds.count(k)} {k}" for k in sorted(set(kinds))) or "0"
        if desc.inactive:
            row["loops"] += f" (+{len(desc.inactive)} inactive)"
        row["mobility"] = str(mech.mobility)
        row["start"] = f"key `{next(iter(desc.keyframes))}`" if desc.keyframes else "qpos0"
        phi = cc.compute_phi(mech, mech.q_ref)
        row["max abs phi at q_ref"] = f"{np.max(np.abs(phi), initial=0.0):.1e}"
        start = time.process_time()
        try:
            traj = cc.simulate(mech, mech.q_ref, np.zeros(mech.nv), T_FINAL)
            cpu = time.process_time() - start
            row["simulate 1 s: CPU [s], max abs phi"] = (
                f"{cpu:.2f}, {traj.info.max_constraint_residual:.1e}"
            )
            page = tmp / "animation.html"
            cc.write_html(mech, traj, page)
            row["animation [MB]"] = f"{page.stat().st_size / MEGABYTE:.2f}"
        except cc.ClosedChainError as exc:
            row["simulate 1 s: CPU [s], max abs phi"] = f"stopped: {_note(exc)}"
        dM, soft, rigid, softness = _compare(
            mech, path, np.random.default_rng(SEED), passive=passive
        )
        row["M vs MuJoCo (rel.)"] = f"{dM:.1e}"
        row["a vs stiff MuJoCo (rel.)"] = f"{soft:.1e}"
        row["a vs rigid KKT from MuJoCo (rel.)"] = f"{rigid:.1e}"
        row["stiff MuJoCo vs its rigid KKT (rel.)"] = f"{softness:.1e}"
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return row


def table(rows: list[dict[str, str]]) -> list[str]:
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + " --- |" * len(COLUMNS)]
    return lines + ["| " + " | ".join(r.get(c, "") for c in COLUMNS) + " |" for r in rows]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("models", nargs="+", type=Path, help="MJCF files")
    parser.add_argument("--out", type=Path, help="also write the table as a generated page")
    parser.add_argument(
        "--passive",
        action="store_true",
        help="compare with MuJoCo's armature, damping and springs (default: zeroed)",
    )
    args = parser.parse_args(argv)
    date, load = bench_page.today(), bench_page.load_average()
    rows = [check(path, passive=args.passive) for path in args.models]
    lines = table(rows)
    print("\n".join(lines))
    if args.out is not None:
        names = " ".join(shlex.quote(f"MODELS/{p.parent.name}/{p.name}") for p in args.models)
        passive = " --passive" if args.passive else ""
        command = f"python scripts/check_mjcf_models.py {names}{passive} --out {args.out}"
        head = bench_page.run_header(
            "MJCF models as shipped",
            command=command,
            date=date,
            load_before=load,
            about="MODELS: the local folder of the models (one folder per model); "
            "columns: see scripts/check_mjcf_models.py.",
        )
        tmp = args.out.with_name(args.out.name + ".tmp")
        tmp.write_text("\n".join(head + lines) + "\n")
        tmp.replace(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
