// closedchain._core: the forward-dynamics methods: KKT, Schur, null space, augmented
// Lagrangian (the reduced method is in core_partitioning.hpp).
// (Member functions of Core, declared in core.hpp.)

#pragma once

#include <algorithm>
#include <cmath>
#include <limits>

#include "al_iteration.hpp"
#include "core.hpp"
#include "small_llt.hpp"

namespace closedchain {

/// The next augmented-Lagrangian penalty after P = M + alpha J^T J showed ``pivot``, its
/// smallest relative pivot (0: not positive definite): the small pivots scale as
/// 1 / alpha, so aim at AL_PENALTY_MARGIN AL_PIVOT_MIN, lowering by at most
/// AL_PENALTY_DROP (lowered_penalty of dynamics/augmented_lagrangian.py).
inline double al_lowered_penalty(double alpha, double pivot) {
  const double f = pivot / (AL_PENALTY_MARGIN * AL_PIVOT_MIN);
  return alpha * (f > AL_PENALTY_DROP ? f : AL_PENALTY_DROP);
}

inline void Core::solve(const RefV &q, const RefV &v, const Vec &tau, double t) {
  eval_terms(q, v);
  ++n_evals_;
  dispatch(q, tau, t);
}

inline void Core::dispatch(const RefV &q, const Vec &tau, double t) {
  switch (method_) {
    case KKT: solve_kkt(q, tau, t); break;
    case SCHUR: solve_schur(q, tau, t); break;
    case NULLSPACE: solve_nullspace(q, tau, t); break;
    case AUGMENTED_LAGRANGIAN: solve_al(q, tau, t); break;
    case REDUCED: solve_reduced(q, tau, t); break;
  }
}

inline void Core::solve_al(const RefV &q, const Vec &tau, double t) {
  if (nc_ == 0) {
    llt_m_.compute(M_);
    if (llt_m_.info() != Eigen::Success)
      singular(q, "the mass matrix M", std::numeric_limits<double>::infinity(),
               "it is not positive definite (a massless subtree)", t);
    a_ = tau - h_;
    llt_m_.solveInPlace(a_);
    return;
  }
  rhs_v_ = tau - h_;
  if (!band_p_ && solve_al_small<1, 1>(q, t)) return;
  al_solve(q, t, rhs_v_, gamma_, a_);
  if (band_p_) {  // the multiplier polish on the band normal equations
    tmp_v_ = rhs_v_;
    m_mul_sub(a_, tmp_v_);
    jt_mul(lam_, dq_);
    tmp_v_ -= dq_;  // r_d
    j_mul(tmp_v_, tmp_c_);
    if (band_n_ && factor_normal_band(AL_NORMAL_EQ_REG)) {
      normal_band_.solve_in_place(tmp_c_);
    } else {  // dense normal equations (no narrow row band, or the band factor failed)
      JJt_.noalias() = J_ * J_.transpose();
      JJt_.diagonal().array() +=
          AL_NORMAL_EQ_REG * std::max(JJt_.trace(), 1.0) / static_cast<double>(nc_);
      llt_c_.compute(JJt_);
      llt_c_.solveInPlace(tmp_c_);
    }
    lam_ += tmp_c_;
    return;
  }
  tmp_v_ = rhs_v_;
  tmp_v_.noalias() -= M_.lazyProduct(a_);
  tmp_v_.noalias() -= J_.transpose().lazyProduct(lam_);  // r_d
  JJt_.triangularView<Eigen::Lower>() = J_.lazyProduct(J_.transpose());
  JJt_.diagonal().array() +=
      AL_NORMAL_EQ_REG * std::max(JJt_.trace(), 1.0) / static_cast<double>(nc_);
  llt_jj_.compute(JJt_);
  tmp_c_.noalias() = J_.lazyProduct(tmp_v_);
  llt_jj_.solveInPlace(tmp_c_);
  lam_ += tmp_c_;
}

template <int NV, int NC>
inline bool Core::solve_al_small(const RefV &q, double t) {
  if constexpr (NV > AL_FIXED_MAX) {
    return false;
  } else {
    if (nv_ != NV || nc_ != NC) {
      if constexpr (NC < NV)
        return solve_al_small<NV, NC + 1>(q, t);
      else
        return solve_al_small<NV + 1, 1>(q, t);
    }
    using MatN = Eigen::Matrix<double, NV, NV>;
    using MatC = Eigen::Matrix<double, NC, NC>;
    using MatJ = Eigen::Matrix<double, NC, NV>;
    using VecN = Eigen::Matrix<double, NV, 1>;
    using VecC = Eigen::Matrix<double, NC, 1>;
    struct Ops {
      const Eigen::Map<const MatN> &M;
      const Eigen::Map<const MatJ> &J;
      const FixedLDLT<NV> &llt;
      void add_j(const VecN &x, VecC &y) { y.noalias() += J * x; }
      void sub_m(const VecN &x, VecN &y) { y.noalias() -= M * x; }
      void sub_jt(const VecC &y, VecN &x) { x.noalias() -= J.transpose() * y; }
      void sub_scaled_jt(double s, const VecC &y, VecN &x) {
        x.noalias() -= s * (J.transpose() * y);
      }
      void solve(VecN &x) { llt.solveInPlace(x); }
    };
    const Eigen::Map<const MatN> M(M_.data());
    const Eigen::Map<const MatJ> J(J_.data());
    double alpha =
        al_penalty_ * M.trace() / std::max(J.squaredNorm(), std::numeric_limits<double>::min());
    const MatN JtJ = J.transpose() * J;
    FixedLDLT<NV> llt;
    int lowerings = 0;
    for (;; ++lowerings) {  // the penalty P can take (al_factor)
      const bool ok = llt.compute(M + alpha * JtJ);
      const double pivot = ok ? llt.min_pivot_ratio() : 0.0;
      if (pivot >= AL_PIVOT_MIN) break;
      if (lowerings == AL_MAX_PENALTY_LOWERINGS) penalized_singular(q, alpha, t);
      alpha = al_lowered_penalty(alpha, pivot);
    }
    Ops ops{M, J, llt};
    const VecN rhs = rhs_v_;
    const VecC g = gamma_;
    VecN x, delta;
    VecC lam, rc;
    al_iterate(ops, alpha, rhs, g, al_max_iter_ * (1 + lowerings), al_tol_, x, lam, delta, rc);
    // the multiplier polish: J J^T dlam = J (rhs - M a - J^T lam), regularized
    const VecN rd = rhs - M * x - J.transpose() * lam;
    MatC JJt = J * J.transpose();
    JJt.diagonal().array() += AL_NORMAL_EQ_REG * std::max(JJt.trace(), 1.0) / double(NC);
    FixedLDLT<NC> llt_c;
    if (!llt_c.compute(JJt)) return false;  // the dynamic path decides
    VecC dlam = J * rd;
    llt_c.solveInPlace(dlam);
    lam += dlam;
    a_ = x;
    lam_ = lam;
    return true;
  }
}

inline double Core::al_factor(const RefV &q, double t) {
  if (p_fact_) return al_alpha_;
  const double jj = band_p_ ? j_squared_norm() : J_.squaredNorm();
  double alpha = al_penalty_ * M_.trace() / std::max(jj, std::numeric_limits<double>::min());
  for (al_lowerings_ = 0;; ++al_lowerings_) {
    double pivot = 0.0;
    if (band_p_) {
      if (factor_penalized_band(alpha)) pivot = penalized_band_.min_pivot_ratio();
    } else {
      P_.triangularView<Eigen::Lower>() = J_.transpose().lazyProduct(J_);
      P_.triangularView<Eigen::Lower>() = alpha * P_ + M_;
      if (llt_p_.compute(P_)) pivot = llt_p_.min_pivot_ratio(P_);
    }
    if (pivot >= AL_PIVOT_MIN) break;
    if (al_lowerings_ == AL_MAX_PENALTY_LOWERINGS) penalized_singular(q, alpha, t);
    alpha = al_lowered_penalty(alpha, pivot);
  }
  p_fact_ = true;
  al_alpha_ = alpha;
  return alpha;
}

inline void Core::penalized_singular(const RefV &q, double alpha, double t) {
  singular(q, "the penalized mass matrix M + alpha J^T J", std::numeric_limits<double>::infinity(),
           "it is not numerically positive definite even at alpha = " + fmt("%.3g", alpha) +
               " (lowered " + std::to_string(AL_MAX_PENALTY_LOWERINGS) +
               " times), so M itself is singular (a massless subtree)",
           t);
}

inline void Core::al_solve(const RefV &q, double t, const Vec &rhs, const Vec &g, Vec &x,
                           bool from_x) {
  const double alpha = al_factor(q, t);
  const int max_iter = al_max_iter_ * (1 + al_lowerings_);
  if (band_p_) {
    BandAlOps ops{*this};
    al_iterate(ops, alpha, rhs, g, max_iter, al_tol_, x, lam_, dq_, tmp_c_, from_x);
  } else {
    DenseAlOps ops{*this};
    al_iterate(ops, alpha, rhs, g, max_iter, al_tol_, x, lam_, dq_, tmp_c_, from_x);
  }
}

inline void Core::singular(const RefV &q, const std::string &what, double cond,
                           const std::string &hint, double t) {
  std::string msg = name_ + ": " + what + " is singular at q = " + vec_str(q) +
                    " (condition number " + fmt("%.3e", cond) + " > cond_max " +
                    fmt("%.1e", cond_max_) + "); " + hint;
  if (!std::isnan(t)) msg = "at t = " + fmt("%.9g", t) + " s: " + msg;
  throw SingularError{msg, cond, t, Vec(q)};
}

inline void Core::check_rcond(const RefV &q, const std::string &what, double rcond, double t) {
  double cond = (rcond > 0 && std::isfinite(rcond)) ? 1.0 / rcond
                                                     : std::numeric_limits<double>::infinity();
  if (!(cond <= cond_max_))
    singular(q, what, cond,
             "the constraint Jacobian has lost rank or the configuration is a singularity", t);
}

inline void Core::solve_kkt(const RefV &q, const Vec &tau, double t) {
  // K = [[M, J^T], [J, 0]] equilibrated, D K D with D = diag(d_v, d_c), d_v = M_ii^-1/2,
  // d_c = 1 / |row of J D_v| (each floored at KKT_SCALE_FLOOR of the largest: kkt.py's
  // kkt_scaling), so that its condition estimate does not depend on the mass unit;
  // assembled column by column (written out: the block assignments cost more than the
  // copy at these sizes), factored in place by DenseLU (dense_lu.hpp); K x = r is
  // solved as (D K D) y = D r, x = D y.
  const Eigen::Index nv = nv_, nc = nc_, n = nv + nc;
  double *d = kkt_scale_.data();
  double top = 0.0;
  for (Eigen::Index i = 0; i < nv; ++i) top = std::max(top, M_(i, i));
  for (Eigen::Index i = 0; i < nv; ++i)
    d[i] = top > 0 ? 1.0 / std::sqrt(std::max(M_(i, i), KKT_SCALE_FLOOR * top)) : 1.0;
  top = 0.0;
  for (Eigen::Index r = 0; r < nc; ++r) {
    double s = 0.0;
    for (Eigen::Index i = 0; i < nv; ++i) s += (J_(r, i) * d[i]) * (J_(r, i) * d[i]);
    d[nv + r] = std::sqrt(s);
    top = std::max(top, d[nv + r]);
  }
  for (Eigen::Index r = 0; r < nc; ++r)
    d[nv + r] = top > 0 ? 1.0 / std::max(d[nv + r], KKT_SCALE_FLOOR * top) : 1.0;
  double *k = kkt_.A.data();
  for (Eigen::Index j = 0; j < nv; ++j) {
    double *col = k + j * n;
    for (Eigen::Index i = 0; i < nv; ++i) col[i] = d[i] * M_(i, j) * d[j];
    for (Eigen::Index r = 0; r < nc; ++r) col[nv + r] = d[nv + r] * J_(r, j) * d[j];
  }
  for (Eigen::Index r = 0; r < nc; ++r) {
    double *col = k + (nv + r) * n;
    for (Eigen::Index i = 0; i < nv; ++i) col[i] = d[nv + r] * J_(r, i) * d[i];
    for (Eigen::Index i = nv; i < n; ++i) col[i] = 0.0;
  }
  for (Eigen::Index i = 0; i < nv; ++i) kkt_solution_[i] = d[i] * (tau[i] - h_[i]);
  for (Eigen::Index r = 0; r < nc; ++r) kkt_solution_[nv + r] = -d[nv + r] * gamma_[r];
  // An exactly singular K leaves a zero pivot: rcond 0 (as LAPACK's info > 0).
  // Away from singular configurations a cheap upper bound of cond_1(K) already
  // shows that the dgecon-style estimate (a lower bound of it) cannot exceed
  // cond_max; only otherwise is the estimate computed.
  const char *what = "the KKT matrix [[M, J^T], [J, 0]] (equilibrated)";
  if (!kkt_.factor_in_place()) {
    check_rcond(q, what, 0.0, t);
  } else if (!(kkt_.anorm * kkt_.inverse_norm_bound() <= cond_max_)) {
    check_rcond(q, what, kkt_.rcond(), t);
  }
  kkt_.solve(kkt_solution_);
  a_ = kkt_solution_.head(nv_).cwiseProduct(kkt_scale_.head(nv_));
  lam_ = kkt_solution_.tail(nc_).cwiseProduct(kkt_scale_.tail(nc_));
}

inline void Core::solve_schur(const RefV &q, const Vec &tau, double t) {
  llt_m_.compute(M_);
  check_rcond(q, "the mass matrix M", llt_m_.info() == Eigen::Success ? llt_m_.rcond() : 0.0, t);
  schur_solves_.leftCols(nc_) = J_.transpose();
  schur_solves_.col(nc_) = tau - h_;
  llt_m_.solveInPlace(schur_solves_);
  if (nc_ == 0) {
    a_ = schur_solves_.col(0);
    return;
  }
  delassus_.noalias() = J_ * schur_solves_.leftCols(nc_);
  tmp_c_.noalias() = J_ * schur_solves_.col(nc_);
  tmp_c_ += gamma_;
  llt_c_.compute(delassus_);
  check_rcond(q, "the Delassus matrix J M^-1 J^T",
              llt_c_.info() == Eigen::Success ? llt_c_.rcond() : 0.0, t);
  lam_ = tmp_c_;
  llt_c_.solveInPlace(lam_);
  a_ = schur_solves_.col(nc_);
  a_.noalias() -= schur_solves_.leftCols(nc_) * lam_;
}

inline void Core::solve_nullspace(const RefV &q, const Vec &tau, double t) {
  const int nr = nv_ - nc_;
  if (nc_ == 0) {
    llt_m_.compute(M_);
    a_ = llt_m_.solve(tau - h_);
    return;
  }
  svd_.compute(J_, Eigen::ComputeFullU | Eigen::ComputeFullV);
  const Vec &s = svd_.singularValues();
  double cond = s[nc_ - 1] > 0 ? s[0] / s[nc_ - 1] : std::numeric_limits<double>::infinity();
  if (!(cond <= cond_max_))
    singular(q, "the constraint Jacobian J", cond,
             "it has lost rank: a singular configuration", t);
  const Mat &U = svd_.matrixU();
  const Mat &V = svd_.matrixV();
  // a_p = -V_r S^-1 U^T gamma
  tmp_c_.noalias() = U.transpose() * gamma_;
  tmp_c_.array() /= s.head(nc_).array();
  a_.noalias() = -(V.leftCols(nc_) * tmp_c_);
  if (nr > 0) {
    auto N = V.rightCols(nr);
    reduced_mass_.noalias() = N.transpose() * M_ * N;
    llt_r_.compute(reduced_mass_);
    check_rcond(q, "the reduced mass matrix N^T M N",
                llt_r_.info() == Eigen::Success ? llt_r_.rcond() : 0.0, t);
    tmp_v_ = tau - h_;
    tmp_v_.noalias() -= M_ * a_;
    nullspace_a_.noalias() = N.transpose() * tmp_v_;
    llt_r_.solveInPlace(nullspace_a_);
    a_.noalias() += N * nullspace_a_;
  }
  tmp_v_ = tau - h_;
  tmp_v_.noalias() -= M_ * a_;
  tmp_c_.noalias() = V.leftCols(nc_).transpose() * tmp_v_;
  tmp_c_.array() /= s.head(nc_).array();
  lam_.noalias() = U * tmp_c_;
}

inline const Vec &Core::tau_at(double t, const RefV &q, const RefV &v) {
  if (tau_mode_ == 0) return zero_v_;
  if (tau_mode_ == 1) return tau_const_;
  bp::object r = np_asarray_(tau_obj_(t, to_numpy(q), to_numpy(v)), "float64");
  bp::extract<Vec> ex(r);
  bool ok = bp::len(r.attr("shape")) == 1 && ex.check();
  if (ok) {
    tau_ = ex();
    ok = tau_.size() == nv_ && tau_.allFinite();
  }
  if (!ok) {
    std::string rep = bp::extract<std::string>(bp::str(r));
    throw SimulationFailure{"tau(t, q, v) returned " + rep + " at t = " + fmt("%.6g", t) +
                                " s; expected finite shape (" + std::to_string(nv_) + ",)",
                            t};
  }
  return tau_;
}

inline void Core::accel(double t, const RefV &q, const RefV &v) {
  const Vec &tau = tau_at(t, q, v);
  solve(q, v, tau, t);
  if (!a_.allFinite())
    // simulate.problem.nonfinite_message
    throw SimulationFailure{
        name_ + ": non-finite acceleration at t = " + fmt("%.9g", t) + " s (max |q| = " +
            fmt("%.3e", q.size() ? q.cwiseAbs().maxCoeff() : 0.0) + ", max |v| = " +
            fmt("%.3e", v.size() ? v.cwiseAbs().maxCoeff() : 0.0) +
            "): the state diverged or the method failed there; a fixed step beyond the "
            "motion's stability limit diverges: use integrator='rk43' or a smaller dt",
        t};
}

}  // namespace closedchain
