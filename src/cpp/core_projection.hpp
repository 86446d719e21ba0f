// closedchain._core: projection onto the constraint manifold and the checks of every step
// (drift, dropped rows, singular positions, rank indicator).
// (Functions over (CoreModel, CoreData): their declarations, then their definitions.)

#pragma once

#include <pinocchio/algorithm/joint-configuration.hpp>

#include <algorithm>
#include <cmath>
#include <limits>

#include "core_data.hpp"
#include "core_methods.hpp"
#include "core_model.hpp"
#include "core_rows.hpp"
#include "core_structure.hpp"
#include "core_tree.hpp"
#include "errors.hpp"
#include "stage_terms.hpp"

namespace closedchain {

// -- declarations ------------------------------------------------------------

/// cond_2(J) from the eigenvalues of J J^T.
double cond_J(const CoreModel &model, CoreData &data);

/// True when cond_2(J) < limit is certain, in O(nc b^2) on the band of A = J J^T
/// (model.banded_normal): lambda_max(A) <= ||A||_1, and A - (||A||_1 / limit^2) I is positive
/// definite (its Cholesky factor exists) iff lambda_min(A) > ||A||_1 / limit^2
/// (Sylvester's law of inertia), which gives cond_2(J)^2 = lambda_max / lambda_min
/// < limit^2. False means "not certain": cond_J() decides (only within a factor
/// sqrt(||A||_1 / lambda_max) <= sqrt(nc) of the limit, i.e. near singular positions).
bool cond_J_below(const CoreModel &model, CoreData &data, double limit);

/// The step's checks at q (Problem.check_regular and LoopClosure.check_rows of the
/// numpy backend), plus the drift limit over every declared row at every step:
/// - every declared row (dropped ones too) within drift_limit, else SimulationFailure
///   naming the row;
/// - a dropped row open by more than max(dropped_row_tol, dropped_row_ratio x the kept
///   rows' residual), or kept rows degenerate (cond(J) > singular_cond while there are
///   dropped rows): RowCheckRequired (the Python side re-selects the rows);
/// - unless singular_robust, cond(J) > singular_cond: SingularError.
void check_regular(const CoreModel &model, CoreData &data, const RefV &q, double t);

/// cond(J) of the kept rows at a projected stage point q of rk4_projected (unless
/// singular_robust): above singular_cond, check_regular's SingularError (an adaptive
/// step's ends can straddle a singular position that its stages come close to),
/// unless the declared rows stay regular (the step's end re-selects the rows).
void check_stage_regular(const CoreModel &model, CoreData &data, const RefV &q, double t);

/// Throw check_regular's SingularError: cond(J) = cond > singular_cond at (t, q).
[[noreturn]] void throw_singular_J(const CoreModel &model, const RefV &q, double t, double cond);

/// Condition number of the nc largest singular values of the declared rows' J at the
/// last eval_phi_J (LoopClosure.check_rows): above singular_cond the mechanism itself
/// is singular there, no re-selection of rows helps.
double declared_cond(const CoreModel &model, CoreData &data);

/// Minimum-norm solution x of J x = b (J full row rank): J^T (J J^T)^-1 b.
/// Where J J^T is ill-conditioned (J nearly rank-deficient, e.g. passing a singular
/// position with stage projection) it is numpy.linalg.lstsq's minimum-norm solution
/// from the SVD, singular values below eps max(nc, nv) s_max treated as zero.
/// The test "the estimate rcond of J J^T exceeds MIN_NORM_RCOND" is decided by an
/// upper bound of cond_1 from the Cholesky factor where it can (rcond >= 1 / that
/// bound), so Eigen's estimator runs only near singular positions.
void min_norm(const CoreModel &model, CoreData &data, const Vec &b, Vec &x);

/// numpy.linalg.lstsq's minimum-norm solution of J x = b (dense SVD of J: only where
/// J J^T is ill-conditioned, i.e. within a step or two of a singular position).
void min_norm_svd(const CoreModel &model, CoreData &data, const Vec &b, Vec &x);

/// Gauss-Newton (minimum-norm) projection of q onto phi = 0, then v onto J v = 0.
/// With mass_orth (the stage projection; problem.project's mass_orthogonal) v is
/// projected in the metric of M: the augmented-Lagrangian iteration (al_solve) at q
/// with right-hand side M v and g = 0. Only where the run passes singular positions
/// (model.singular_robust), as problem.project. data.M (mass_at_kinematics: no velocity pass)
/// and the factor of M + alpha J^T J are then those of q and stay for the evaluation
/// at q that follows (eval_terms: the bias forces only; solve_al: no second
/// factorization); data.lam is overwritten.
void project(const CoreModel &model, CoreData &data, Vec &q, Vec &v, bool mass_orth = false);

/// sqrt(mu / mean eigenvalue of J J^T) at q, capped: mu the Rayleigh quotient after
/// RANK_INDICATOR_ITERS inverse iterations from the ones vector (fixed.rank_indicator).
/// With a narrow row band (set_band's banded_n) J J^T is factorized as a band and
/// x^T J J^T x = |J^T x|^2: O(nc) instead of the dense product and Cholesky, O(nc^3)
/// (the same quantity to round-off; also the ALI3-P loop's indicator).
double rank_indicator(const CoreModel &model, CoreData &data, const Vec &q,
                      double cap = RANK_INDICATOR_CAP);

// -- definitions -------------------------------------------------------------

inline double cond_J(const CoreModel &model, CoreData &data) {
  if (model.nc == 0) return 1.0;
  data.JJt.noalias() = data.J * data.J.transpose();
  data.eig.compute(data.JJt, Eigen::EigenvaluesOnly);
  const Vec &ev = data.eig.eigenvalues();
  if (!(ev[0] > 0)) return std::numeric_limits<double>::infinity();
  return std::sqrt(ev[model.nc - 1] / ev[0]);
}

inline bool cond_J_below(const CoreModel &model, CoreData &data, double limit) {
  const int b = data.normal_band.bandwidth();
  assemble_normal_band(model, data, 0.0);
  Mat &A = data.normal_band.A;
  double anorm = 0.0;
  for (int j = 0; j < model.nc; ++j) {
    double s = 0.0;
    for (int k = 0; k <= b && j + k < model.nc; ++k) s += std::abs(A(k, j));
    for (int k = 1; k <= b && j - k >= 0; ++k) s += std::abs(A(k, j - k));
    anorm = std::max(anorm, s);
  }
  if (!(anorm > 0.0) || !std::isfinite(anorm)) return false;
  A.row(0).array() -= anorm / (limit * limit);
  return data.normal_band.factor();
}

inline void check_regular(const CoreModel &model, CoreData &data, const RefV &q, double t) {
  if (model.nc == 0 && model.declared_rows.empty()) return;
  eval_phi_J(model, data, q);  // placements at q for the declared rows too
  const int nd = static_cast<int>(model.declared_rows.size());
  double res = 0.0, kept_res = 0.0, drop_res = 0.0;
  int worst = -1, worst_drop = -1;
  if (nd) {
    declared_phi(model, data);
    for (int r = 0; r < nd; ++r) {
      const double x = std::abs(data.declared_residuals[r]);
      if (!(x <= res)) {  // NaN is the worst
        res = x;
        worst = r;
      }
      if (model.declared_kept[r]) {
        kept_res = std::max(kept_res, x);
      } else if (!(x <= drop_res)) {
        drop_res = x;
        worst_drop = r;
      }
    }
  } else {
    res = model.nc ? data.phi.cwiseAbs().maxCoeff() : 0.0;
  }
  check_drift(model, res, worst, t);
  const bool has_dropped = nd > model.nc;
  if (has_dropped && drop_res > std::max(model.dropped_tol, model.dropped_ratio * kept_res))
    throw RowCheckRequired{"dropped row " + model.declared_labels[worst_drop] + " open by " +
                               fmt("%.3e", drop_res) + " (kept rows " + fmt("%.3e", kept_res) +
                               ") at t = " + fmt("%.9g", t) + " s",
                           t};
  if (model.singular_robust || data.rows_only || model.nc == 0) return;
  if (model.banded_normal && cond_J_below(model, data, model.singular_cond)) return;
  double cond = cond_J(model, data);
  if (!(cond <= model.singular_cond)) {
    if (has_dropped && declared_cond(model, data) <= model.singular_cond)
      throw RowCheckRequired{"kept rows degenerate (condition number " + fmt("%.3e", cond) +
                                 ") at t = " + fmt("%.9g", t) + " s",
                             t};
    throw_singular_J(model, q, t, cond);
  }
}

inline void throw_singular_J(const CoreModel &model, const RefV &q, double t, double cond) {
  std::string msg =
      model.name + ": at t = " + fmt("%.9g", t) +
      " s the constraint Jacobian is close to losing rank at q = " + vec_str(q) +
      " (condition number " + fmt("%.3e", cond) + " > singular_cond " +
      fmt("%.1e", model.singular_cond) +
      "); a singular configuration, where the motion is not determined by the equations "
      "and method '" + model.method_name + "' loses accuracy without any error estimate "
      "noticing; " + PASSING_HINT;
  throw SingularError{msg, cond, t, Vec(q)};
}

inline void check_stage_regular(const CoreModel &model, CoreData &data, const RefV &q, double t) {
  if (model.singular_robust || data.rows_only || model.nc == 0) return;
  eval_phi_J(model, data, q);
  if (model.banded_normal && cond_J_below(model, data, model.singular_cond)) return;
  const double cond = cond_J(model, data);
  if (cond <= model.singular_cond) return;
  // Kept rows that degenerate where the declared ones do not: the step's end re-selects.
  if (static_cast<int>(model.declared_rows.size()) > model.nc &&
      declared_cond(model, data) <= model.singular_cond)
    return;
  throw_singular_J(model, q, t, cond);
}

inline double declared_cond(const CoreModel &model, CoreData &data) {
  const int nd = static_cast<int>(model.declared_rows.size());
  Mat Jd(nd, model.nv);  // only where the kept rows degenerate: not the hot path
  for (int r = 0; r < nd; ++r) row_jacobian(model, data, model.declared_rows[r], Jd.row(r));
  Eigen::JacobiSVD<Mat> svd(Jd);
  const Vec &sv = svd.singularValues();
  if (model.nc == 0 || sv.size() < model.nc || !(sv[model.nc - 1] > 0))
    return std::numeric_limits<double>::infinity();
  return sv[0] / sv[model.nc - 1];
}

inline void min_norm(const CoreModel &model, CoreData &data, const Vec &b, Vec &x) {
  if (model.banded_normal) {
    // The same test and solve on the band of J J^T. Where it is ill-conditioned the
    // SVD below, as the dense path: the numpy backend's regularized normal equations
    // (J J^T + eps I) there were measured less accurate through the N-four-bar's
    // flat positions (N = 10, 20 s: B0 error 2.2e-6 m against 3.1e-8 m) and barely
    // cheaper (N = 40: 5 %).
    if (factor_normal_band(model, data, 0.0) && data.normal_band.rcond() > MIN_NORM_RCOND) {
      data.tmp_c = b;
      data.normal_band.solve_in_place(data.tmp_c);
      jt_mul(model, data, data.tmp_c, x);
      return;
    }
  } else {
    data.JJt.triangularView<Eigen::Lower>() = data.J.lazyProduct(data.J.transpose());
    bool regular = false;
    if (data.llt_jj.compute(data.JJt)) {
      const double anorm = lower_norm1(data.JJt);
      if (anorm * data.llt_jj.inverse_norm_bound(INVERSE_BOUND_MARGIN) < 1.0 / MIN_NORM_RCOND) {
        regular = true;
      } else {
        data.JJt.triangularView<Eigen::StrictlyUpper>() = data.JJt.transpose();
        data.llt_c.compute(data.JJt);
        regular = data.llt_c.info() == Eigen::Success && data.llt_c.rcond() > MIN_NORM_RCOND;
      }
    }
    if (regular) {
      data.tmp_c = b;
      data.llt_jj.solveInPlace(data.tmp_c);
      x.noalias() = data.J.transpose().lazyProduct(data.tmp_c);
      return;
    }
  }
  min_norm_svd(model, data, b, x);
}

inline void min_norm_svd(const CoreModel &model, CoreData &data, const Vec &b, Vec &x) {
  data.svd.compute(data.J, Eigen::ComputeFullU | Eigen::ComputeFullV);
  const Vec &sv = data.svd.singularValues();
  const double cut = std::numeric_limits<double>::epsilon() * std::max(model.nc, model.nv) *
                     (sv.size() ? sv[0] : 0.0);
  x.setZero();
  for (Eigen::Index i = 0; i < sv.size(); ++i)
    if (sv[i] > cut) x += (data.svd.matrixU().col(i).dot(b) / sv[i]) * data.svd.matrixV().col(i);
}

inline void project(const CoreModel &model, CoreData &data, Vec &q, Vec &v, bool mass_orth) {
  mass_orth = mass_orth && model.singular_robust;
  if (model.nc == 0) return;
  for (int it = 0; it < model.projection_iters; ++it) {
    eval_phi_J(model, data, q);
    if (data.phi.cwiseAbs().maxCoeff() <= model.projection_tol) break;
    data.tmp_c = -data.phi;
    min_norm(model, data, data.tmp_c, data.dq);
    data.q_prev = q;
    pinocchio::integrate(model.tree, data.q_prev, data.dq, q);
  }
  if (model.project_velocities && mass_orth) {
    eval_phi_J(model, data, q);
    if (model.tree_solves()) return tree_project_velocity(model, data, q, v);
    data.mv.noalias() = mass_at_J(model, data) * v;
    // From v itself (problem.project's a0): its correction is small here.
    al_solve(model, data, q, std::numeric_limits<double>::quiet_NaN(), data.mv, data.zero_c, v,
             true);
  } else if (model.project_velocities) {
    eval_phi_J(model, data, q);
    if (model.banded_normal)
      j_mul(model, data, v, data.vel_c);
    else
      data.vel_c.noalias() = data.J * v;
    min_norm(model, data, data.vel_c, data.dq);
    v -= data.dq;
  }
}

inline double rank_indicator(const CoreModel &model, CoreData &data, const Vec &q, double cap) {
  if (model.nc == 0) return cap;
  eval_phi_J(model, data, q);
  if (model.banded_normal) {
    assemble_normal_band(model, data, 0.0);
    const double ref = data.normal_band.A.row(0).sum() / model.nc;
    if (!(ref > 0.0)) return 0.0;
    if (!data.normal_band.factor()) return 0.0;
    data.al_wc.setConstant(1.0 / std::sqrt(static_cast<double>(model.nc)));
    for (int i = 0; i < RANK_INDICATOR_ITERS; ++i) {
      data.normal_band.solve_in_place(data.al_wc);
      data.al_wc /= data.al_wc.norm();
    }
    jt_mul(model, data, data.al_wc, data.al_wv);
    const double mu = data.al_wv.squaredNorm();
    return std::min(std::sqrt(std::max(mu, 0.0) / ref), cap);
  }
  data.JJt.noalias() =
      data.J.lazyProduct(data.J.transpose());  // small (no row band): coefficient-based
  const double ref = data.JJt.trace() / model.nc;
  if (!(ref > 0.0)) return 0.0;
  data.llt_c.compute(data.JJt);
  if (data.llt_c.info() != Eigen::Success) return 0.0;
  data.tmp_c.setConstant(1.0 / std::sqrt(static_cast<double>(model.nc)));
  for (int i = 0; i < RANK_INDICATOR_ITERS; ++i) {
    data.llt_c.solveInPlace(data.tmp_c);
    data.tmp_c /= data.tmp_c.norm();
  }
  data.vel_c.noalias() = data.JJt * data.tmp_c;
  const double mu = data.tmp_c.dot(data.vel_c);
  return std::min(std::sqrt(std::max(mu, 0.0) / ref), cap);
}

}  // namespace closedchain
