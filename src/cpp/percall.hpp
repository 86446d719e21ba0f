// closedchain._core: the per-call entry points of the public API (closedchain._percall):
// forward dynamics, the rows phi / J / gamma, the velocity projection, the assembly and the
// inverse dynamics of one state, each checking its arguments in C++ (arg_checks.hpp: the
// messages of the numpy path) and returning fresh arrays. Free functions over a Core's
// model and data (core_all.hpp), bound as its methods by expose-core.cpp.

#pragma once

#include <Eigen/Eigenvalues>
#include <Eigen/SVD>

#include <algorithm>
#include <cmath>
#include <limits>
#include <string>
#include <utility>
#include <vector>

#include "arg_checks.hpp"
#include "closure_newton.hpp"
#include "core_all.hpp"

namespace closedchain {

/// Largest |x_i|, 0 for an empty x.
inline double max_abs(const Vec &x) { return x.size() ? x.cwiseAbs().maxCoeff() : 0.0; }

/// (a, lam, J, gamma) at (q, v) with generalized force tau (None: zero), one whole
/// evaluation of the configured method; NonFinite when a or lam overflowed (the message
/// of closedchain.forward_dynamics).
inline bp::tuple forward_checked(Core &core, bp::object q, bp::object v, bp::object tau) {
  const CoreModel &model = core.model();
  CoreData &data = core.data();
  const ConfigurationArg qa(q, model.tree);
  const VectorArg va(v, "v", model.nv);
  Vec t = Vec::Zero(model.nv);
  if (!tau.is_none()) t = VectorArg(tau, "tau", model.nv).map();
  invalidate_kinematics(data);  // one whole evaluation per call
  solve(model, data, qa.map(), va.map(), t, std::numeric_limits<double>::quiet_NaN());
  const Vec &a = data.a, &lam = data.lam;
  if (!(a.allFinite() && lam.allFinite())) {
    const bp::object msg =
        bp::str("{}: method {!r} overflowed to non-finite accelerations or multipliers at "
                "max|v| = {:.3g}, max|tau| = {:.3g}: v and tau must be small enough for "
                "M a + h (quadratic in v) to stay finite in double precision")
            .attr("format")(model.name, model.method_name, max_abs(va.map()), max_abs(t));
    throw NonFinite{bp::extract<std::string>(msg)};
  }
  return bp::make_tuple(Vec(a), Vec(lam), Mat(data.J), Vec(data.gamma));
}

/// phi(q) of the core's rows, shape (nc,).
inline Vec phi_checked(Core &core, bp::object q) {
  const CoreModel &model = core.model();
  CoreData &data = core.data();
  const ConfigurationArg qa(q, model.tree);
  invalidate_kinematics(data);
  eval_phi(model, data, qa.map());
  return data.phi;
}

/// J(q) of the core's rows, shape (nc, nv).
inline Mat jacobian_checked(Core &core, bp::object q) {
  const CoreModel &model = core.model();
  CoreData &data = core.data();
  const ConfigurationArg qa(q, model.tree);
  invalidate_kinematics(data);
  eval_phi_J(model, data, qa.map());
  return data.J;
}

/// gamma(q, v) = Jdot v of the core's rows, shape (nc,) (Baumgarte terms when configured).
inline Vec gamma_checked(Core &core, bp::object q, bp::object v) {
  const CoreModel &model = core.model();
  CoreData &data = core.data();
  const ConfigurationArg qa(q, model.tree);
  const VectorArg va(v, "v", model.nv);
  invalidate_kinematics(data);
  eval_terms(model, data, qa.map(), va.map());
  return data.gamma;
}

/// The projection of closedchain.project_velocity on the core's rows J(q): v with its
/// ``free`` entries corrected by the least-squares minimum-norm solution of
/// J_free dv = J v (singular values at most rcond sigma_max(J_free) dropped, as
/// numpy.linalg.lstsq). Returns (v, max |J v|, argmax row, sigma_max(J)).
inline bp::tuple project_checked(Core &core, bp::object q, bp::object v,
                                 const Eigen::VectorXi &free, double rcond) {
  const CoreModel &model = core.model();
  CoreData &data = core.data();
  const ConfigurationArg qa(q, model.tree);
  const VectorArg va(v, "v", model.nv);
  invalidate_kinematics(data);
  eval_phi_J(model, data, qa.map());
  const Mat &J = data.J;
  Vec out = va.map();
  const Eigen::Index nc = J.rows();
  if (nc == 0) return bp::make_tuple(out, 0.0, 0, 0.0);
  Mat Jf(nc, free.size());
  for (Eigen::Index k = 0; k < free.size(); ++k) Jf.col(k) = J.col(free[k]);
  if (free.size()) {
    Eigen::JacobiSVD<Mat> svd(Jf, Eigen::ComputeThinU | Eigen::ComputeThinV);
    svd.setThreshold(rcond);
    const Vec dv = svd.solve(J * out);
    for (Eigen::Index k = 0; k < free.size(); ++k) out[free[k]] -= dv[k];
  }
  const Vec Jv = (J * out).cwiseAbs();
  Eigen::Index row = 0;
  const double residual = Jv.maxCoeff(&row);
  const double sigma_max = Eigen::JacobiSVD<Mat>(J).singularValues()(0);
  return bp::make_tuple(out, residual, static_cast<int>(row), sigma_max);
}

/// closedchain.assemble on the core's rows (a core of every declared row, compiled.declared_core):
/// Gauss-Newton from q_guess moving the velocity coordinates `free` (closure_newton with the
/// fields of AssemblySettings), then the loops' alignment checks (misaligned_loops). Returns
/// the configuration, shape (nq,), where max |phi| <= tol was reached on an aligned closure;
/// None where Gauss-Newton stopped above tol or on a spurious closure: the caller then runs
/// closure.assemble_closure, whose least-squares solve and messages take over.
inline bp::object assemble_checked(Core &core, bp::object q_guess, const Eigen::VectorXi &free,
                                   double tol, int max_iter, int max_halvings,
                                   double fallback_rcond, double contraction) {
  const CoreModel &model = core.model();
  CoreData &data = core.data();
  const ConfigurationArg qa(q_guess, model.tree, "q_guess");
  Vec q = qa.map();
  invalidate_kinematics(data);
  const ClosureNewtonSettings settings{tol, max_iter, max_halvings, fallback_rcond, contraction};
  if (!closure_newton(model, data, q, free, settings) || !misaligned_loops(model, data, q).empty())
    return bp::object();
  return to_numpy(q);
}

/// Outcome codes of inverse_checked (closedchain.inverse reads them).
enum InverseStatus {
  INVERSE_OK = 0,
  INVERSE_JF_SINGULAR = 1,  // cond(J_F) > cond_max
  INVERSE_NON_FINITE = 2,  // M a + h - tau_passive overflowed
  INVERSE_J_SINGULAR = 3,  // cond(J) > cond_max
  INVERSE_ACTUATION_SINGULAR = 4,  // cond(N^T B) > cond_max
};

/// Condition number 1 / rcond of an LU factorization (Eigen's 1-norm estimate, as
/// LAPACK's dgecon), inf when it is singular.
inline double lu_cond(const Eigen::PartialPivLU<Mat> &lu) {
  const double rc = lu.rcond();
  return rc > 0.0 ? 1.0 / rc : std::numeric_limits<double>::infinity();
}

/// The torques of more actuated coordinates A (n_A) than degrees of freedom (mobility =
/// nv - nc), closedchain/inverse.py's equations: with the full SVD J = U S V^T (cond(J) =
/// s_0 / s_(nc-1) checked), N = V's last nv - nc columns and G = N^T B (mobility x n_A, the
/// rows A of N), tau_A is G's minimum-norm solution of G tau_A = N^T b (cond(G) = 1 /
/// sigma_min(G), the actuators' reach relative to the ideal 1, checked) plus, where J has weak
/// directions W (right singular vectors with s_i < weak_rcond s_0), the spare torques Z y
/// (Z: G's null space) with y the minimum-norm least-squares solution of W^T B Z y =
/// W^T (b - B tau_A), singular values at most weak_rcond dropped (_balance_weak_directions);
/// lam = U S^-1 V_r^T (tau - b). Fills tau (at A) and lam; returns (status, the failed
/// matrix's condition number).
inline std::pair<InverseStatus, double> redundant_torques(
    const Mat &J, const Vec &b, const Eigen::Ref<const Eigen::VectorXi> &A, double cond_max,
    double weak_rcond, Vec &tau, Vec &lam) {
  const Eigen::Index nc = J.rows(), nv = J.cols(), mob = nv - nc, n_A = A.size();
  const double inf = std::numeric_limits<double>::infinity();
  Mat N = Mat::Identity(nv, nv);
  Eigen::JacobiSVD<Mat> svd;
  if (nc) {
    svd.compute(J, Eigen::ComputeFullU | Eigen::ComputeFullV);
    const double cond = singular_value_cond(svd.singularValues());
    if (cond > cond_max) return {INVERSE_J_SINGULAR, cond};
    N = svd.matrixV().rightCols(mob);
  }
  Mat G(mob, n_A);
  for (Eigen::Index k = 0; k < n_A; ++k) G.col(k) = N.row(A[k]).transpose();
  const Eigen::JacobiSVD<Mat> svd_g(G, Eigen::ComputeFullU | Eigen::ComputeFullV);
  const Vec &sg = svd_g.singularValues();
  const double cond_g = sg[mob - 1] > 0.0 ? 1.0 / sg[mob - 1] : inf;
  if (cond_g > cond_max) return {INVERSE_ACTUATION_SINGULAR, cond_g};
  const Mat &Vg = svd_g.matrixV();
  Vec tau_A = Vg.leftCols(mob) *
              ((svd_g.matrixU().transpose() * (N.transpose() * b)).array() / sg.array()).matrix();
  if (nc) {
    const Vec &s = svd.singularValues();
    std::vector<Eigen::Index> weak;
    for (Eigen::Index i = 0; i < nc; ++i)
      if (s[i] < weak_rcond * s[0]) weak.push_back(i);
    if (!weak.empty()) {
      const auto Z = Vg.rightCols(n_A - mob);
      Mat W(weak.size(), nv), WA(weak.size(), n_A);
      for (std::size_t r = 0; r < weak.size(); ++r) W.row(r) = svd.matrixV().col(weak[r]);
      for (Eigen::Index k = 0; k < n_A; ++k) WA.col(k) = W.col(A[k]);
      const Eigen::JacobiSVD<Mat> svd_c(WA * Z, Eigen::ComputeThinU | Eigen::ComputeThinV);
      const Vec &sc = svd_c.singularValues();
      Eigen::Index k = 0;
      while (k < sc.size() && sc[k] > weak_rcond) ++k;
      const Vec r = W * b - WA * tau_A;
      const Vec y = svd_c.matrixV().leftCols(k) *
                    ((svd_c.matrixU().leftCols(k).transpose() * r).array() / sc.head(k).array())
                        .matrix();
      tau_A += Z * y;
    }
  }
  for (Eigen::Index k = 0; k < n_A; ++k) tau[A[k]] = tau_A[k];
  if (nc) {
    const Vec &s = svd.singularValues();
    const Vec f = tau - b;
    lam = svd.matrixU() *
          ((svd.matrixV().leftCols(nc).transpose() * f).array() / s.array()).matrix();
  }
  return {INVERSE_OK, 1.0};
}

/// Closed-chain inverse dynamics (closedchain/inverse.py's equations) with as many
/// actuated coordinates A as degrees of freedom, on the core's rows:
///   J_F a_F = -gamma - J_P a_P,   b = M a + h - tau_passive,
///   J_Abar^T lam = -b_Abar,   tau_A = b_A + J_A^T lam
/// (the rows of [B -J^T] [tau_A; lam] = b off and on A; Abar, the other coordinates,
/// has nc entries). The actuation's condition number is that of the numpy path,
/// 1 / sigma_min(N^T B) = sqrt(1 + ||J_Abar^-1 J_A||_2^2) for an orthonormal null-space
/// basis N of J. With more actuated coordinates than degrees of freedom the torques are
/// redundant_torques'. `indices` holds P, F, A and Abar one after the other (sizes mobility,
/// nc, n_A, nv - n_A; mobility = a_P's size). Returns (status, cond, a, tau, lam, J,
/// gamma, max |M a + h + J^T lam - tau|, max |J a + gamma|); with status != INVERSE_OK,
/// cond is the failed matrix's condition number and the arrays are not meaningful.
inline bp::tuple inverse_checked(Core &core, bp::object q, bp::object v, const Vec &a_P,
                                 const Eigen::VectorXi &indices, int n_A, bp::object tau_passive,
                                 double cond_max, double weak_rcond) {
  const CoreModel &model = core.model();
  CoreData &data = core.data();
  auto fail = [&](InverseStatus status, double cond) {
    return bp::make_tuple(static_cast<int>(status), cond, bp::object(), bp::object(),
                          bp::object(), bp::object(), bp::object(), 0.0, 0.0);
  };
  // A non-finite a_P is reported first, as on numpy (closedchain.inverse then names it).
  if (!a_P.allFinite()) return fail(INVERSE_NON_FINITE, 0.0);
  const ConfigurationArg qa(q, model.tree);
  const VectorArg va(v, "v", model.nv);
  const int nv = model.nv;
  const Eigen::Index n_P = a_P.size(), n_F = nv - n_P;
  if (n_P > nv || n_A < n_P || n_A > nv || indices.size() != 2 * nv)
    throw BadArgument{"indices: expected P, F, A, Abar (" + std::to_string(2 * nv) +
                      " entries, n_A in [mobility, nv]), got " + std::to_string(indices.size())};
  const auto P = indices.segment(0, n_P), F = indices.segment(n_P, n_F),
             A = indices.segment(nv, n_A), Abar = indices.segment(nv + n_A, nv - n_A);
  invalidate_kinematics(data);
  eval_terms(model, data, qa.map(), va.map());
  const Mat &M = mass_at_J(model, data), &J = data.J;
  const Vec &h = data.h, &gamma = data.gamma;
  const Eigen::Index nc = J.rows();
  Vec a = Vec::Zero(nv);
  for (Eigen::Index i = 0; i < P.size(); ++i) a[P[i]] = a_P[i];
  if (nc) {
    Mat JF(nc, F.size());
    for (Eigen::Index k = 0; k < F.size(); ++k) JF.col(k) = J.col(F[k]);
    const Eigen::PartialPivLU<Mat> lu(JF);
    const double cond = lu_cond(lu);
    if (cond > cond_max) return fail(INVERSE_JF_SINGULAR, cond);
    Vec rhs = -gamma;
    for (Eigen::Index i = 0; i < P.size(); ++i) rhs -= J.col(P[i]) * a_P[i];
    const Vec aF = lu.solve(rhs);
    for (Eigen::Index k = 0; k < F.size(); ++k) a[F[k]] = aF[k];
  }
  Vec b = M * a + h;
  if (!tau_passive.is_none()) b -= VectorArg(tau_passive, "tau_passive", nv).map();
  if (!b.allFinite()) return fail(INVERSE_NON_FINITE, 0.0);
  Vec lam = Vec::Zero(nc), tau = Vec::Zero(nv);
  if (n_A > n_P) {
    const auto [status, cond] = redundant_torques(J, b, A, cond_max, weak_rcond, tau, lam);
    if (status != INVERSE_OK) return fail(status, cond);
  } else if (nc) {
    const double cond = singular_value_cond(Eigen::JacobiSVD<Mat>(J).singularValues());
    if (cond > cond_max) return fail(INVERSE_J_SINGULAR, cond);
    Mat JA(nc, A.size()), JAbar(nc, Abar.size());
    for (Eigen::Index k = 0; k < A.size(); ++k) JA.col(k) = J.col(A[k]);
    for (Eigen::Index k = 0; k < Abar.size(); ++k) JAbar.col(k) = J.col(Abar[k]);
    const Eigen::PartialPivLU<Mat> lu(JAbar);
    const Mat K = lu.solve(JA);
    double cond_g = std::numeric_limits<double>::infinity();
    if (std::isfinite(lu_cond(lu)) && K.allFinite()) {
      // ||K||_2^2, the largest eigenvalue of the nc x nc K K^T (relatively accurate for
      // the largest singular value, which is all the bound needs).
      const Mat KKt = K * K.transpose();
      double k2 = K.size() ? Eigen::SelfAdjointEigenSolver<Mat>(KKt, Eigen::EigenvaluesOnly)
                                 .eigenvalues()
                                 .maxCoeff()
                           : 0.0;
      if (!(k2 >= 0.0)) k2 = std::numeric_limits<double>::infinity();  // NaN: overflowed
      cond_g = std::sqrt(1.0 + k2);
    }
    if (cond_g > cond_max) return fail(INVERSE_ACTUATION_SINGULAR, cond_g);
    Vec b_bar(Abar.size());
    for (Eigen::Index k = 0; k < Abar.size(); ++k) b_bar[k] = -b[Abar[k]];
    lam = lu.transpose().solve(b_bar);
  }
  const Vec JtLam = J.transpose() * lam;
  if (n_A == n_P)
    for (Eigen::Index k = 0; k < A.size(); ++k) tau[A[k]] = b[A[k]] + JtLam[A[k]];
  const double dyn = max_abs(b + JtLam - tau);
  const double con = max_abs(J * a + gamma);
  return bp::make_tuple(static_cast<int>(INVERSE_OK), 1.0, a, tau, lam, Mat(J), Vec(gamma), dyn,
                        con);
}

}  // namespace closedchain
