"""Run the parallel-robot workflow on a robot of example-parallel-robots and print its figures.

For ``ROBOT/robot.urdf`` + ``ROBOT/robot.yaml`` (Gepetto/example-parallel-robots, BSD-3;
not in CI) and an output frame (a foot):

1. forward kinematics from the motors of ``q_ref`` moved by ``--offset`` [rad]: closure
   residual, sigma_min of J_D;
2. inverse kinematics of the frame's pose there (6d), started from ``q_ref``: the motors
   it finds against the ones held;
3. motor torques at rest (``gravity_torque``) against virtual work, the central difference
   of Pinocchio's potential energy over the motors (through forward kinematics); the
   legs' rods spin freely about their axes (two ball joints), so a robot's mobility can
   exceed its motors: the spins then join the actuated coordinates, and their torques,
   zero for a rod whose mass lies on its axis, are printed;
4. the two actuation singularity measures there (type II, J_D; type I, the frame).

Run::

    python scripts/parallel_workflow.py /path/to/example-parallel-robots/robots/talos_like \\
        --frame foot
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import numpy as np
import pinocchio as pin

import closedchain as cc
from closedchain.parallel import _motor_values

#: Central-difference step of the potential energy over the motors [rad].
FD_STEP = 1e-6


def _spin_coordinates(mech: cc.Mechanism, q: np.ndarray) -> list[int]:
    """Velocity indices that complete the motors to the mobility: for each direction of
    the motion space that the motors leave free (a rod's spin), its largest coordinate."""
    J = cc.compute_jacobian(mech, q)
    S = np.zeros((len(mech.actuated_idx_v), mech.nv))
    S[np.arange(len(mech.actuated_idx_v)), mech.actuated_idx_v] = 1.0
    _, s, Vt = np.linalg.svd(np.vstack([J, S]))
    free = Vt[int(np.sum(s > 1e-9 * s[0])) :]
    out: list[int] = []
    for direction in free:
        ranked = np.argsort(-np.abs(direction))
        out.append(int(next(i for i in ranked if i not in out)))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("robot", type=Path, help="folder with robot.urdf and robot.yaml")
    p.add_argument("--frame", default="foot", help="output frame (default foot)")
    p.add_argument("--offset", type=float, default=0.05, help="motor offset from q_ref [rad]")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)

    t0 = time.process_time()
    mech = cc.load(args.robot / "robot.urdf", loops=args.robot / "robot.yaml")
    print(
        f"{args.robot.name}: nv {mech.nv}, rows {mech.nc}, mobility {mech.mobility}, "
        f"motors {len(mech.actuated_joints)} ({', '.join(mech.actuated_joints)}); "
        f"load {time.process_time() - t0:.2f} s CPU"
    )
    motors = _motor_values(mech, mech.q_ref) + args.offset

    t0 = time.process_time()
    fk = cc.forward_kinematics(mech, motors)
    print(
        f"forward kinematics: closure residual {fk.closure_residual:.2e}, sigma_min(J_D) "
        f"{fk.sigma_min_JD:.3g}; {1e3 * (time.process_time() - t0):.1f} ms CPU"
    )

    fid = mech.model.getFrameId(args.frame)
    pin.framesForwardKinematics(mech.model, mech.data, fk.q)
    target = mech.data.oMf[fid].copy()
    t0 = time.process_time()
    ik = cc.inverse_kinematics(mech, args.frame, target)
    err = np.max(np.abs(np.angle(np.exp(1j * (ik.motors - motors)))))
    print(
        f"inverse kinematics of {args.frame!r} (6d) from q_ref: max |motor error| "
        f"{err:.2e} rad, frame error {ik.frame_error:.2e}, closure residual "
        f"{ik.closure_residual:.2e}; {1e3 * (time.process_time() - t0):.1f} ms CPU"
    )

    spins = _spin_coordinates(mech, fk.q)
    motor_v = [mech.model.joints[mech.model.getJointId(n)].idx_v for n in mech.actuated_joints]
    actuated = motor_v + spins
    rest = cc.inverse_dynamics(
        mech,
        fk.q,
        np.zeros(mech.nv),
        np.zeros(len(actuated)),
        actuated=actuated,
        coordinates=actuated,
    )
    data = mech.model.createData()

    def V(m: np.ndarray) -> float:
        q = cc.forward_kinematics(mech, m, q_guess=fk.q).q
        return pin.computePotentialEnergy(mech.model, data, q)

    grad = np.array(
        [(V(motors + h) - V(motors - h)) / (2 * FD_STEP) for h in FD_STEP * np.eye(len(motors))]
    )
    tau = rest.tau[motor_v]
    print(
        f"motor torques at rest [N m]: {np.array2string(tau, precision=4)}; against virtual "
        f"work: max |difference| {np.max(np.abs(tau - grad)):.2e}"
    )
    if spins:
        names = ", ".join(mech.coordinate_names[i] for i in spins)
        print(
            f"  {len(spins)} free spin(s) beyond the motors, held through {names}: torques "
            f"{np.array2string(rest.tau[spins], precision=2)}"
        )
    s = cc.actuation_singularities(mech, fk.q, frame=args.frame)
    print(f"actuation singularities: type II sigma {s.parallel:.3g}, type I sigma {s.serial:.3g}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
