"""Benchmark scenarios as data: a model file, an initial state, torques and a horizon.

Nothing here is specific to one mechanism's code: a scenario names a URDF in the
models directory, an assembly guess (joint values held fixed while the others are
solved), initial rates of the independent coordinates, a gravity vector and a
torque profile on the actuated joints.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..exceptions import UnknownChoiceError
from ..kinematics import assemble, project_velocity
from ..mechanism import Mechanism, load


@dataclass(frozen=True)
class Scenario:
    """One benchmark scenario.

    Attributes:
        name: registry key (``mechanism-what``).
        urdf: file name in the models directory.
        t_final: horizon of the full benchmark [s].
        quick_t_final: horizon of ``--quick`` [s].
        guess: assembly guess, one value per velocity coordinate [rad or m];
            None: the model's ``q_ref``.
        fixed: joints held at ``guess`` during assembly.
        v_independent: initial rates of the independent coordinates [rad/s or m/s].
        gravity: world gravity [m/s^2].
        torque_amplitude: amplitude of ``tau = A sin(2 pi f t)`` on every actuated
            joint [N m or N]; 0: passive.
        torque_frequency: f [Hz].
        output_dt: spacing of the comparison grid [s] (every fixed step divides it).
        description: one line for the charts.
    """

    name: str
    urdf: str
    t_final: float
    quick_t_final: float
    guess: tuple[float, ...] | None = None
    fixed: tuple[str, ...] = ()
    v_independent: tuple[float, ...] | None = None
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)
    torque_amplitude: float = 0.0
    torque_frequency: float = 0.0
    output_dt: float = 0.01
    description: str = ""
    tags: tuple[str, ...] = field(default=())

    @property
    def passive(self) -> bool:
        """No applied torque: energy is conserved."""
        return self.torque_amplitude == 0.0


#: Crossed assembly branch of the seed's 4-bar at theta2 = 10 deg (tests/test_simulate.py).
_FOURBAR_CROSSED = tuple(math.radians(x) for x in (10.0, -65.0, -104.0))

#: name -> scenario.
SCENARIOS: dict[str, Scenario] = {
    s.name: s
    for s in (
        Scenario(
            "fourbar-passive",
            "fourbar.urdf",
            t_final=10.0,
            quick_t_final=2.0,
            guess=_FOURBAR_CROSSED,
            fixed=("crank_joint",),
            description="4-bar, crossed branch, passive under gravity",
        ),
        Scenario(
            "fourbar-driven",
            "fourbar.urdf",
            t_final=10.0,
            quick_t_final=2.0,
            guess=_FOURBAR_CROSSED,
            fixed=("crank_joint",),
            torque_amplitude=0.5,
            torque_frequency=0.5,
            description="4-bar, crossed branch, crank torque 0.5 sin(pi t) N m",
        ),
        Scenario(
            "agile_eye-coasting",
            "agile_eye.urdf",
            t_final=10.0,
            quick_t_final=2.0,
            v_independent=(0.3, -0.2, 0.1),
            gravity=(0.0, 0.0, 0.0),
            description="Agile Eye coasting from home, no gravity",
        ),
    )
}


def get_scenario(name: str) -> Scenario:
    """Return the scenario ``name`` or raise listing the valid names."""
    try:
        return SCENARIOS[name]
    except KeyError:
        raise UnknownChoiceError("scenario", name, SCENARIOS) from None


@functools.lru_cache(maxsize=16)
def load_scenario_mechanism(models_dir: str, urdf: str, gravity: tuple[float, ...]) -> Mechanism:
    """Load (once per process) the mechanism of a scenario."""
    return load(Path(models_dir) / urdf, gravity=gravity)


def initial_state(mech: Mechanism, scenario: Scenario) -> tuple[np.ndarray, np.ndarray]:
    """Return the assembled (q0, v0) of ``scenario``: shapes (nq,), (nv,)."""
    if scenario.guess is None:
        q0 = mech.q_ref.copy()
    else:
        q0 = assemble(mech, np.asarray(scenario.guess), fixed=list(scenario.fixed))
    v0 = np.zeros(mech.nv)
    if scenario.v_independent is not None:
        v0[mech.independent_idx_v] = scenario.v_independent
        v0 = project_velocity(mech, q0, v0, fixed="independent")
    return q0, v0


def torque_function(mech: Mechanism, scenario: Scenario):
    """Return ``tau(t, q, v) -> (nv,)`` of ``scenario`` (None when passive)."""
    if scenario.passive:
        return None
    idx = mech.actuated_idx_v
    amp, omega = scenario.torque_amplitude, 2.0 * math.pi * scenario.torque_frequency
    tau = np.zeros(mech.nv)

    def f(t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        tau[idx] = amp * math.sin(omega * t)
        return tau

    return f
