// closedchain._core: the assembly's Gauss-Newton onto phi(q) = 0 moving a set of free velocity
// coordinates, the algorithm of closedchain/closure/assembly.py (_newton) on the core's rows:
//
//   dv_F = -J_F(q_k)^+ phi(q_k),   q_{k+1} = q_k (+) alpha dv   (pinocchio::integrate),
//
// with J_F the free columns of J and + the minimum-norm least-squares solution of
// numpy.linalg.lstsq (singular values at most rcond times the largest dropped). Its step,
// trial point and acceptance test serve the dependent solve of coordinate partitioning too
// (core_partitioning.hpp's newton_dependent).
// (Functions over (CoreModel, CoreData): their declarations, then their definitions.)

#pragma once

#include <pinocchio/algorithm/joint-configuration.hpp>

#include <Eigen/SVD>

#include <algorithm>
#include <cmath>
#include <limits>
#include <string>
#include <vector>

#include "core_data.hpp"
#include "core_model.hpp"
#include "core_rows.hpp"
#include "errors.hpp"

namespace closedchain {

// -- declarations ------------------------------------------------------------

/// The settings of closure_newton: the fields of closedchain.closure.AssemblySettings that
/// Gauss-Newton reads.
struct ClosureNewtonSettings {
  /// Convergence threshold on max |phi| [m or -].
  double tol;
  /// Gauss-Newton iterations.
  int max_iter;
  /// Step halvings of the line search per candidate step.
  int max_halvings;
  /// Relative singular-value cut-off of the second candidate step.
  double fallback_rcond;
  /// The full step is taken alone when it multiplies |phi|^2 by at most this.
  double contraction;
};

/// The best trial point of one Gauss-Newton iteration's line searches so far.
struct TrialBest {
  /// Whether a trial point was accepted.
  bool have = false;
  /// Its sum of squares |phi|^2 and max |phi|.
  double sq = 0.0, res = 0.0;
};

/// step = -A^+ phi from the SVD of A (thin or full U and V): the minimum-norm least-squares
/// Gauss-Newton step with the singular values at most rcond times the largest dropped
/// (numpy.linalg.lstsq's rule; a zero A gives a zero step).
void gauss_newton_svd_step(const Eigen::JacobiSVD<Mat> &svd, const Vec &phi, double rcond,
                           Vec &step);

/// q_try = q (+) dq (pinocchio::integrate; q + dq where every joint is revolute or
/// prismatic, the same numbers).
void integrate_trial(const CoreModel &model, const Vec &q, const Vec &dq, Vec &q_try);

/// Gauss-Newton's test of a line-search trial point q_try whose residuals are data.phi: it
/// ends the search when it lowers |phi|^2 below sq or meets max |phi| <= tol (returns true),
/// and then becomes the best (best; q_best, phi_best) when lower than the best so far.
bool accept_trial(const CoreData &data, const Vec &q_try, double sq, double tol, TrialBest &best,
                  Vec &q_best, Vec &phi_best);

/// Size data.closure_newton for the free velocity indices `free` (each in 0..nv-1, else
/// BadArgument): J_F's shape and the held configuration entries. Allocates only when `free`
/// differs from the last call's.
void closure_newton_resize(const CoreModel &model, CoreData &data, const Eigen::VectorXi &free);

/// max |x_i| with numpy's NaN: NaN when x holds one (never accepted, never converged), 0
/// for an empty x.
double max_abs_nan(const Vec &x);

/// The Gauss-Newton step into data.closure_newton.step, -J_F^+ phi (gauss_newton_svd_step)
/// from data.closure_newton.svd, J_F's SVD that closure_newton computes once per iteration
/// for both candidate steps (through the QR factor of its longer side, Eigen's JacobiSVD
/// preconditioner: an nc x nc SVD for nc rows of many columns).
void closure_newton_step(CoreData &data, double rcond);

/// The backtracking line search of one candidate step from q, whose residual has sum of
/// squares sq: alpha = 1, 1/2, ... (settings.max_halvings tries) until accept_trial
/// (best; data.closure_newton.q_best, phi_best). The held configuration entries are kept
/// exact.
void closure_newton_line_search(const CoreModel &model, CoreData &data, const Vec &q, double sq,
                                const ClosureNewtonSettings &settings, TrialBest &best);

/// Gauss-Newton onto phi(q) = 0 from q moving the velocity coordinates `free` only
/// (closure/assembly.py's _newton): per iteration the full minimum-norm step (rcond
/// eps max(nc, n_free), numpy's default) and, unless its line search ends at a sum of
/// squares at most settings.contraction times the current one (or meets tol), the step
/// without J_F's directions below settings.fallback_rcond of its largest singular value;
/// the candidate whose line search ends lower is taken. Stops when max |phi| <= tol, after
/// settings.max_iter iterations, or when neither candidate lowers the residual. Every trial
/// point is evaluated with its J (eval_phi_J): the accepted one's J serves the next
/// iteration from the memo. Returns whether max |phi| <= settings.tol; q holds the last
/// iterate either way.
bool closure_newton(const CoreModel &model, CoreData &data, Vec &q, const Eigen::VectorXi &free,
                    const ClosureNewtonSettings &settings);

// -- definitions -------------------------------------------------------------

inline void gauss_newton_svd_step(const Eigen::JacobiSVD<Mat> &svd, const Vec &phi, double rcond,
                                  Vec &step) {
  const Vec &sv = svd.singularValues();
  step.setZero();
  for (Eigen::Index i = 0; i < sv.size(); ++i)
    if (sv[i] > rcond * sv[0])
      step.noalias() -= (svd.matrixU().col(i).dot(phi) / sv[i]) * svd.matrixV().col(i);
}

inline void integrate_trial(const CoreModel &model, const Vec &q, const Vec &dq, Vec &q_try) {
  if (model.vector_space)
    q_try = q + dq;  // pinocchio::integrate on revolute/prismatic joints: q + dq
  else
    pinocchio::integrate(model.tree, q, dq, q_try);
}

inline bool accept_trial(const CoreData &data, const Vec &q_try, double sq, double tol,
                         TrialBest &best, Vec &q_best, Vec &phi_best) {
  const double res = max_abs_nan(data.phi), sq_try = data.phi.squaredNorm();
  if (!(sq_try < sq || res <= tol)) return false;
  if (!best.have || sq_try < best.sq) {
    best = {true, sq_try, res};
    q_best = q_try;
    phi_best = data.phi;
  }
  return true;
}

inline void closure_newton_resize(const CoreModel &model, CoreData &data,
                                  const Eigen::VectorXi &free) {
  ClosureNewtonData &w = data.closure_newton;
  const Eigen::Index nf = free.size();
  bool same = static_cast<Eigen::Index>(w.free.size()) == nf && w.phi.size() == model.nc;
  for (Eigen::Index k = 0; same && k < nf; ++k) same = w.free[k] == free[k];
  if (same) return;
  std::vector<char> moving(static_cast<std::size_t>(model.nv), 0);
  for (Eigen::Index k = 0; k < nf; ++k) {
    if (free[k] < 0 || free[k] >= model.nv)
      throw BadArgument{"free: velocity index " + std::to_string(free[k]) + " out of range 0.." +
                        std::to_string(model.nv - 1)};
    moving[static_cast<std::size_t>(free[k])] = 1;
  }
  w.free.assign(free.data(), free.data() + nf);
  w.held_q.clear();
  const Model &tree = model.tree;
  for (std::size_t j = 1; j < static_cast<std::size_t>(tree.njoints); ++j) {
    bool moves = false;
    for (int c = 0; c < tree.nvs[j]; ++c) moves |= moving[tree.idx_vs[j] + c] != 0;
    if (!moves)
      for (int c = 0; c < tree.nqs[j]; ++c) w.held_q.push_back(tree.idx_qs[j] + c);
  }
  w.q_held = Vec::Zero(static_cast<Eigen::Index>(w.held_q.size()));
  w.J_free = Mat::Zero(model.nc, nf);
  if (nf > 0)
    w.svd = Eigen::JacobiSVD<Mat>(model.nc, nf, Eigen::ComputeThinU | Eigen::ComputeThinV);
  w.step = Vec::Zero(nf);
  w.dv = Vec::Zero(model.nv);
  w.dq = Vec::Zero(model.nv);
  w.phi = Vec::Zero(model.nc);
  w.phi_best = Vec::Zero(model.nc);
  w.q_try = Vec::Zero(model.nq);
  w.q_best = Vec::Zero(model.nq);
}

inline double max_abs_nan(const Vec &x) {
  if (x.hasNaN()) return std::numeric_limits<double>::quiet_NaN();
  return x.size() ? x.cwiseAbs().maxCoeff() : 0.0;
}

inline void closure_newton_step(CoreData &data, double rcond) {
  ClosureNewtonData &w = data.closure_newton;
  if (w.step.size() == 0) return;  // nothing free: the line search finds no descent
  gauss_newton_svd_step(w.svd, w.phi, rcond, w.step);
}

inline void closure_newton_line_search(const CoreModel &model, CoreData &data, const Vec &q,
                                       double sq, const ClosureNewtonSettings &settings,
                                       TrialBest &best) {
  ClosureNewtonData &w = data.closure_newton;
  w.dv.setZero();
  for (std::size_t k = 0; k < w.free.size(); ++k) w.dv[w.free[k]] = w.step[k];
  double alpha = 1.0;
  for (int h = 0; h < settings.max_halvings; ++h, alpha *= 0.5) {
    w.dq = alpha * w.dv;
    integrate_trial(model, q, w.dq, w.q_try);
    for (std::size_t k = 0; k < w.held_q.size(); ++k) w.q_try[w.held_q[k]] = w.q_held[k];
    eval_phi_J(model, data, w.q_try);
    if (accept_trial(data, w.q_try, sq, settings.tol, best, w.q_best, w.phi_best)) return;
  }
}

inline bool closure_newton(const CoreModel &model, CoreData &data, Vec &q,
                           const Eigen::VectorXi &free, const ClosureNewtonSettings &settings) {
  if (model.nc == 0) return true;  // nothing to close
  closure_newton_resize(model, data, free);
  ClosureNewtonData &w = data.closure_newton;
  for (std::size_t k = 0; k < w.held_q.size(); ++k) w.q_held[k] = q[w.held_q[k]];
  eval_phi_J(model, data, q);
  w.phi = data.phi;
  double res = max_abs_nan(w.phi);
  // numpy.linalg.lstsq's default rcond for J_F of shape (nc, n_free)
  const double rcond_full =
      std::numeric_limits<double>::epsilon() * std::max<Eigen::Index>(model.nc, free.size());
  for (int it = 0; it < settings.max_iter; ++it) {
    if (res <= settings.tol) return true;
    eval_phi_J(model, data, q);  // the memo of the accepted trial point
    if (!data.J.allFinite()) return false;  // lstsq would raise; the caller's fallback does
    for (std::size_t k = 0; k < w.free.size(); ++k)
      w.J_free.col(static_cast<Eigen::Index>(k)) = data.J.col(w.free[k]);
    // Accept on the sum of squares, the merit function the Gauss-Newton step descends.
    const double sq = w.phi.squaredNorm();
    if (w.step.size()) w.svd.compute(w.J_free);  // one SVD serves both candidate steps
    TrialBest best;
    for (const double rcond : {rcond_full, settings.fallback_rcond}) {
      closure_newton_step(data, rcond);
      closure_newton_line_search(model, data, q, sq, settings, best);
      if (best.have && (best.res <= settings.tol || best.sq <= settings.contraction * sq)) break;
    }
    if (!best.have) break;
    q = w.q_best;
    w.phi = w.phi_best;
    res = best.res;
  }
  return res <= settings.tol;
}

}  // namespace closedchain
