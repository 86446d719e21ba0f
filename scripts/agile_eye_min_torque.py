r"""Minimum-torque reorientation of the Agile Eye: multiple shooting with analytical step
derivatives.

The Agile Eye (models/agile_eye.urdf: three legs of two revolute joints closing on a
platform, its orientation the joints ``platform_yaw``, ``platform_pitch``,
``platform_roll``) starts at rest at its reference orientation and must be at rest at
``target`` after ``t_final`` seconds, with the least actuator effort. Transcription: N
intervals of length h = t_final / N, the actuator torques u_k (3 motors) constant over
each, the states x_k = (q_k, v_k) at the nodes free, and the dynamics one step of rk4
with stage projection (:func:`closedchain.step_derivatives`, the step
``closedchain.simulate`` takes with ``integrator="rk4"``):

.. math::

    \min_{x_1..x_N,\, u_0..u_{N-1}} \; \frac{h}{2} \sum_k |u_k|^2
    \quad \text{s.t.} \quad x_{k+1} - F_h(x_k, B u_k) = 0, \quad
    q_{N,P} = q_{target}, \quad v_{N,P} = 0,

with B the motors' selection and P the platform's coordinates. scipy's SLSQP solves it
with the constraints' Jacobian assembled from the step derivatives (dq+/dq, dq+/dv,
dq+/dtau, ...), block-bidiagonal. Every node lies on the constraint manifold (each step
ends projected onto phi = 0, J v = 0). The torques enter the solver divided by the
mechanism's gravity-torque scale and the cost divided by t_final times its square, so
that both are of order one (SLSQP's quasi-Newton Hessian starts at the identity).

Run: ``python scripts/agile_eye_min_torque.py --plot docs/img/agile_eye_min_torque.png
--html agile_eye_min_torque.html`` (the plot on the docs page; the HTML animation
replays the torques with ``simulate``).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.optimize

import closedchain as cc

MODEL = Path(__file__).resolve().parent.parent / "models" / "agile_eye.urdf"
#: The platform's orientation coordinates (yaw, pitch, roll joints) [rad].
PLATFORM = ("platform_yaw", "platform_pitch", "platform_roll")
#: The default target orientation (yaw, pitch, roll) [rad] and duration [s].
TARGET = (0.3, -0.2, 0.15)
T_FINAL = 0.6
#: Shooting intervals of the documented run.
N_INTERVALS = 12
#: SLSQP's stopping tolerance on the cost's change (its ``ftol``) and iteration cap.
FTOL = 1e-8
MAX_ITER = 200


@dataclass(frozen=True)
class Reorientation:
    """The solved transcription.

    Attributes:
        t: node times, shape (N + 1,) [s].
        q: node configurations, shape (N + 1, nq) [rad].
        v: node velocities, shape (N + 1, nv) [rad/s].
        u: motor torques per interval, shape (N, 3) [N m].
        tau: the same as generalized forces, shape (N, nv) [N m].
        success: SLSQP's flag; message: its message; iterations: its iterations.
        orientation_error: max |q_N,P - target| [rad].
        terminal_rate: max |v_N,P| [rad/s].
        max_defect: the largest dynamics defect max |x_k+1 - F_h(x_k, u_k)| [rad, rad/s].
        effort: h / 2 sum |u_k|^2 [N^2 m^2 s].
        cpu_time: CPU time of the solve [s].
    """

    t: np.ndarray
    q: np.ndarray
    v: np.ndarray
    u: np.ndarray
    tau: np.ndarray
    success: bool
    message: str
    iterations: int
    orientation_error: float
    terminal_rate: float
    max_defect: float
    effort: float
    cpu_time: float


class _Transcription:
    """Variables z = (x_1..x_N, u_0..u_{N-1}), x_k = (q_k, v_k); defects and their Jacobian."""

    def __init__(self, mech: cc.Mechanism, q0, v0, target, t_final: float, n: int) -> None:
        if mech.nq != mech.nv:
            raise cc.ClosedChainError("this transcription adds q as a vector: nq must be nv")
        self.mech, self.n, self.h = mech, n, t_final / n
        self.nv = mech.nv
        self.nx = 2 * self.nv
        self.A = mech.coordinate_indices("actuated")
        self.P = mech.coordinate_indices(list(PLATFORM))
        self.nu = len(self.A)
        self.x0 = np.concatenate([q0, v0])
        #: The torque unit of the variables [N m] (module docstring).
        self.u_scale = mech.gravity_torque_scale() or 1.0
        self.target = np.asarray(target, dtype=float)
        self._memo: tuple[bytes, list] | None = None

    def split(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return the node states (N + 1, 2 nv), x_0 included, and the torques (N, nu)
        [N m]."""
        X = np.vstack([self.x0, z[: self.n * self.nx].reshape(self.n, self.nx)])
        return X, self.u_scale * z[self.n * self.nx :].reshape(self.n, self.nu)

    def tau(self, u: np.ndarray) -> np.ndarray:
        """Generalized forces of motor torques u, shape (nv,)."""
        tau = np.zeros(self.nv)
        tau[self.A] = u
        return tau

    def steps(self, z: np.ndarray) -> list:
        """One :func:`closedchain.step_derivatives` per interval (cached per z)."""
        key = z.tobytes()
        if self._memo is None or self._memo[0] != key:
            X, U = self.split(z)
            nv = self.nv
            out = [
                cc.step_derivatives(
                    self.mech, X[k, :nv], X[k, nv:], self.tau(U[k]), self.h, integrator="rk4"
                )
                for k in range(self.n)
            ]
            self._memo = (key, out)
        return self._memo[1]

    def effort(self, z: np.ndarray) -> float:
        """h / 2 sum |u_k|^2 [N^2 m^2 s]."""
        u = self.u_scale * z[self.n * self.nx :]
        return 0.5 * self.h * float(u @ u)

    def cost(self, z: np.ndarray) -> float:
        """The effort in units of t_final u_scale^2."""
        w = z[self.n * self.nx :]
        return 0.5 * float(w @ w) / self.n

    def cost_gradient(self, z: np.ndarray) -> np.ndarray:
        g = np.zeros_like(z)
        g[self.n * self.nx :] = z[self.n * self.nx :] / self.n
        return g

    def constraints(self, z: np.ndarray) -> np.ndarray:
        """Defects x_k+1 - F_h(x_k, u_k) (N 2 nv), then q_N,P - target and v_N,P."""
        X, _ = self.split(z)
        F = np.array([np.concatenate([s.q, s.v]) for s in self.steps(z)])
        nv = self.nv
        end = X[-1]
        return np.concatenate(
            [(X[1:] - F).ravel(), end[:nv][self.P] - self.target, end[nv:][self.P]]
        )

    def jacobian(self, z: np.ndarray) -> np.ndarray:
        n, nx, nu, nv = self.n, self.nx, self.nu, self.nv
        G = np.zeros((n * nx + 2 * len(self.P), z.size))
        for k, s in enumerate(self.steps(z)):
            rows = slice(k * nx, (k + 1) * nx)
            G[rows, k * nx : (k + 1) * nx] = np.eye(nx)  # x_k+1 (z holds x_1 first)
            if k > 0:
                G[rows, (k - 1) * nx : k * nx] = -np.block([[s.dq_dq, s.dq_dv], [s.dv_dq, s.dv_dv]])
            cols = slice(n * nx + k * nu, n * nx + (k + 1) * nu)
            G[rows, cols] = -self.u_scale * np.vstack([s.dq_dtau[:, self.A], s.dv_dtau[:, self.A]])
        last = (n - 1) * nx
        r = n * nx
        G[r + np.arange(len(self.P)), last + self.P] = 1.0
        G[r + len(self.P) + np.arange(len(self.P)), last + nv + self.P] = 1.0
        return G


def initial_guess(tr: _Transcription) -> np.ndarray:
    """Nodes on the manifold along a smooth-step of the platform angles, at rest; torques
    that hold each node against gravity."""
    mech = tr.mech
    q0 = tr.x0[: tr.nv]
    X, U = [], []
    for k in range(tr.n + 1):
        s = k / tr.n
        w = s * s * (3.0 - 2.0 * s)
        q = q0.copy()
        q[tr.P] = (1.0 - w) * q0[tr.P] + w * tr.target
        q = cc.assemble(mech, q, fixed=list(PLATFORM))
        if k:
            X.append(np.concatenate([q, np.zeros(tr.nv)]))
        if k < tr.n:
            U.append(cc.gravity_torque(mech, q)[tr.A] / tr.u_scale)
    return np.concatenate([np.ravel(X), np.ravel(U)])


def solve(
    n_intervals: int = N_INTERVALS,
    t_final: float = T_FINAL,
    target=TARGET,
    *,
    max_iter: int = MAX_ITER,
    ftol: float = FTOL,
) -> Reorientation:
    """Solve the minimum-torque reorientation (module docstring).

    Args:
        n_intervals: shooting intervals N.
        t_final: duration [s].
        target: platform orientation (yaw, pitch, roll) at t_final [rad].
        max_iter: SLSQP's iteration cap.
        ftol: SLSQP's tolerance.

    Returns:
        The nodes, torques and the residuals that judge them (:class:`Reorientation`).
    """
    mech = cc.load(MODEL)
    q0, v0 = mech.q_ref.copy(), np.zeros(mech.nv)
    tr = _Transcription(mech, q0, v0, target, t_final, n_intervals)
    cpu0 = time.process_time()
    res = scipy.optimize.minimize(
        tr.cost,
        initial_guess(tr),
        jac=tr.cost_gradient,
        method="SLSQP",
        constraints=[{"type": "eq", "fun": tr.constraints, "jac": tr.jacobian}],
        options={"maxiter": max_iter, "ftol": ftol},
    )
    cpu = time.process_time() - cpu0
    X, U = tr.split(res.x)
    c = tr.constraints(res.x)
    nd = tr.n * tr.nx
    nv, npl = tr.nv, len(tr.P)
    return Reorientation(
        t=np.linspace(0.0, t_final, n_intervals + 1),
        q=X[:, :nv].copy(),
        v=X[:, nv:].copy(),
        u=U.copy(),
        tau=np.array([tr.tau(u) for u in U]),
        success=bool(res.success),
        message=str(res.message),
        iterations=int(res.nit),
        orientation_error=float(np.max(np.abs(c[nd : nd + npl]))),
        terminal_rate=float(np.max(np.abs(c[nd + npl :]))),
        max_defect=float(np.max(np.abs(c[:nd]))),
        effort=tr.effort(res.x),
        cpu_time=cpu,
    )


def replay(result: Reorientation, **simulate_options) -> cc.Trajectory:
    """Simulate the torques (piecewise constant) from the first node with ``simulate``."""
    mech = cc.load(MODEL)
    t = result.t
    h = t[1] - t[0]

    def tau(time, q, v):
        return result.tau[min(int(time / h), len(result.tau) - 1)]

    return cc.simulate(
        mech, result.q[0], result.v[0], float(t[-1]), tau=tau, t_eval=t, **simulate_options
    )


def plot(result: Reorientation, path: Path, target=TARGET) -> None:
    """Platform angles and motor torques against time, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mech = cc.load(MODEL)
    P = mech.coordinate_indices(list(PLATFORM))
    A = mech.coordinate_indices("actuated")
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    for i, name in enumerate(PLATFORM):
        (line,) = ax1.plot(result.t, result.q[:, P[i]], "o-", ms=3, label=name)
        ax1.axhline(target[i], ls="--", lw=0.8, color=line.get_color())
    ax1.set_ylabel("platform angle [rad]")
    ax1.legend(loc="best", fontsize=8)
    for j, i in enumerate(A):
        ax2.step(
            result.t,
            np.append(result.u[:, j], result.u[-1, j]),
            where="post",
            label=mech.coordinate_names[i],
        )
    ax2.set_ylabel("motor torque [N m]")
    ax2.set_xlabel("t [s]")
    ax2.legend(loc="best", fontsize=8)
    fig.suptitle(
        f"Agile Eye, minimum torque, {len(result.u)} intervals: orientation error "
        f"{result.orientation_error:.1e} rad, max defect {result.max_defect:.1e}",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--intervals", type=int, default=N_INTERVALS)
    parser.add_argument("--t-final", type=float, default=T_FINAL)
    parser.add_argument("--plot", type=Path, help="write the PNG here")
    parser.add_argument("--html", type=Path, help="write the replayed animation here")
    args = parser.parse_args(argv)
    r = solve(args.intervals, args.t_final)
    print(
        f"{r.message} after {r.iterations} iterations, CPU {r.cpu_time:.1f} s: orientation "
        f"error {r.orientation_error:.2e} rad, terminal rate {r.terminal_rate:.2e} rad/s, "
        f"max defect {r.max_defect:.2e}, effort {r.effort:.4g} N^2 m^2 s"
    )
    if args.plot:
        plot(r, args.plot)
    if args.html:
        # The torques from the first node through the default integrator: the difference
        # from the target is the transcription's error (rk4 at h on each interval).
        traj = replay(r)
        P = cc.load(MODEL).coordinate_indices(list(PLATFORM))
        err = np.max(np.abs(traj.q[-1, P] - np.asarray(TARGET)))
        print(f"replay with the default integrator: final orientation error {err:.2e} rad")
        cc.write_html(cc.load(MODEL), traj, args.html, fps=30)


if __name__ == "__main__":
    main()
