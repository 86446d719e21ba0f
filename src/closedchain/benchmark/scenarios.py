"""Benchmark scenarios as data: a model file, an initial state, torques and a horizon.

Nothing here is specific to one mechanism's code: a scenario names a URDF in the
models directory, an assembly guess (joint values held fixed while the others are
solved), initial rates of the independent coordinates, a gravity vector and a
torque profile on the actuated joints, or the model's own ``<scene>`` (computed-torque
tracking), or a computed-torque path given here. A scenario may name an exact reference
(:mod:`.references`) that replaces the numerical reference and its confirmation.
"""

from __future__ import annotations

import functools
import math
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..control import computed_torque_controller, default_scene, sinusoid_reference
from ..exceptions import UnknownChoiceError
from ..kinematics import assemble, project_velocity
from ..mechanism import Mechanism, load
from ..urdf import SinusoidSpec


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
        tags: free labels.
        loops: overlay file (in the models directory) merged into ``urdf``, which may
            then be ``erd:<name>`` (a robot of example-robot-data).
        method: closedchain's forward-dynamics method on this scenario (a singular
            passage needs a singular-robust one).
        scene: initial state and torques from the model's ``<scene>`` element
            (:func:`closedchain.control.default_scene`); ``guess`` etc. are ignored.
        track: computed-torque path ``(joint, offset [rad], amplitude [rad],
            frequency [Hz])`` per tracked joint (mobility many), gains ``kp``, ``kd``;
            the start is assembled on the path with the matching velocity.
        kp: position gain of ``track`` [1/s^2].
        kd: velocity gain of ``track`` [1/s].
        exact: name of an exact reference in :data:`.references.EXACT_REFERENCES`.
        max_steps: fixed-step runs longer than this many steps are left out (where each
            evaluation is costly, e.g. a controller in Python); None: no cap.
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
    loops: str | None = None
    method: str = "kkt"
    scene: bool = False
    track: tuple[tuple[str, float, float, float], ...] = ()
    kp: float = 100.0
    kd: float = 20.0
    exact: str | None = None
    max_steps: int | None = None

    @property
    def passive(self) -> bool:
        """No applied torque: energy is conserved."""
        return self.torque_amplitude == 0.0 and not self.scene and not self.track


#: Crossed assembly branch of the lesson's 4-bar at theta2 = 10 deg (tests/test_simulate.py).
_FOURBAR_CROSSED = tuple(math.radians(x) for x in (10.0, -65.0, -104.0))

#: IFToMM A02 start (tests/nfourbar_reference.py): cranks vertical, couplers horizontal.
_NFOURBAR_START = (math.pi / 2, -math.pi / 2, math.pi / 2, -math.pi / 2, math.pi / 2)

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
        Scenario(
            "agile_eye-computed-torque",
            "agile_eye.urdf",
            t_final=5.0,
            quick_t_final=1.0,
            scene=True,
            # Each evaluation runs the computed-torque controller (closed-chain inverse
            # dynamics in Python, ~0.5 ms): 5 s, and fixed steps below 5e-4 s left out.
            max_steps=10_000,
            description="Agile Eye, computed-torque orientation path (the model's <scene>), 5 s",
        ),
        Scenario(
            "nfourbar2-singular",
            "nfourbar_2.urdf",
            t_final=4.0,
            quick_t_final=1.0,
            guess=_NFOURBAR_START,
            fixed=("crank_2_joint",),
            v_independent=(-1.0,),
            # Comparison grid 0.05 s (81 samples): fixed steps up to 0.05 s run (rk4 reaches
            # 1e-3 rad there); every peer step divides it. The error's maximum is the same
            # as on the 0.01 s grid to 3 digits (it grows with time: measured for rk4 at
            # 1e-2 s, 2.89e-7 both, and Pinocchio's Euler loop at 2e-4 s, 3.98e-7 both).
            output_dt=0.05,
            method="augmented-lagrangian",
            exact="nfourbar-parallelogram",
            description="N-four-bar N = 2 through its flat (singular) positions, 4 s",
        ),
        Scenario(
            "pendulum3-passive",
            "pendulum3.urdf",
            t_final=5.0,
            quick_t_final=1.0,
            v_independent=(1.0, 0.0, 0.0),
            description="triple pendulum (an open chain, no loops), passive under gravity, 5 s",
        ),
        Scenario(
            "ur5_crank-passive",
            "erd:ur5",
            loops="ur5_crank.urdf",
            t_final=5.0,
            quick_t_final=1.0,
            v_independent=(1.0, 0.5),
            description="UR5 (example-robot-data) turning a crank, passive under gravity, 5 s",
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
def _load(models_dir: str, urdf: str, loops: str | None, gravity: tuple[float, ...]) -> Mechanism:
    path = urdf if urdf.startswith("erd:") else Path(models_dir) / urdf
    return load(path, loops=None if loops is None else Path(models_dir) / loops, gravity=gravity)


#: Held while a scenario's mechanism is looked up or loaded: the threads of a Dask worker
#: that start together load it once (lru_cache alone lets both miss and load).
_LOAD_LOCK = threading.Lock()


def load_scenario_mechanism(models_dir: str, scenario: Scenario) -> Mechanism:
    """Load (once per process) the mechanism of a scenario."""
    with _LOAD_LOCK:
        return _load(str(models_dir), scenario.urdf, scenario.loops, tuple(scenario.gravity))


def fresh_compiled_core(mech: Mechanism) -> None:
    """Give ``mech`` a newly built shared compiled core, before a job's timer starts.

    The simulator reconfigures the mechanism's shared core at every run. A state that
    survived a run was found this way (a fixed-step partitioning run left the core's
    rows-only check set, so on the N-four-bar kkt + rk4 + stage projection at 0.01 s ran
    through the flat position it stops at, t = 4.6 s; fixed in the core, regression test
    ``tests/test_compiled.py::test_a_partitioning_run_leaves_no_state_in_the_shared_core``);
    a new core per job keeps the jobs independent whatever else a core may keep (1.4-2.4 ms
    to build, outside the timed integration).
    """
    from .. import compiled

    if compiled.available():
        with mech.lock:  # a worker's other thread may be running a job on mech
            mech.__dict__.pop("_compiled_cores", None)  # make_core's cache (tests/test_band.py)
            compiled.make_core(mech)


def _track_controller(mech: Mechanism, scenario: Scenario):
    specs = [SinusoidSpec(*t) for t in scenario.track]
    reference = sinusoid_reference(specs)
    names = [s.joint for s in specs]
    tau = computed_torque_controller(
        mech, reference, kp=scenario.kp, kd=scenario.kd, coordinates=names
    )
    return names, reference, tau


def initial_state(mech: Mechanism, scenario: Scenario) -> tuple[np.ndarray, np.ndarray]:
    """Return the assembled (q0, v0) of ``scenario``: shapes (nq,), (nv,)."""
    if scenario.scene:
        scene = default_scene(mech)
        return scene.q0, scene.v0
    if scenario.track:
        names, reference, _ = _track_controller(mech, scenario)
        q_ref0, v_ref0, _ = reference(0.0)
        joints = [mech.model.joints[mech.model.getJointId(n)] for n in names]
        q = mech.q_ref.copy()
        q[[j.idx_q for j in joints]] = q_ref0
        q0 = assemble(mech, q, fixed=names)
        v = np.zeros(mech.nv)
        v[[j.idx_v for j in joints]] = v_ref0
        return q0, project_velocity(mech, q0, v, fixed=names)
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
    if scenario.scene:
        return default_scene(mech).tau
    if scenario.track:
        return _track_controller(mech, scenario)[2]
    if scenario.passive:
        return None
    idx = mech.actuated_idx_v
    amp, omega = scenario.torque_amplitude, 2.0 * math.pi * scenario.torque_frequency
    tau = np.zeros(mech.nv)

    def f(t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        tau[idx] = amp * math.sin(omega * t)
        return tau

    return f
