// closedchain._core: projection onto the constraint manifold and the checks of every step
// (drift, dropped rows, singular positions, rank indicator).
// (Member functions of Core, declared in core.hpp.)

#pragma once

#include <pinocchio/algorithm/joint-configuration.hpp>

#include <algorithm>
#include <cmath>
#include <limits>

#include "core.hpp"
#include "stage_terms.hpp"

namespace closedchain {

inline double Core::cond_J() {
  if (nc_ == 0) return 1.0;
  JJt_.noalias() = J_ * J_.transpose();
  eig_.compute(JJt_, Eigen::EigenvaluesOnly);
  const Vec &ev = eig_.eigenvalues();
  if (!(ev[0] > 0)) return std::numeric_limits<double>::infinity();
  return std::sqrt(ev[nc_ - 1] / ev[0]);
}

inline bool Core::cond_J_below(double limit) {
  const int b = normal_band_.bandwidth();
  assemble_normal_band(0.0);
  Mat &A = normal_band_.A;
  double anorm = 0.0;
  for (int j = 0; j < nc_; ++j) {
    double s = 0.0;
    for (int k = 0; k <= b && j + k < nc_; ++k) s += std::abs(A(k, j));
    for (int k = 1; k <= b && j - k >= 0; ++k) s += std::abs(A(k, j - k));
    anorm = std::max(anorm, s);
  }
  if (!(anorm > 0.0) || !std::isfinite(anorm)) return false;
  A.row(0).array() -= anorm / (limit * limit);
  return normal_band_.factor();
}

inline void Core::check_regular(const RefV &q, double t) {
  if (nc_ == 0 && drows_.empty()) return;
  eval_phi_J(q);  // placements at q for the declared rows too
  const int nd = static_cast<int>(drows_.size());
  double res = 0.0, kept_res = 0.0, drop_res = 0.0;
  int worst = -1, worst_drop = -1;
  if (nd) {
    declared_phi();
    for (int r = 0; r < nd; ++r) {
      const double x = std::abs(dphi_[r]);
      if (!(x <= res)) {  // NaN is the worst
        res = x;
        worst = r;
      }
      if (dkept_[r]) {
        kept_res = std::max(kept_res, x);
      } else if (!(x <= drop_res)) {
        drop_res = x;
        worst_drop = r;
      }
    }
  } else {
    res = nc_ ? phi_.cwiseAbs().maxCoeff() : 0.0;
  }
  if (!std::isfinite(res) || res > drift_limit_)
    throw SimulationFailure{
        name_ + ": the state left the constraint manifold at t = " + fmt("%.9g", t) +
            " s (max |phi| = " + fmt("%.3e", res) + " > drift_limit " +
            fmt("%.1e", drift_limit_) + (worst >= 0 ? ", row " + dlabels_[worst] : "") +
            "); use a stabilization or a smaller step",
        t};
  const bool has_dropped = nd > nc_;
  if (has_dropped && drop_res > std::max(dropped_tol_, dropped_ratio_ * kept_res))
    throw RowCheckRequired{"dropped row " + dlabels_[worst_drop] + " open by " +
                               fmt("%.3e", drop_res) + " (kept rows " + fmt("%.3e", kept_res) +
                               ") at t = " + fmt("%.9g", t) + " s",
                           t};
  if (singular_robust_ || rows_only_ || nc_ == 0) return;
  if (band_n_ && cond_J_below(singular_cond_)) return;
  double cond = cond_J();
  if (!(cond <= singular_cond_)) {
    if (has_dropped && declared_cond() <= singular_cond_)
      throw RowCheckRequired{"kept rows degenerate (condition number " + fmt("%.3e", cond) +
                                 ") at t = " + fmt("%.9g", t) + " s",
                             t};
    throw_singular_J(q, t, cond);
  }
}

inline void Core::throw_singular_J(const RefV &q, double t, double cond) {
  std::string msg =
      name_ + ": at t = " + fmt("%.9g", t) +
      " s the constraint Jacobian is close to losing rank at q = " + vec_str(q) +
      " (condition number " + fmt("%.3e", cond) + " > singular_cond " +
      fmt("%.1e", singular_cond_) +
      "): a singular configuration, where the motion is not determined by the equations "
      "and method '" + method_name_ + "' loses accuracy without any error estimate "
      "noticing; to pass singular positions use method='augmented-lagrangian' with "
      "stabilization='stage-projection' (and a fixed-step integrator)";
  throw SingularError{msg, cond, t, Vec(q)};
}

inline void Core::check_stage_regular(const RefV &q, double t) {
  if (singular_robust_ || rows_only_ || nc_ == 0) return;
  eval_phi_J(q);
  if (band_n_ && cond_J_below(singular_cond_)) return;
  const double cond = cond_J();
  if (cond <= singular_cond_) return;
  // Kept rows that degenerate where the declared ones do not: the step's end re-selects.
  if (static_cast<int>(drows_.size()) > nc_ && declared_cond() <= singular_cond_) return;
  throw_singular_J(q, t, cond);
}

inline double Core::declared_cond() {
  const int nd = static_cast<int>(drows_.size());
  Mat Jd(nd, nv_);  // only where the kept rows degenerate: not the hot path
  for (int r = 0; r < nd; ++r) row_jacobian(drows_[r], Jd.row(r));
  Eigen::JacobiSVD<Mat> svd(Jd);
  const Vec &sv = svd.singularValues();
  if (nc_ == 0 || sv.size() < nc_ || !(sv[nc_ - 1] > 0))
    return std::numeric_limits<double>::infinity();
  return sv[0] / sv[nc_ - 1];
}

inline void Core::min_norm(const Vec &b, Vec &x) {
  if (band_n_) {
    // The same test and solve on the band of J J^T. Where it is ill-conditioned the
    // SVD below, as the dense path: the numpy backend's regularized normal equations
    // (J J^T + eps I) there were measured less accurate through the N-four-bar's
    // flat positions (N = 10, 20 s: B0 error 2.2e-6 m against 3.1e-8 m) and barely
    // cheaper (N = 40: 5 %).
    if (factor_normal_band(0.0) && normal_band_.rcond() > MIN_NORM_RCOND) {
      tmp_c_ = b;
      normal_band_.solve_in_place(tmp_c_);
      jt_mul(tmp_c_, x);
      return;
    }
  } else {
    JJt_.triangularView<Eigen::Lower>() = J_.lazyProduct(J_.transpose());
    bool regular = false;
    if (llt_jj_.compute(JJt_)) {
      double anorm = 0.0;  // ||J J^T||_1 from its lower triangle
      for (Eigen::Index j = 0; j < nc_; ++j) {
        double c = 0.0;
        for (Eigen::Index i = 0; i < nc_; ++i) c += std::abs(i >= j ? JJt_(i, j) : JJt_(j, i));
        anorm = std::max(anorm, c);
      }
      if (anorm * llt_jj_.inverse_norm_bound(INVERSE_BOUND_MARGIN) < 1.0 / MIN_NORM_RCOND) {
        regular = true;
      } else {
        JJt_.triangularView<Eigen::StrictlyUpper>() = JJt_.transpose();
        llt_c_.compute(JJt_);
        regular = llt_c_.info() == Eigen::Success && llt_c_.rcond() > MIN_NORM_RCOND;
      }
    }
    if (regular) {
      tmp_c_ = b;
      llt_jj_.solveInPlace(tmp_c_);
      x.noalias() = J_.transpose().lazyProduct(tmp_c_);
      return;
    }
  }
  min_norm_svd(b, x);
}

inline void Core::min_norm_svd(const Vec &b, Vec &x) {
  svd_.compute(J_, Eigen::ComputeFullU | Eigen::ComputeFullV);
  const Vec &sv = svd_.singularValues();
  const double cut = std::numeric_limits<double>::epsilon() * std::max(nc_, nv_) *
                     (sv.size() ? sv[0] : 0.0);
  x.setZero();
  for (Eigen::Index i = 0; i < sv.size(); ++i)
    if (sv[i] > cut)
      x += (svd_.matrixU().col(i).dot(b) / sv[i]) * svd_.matrixV().col(i);
}

inline void Core::project(Vec &q, Vec &v, bool mass_orth) {
  mass_orth = mass_orth && singular_robust_;
  if (nc_ == 0) return;
  for (int it = 0; it < projection_iters_; ++it) {
    eval_phi_J(q);
    if (phi_.cwiseAbs().maxCoeff() <= projection_tol_) break;
    tmp_c_ = -phi_;
    min_norm(tmp_c_, dq_);
    q_prev_ = q;
    pinocchio::integrate(model_, q_prev_, dq_, q);
  }
  if (project_velocities_ && mass_orth) {
    eval_phi_J(q);
    if (!m_at_J_) {
      mass_at_kinematics(plan_, model_, data_, M_);
      m_at_J_ = true;
      p_fact_ = false;
      terms_q_.setConstant(std::numeric_limits<double>::quiet_NaN());  // M_, not potential_energy_
    }
    mv_.noalias() = M_ * v;
    // From v itself (problem.project's a0): its correction is small here.
    al_solve(q, std::numeric_limits<double>::quiet_NaN(), mv_, zero_c_, v, true);
  } else if (project_velocities_) {
    eval_phi_J(q);
    if (band_n_)
      j_mul(v, vel_c_);
    else
      vel_c_.noalias() = J_ * v;
    min_norm(vel_c_, dq_);
    v -= dq_;
  }
}

inline double Core::rank_indicator(const Vec &q) {
  if (nc_ == 0) return RANK_INDICATOR_CAP;
  eval_phi_J(q);
  if (band_n_) {
    assemble_normal_band(0.0);
    const double ref = normal_band_.A.row(0).sum() / nc_;
    if (!(ref > 0.0)) return 0.0;
    if (!normal_band_.factor()) return 0.0;
    al_wc_.setConstant(1.0 / std::sqrt(static_cast<double>(nc_)));
    for (int i = 0; i < RANK_INDICATOR_ITERS; ++i) {
      normal_band_.solve_in_place(al_wc_);
      al_wc_ /= al_wc_.norm();
    }
    jt_mul(al_wc_, al_wv_);
    const double mu = al_wv_.squaredNorm();
    return std::min(std::sqrt(std::max(mu, 0.0) / ref), RANK_INDICATOR_CAP);
  }
  JJt_.noalias() = J_.lazyProduct(J_.transpose());  // small (no row band): coefficient-based
  const double ref = JJt_.trace() / nc_;
  if (!(ref > 0.0)) return 0.0;
  llt_c_.compute(JJt_);
  if (llt_c_.info() != Eigen::Success) return 0.0;
  tmp_c_.setConstant(1.0 / std::sqrt(static_cast<double>(nc_)));
  for (int i = 0; i < RANK_INDICATOR_ITERS; ++i) {
    llt_c_.solveInPlace(tmp_c_);
    tmp_c_ /= tmp_c_.norm();
  }
  vel_c_.noalias() = JJt_ * tmp_c_;
  const double mu = tmp_c_.dot(vel_c_);
  return std::min(std::sqrt(std::max(mu, 0.0) / ref), RANK_INDICATOR_CAP);
}

}  // namespace closedchain
