"""Run the lesson's Python program (Section 7) through closedchain and print its lines.

The lesson is the course text the project grew from (Chapter 15, Lesson 3; cited in
docs/references.md, not distributed with closedchain).

The lesson integrates the 4-bar with an explicit-Euler-style step (v += dt a; q += dt v)
followed by two Gauss-Newton projection steps, dt = 1 ms, 1000 steps, a 1 N m crank
torque, from rest at theta2 = 10 deg. In closedchain that is one configuration::

    simulate(mech, q0, v0, 1.0, method="kkt", integrator="semi-implicit",
             stabilization="projection", settings=lesson_settings(), dt=1e-3, tau=[1, 0, 0])

Differences from the lesson's printout, by design: the mass matrix and bias forces are
Pinocchio's exact ones for the URDF's rods (the lesson uses a diagonal approximation);
the lesson's initial guess (10, 60, 30) deg is not on phi = 0 (|phi| = 0.36 m), so it is
closed first holding theta2 (the open assembly, theta4 = 90.69 deg). The lesson prints
the multipliers of step k, computed at the state before the step, with the angle after
it; so does this script. Run: python scripts/lesson_fourbar.py
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import closedchain as cc
from closedchain.simulate import lesson_settings, simulate

MODEL = Path(__file__).resolve().parent.parent / "models" / "fourbar.urdf"
#: The lesson's absolute angles [theta2, theta3, theta4] [deg] and run parameters.
LESSON_THETA_DEG = (10.0, 60.0, 30.0)
DT = 1e-3
STEPS = 1000
TAU = np.array([1.0, 0.0, 0.0])
PRINT_EVERY = 100


def main() -> None:
    mech = cc.load(MODEL)
    th2, th3, th4 = np.radians(LESSON_THETA_DEG)
    q_guess = np.array([th2, th3 - th2, th4])  # the URDF header's q = [th2, th3 - th2, th4]
    q0 = cc.assemble(mech, q_guess, fixed=["crank_joint"])
    traj = simulate(
        mech,
        q0,
        np.zeros(mech.nv),
        STEPS * DT,
        method="kkt",
        integrator="semi-implicit",
        stabilization="projection",
        settings=lesson_settings(),
        dt=DT,
        tau=TAU,
    )
    for k in range(0, STEPS, PRINT_EVERY):
        print(f"step {k}: th2 = {np.rad2deg(traj.q[k + 1, 0]):.2f} deg, lambda = {traj.lam[k]}")
    print(
        f"max |phi| = {traj.max_constraint_residual:.3e} m, "
        f"CPU {traj.info.cpu_time:.3f} s for {traj.info.steps} steps"
    )


if __name__ == "__main__":
    main()
