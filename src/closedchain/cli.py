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

import numpy as np

from .exceptions import ClosedChainError


def _fmt(x: float) -> str:
    return f"{x:.3e}"


def _print_table(rows: list[tuple[str, ...]], header: tuple[str, ...]) -> None:
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]
    line = "  ".join(h.ljust(w) for h, w in zip(header, widths, strict=True))
    print(line)
    print("  ".join("-" * w for w in widths))
    for r in rows:
        print("  ".join(str(c).ljust(w) for c, w in zip(r, widths, strict=True)))


def _load(args):
    from .mechanism import load

    gravity = getattr(args, "gravity", None)
    return load(args.file) if gravity is None else load(args.file, gravity=gravity)


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
    p.add_argument("--method", default="kkt", choices=sorted(METHODS), help="method to check")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; return the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING)
    try:
        return int(args.handler(args))
    except ClosedChainError as exc:
        print(f"closedchain: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
