// closedchain._core: the forward-dynamics methods: KKT, Schur, null space, augmented
// Lagrangian (the reduced method is in core_partitioning.hpp).
// (Functions over (CoreModel, CoreData): their declarations, then their definitions.)

#pragma once

#include <algorithm>
#include <cmath>
#include <limits>

#include "al_iteration.hpp"
#include "core_data.hpp"
#include "core_model.hpp"
#include "core_rows.hpp"
#include "core_structure.hpp"
#include "dense_lu.hpp"
#include "errors.hpp"
#include "gil.hpp"
#include "small_llt.hpp"

namespace closedchain {

// solve_al for nv <= AL_FIXED_MAX (the 4-bar: nv 3, nc 2) on fixed-size matrices:
// the same iteration (al_iterate), penalty, acceptance test of P's Cholesky and
// multiplier polish, with Eigen's unrolled fixed-size products and small_llt.hpp's
// FixedLDLT in place of the dynamic-size ones (on the 4-bar the solve is the larger
// part of one evaluation's cost). The results differ from the dynamic path by
// round-off. P is factored here each time (a few dozen operations);
// the factor kept for the stage projection (data.P_factored, data.llt_p) is left as it is.
/// The largest nv solved on fixed-size matrices by solve_al_small.
constexpr int AL_FIXED_MAX = 6;

/// al_iterate's products (al_iteration.hpp) for the dense path: coefficient-based
/// (lazyProduct; small dynamic sizes, no BLAS-style kernels) on P's SmallLLT.
struct DenseAlOps {
  /// The mechanism (unused by the dense products; the band ones need it).
  const CoreModel &model;
  /// M, J and the factor of P (data.llt_p) of the last evaluation.
  CoreData &data;
  /// y += J x.
  void add_j(const Vec &x, Vec &y) { y.noalias() += data.J.lazyProduct(x); }
  /// y -= M x.
  void sub_m(const Vec &x, Vec &y) { y.noalias() -= data.M.lazyProduct(x); }
  /// x -= J^T y.
  void sub_jt(const Vec &y, Vec &x) { x.noalias() -= data.J.transpose().lazyProduct(y); }
  /// x -= s J^T y.
  void sub_scaled_jt(double s, const Vec &y, Vec &x) {
    x.noalias() -= s * data.J.transpose().lazyProduct(y);
  }
  /// x <- P^-1 x.
  void solve(Vec &x) { data.llt_p.solveInPlace(x); }
};

/// ... and for the band path (set_band): the products over the structural hulls, P's
/// band Cholesky in the order model.perm (O(nv) per iterate for a chain of loops).
struct BandAlOps {
  /// The structure (hulls, band order).
  const CoreModel &model;
  /// M, J, the band factor of P and the products' work vectors (al_wc, al_wv).
  CoreData &data;
  /// y += J x.
  void add_j(const Vec &x, Vec &y) {
    j_mul(model, data, x, data.al_wc);
    y += data.al_wc;
  }
  /// y -= M x.
  void sub_m(const Vec &x, Vec &y) { m_mul_sub(model, data, x, y); }
  /// x -= J^T y.
  void sub_jt(const Vec &y, Vec &x) {
    jt_mul(model, data, y, data.al_wv);
    x -= data.al_wv;
  }
  /// x -= s J^T y.
  void sub_scaled_jt(double s, const Vec &y, Vec &x) {
    jt_mul(model, data, y, data.al_wv);
    x -= s * data.al_wv;
  }
  /// x <- P^-1 x.
  void solve(Vec &x) { solve_penalized_band(model, data, x); }
};

// -- declarations ------------------------------------------------------------

/// Accelerations data.a and multipliers data.lam at (q, v) with generalized force tau.
void solve(const CoreModel &model, CoreData &data, const RefV &q, const RefV &v, const Vec &tau,
           double t);

/// The configured method's solve at the terms of the last evaluation (model.method; on the
/// tree path where model.tree_solves()).
void dispatch(const CoreModel &model, CoreData &data, const RefV &q, const Vec &tau, double t);

/// The configured method on the tree path (defined in core_tree.hpp).
void solve_tree(const CoreModel &model, CoreData &data, const RefV &q, const Vec &tau, double t);

/// Augmented Lagrangian at the acceleration level (closedchain/dynamics/
/// augmented_lagrangian.py, Bayo & Ledesma 1996): P = M + alpha J^T J with
/// alpha = rho tr(M) / tr(J^T J), lowered where P's Cholesky cannot take it
/// (al_factor); from lam_0 = 0,
///   a_1 = P^-1 (tau - h - alpha J^T gamma),  lam_1 = alpha (J a_1 + gamma),
///   a_{k+1} = a_k + P^-1 (tau - h - M a_k - J^T (lam_k + alpha (J a_k + gamma))),
///   lam_{k+1} = lam_k + alpha (J a_{k+1} + gamma),
/// until max |a_{k+1} - a_k| <= al_tol (1 + max |a_{k+1}|); then lam is polished by
/// the regularized normal equations J J^T dlam = J (tau - h - M a - J^T lam).
void solve_al(const CoreModel &model, CoreData &data, const RefV &q, const Vec &tau, double t);

/// solve_al on fixed-size matrices for (nv, nc) = (NV, NC) and up (see AL_FIXED_MAX);
/// false when (nv, nc) is not among the sizes compiled or the polish's factor fails.
template <int NV, int NC>
bool solve_al_small(const CoreModel &model, CoreData &data, const RefV &q, double t);

/// The next augmented-Lagrangian penalty after P = M + alpha J^T J showed `pivot`, its
/// smallest relative pivot (0: not positive definite): the small pivots scale as
/// 1 / alpha, so aim at AL_PENALTY_MARGIN AL_PIVOT_MIN, lowering by at most
/// AL_PENALTY_DROP (lowered_penalty of dynamics/augmented_lagrangian.py).
double al_lowered_penalty(double alpha, double pivot);

/// The augmented-Lagrangian penalty: alpha0 lowered by al_lowered_penalty while
/// factor(alpha), which factors the penalized matrix at alpha and returns its smallest
/// relative pivot (0 when the Cholesky failed), is below AL_PIVOT_MIN, at most
/// AL_MAX_PENALTY_LOWERINGS times (then penalized_singular). Returns the alpha the last
/// factor(alpha) accepted; lowerings: how many times it was lowered. The rule of al_factor
/// (P = M + alpha J^T J, dense or band), solve_al_small and the tree path's tree_penalize
/// (I / alpha + D).
template <class Factor>
double al_choose_penalty(const CoreModel &model, const RefV &q, double t, double alpha0,
                         Factor &&factor, int &lowerings);

/// P = M + alpha J^T J at the last evaluation, factored (dense SmallLLT of P's lower
/// triangle, or the band Cholesky) unless the factor of these data.M and data.J is kept
/// (data.P_factored); returns alpha. alpha starts at al_penalty tr(M) / tr(J^T J) and is
/// lowered (al_lowered_penalty, data.al_lowerings times) while the Cholesky fails or shows
/// a relative pivot below AL_PIVOT_MIN (constants.hpp; numpy's
/// PenalizedSolver.factor_relative); data.al_alpha keeps it while data.P_factored.
double al_factor(const CoreModel &model, CoreData &data, const RefV &q, double t);

/// Throw SingularError: P = M + alpha J^T J is not positive definite at the lowest alpha.
[[noreturn]] void penalized_singular(const CoreModel &model, const RefV &q, double alpha,
                                     double t);

/// The augmented-Lagrangian iteration (al_iterate) at the last evaluation: x and
/// data.lam with M x + J^T lam = rhs, J x + g = 0 (to al_tol), no multiplier polish;
/// from_x: start from x as given (al_iterate).
void al_solve(const CoreModel &model, CoreData &data, const RefV &q, double t, const Vec &rhs,
              const Vec &g, Vec &x, bool from_x = false);

/// Throw SingularError: `what` is singular at q (condition number cond > cond_max); hint
/// says what to do; t NaN outside a simulation.
[[noreturn]] void singular(const CoreModel &model, const RefV &q, const std::string &what,
                           double cond, const std::string &hint, double t);

/// singular() with `hint` (RANK_LOSS_HINT, MASS_HINT or KKT_HINT: why `what` can be
/// singular) unless the condition number 1 / rcond is at most cond_max.
void check_rcond(const CoreModel &model, const RefV &q, const std::string &what, double rcond,
                 const char *hint, double t);

/// The KKT method: [[M, J^T], [J, 0]] [a; lam] = [tau - h; -gamma] by LU (dense_lu.hpp);
/// singular where cond(D K D) > cond_max (D: kkt_equilibration), estimated on K's factors.
void solve_kkt(const CoreModel &model, CoreData &data, const RefV &q, const Vec &tau, double t);

/// The equilibration D = diag(d_v, d_c) of K into data.kkt_scale, D^-1 into
/// data.kkt_unscale (dynamics/kkt.py kkt_scaling): d_v = M_ii^-1/2, d_c = 1 / |row of
/// J D_v|, each floored at KKT_SCALE_FLOOR of the largest.
void kkt_equilibration(const CoreModel &model, CoreData &data);

/// The Schur complement: lam from (J M^-1 J^T) lam = J M^-1 (tau - h) + gamma, then
/// a = M^-1 (tau - h - J^T lam).
void solve_schur(const CoreModel &model, CoreData &data, const RefV &q, const Vec &tau, double t);

/// singular() naming J unless cond(J) = s_max / s_min is at most cond_max; s: J's singular
/// values, descending, shape (nc,) (the null-space method's check, dense and tree path).
void check_jacobian_rank(const CoreModel &model, const RefV &q, const Vec &s, double t);

/// The 2-norm condition number s_0 / s_(n-1) from singular values s, largest first, shape
/// (n,), n >= 1 (infinity where the smallest is 0).
double singular_value_cond(const Vec &s);

/// The null-space method: J = U S V^T; a = a_p + N z with a_p = -V_r S^-1 U^T gamma,
/// (N^T M N) z = N^T (tau - h - M a_p), lam from the range rows.
void solve_nullspace(const CoreModel &model, CoreData &data, const RefV &q, const Vec &tau,
                     double t);

/// The generalized force at (t, q, v) into data.tau.
const Vec &tau_at(const CoreModel &model, CoreData &data, double t, const RefV &q, const RefV &v);

/// The right-hand side of a simulation: data.a (and data.lam) at (t, q, v).
void accel(const CoreModel &model, CoreData &data, double t, const RefV &q, const RefV &v);

/// J_D: the columns dep of data.J into data.JD.
void gather_JD(const CoreModel &model, CoreData &data, const std::vector<int> &dep);

/// J_D (gather_JD of model.method_dependent) LU-factored into data.lu_jd, singular() where
/// cond_1(J_D) exceeds cond_max (the reduced method's check, dense and tree path).
void factor_method_JD(const CoreModel &model, CoreData &data, const RefV &q, double t);

/// Reduced coordinates (dynamics/reduced.py): a = S a_I + c with S = [I; -J_D^-1 J_I],
/// c = [0; -J_D^-1 gamma]; (S^T M S) a_I = S^T (tau - h - M c); lam = J_D^-T (tau - h - M a)_D.
void solve_reduced(const CoreModel &model, CoreData &data, const RefV &q, const Vec &tau, double t);

// -- definitions -------------------------------------------------------------

inline double al_lowered_penalty(double alpha, double pivot) {
  const double f = pivot / (AL_PENALTY_MARGIN * AL_PIVOT_MIN);
  return alpha * (f > AL_PENALTY_DROP ? f : AL_PENALTY_DROP);
}

template <class Factor>
inline double al_choose_penalty(const CoreModel &model, const RefV &q, double t, double alpha0,
                                Factor &&factor, int &lowerings) {
  double alpha = alpha0;
  for (lowerings = 0;; ++lowerings) {
    const double pivot = factor(alpha);
    if (pivot >= AL_PIVOT_MIN) return alpha;
    if (lowerings == AL_MAX_PENALTY_LOWERINGS) penalized_singular(model, q, alpha, t);
    alpha = al_lowered_penalty(alpha, pivot);
  }
}

inline void solve(const CoreModel &model, CoreData &data, const RefV &q, const RefV &v,
                  const Vec &tau, double t) {
  eval_terms(model, data, q, v);
  ++data.n_evals;
  dispatch(model, data, q, tau, t);
}

/// The method of the solves: data.method_override when set, else model.method.
inline Method active_method(const CoreModel &model, const CoreData &data) {
  return data.method_override >= 0 ? static_cast<Method>(data.method_override) : model.method;
}

inline void dispatch(const CoreModel &model, CoreData &data, const RefV &q, const Vec &tau,
                     double t) {
  if (model.tree_solves()) return solve_tree(model, data, q, tau, t);
  switch (active_method(model, data)) {
    case KKT:
      solve_kkt(model, data, q, tau, t);
      break;
    case SCHUR:
      solve_schur(model, data, q, tau, t);
      break;
    case NULLSPACE:
      solve_nullspace(model, data, q, tau, t);
      break;
    case AUGMENTED_LAGRANGIAN:
      solve_al(model, data, q, tau, t);
      break;
    case REDUCED:
      solve_reduced(model, data, q, tau, t);
      break;
  }
}

inline void solve_al(const CoreModel &model, CoreData &data, const RefV &q, const Vec &tau,
                     double t) {
  if (model.nc == 0) {
    data.llt_m.compute(data.M);
    if (data.llt_m.info() != Eigen::Success)
      singular(model, q, "the mass matrix M", std::numeric_limits<double>::infinity(),
               "it is not positive definite (a massless subtree)", t);
    data.a = tau - data.h;
    data.llt_m.solveInPlace(data.a);
    return;
  }
  data.rhs_v = tau - data.h;
  if (!model.banded_penalized && solve_al_small<1, 1>(model, data, q, t)) return;
  al_solve(model, data, q, t, data.rhs_v, data.gamma, data.a);
  if (model.banded_penalized) {  // the multiplier polish on the band normal equations
    data.tmp_v = data.rhs_v;
    m_mul_sub(model, data, data.a, data.tmp_v);
    jt_mul(model, data, data.lam, data.dq);
    data.tmp_v -= data.dq;  // r_d
    j_mul(model, data, data.tmp_v, data.tmp_c);
    if (model.banded_normal && factor_normal_band(model, data, AL_NORMAL_EQ_REG)) {
      data.normal_band.solve_in_place(data.tmp_c);
    } else {  // dense normal equations (no narrow row band, or the band factor failed)
      data.JJt.noalias() = data.J * data.J.transpose();
      data.JJt.diagonal().array() +=
          AL_NORMAL_EQ_REG * std::max(data.JJt.trace(), 1.0) / static_cast<double>(model.nc);
      data.llt_c.compute(data.JJt);
      data.llt_c.solveInPlace(data.tmp_c);
    }
    data.lam += data.tmp_c;
    return;
  }
  data.tmp_v = data.rhs_v;
  data.tmp_v.noalias() -= data.M.lazyProduct(data.a);
  data.tmp_v.noalias() -= data.J.transpose().lazyProduct(data.lam);  // r_d
  data.JJt.triangularView<Eigen::Lower>() = data.J.lazyProduct(data.J.transpose());
  data.JJt.diagonal().array() +=
      AL_NORMAL_EQ_REG * std::max(data.JJt.trace(), 1.0) / static_cast<double>(model.nc);
  data.llt_jj.compute(data.JJt);
  data.tmp_c.noalias() = data.J.lazyProduct(data.tmp_v);
  data.llt_jj.solveInPlace(data.tmp_c);
  data.lam += data.tmp_c;
}

template <int NV, int NC>
inline bool solve_al_small(const CoreModel &model, CoreData &data, const RefV &q, double t) {
  if constexpr (NV > AL_FIXED_MAX) {
    return false;
  } else {
    if (model.nv != NV || model.nc != NC) {
      if constexpr (NC < NV)
        return solve_al_small<NV, NC + 1>(model, data, q, t);
      else
        return solve_al_small<NV + 1, 1>(model, data, q, t);
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
    const Eigen::Map<const MatN> M(data.M.data());
    const Eigen::Map<const MatJ> J(data.J.data());
    const MatN JtJ = J.transpose() * J;
    FixedLDLT<NV> llt;
    int lowerings = 0;
    const double jj = std::max(J.squaredNorm(), std::numeric_limits<double>::min());
    const double alpha = al_choose_penalty(
        model, q, t, model.al_penalty * M.trace() / jj,
        [&](double penalty) {
          return llt.compute(M + penalty * JtJ) ? llt.min_pivot_ratio() : 0.0;
        },
        lowerings);
    Ops ops{M, J, llt};
    const VecN rhs = data.rhs_v;
    const VecC g = data.gamma;
    VecN x, delta;
    VecC lam, rc;
    al_iterate(ops, alpha, rhs, g, model.al_max_iter * (1 + lowerings), model.al_tol, x, lam,
               delta, rc);
    // the multiplier polish: J J^T dlam = J (rhs - M a - J^T lam), regularized
    const VecN rd = rhs - M * x - J.transpose() * lam;
    MatC JJt = J * J.transpose();
    JJt.diagonal().array() += AL_NORMAL_EQ_REG * std::max(JJt.trace(), 1.0) / double(NC);
    FixedLDLT<NC> llt_c;
    if (!llt_c.compute(JJt)) return false;  // the dynamic path decides
    VecC dlam = J * rd;
    llt_c.solveInPlace(dlam);
    lam += dlam;
    data.a = x;
    data.lam = lam;
    return true;
  }
}

inline double al_factor(const CoreModel &model, CoreData &data, const RefV &q, double t) {
  if (data.P_factored) return data.al_alpha;
  const double jj = model.banded_penalized ? j_squared_norm(model, data) : data.J.squaredNorm();
  const double alpha = al_choose_penalty(
      model, q, t,
      model.al_penalty * data.M.trace() / std::max(jj, std::numeric_limits<double>::min()),
      [&](double penalty) {
        if (model.banded_penalized)
          return factor_penalized_band(model, data, penalty)
                     ? data.penalized_band.min_pivot_ratio()
                     : 0.0;
        data.P.triangularView<Eigen::Lower>() = data.J.transpose().lazyProduct(data.J);
        data.P.triangularView<Eigen::Lower>() = penalty * data.P + data.M;
        return data.llt_p.compute(data.P) ? data.llt_p.min_pivot_ratio(data.P) : 0.0;
      },
      data.al_lowerings);
  data.P_factored = true;
  data.al_alpha = alpha;
  return alpha;
}

inline void penalized_singular(const CoreModel &model, const RefV &q, double alpha, double t) {
  singular(model, q, "the penalized mass matrix M + alpha J^T J",
           std::numeric_limits<double>::infinity(),
           "it is not numerically positive definite even at alpha = " + fmt("%.3g", alpha) +
               " (lowered " + std::to_string(AL_MAX_PENALTY_LOWERINGS) +
               " times), so M itself is singular (a massless subtree)",
           t);
}

inline void al_solve(const CoreModel &model, CoreData &data, const RefV &q, double t,
                     const Vec &rhs, const Vec &g, Vec &x, bool from_x) {
  const double alpha = al_factor(model, data, q, t);
  const int max_iter = model.al_max_iter * (1 + data.al_lowerings);
  if (model.banded_penalized) {
    BandAlOps ops{model, data};
    al_iterate(ops, alpha, rhs, g, max_iter, model.al_tol, x, data.lam, data.dq, data.tmp_c,
               from_x);
  } else {
    DenseAlOps ops{model, data};
    al_iterate(ops, alpha, rhs, g, max_iter, model.al_tol, x, data.lam, data.dq, data.tmp_c,
               from_x);
  }
}

inline void singular(const CoreModel &model, const RefV &q, const std::string &what, double cond,
                     const std::string &hint, double t) {
  std::string msg = model.name + ": " + what + " is singular at q = " + vec_str(q) +
                    " (condition number " + fmt("%.3e", cond) + " > cond_max " +
                    fmt("%.1e", model.cond_max) + "); " + hint;
  if (!std::isnan(t)) msg = "at t = " + fmt("%.9g", t) + " s: " + msg;
  throw SingularError{msg, cond, t, Vec(q)};
}

inline void check_rcond(const CoreModel &model, const RefV &q, const std::string &what,
                        double rcond, const char *hint, double t) {
  double cond =
      (rcond > 0 && std::isfinite(rcond)) ? 1.0 / rcond : std::numeric_limits<double>::infinity();
  if (!(cond <= model.cond_max))
    singular(model, q, what, cond, hint, t);
}

inline void kkt_equilibration(const CoreModel &model, CoreData &data) {
  const Eigen::Index nv = model.nv, nc = model.nc;
  double *d = data.kkt_scale.data(), *u = data.kkt_unscale.data();
  double top = 0.0;
  for (Eigen::Index i = 0; i < nv; ++i) top = std::max(top, data.M(i, i));
  for (Eigen::Index i = 0; i < nv; ++i) {
    u[i] = top > 0 ? std::sqrt(std::max(data.M(i, i), KKT_SCALE_FLOOR * top)) : 1.0;
    d[i] = 1.0 / u[i];
  }
  top = 0.0;
  for (Eigen::Index r = 0; r < nc; ++r) {
    double s = 0.0;
    for (Eigen::Index i = 0; i < nv; ++i) s += (data.J(r, i) * d[i]) * (data.J(r, i) * d[i]);
    u[nv + r] = std::sqrt(s);
    top = std::max(top, u[nv + r]);
  }
  for (Eigen::Index r = 0; r < nc; ++r) {
    u[nv + r] = top > 0 ? std::max(u[nv + r], KKT_SCALE_FLOOR * top) : 1.0;
    d[nv + r] = 1.0 / u[nv + r];
  }
}

inline void solve_kkt(const CoreModel &model, CoreData &data, const RefV &q, const Vec &tau,
                      double t) {
  // K = [[M, J^T], [J, 0]] column by column (written out: the block assignments cost
  // more than the copy at these sizes), factored in place by DenseLU (dense_lu.hpp) and
  // solved as it stands: equilibrating it first costs accuracy where J is nearly
  // singular (agile_eye, sigma_min(J) 1.6e-3: 8.4e-11 relative against 1.8e-14). Only the
  // decision "singular" uses the equilibration D (kkt_equilibration), so that it does not
  // depend on the mass unit: cond(D K D) = ||D K D||_1 ||D^-1 K^-1 D^-1||_1, the second
  // factor estimated with K's own factors (dynamics/kkt.py solve_kkt).
  const Eigen::Index nv = model.nv, nc = model.nc, n = nv + nc;
  kkt_equilibration(model, data);
  const double *d = data.kkt_scale.data();
  double *k = data.kkt.A.data();
  double scaled_norm = 0.0;  // ||D K D||_1, its largest column sum
  for (Eigen::Index j = 0; j < nv; ++j) {
    double *col = k + j * n;
    double s = 0.0;
    for (Eigen::Index i = 0; i < nv; ++i) {
      col[i] = data.M(i, j);
      s += d[i] * std::abs(col[i]);
    }
    for (Eigen::Index r = 0; r < nc; ++r) {
      col[nv + r] = data.J(r, j);
      s += d[nv + r] * std::abs(col[nv + r]);
    }
    scaled_norm = std::max(scaled_norm, s * d[j]);
  }
  for (Eigen::Index r = 0; r < nc; ++r) {
    double *col = k + (nv + r) * n;
    double s = 0.0;
    for (Eigen::Index i = 0; i < nv; ++i) {
      col[i] = data.J(r, i);
      s += d[i] * std::abs(col[i]);
    }
    for (Eigen::Index i = nv; i < n; ++i) col[i] = 0.0;
    scaled_norm = std::max(scaled_norm, s * d[nv + r]);
  }
  for (Eigen::Index i = 0; i < nv; ++i) data.kkt_solution[i] = tau[i] - data.h[i];
  for (Eigen::Index r = 0; r < nc; ++r) data.kkt_solution[nv + r] = -data.gamma[r];
  // An exactly singular K leaves a zero pivot: rcond 0 (as LAPACK's info > 0).
  // Away from singular configurations a cheap upper bound of ||D^-1 K^-1 D^-1||_1
  // already shows that the estimate (a lower bound of it) cannot exceed cond_max; only
  // otherwise is the estimate computed.
  const char *what = "the KKT matrix [[M, J^T], [J, 0]] (equilibrated)";
  const double *s = data.kkt_unscale.data();
  if (!data.kkt.factor_in_place()) {
    check_rcond(model, q, what, 0.0, KKT_HINT, t);
  } else if (!(scaled_norm * data.kkt.scaled_inverse_norm_bound(s) <= model.cond_max)) {
    check_rcond(model, q, what,
                DenseLU::reciprocal(scaled_norm, data.kkt.inverse_norm_estimate(s)), KKT_HINT, t);
  }
  data.kkt.solve(data.kkt_solution);
  data.a = data.kkt_solution.head(model.nv);
  data.lam = data.kkt_solution.tail(model.nc);
}

inline void solve_schur(const CoreModel &model, CoreData &data, const RefV &q, const Vec &tau,
                        double t) {
  data.llt_m.compute(data.M);
  check_rcond(model, q, "the mass matrix M",
              data.llt_m.info() == Eigen::Success ? data.llt_m.rcond() : 0.0, MASS_HINT, t);
  data.schur_solves.leftCols(model.nc) = data.J.transpose();
  data.schur_solves.col(model.nc) = tau - data.h;
  data.llt_m.solveInPlace(data.schur_solves);
  if (model.nc == 0) {
    data.a = data.schur_solves.col(0);
    return;
  }
  data.delassus.noalias() = data.J * data.schur_solves.leftCols(model.nc);
  data.tmp_c.noalias() = data.J * data.schur_solves.col(model.nc);
  data.tmp_c += data.gamma;
  data.llt_c.compute(data.delassus);
  check_rcond(model, q, "the Delassus matrix J M^-1 J^T",
              data.llt_c.info() == Eigen::Success ? data.llt_c.rcond() : 0.0, RANK_LOSS_HINT, t);
  data.lam = data.tmp_c;
  data.llt_c.solveInPlace(data.lam);
  data.a = data.schur_solves.col(model.nc);
  data.a.noalias() -= data.schur_solves.leftCols(model.nc) * data.lam;
}

inline double singular_value_cond(const Vec &s) {
  const Eigen::Index n = s.size();
  return s[n - 1] > 0 ? s[0] / s[n - 1] : std::numeric_limits<double>::infinity();
}

inline void check_jacobian_rank(const CoreModel &model, const RefV &q, const Vec &s, double t) {
  const double cond = singular_value_cond(s);
  if (!(cond <= model.cond_max))
    singular(model, q, "the constraint Jacobian J", cond,
             "it has lost rank: a singular configuration", t);
}

inline void solve_nullspace(const CoreModel &model, CoreData &data, const RefV &q, const Vec &tau,
                            double t) {
  const int nr = model.nv - model.nc;
  if (model.nc == 0) {
    data.llt_m.compute(data.M);
    data.a = data.llt_m.solve(tau - data.h);
    return;
  }
  data.svd.compute(data.J, Eigen::ComputeFullU | Eigen::ComputeFullV);
  const Vec &s = data.svd.singularValues();
  check_jacobian_rank(model, q, s, t);
  const Mat &U = data.svd.matrixU();
  const Mat &V = data.svd.matrixV();
  // a_p = -V_r S^-1 U^T gamma
  data.tmp_c.noalias() = U.transpose() * data.gamma;
  data.tmp_c.array() /= s.head(model.nc).array();
  data.a.noalias() = -(V.leftCols(model.nc) * data.tmp_c);
  if (nr > 0) {
    auto N = V.rightCols(nr);
    data.reduced_mass.noalias() = N.transpose() * data.M * N;
    data.llt_r.compute(data.reduced_mass);
    check_rcond(model, q, "the reduced mass matrix N^T M N",
                data.llt_r.info() == Eigen::Success ? data.llt_r.rcond() : 0.0, MASS_HINT, t);
    data.tmp_v = tau - data.h;
    data.tmp_v.noalias() -= data.M * data.a;
    data.nullspace_a.noalias() = N.transpose() * data.tmp_v;
    data.llt_r.solveInPlace(data.nullspace_a);
    data.a.noalias() += N * data.nullspace_a;
  }
  data.tmp_v = tau - data.h;
  data.tmp_v.noalias() -= data.M * data.a;
  data.tmp_c.noalias() = V.leftCols(model.nc).transpose() * data.tmp_v;
  data.tmp_c.array() /= s.head(model.nc).array();
  data.lam.noalias() = U * data.tmp_c;
}

inline const Vec &tau_at(const CoreModel &model, CoreData &data, double t, const RefV &q,
                         const RefV &v) {
  if (model.tau_mode == 0) return data.zero_v;
  if (model.tau_mode == 1) return model.tau_constant;
  GilHeld gil;  // a Python tau(t, q, v), called from a loop that released the GIL
  bp::object r = model.np_asarray(model.tau_function(t, to_numpy(q), to_numpy(v)), "float64");
  bp::extract<Vec> ex(r);
  bool ok = bp::len(r.attr("shape")) == 1 && ex.check();
  if (ok) {
    data.tau = ex();
    ok = data.tau.size() == model.nv && data.tau.allFinite();
  }
  if (!ok) {
    std::string rep = bp::extract<std::string>(bp::str(r));
    throw SimulationFailure{"tau(t, q, v) returned " + rep + " at t = " + fmt("%.6g", t) +
                                " s; expected finite shape (" + std::to_string(model.nv) + ",)",
                            t};
  }
  return data.tau;
}

inline void accel(const CoreModel &model, CoreData &data, double t, const RefV &q, const RefV &v) {
  const Vec &tau = tau_at(model, data, t, q, v);
  solve(model, data, q, v, tau, t);
  if (!data.a.allFinite())
    // simulate.problem.nonfinite_message
    throw SimulationFailure{
        model.name + ": non-finite acceleration at t = " + fmt("%.9g", t) + " s (max |q| = " +
            fmt("%.3e", q.size() ? q.cwiseAbs().maxCoeff() : 0.0) + ", max |v| = " +
            fmt("%.3e", v.size() ? v.cwiseAbs().maxCoeff() : 0.0) + "): " + NONFINITE_HINT,
        t};
}

inline void gather_JD(const CoreModel &model, CoreData &data, const std::vector<int> &dep) {
  for (int c = 0; c < model.nc; ++c) data.JD.col(c) = data.J.col(dep[c]);
}

inline void factor_method_JD(const CoreModel &model, CoreData &data, const RefV &q, double t) {
  gather_JD(model, data, model.method_dependent);
  const double rcond = data.lu_jd.factor(data.JD) ? data.lu_jd.rcond() : 0.0;
  const double cond = rcond > 0.0 ? 1.0 / rcond : std::numeric_limits<double>::infinity();
  if (!(cond <= model.cond_max))
    singular(model, q, model.method_jd_label, cond,
             "this partition cannot describe the motion here (its block J_D is singular): "
             "re-partition with choose_partition(mech, q), or the configuration is a "
             "singularity of the mechanism",
             t);
}

inline void solve_reduced(const CoreModel &model, CoreData &data, const RefV &q, const Vec &tau,
                          double t) {
  const int m = model.nv - model.nc;
  data.reduced_force = tau - data.h;
  if (model.nc) {
    factor_method_JD(model, data, q, t);
    for (int k = 0; k < m; ++k) {
      data.tmp_c = data.J.col(model.method_independent[k]);
      data.lu_jd.solve(data.tmp_c);
      for (int i = 0; i < model.nc; ++i)
        data.reduced_basis(model.method_dependent[i], k) = -data.tmp_c[i];
    }
    data.tmp_c = data.gamma;
    data.lu_jd.solve(data.tmp_c);
    for (int i = 0; i < model.nc; ++i)
      data.reduced_offset[model.method_dependent[i]] = -data.tmp_c[i];
    data.reduced_force.noalias() -= data.M * data.reduced_offset;
  }
  if (m) {
    data.mass_reduced_basis.noalias() = data.M * data.reduced_basis;
    data.reduced_mass.noalias() = data.reduced_basis.transpose() * data.mass_reduced_basis;
    data.llt_r.compute(data.reduced_mass);
    check_rcond(model, q, "the reduced mass matrix S^T M S",
                data.llt_r.info() == Eigen::Success ? data.llt_r.rcond() : 0.0, MASS_HINT, t);
    data.independent_a.noalias() = data.reduced_basis.transpose() * data.reduced_force;
    data.llt_r.solveInPlace(data.independent_a);
    data.a.noalias() = data.reduced_basis * data.independent_a;
    data.a += data.reduced_offset;
    if (!model.nc) return;
    data.reduced_force.noalias() -= data.mass_reduced_basis * data.independent_a;
  } else {
    data.a = data.reduced_offset;
  }
  for (int i = 0; i < model.nc; ++i) data.tmp_c[i] = data.reduced_force[model.method_dependent[i]];
  data.lu_jd.solve_transposed(data.tmp_c);
  data.lam = data.tmp_c;
}

}  // namespace closedchain
