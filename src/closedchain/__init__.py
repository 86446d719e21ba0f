"""closedchain: dynamics of closed-chain mechanisms on top of Pinocchio.

A mechanism is a URDF file plus URDF+ ``<loop>`` elements for the joints that
close kinematic loops and ``<transmission>`` elements for actuators::

    import closedchain as cc

    mech = cc.load("models/fourbar.urdf")
    q = cc.assemble(mech, mech.q_ref)
    res = cc.forward_dynamics(mech, q, v, tau, method="kkt")
    report = cc.validate(mech, n_samples=100)

Docstrings cite their sources by author and year; the documentation's References
page lists them. "The lesson" (with its Section and Problem numbers) is the course
text the project grew from: "Closed-Chain Examples (4-bar, parallel wrists)", Chapter 15,
Lesson 3, cited there and not distributed with closedchain.
"""

from __future__ import annotations

from .control import (
    computed_torque_controller,
    gravity_torque,
    spring_torque,
)
from .derivatives import (
    ConstraintDerivatives,
    ForwardDynamicsDerivatives,
    InverseDynamicsDerivatives,
    StepDerivatives,
    constraint_derivatives,
    forward_dynamics_derivatives,
    inverse_dynamics_derivatives,
    step_derivatives,
)
from .dynamics import METHODS, ForwardDynamicsResult, SolverSettings, forward_dynamics
from .exceptions import (
    AssemblyError,
    BatchError,
    ClosedChainError,
    InvalidArgumentError,
    LoopClosureError,
    ModelFileError,
    ModelTooLargeError,
    NonFiniteError,
    SingularConfigurationError,
    UnknownChoiceError,
    URDFError,
    ValidationUnavailableError,
)
from .inverse import (
    InverseDynamicsResult,
    JointReaction,
    LoopReaction,
    inverse_dynamics,
    joint_reactions,
)
from .kinematics import (
    AssemblySettings,
    assemble,
    compute_gamma,
    compute_jacobian,
    compute_phi,
    project_velocity,
    random_consistent_state,
    singularity_measures,
)
from .mechanism import LoadSettings, Mechanism, load
from .parallel import (
    ActuationSingularities,
    ForwardKinematicsResult,
    InverseKinematicsResult,
    actuation_singularities,
    forward_kinematics,
    inverse_kinematics,
)
from .plotting import coordinate_series, plot_trajectory
from .simulate import (
    INTEGRATORS,
    STABILIZATIONS,
    BatchResult,
    Rollout,
    SimulationError,
    SimulationSettings,
    lesson_settings,
    simulate,
    simulate_batch,
)
from .trajectory import SimulationInfo, StopInfo, Trajectory
from .validation import ValidationReport, validate
from .visualize import write_html

__version__ = "0.1.0"

__all__ = [
    "INTEGRATORS",
    "STABILIZATIONS",
    "SimulationError",
    "SimulationSettings",
    "lesson_settings",
    "simulate",
    "simulate_batch",
    "BatchResult",
    "Rollout",
    "METHODS",
    "ActuationSingularities",
    "AssemblyError",
    "AssemblySettings",
    "BatchError",
    "ClosedChainError",
    "ConstraintDerivatives",
    "ForwardDynamicsDerivatives",
    "InverseDynamicsDerivatives",
    "StepDerivatives",
    "ForwardDynamicsResult",
    "ForwardKinematicsResult",
    "InvalidArgumentError",
    "InverseDynamicsResult",
    "InverseKinematicsResult",
    "LoadSettings",
    "LoopClosureError",
    "JointReaction",
    "LoopReaction",
    "Mechanism",
    "ModelTooLargeError",
    "NonFiniteError",
    "SingularConfigurationError",
    "SolverSettings",
    "SimulationInfo",
    "StopInfo",
    "Trajectory",
    "ModelFileError",
    "URDFError",
    "UnknownChoiceError",
    "ValidationReport",
    "ValidationUnavailableError",
    "actuation_singularities",
    "assemble",
    "compute_gamma",
    "constraint_derivatives",
    "computed_torque_controller",
    "gravity_torque",
    "compute_jacobian",
    "compute_phi",
    "forward_dynamics",
    "forward_dynamics_derivatives",
    "step_derivatives",
    "forward_kinematics",
    "inverse_dynamics",
    "inverse_dynamics_derivatives",
    "inverse_kinematics",
    "joint_reactions",
    "load",
    "coordinate_series",
    "plot_trajectory",
    "project_velocity",
    "random_consistent_state",
    "singularity_measures",
    "spring_torque",
    "validate",
    "write_html",
]
