"""The peers the benchmark runs beside closedchain (run here, never cited).

Each runner integrates a scenario's mechanism from (q0, v0) and returns the
configurations and velocities on the comparison grid with the CPU seconds of
the integration alone (``time.process_time``; loading and set-up excluded):

``scipy``
    the thirty-line script a savvy user writes: ``pinocchio.constraintDynamics``
    with exact proximal settings as the right-hand side of
    ``scipy.integrate.solve_ivp`` (DOP853 or Radau).
``pinocchio-euler``
    Pinocchio's recommended loop: ``constraintDynamics`` with Baumgarte gains on
    the constraint models, semi-implicit Euler, ``pin.integrate``.
``mujoco``
    the mechanism exported by :func:`closedchain.export.export_mjcf` (loops as
    equality constraints), ``mj_step`` with MuJoCo's default or stiff
    solref/solimp.
``lesson``
    the algorithm of the lesson's program (Euler step, two Newton projections, exact M),
    as reproduced by :func:`closedchain.lesson_settings`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from ..constraints import build_pinocchio_constraints
from ..exceptions import ClosedChainError
from ..simulate import SimulationSettings, lesson_settings, simulate


@dataclass(frozen=True)
class PeerSettings:
    """Settings of the peers.

    Attributes:
        proximal_accuracy: absolute accuracy of ``constraintDynamics`` (scipy peer).
        proximal_mu: proximal regularization (scipy peer; mu = 0
            returns NaN on redundant rows).
        proximal_max_iter: proximal iteration cap.
        euler_mu: regularization of the Euler loop.
        euler_accuracy: accuracy of the Euler loop's proximal solve.
        baumgarte_kp: position gain on the constraint models of the Euler loop [1/s^2].
        baumgarte_kd: velocity gain [1/s].
    """

    proximal_accuracy: float = 1e-12
    proximal_mu: float = 1e-8
    proximal_max_iter: int = 100
    euler_mu: float = 1e-8
    euler_accuracy: float = 1e-10
    baumgarte_kp: float = 100.0
    baumgarte_kd: float = 20.0


DEFAULT_PEER_SETTINGS = PeerSettings()


@dataclass
class RunOutput:
    """What one run returns: states on the grid, CPU seconds, status and message."""

    q: np.ndarray
    v: np.ndarray
    cpu_s: float
    status: str = "ok"
    message: str = ""
    steps: int = 0


def _constraints(mech, kp: float = 0.0, kd: float = 0.0):
    cms, _ = build_pinocchio_constraints(mech.model, mech.declared)
    cds = pin.StdVec_RigidConstraintData()
    for cm in cms:
        if kp or kd:
            b = cm.m_baumgarte_parameters
            b.Kp = kp
            b.Kd = kd
            cm.setBaumgarteCorrectorParameters(b)
        cds.append(cm.createData())
    data = mech.model.createData()
    pin.initConstraintDynamics(mech.model, data, cms, cds)
    return cms, cds, data


def _grid_stride(t_grid: np.ndarray, dt: float) -> int:
    spacing = t_grid[1] - t_grid[0]
    stride = round(spacing / dt)
    if stride < 1 or abs(stride * dt - spacing) > 1e-9 * spacing:
        raise ClosedChainError(f"step dt={dt} must divide the output spacing {spacing}")
    return stride


def run_scipy(
    mech,
    q0,
    v0,
    t_grid,
    tau_fn,
    *,
    integrator: str,
    tol: float,
    peer: PeerSettings = DEFAULT_PEER_SETTINGS,
) -> RunOutput:
    """The thirty-line script: constraintDynamics as the rhs of scipy's solve_ivp."""
    from scipy.integrate import solve_ivp

    model = mech.model
    chart = mech.nq != mech.nv
    if chart and any(j.nv != 1 for j in model.joints[1:]):
        raise ClosedChainError(
            "the scipy peer integrates q as a vector: it needs nq == nv or only 1-dof joints"
        )
    cms, cds, data = _constraints(mech)
    prox = pin.ProximalSettings(
        peer.proximal_accuracy, 0.0, peer.proximal_mu, peer.proximal_max_iter
    )
    nv = mech.nv
    zero = np.zeros(nv)
    passive = mech.passive

    # With continuous joints (cos, sin) the script integrates x = q (-) q0 in the tangent
    # space at q0: for 1-dof joints (R and SO(2) are abelian) dx/dt = v exactly.
    def rhs(t, x):
        q = pin.integrate(model, q0, x[:nv]) if chart else x[:nv]
        v = x[nv:]
        tau = zero if tau_fn is None else tau_fn(t, q, v)
        tau = passive.added_to(tau, q, v)  # Pinocchio has no joint springs or damping
        a = pin.constraintDynamics(model, data, q, v, tau, cms, cds, prox)
        return np.concatenate([v, a])

    x0 = np.concatenate([np.zeros(nv) if chart else q0, v0])
    cpu0 = time.process_time()
    sol = solve_ivp(
        rhs, (t_grid[0], t_grid[-1]), x0, method=integrator, rtol=tol, atol=tol, t_eval=t_grid
    )
    if sol.success and chart:
        qs = np.array([pin.integrate(model, q0, x) for x in sol.y[:nv].T])
    elif sol.success:
        qs = sol.y[:nv].T
    cpu = time.process_time() - cpu0
    if not sol.success:
        return RunOutput(np.empty((0, mech.nq)), np.empty((0, nv)), cpu, "raised", sol.message)
    return RunOutput(qs, sol.y[nv:].T, cpu, steps=int(sol.nfev))


def run_pinocchio_euler(
    mech, q0, v0, t_grid, tau_fn, *, dt: float, peer: PeerSettings = DEFAULT_PEER_SETTINGS
) -> RunOutput:
    """constraintDynamics (Baumgarte gains) + semi-implicit Euler + pin.integrate."""
    model = mech.model
    cms, cds, data = _constraints(mech, peer.baumgarte_kp, peer.baumgarte_kd)
    prox = pin.ProximalSettings(peer.euler_accuracy, 0.0, peer.euler_mu, peer.proximal_max_iter)
    stride = _grid_stride(t_grid, dt)
    n = (len(t_grid) - 1) * stride
    qs, vs = [q0.copy()], [v0.copy()]
    q, v = q0.copy(), v0.copy()
    zero = np.zeros(mech.nv)
    passive = mech.passive
    status, message = "ok", ""
    cpu0 = time.process_time()
    for k in range(1, n + 1):
        t = (k - 1) * dt
        tau = zero if tau_fn is None else tau_fn(t, q, v)
        tau = passive.added_to(tau, q, v)  # Pinocchio has no joint springs or damping
        a = pin.constraintDynamics(model, data, q, v, tau, cms, cds, prox)
        v = v + dt * a
        q = pin.integrate(model, q, v * dt)
        if k % stride == 0:
            if not (np.all(np.isfinite(q)) and np.all(np.isfinite(v))):
                status, message = "diverged", f"non-finite state at t = {k * dt:.4g} s"
                break
            qs.append(q)
            vs.append(v)
    cpu = time.process_time() - cpu0
    return RunOutput(np.array(qs), np.array(vs), cpu, status, message, steps=n)


def run_mujoco(mech, q0, v0, t_grid, tau_fn, *, dt: float, stiff: bool) -> RunOutput:
    """The exported MJCF stepped by mj_step (Euler), default or stiff equalities."""
    import mujoco

    from ..export.mjcf import STIFF, MjcfSettings, load_mujoco, mujoco_state

    base = STIFF if stiff else MjcfSettings()
    settings = MjcfSettings(solref=base.solref, solimp=base.solimp, timestep=dt)
    m, d = load_mujoco(mech, settings=settings)
    d.qpos[:], d.qvel[:] = mujoco_state(mech, q0, v0)
    mujoco.mj_forward(m, d)
    stride = _grid_stride(t_grid, dt)
    n = (len(t_grid) - 1) * stride
    qs, vs = [d.qpos.copy()], [d.qvel.copy()]
    status, message = "ok", ""
    bad = int(mujoco.mjtWarning.mjWARN_BADQACC)
    cpu0 = time.process_time()
    for k in range(1, n + 1):
        if tau_fn is not None:
            q = d.qpos if mech.nq == mech.nv else pinocchio_configuration(mech, d.qpos)
            d.qfrc_applied[:] = tau_fn(d.time, q, d.qvel)
        mujoco.mj_step(m, d)
        if k % stride == 0:
            if d.warning[bad].number > 0:
                status, message = "diverged", f"MuJoCo reset (bad qacc) at t = {k * dt:.4g} s"
                break
            qs.append(d.qpos.copy())
            vs.append(d.qvel.copy())
    cpu = time.process_time() - cpu0
    qs = [pinocchio_configuration(mech, x) for x in qs]
    return RunOutput(np.array(qs), np.array(vs), cpu, status, message, steps=n)


def pinocchio_configuration(mech, qpos: np.ndarray) -> np.ndarray:
    """Map MuJoCo's qpos of the exported model back to Pinocchio's q, shape (nq,):
    the inverse of :func:`closedchain.export.mjcf.mujoco_state`."""
    model = mech.model
    q = np.empty(mech.nq)
    k = 0
    for j in range(1, model.njoints):
        jm = model.joints[j]
        short = jm.shortname()
        if short.startswith("JointModelRUB") or short == "JointModelRevoluteUnboundedUnaligned":
            q[jm.idx_q : jm.idx_q + 2] = math.cos(qpos[k]), math.sin(qpos[k])
            k += 1
        elif short == "JointModelSpherical":
            w, x, y, z = qpos[k : k + 4]
            q[jm.idx_q : jm.idx_q + 4] = x, y, z, w
            k += 4
        elif short == "JointModelFreeFlyer":
            q[jm.idx_q : jm.idx_q + 3] = qpos[k : k + 3]
            w, x, y, z = qpos[k + 3 : k + 7]
            q[jm.idx_q + 3 : jm.idx_q + 7] = x, y, z, w
            k += 7
        else:
            q[jm.idx_q : jm.idx_q + jm.nq] = qpos[k : k + jm.nq]
            k += jm.nq
    return q


#: Settings of the swept runs: the benchmark measures each run's error itself, so a coarse
#: setting's inaccurate run is a data point, not an error (no ``energy_tol``).
SWEEP_SETTINGS = SimulationSettings(energy_tol=None)


def run_lesson(mech, q0, v0, t_grid, tau_fn, *, dt: float, backend: str = "numpy") -> RunOutput:
    """The lesson's program: Euler step and two Newton projections (closedchain.lesson_settings),
    on closedchain's ``backend`` (numpy or compiled)."""
    cpu0 = time.process_time()
    traj = simulate(
        mech,
        q0,
        v0,
        float(t_grid[-1]),
        method="kkt",
        integrator="semi-implicit",
        stabilization="projection",
        dt=dt,
        tau=tau_fn,
        t_eval=t_grid,
        settings=lesson_settings(),
        backend=backend,
    )
    cpu = time.process_time() - cpu0
    return RunOutput(traj.q, traj.v, cpu, steps=int(traj.info["steps"]))


def run_closedchain(
    mech,
    q0,
    v0,
    t_grid,
    tau_fn,
    *,
    method: str,
    integrator: str,
    stabilization: str | None,
    dt: float | None = None,
    tol: float | None = None,
    backend: str = "auto",
) -> RunOutput:
    """closedchain.simulate with one configuration (``backend``: numpy, compiled or auto)."""
    cpu0 = time.process_time()
    traj = simulate(
        mech,
        q0,
        v0,
        float(t_grid[-1]),
        method=method,
        integrator=integrator,
        stabilization=stabilization,
        dt=dt,
        rtol=tol,
        atol=tol,
        tau=tau_fn,
        t_eval=t_grid,
        settings=SWEEP_SETTINGS,
        backend=backend,
    )
    cpu = time.process_time() - cpu0
    return RunOutput(traj.q, traj.v, cpu, steps=int(traj.info["steps"]))


#: family -> runner (closedchain first).
RUNNERS = {
    "closedchain": run_closedchain,
    "scipy": run_scipy,
    "pinocchio-euler": run_pinocchio_euler,
    "mujoco": run_mujoco,
    "lesson": run_lesson,
}

__all__ = ["DEFAULT_PEER_SETTINGS", "PeerSettings", "RUNNERS", "RunOutput"]
