"""closedchain: dynamics of closed-chain mechanisms on top of Pinocchio.

A mechanism is a URDF file plus URDF+ ``<loop>`` elements for the joints that
close kinematic loops and ``<transmission>`` elements for actuators::

    import closedchain as cc

    mech = cc.load("models/fourbar.urdf")
    q = cc.assemble(mech, mech.q_ref)
    res = cc.forward_dynamics(mech, q, v, tau, method="kkt")
    report = cc.validate(mech, n_samples=100)
"""

from __future__ import annotations

from .dynamics import METHODS, ForwardDynamicsResult, SolverSettings, forward_dynamics
from .exceptions import (
    AssemblyError,
    ClosedChainError,
    LoopClosureError,
    SingularConfigurationError,
    UnknownChoiceError,
    URDFError,
    ValidationUnavailableError,
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
from .trajectory import Trajectory
from .validation import ValidationReport, validate

__version__ = "0.1.0"

__all__ = [
    "METHODS",
    "AssemblyError",
    "AssemblySettings",
    "ClosedChainError",
    "ForwardDynamicsResult",
    "LoadSettings",
    "LoopClosureError",
    "Mechanism",
    "SingularConfigurationError",
    "SolverSettings",
    "Trajectory",
    "URDFError",
    "UnknownChoiceError",
    "ValidationReport",
    "ValidationUnavailableError",
    "assemble",
    "compute_gamma",
    "compute_jacobian",
    "compute_phi",
    "forward_dynamics",
    "load",
    "project_velocity",
    "random_consistent_state",
    "singularity_measures",
    "validate",
]
