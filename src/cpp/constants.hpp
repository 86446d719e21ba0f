// closedchain._core: the numerical constants shared with the numpy backend, and the
// method and integrator codes.

#pragma once

namespace closedchain {

//: Relative regularization of the normal equations that polish the augmented-
//: Lagrangian multipliers (NORMAL_EQ_REG of dynamics/augmented_lagrangian.py).
constexpr double AL_NORMAL_EQ_REG = 1e-14;

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

//: rk43's step-size control (closedchain/simulate/rk43.py): safety factor, bounds of the
//: step's change, exponent of the error (an estimate of order 3: err ~ h^4).
constexpr double RK43_SAFETY = 0.9;
constexpr double RK43_MIN_FACTOR = 0.2;
constexpr double RK43_MAX_FACTOR = 5.0;
constexpr double RK43_ERROR_EXPONENT = -0.25;

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
