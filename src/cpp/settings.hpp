// closedchain._core: the typed settings of Core::configure and Core::run_ali3p, bound as
// classes by expose-settings.cpp and filled field by field by closedchain.compiled from
// the Python settings dataclasses (same field names; the defaults are those of the
// dataclasses, checked by tests/test_compiled.py).

#pragma once

#include <Eigen/Core>

#include <string>

namespace closedchain {

/// The method and the options of one configuration (closedchain.compiled.configure).
struct RunOptions {
  /// Forward-dynamics method: kkt, schur, nullspace, augmented-lagrangian or reduced.
  std::string method = "kkt";
  /// Project every stage state of a fixed-step loop (stabilization stage-projection).
  bool stage_projects = false;
  /// Pass singular positions: no stop on cond(J) (Problem.singular_robust).
  bool singular_robust = false;
  /// Stabilization partitioning: integrate the independent coordinates, solve the
  /// dependent ones at every evaluation.
  bool partitions = false;
  /// The partition a partitioning run starts from (velocity indices); empty: the one
  /// of the last configuration that gave it (set_partition's at first).
  Eigen::VectorXi independent;
};

/// closedchain.dynamics.base.SolverSettings: the fields the compiled core reads.
struct SolverSettings {
  /// Largest condition number of a matrix a method factorizes.
  double cond_max = 1e12;
  /// Baumgarte stabilization on, with gains (baumgarte_alpha, baumgarte_beta) [1/s].
  bool baumgarte = false;
  double baumgarte_alpha = 0.0;
  double baumgarte_beta = 0.0;
  /// Relative penalty rho of the augmented-Lagrangian method (dimensionless).
  double al_penalty = 1e11;
  /// Its iteration stops when max |a_{k+1} - a_k| <= al_tol (1 + max |a_{k+1}|).
  double al_tol = 1e-13;
  /// Its iteration cap.
  int al_max_iter = 30;
};

/// closedchain.simulate.settings.SimulationSettings: the fields the compiled loops read.
struct SimulationSettings {
  /// Target max |phi| of the position projection [m or -].
  double projection_tol = 1e-13;
  /// Gauss-Newton iterations of the position projection.
  int projection_iters = 10;
  /// Project v onto J v = 0 after each step.
  bool project_velocities = true;
  /// Stop when cond_2(J) at a step exceeds this.
  double singular_cond = 1e3;
  /// Stop when max |phi| over every declared row exceeds this [m or -].
  double drift_limit = 1e-2;
  /// ALI3-P keeps its step ends this many steps away from a singular position.
  double singular_zone = 0.04;
  /// rk4 with stage projection keeps its evaluation points this many steps away.
  double stage_singular_zone = 0.3;
  /// A dropped row open by more than this [m or -] (and dropped_row_ratio times the
  /// kept rows' residual) means the rows must be re-selected.
  double dropped_row_tol = 1e-9;
  double dropped_row_ratio = 100.0;
  /// Max |phi| of the dependent-coordinate solve (partitioning) [m or -].
  double dependent_tol = 1e-13;
  /// Re-partition when cond(J_D) exceeds this.
  double repartition_cond = 10.0;
  /// Stop when even the best-conditioned J_D has a condition number above this.
  double partition_singular_cond = 1e4;
};

/// The settings of one ALI3-P run (SimulationSettings.ali3p_*).
struct Ali3pSettings {
  /// Newton stops when the largest correction of the displacement is below this [rad or m].
  double tol = 1e-10;
  /// ... and max |phi| at the iterate is below this [m or -].
  double phi_tol = 1e-13;
  /// Newton iterations per step at most (then SimulationError).
  int max_iter = 50;
  /// Relative penalty rho, h^2 alpha / 4 = rho tr(M) / tr(J^T J) (dimensionless).
  double penalty = 1e11;
};

}  // namespace closedchain
