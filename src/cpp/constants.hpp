// closedchain._core: the numerical constants shared with the numpy backend, and the
// method and integrator codes.

#pragma once

namespace closedchain {

//: Relative regularization of the normal equations that polish the augmented-
//: Lagrangian multipliers (NORMAL_EQ_REG of dynamics/augmented_lagrangian.py).
constexpr double AL_NORMAL_EQ_REG = 1e-14;

//: The penalty that P = M + alpha J^T J can take (PenalizedSolver.factor_relative of
//: dynamics/augmented_lagrangian.py): alpha starts at rho tr(M) / tr(J^T J) and is
//: lowered while P's Cholesky fails or shows a relative pivot L_ii^2 / P_ii below
//: AL_PIVOT_MIN, at most AL_MAX_PENALTY_LOWERINGS times (PIVOT_MIN, PENALTY_MARGIN,
//: PENALTY_DROP, MAX_PENALTY_LOWERINGS there).
constexpr double AL_PIVOT_MIN = 1e-13;
constexpr double AL_PENALTY_MARGIN = 10.0;
constexpr double AL_PENALTY_DROP = 1e-4;
constexpr int AL_MAX_PENALTY_LOWERINGS = 8;

//: The next penalty after P showed `pivot`, its smallest relative pivot (0: not
//: positive definite): the small pivots scale as 1 / alpha, so aim at AL_PENALTY_MARGIN
//: AL_PIVOT_MIN, lowering by at most AL_PENALTY_DROP (lowered_penalty in numpy).
inline double al_lowered_penalty(double alpha, double pivot) {
  const double f = pivot / (AL_PENALTY_MARGIN * AL_PIVOT_MIN);
  return alpha * (f > AL_PENALTY_DROP ? f : AL_PENALTY_DROP);
}

//: min_norm solves through J J^T while its reciprocal condition number is above
//: this (cond(J) below ~1e4), else through the SVD of J.
constexpr double MIN_NORM_RCOND = 1e-8;

//: rk4 with stage projection near singular positions: the constants of
//: closedchain/simulate/fixed.py (RANK_INDICATOR_CAP, RETAKE_GRID, CROSSING_FIT_RTOL,
//: RANK_INDICATOR_ITERS).
constexpr double RANK_INDICATOR_CAP = 1e-2;
constexpr int RETAKE_GRID = 40;
constexpr double CROSSING_FIT_RTOL = 0.5;
constexpr int RANK_INDICATOR_ITERS = 4;

//: Relative margin of the Cholesky inverse-norm bound (min_norm) over its own round-off.
constexpr double INVERSE_BOUND_MARGIN = 1e-8;

//: How to pass singular positions (simulate.problem.passing_hint with the registries
//: of this build), appended to the partitioning stabilization's singular errors.
static const char *const PASSING_HINT =
    "to pass singular positions use method='augmented-lagrangian' with "
    "stabilization='stage-projection' (and a fixed-step integrator)";

enum Method { KKT = 0, SCHUR = 1, NULLSPACE = 2, AUGMENTED_LAGRANGIAN = 3, REDUCED = 4 };
enum Integrator { EULER = 0, SEMI_IMPLICIT = 1, RK4 = 2, RK45 = 3, DOP853 = 4 };

}  // namespace closedchain
