// closedchain._core: the loop rows of the tree path: a tree with few loop rows solved in
// O(nv) for the tree plus a dense nc x nc solve for the rows, M never formed
// (tree_solve.hpp's articulated-body factorization).
//
// With W = M^-1 J^T (nc solves), the Delassus matrix D = J W (nc x nc), the motion
// without the rows a_f = M^-1 rhs (rhs = tau - h) and b = J a_f + g (g = gamma), every
// solution is a = a_f - W lam: M a + J^T lam = rhs holds by construction and only lam is
// solved for, in the rows' space:
//   kkt: D lam = b (the KKT system's Schur complement on M);
//   augmented Lagrangian: the iteration of al_iteration.hpp, whose iterates satisfy
//        M a_k + J^T lam_k = rhs when P^-1 is exact (Woodbury:
//        P^-1 = (M + alpha J^T J)^-1 = M^-1 - W (I / alpha + D)^-1 W^T), written for lam
//        (its dual form):
//        (I / alpha + D) (lam_{k+1} - lam_k) = J a_k + g = b - D lam_k from lam_0 = 0,
//        with al_iterate's stopping rule on max |a_{k+1} - a_k| = max |W (lam_{k+1} -
//        lam_k)|. I / alpha + D stays positive definite where J loses rank; the penalty
//        is lowered where its Cholesky shows too small a pivot (core_tree.hpp, the dense
//        path's rule on P = M + alpha J^T J). No multiplier polish: a and lam agree by
//        construction;
//   the mass-orthogonal velocity projection (stage projection): the same iteration with
//        rhs = M v, so a_f = v and no product with M or M^-1 at all;
//   null space and reduced coordinates: the range-space form (tree_range_solve), with
//        W_r = M^-1 V_r and G = V_r^T W_r for an orthonormal basis V_r of range(J^T) in
//        place of W and D.
// Per evaluation O(nv nc + nc^3) besides the tree pass and the factorization, against
// the dense path's O(nv^3).
//
// Free functions over the Pinocchio model and data (the kinematics of the configuration),
// the factorization (TreeFactor) and the row buffers (TreeRows), sized once: no
// allocation per call. core_tree.hpp calls them over (CoreModel, CoreData).

#pragma once

#include <limits>

#include "al_iteration.hpp"
#include "common.hpp"
#include "small_llt.hpp"
#include "tree_solve.hpp"

namespace closedchain {

/// The loop-row part of the tree path at one configuration: W, D and the factors of D
/// (kkt) and of I / alpha + D (augmented Lagrangian), with their scratch.
struct TreeRows {
  /// Empty buffers.
  TreeRows() = default;

  /// Buffers for nv velocities and nc rows.
  TreeRows(int nv, int nc)
      : W(Mat::Zero(nv, nc)), D(Mat::Zero(nc, nc)), A(Mat::Zero(nc, nc)), llt_d(nc), llt_a(nc),
        b(Vec::Zero(nc)), r(Vec::Zero(nc)), da(Vec::Zero(nv)),
        svd(nc, nv, Eigen::ComputeThinU | Eigen::ComputeThinV), Wr(Mat::Zero(nv, nc)),
        G(Mat::Zero(nc, nc)), llt_g(nc) {}

  Mat W;               ///< M^-1 J^T, shape (nv, nc)
  Mat D;               ///< the Delassus matrix J M^-1 J^T, shape (nc, nc), lower triangle
  Mat A;               ///< I / alpha + D, shape (nc, nc), lower triangle
  SmallLLT llt_d;      ///< Cholesky factor of D (kkt)
  SmallLLT llt_a;      ///< Cholesky factor of I / alpha + D (augmented Lagrangian)
  Vec b;               ///< J a_f + g, shape (nc,)
  Vec r;               ///< the iteration's multiplier step, shape (nc,)
  Vec da;              ///< the iteration's acceleration step, shape (nv,)
  double alpha = 0.0;  ///< the penalty of llt_a
  int lowerings = 0;   ///< how many times alpha was lowered from its first value
  /// The thin SVD J = U Sigma V_r^T (null space, reduced: V_r, shape (nv, nc)).
  Eigen::JacobiSVD<Mat> svd;
  Mat Wr;         ///< M^-1 V_r, shape (nv, nc)
  Mat G;          ///< V_r^T M^-1 V_r, shape (nc, nc), lower triangle
  SmallLLT llt_g;  ///< Cholesky factor of G
};

/// W = M^-1 J^T and the Delassus matrix D = J W (lower triangle) into `tr`, after
/// tree_factor at the kinematics in `data`. J: constraint Jacobian, shape (nc, nv).
inline void tree_delassus(const Model &model, const Data &data, TreeFactor &tf, const Mat &J,
                          TreeRows &tr) {
  for (Eigen::Index r = 0; r < J.rows(); ++r) {
    tr.W.col(r) = J.row(r).transpose();
    tree_solve_in_place(model, data, tf, tr.W.col(r));
  }
  tr.D.triangularView<Eigen::Lower>() = J.lazyProduct(tr.W);
}

/// Factor the symmetric positive definite A (its lower triangle) into llt; returns an
/// upper bound of cond_1(A) (infinity when A is not numerically positive definite): D after
/// tree_delassus, G after tree_range. margin: inverse_norm_bound's.
inline double factor_cond_bound(const Mat &A, SmallLLT &llt, double margin) {
  if (!llt.compute(A)) return std::numeric_limits<double>::infinity();
  return lower_norm1(A) * llt.inverse_norm_bound(margin);
}

/// The range-space form of the null-space and reduced methods (Z: any basis of null(J),
/// J of full row rank; V_r: an orthonormal basis of range(J^T), tr.svd's V, so that
/// Q = [V_r | Z] is a basis of R^nv). The block inverse of Q^T M Q gives
///
///   Z (Z^T M Z)^-1 Z^T = P := M^-1 - W_r G^-1 W_r^T,   W_r = M^-1 V_r,   G = V_r^T W_r,
///
/// (P V_r = 0, V_r^T P = 0): the projected solve of both methods without N^T M N or
/// S^T M S. Every a with J a + g = 0 has the same range part V_r^T a =: c_r
/// (= -Sigma^-1 U^T g), and with a particular solution c (a_p of the null space, the
/// dependent offset of reduced coordinates), a_f = M^-1 (tau - h) and W_r^T M = V_r^T,
///
///   a = c + P (tau - h - M c) = a_f - W_r mu,   G mu = V_r^T a_f - c_r:
///
/// no product with M. The multipliers follow from M a + V_r mu = tau - h, i.e.
/// J^T lam = V_r mu: lam = U Sigma^-1 mu (null space), or from the dependent rows
/// J_D^T lam = (V_r mu)_D (reduced). G's condition number is at most M's (V_r is
/// orthonormal), not cond(J)^2 cond(M) as the Delassus matrix D = U Sigma G Sigma U^T of
/// kkt: the errors still grow like cond(J), as those of the dense null-space method.
/// Cost: nc solves with M (O(nv nc)), the SVD of the wide J (O(nv nc^2)) and O(nc^3).
///
/// This function: W_r = M^-1 V_r and G (lower triangle) into `tr`, after tree_factor at
/// the kinematics in `data` and tr.svd.compute(J) (thin V).
inline void tree_range(const Model &model, const Data &data, TreeFactor &tf, TreeRows &tr) {
  const Mat &Vr = tr.svd.matrixV();
  for (Eigen::Index r = 0; r < Vr.cols(); ++r) {
    tr.Wr.col(r) = Vr.col(r);
    tree_solve_in_place(model, data, tf, tr.Wr.col(r));
  }
  tr.G.triangularView<Eigen::Lower>() = Vr.transpose().lazyProduct(tr.Wr);
}

/// The range-space solve (tree_range's formulas; G factored into tr.llt_g): a = a_f on
/// entry, a_f - W_r mu on return, mu into tr.r. c_r: V_r^T a of the solution, shape (nc,);
/// a: shape (nv,) [m/s^2, rad/s^2].
inline void tree_range_solve(TreeRows &tr, const Vec &c_r, Vec &a) {
  tr.r.noalias() = tr.svd.matrixV().transpose().lazyProduct(a);
  tr.r -= c_r;
  tr.llt_g.solveInPlace(tr.r);
  a.noalias() -= tr.Wr.lazyProduct(tr.r);
}

/// I / alpha + D into tr.A and its Cholesky factor tr.llt_a (alpha: the augmented
/// Lagrangian's penalty); returns the factor's smallest relative pivot, 0 when it failed. After
/// tree_delassus.
inline double tree_factor_penalized(TreeRows &tr, double alpha) {
  tr.A.triangularView<Eigen::Lower>() = tr.D;
  tr.A.diagonal().array() += 1.0 / alpha;
  return tr.llt_a.compute(tr.A) ? tr.llt_a.min_pivot_ratio(tr.A) : 0.0;
}

/// The motion without the rows, a = a_f = M^-1 rhs, and tr.b = J a_f + g, after
/// tree_factor. rhs: shape (nv,) [N, N m]; g: shape (nc,); a: shape (nv,) [m/s^2, rad/s^2].
inline void tree_free_motion(const Model &model, const Data &data, TreeFactor &tf, const Mat &J,
                             TreeRows &tr, const Vec &rhs, const Vec &g, Vec &a) {
  a = rhs;
  tree_solve_in_place(model, data, tf, a);
  tr.b = g;
  tr.b.noalias() += J.lazyProduct(a);
}

/// kkt on the tree (D factored by tree_factor_kkt; a = a_f and tr.b from
/// tree_free_motion): lam = D^-1 b, a = a_f - W lam. lam: shape (nc,) [N, N m].
inline void tree_kkt(TreeRows &tr, Vec &a, Vec &lam) {
  lam = tr.b;
  tr.llt_d.solveInPlace(lam);
  a.noalias() -= tr.W.lazyProduct(lam);
}

/// The augmented-Lagrangian iteration in its dual form (the formulas above; after
/// tree_factor_penalized, with a = a_f and tr.b = J a_f + g): lam overwritten from
/// lam_0 = 0, a updated, until max |a_{k+1} - a_k| <= tol (1 + max |a_{k+1}|), or the
/// change stops shrinking (the round-off floor), or max_iter iterates; SingularError where
/// the change grows (check_al_divergence): al_iterate's rules. Returns the number of
/// iterates.
inline int tree_al_iterate(TreeRows &tr, int max_iter, double tol, Vec &a, Vec &lam) {
  lam.setZero();
  double last_change = std::numeric_limits<double>::infinity();
  int it = 0;
  while (it < max_iter) {
    tr.r = tr.b;  // J a_k + g
    tr.r.noalias() -= tr.D.selfadjointView<Eigen::Lower>() * lam;
    tr.llt_a.solveInPlace(tr.r);
    lam += tr.r;
    tr.da.noalias() = tr.W.lazyProduct(tr.r);
    a -= tr.da;
    if (++it == 1) continue;  // x_1 of al_iterate: no change to test yet
    const double change = tr.da.cwiseAbs().maxCoeff();
    const double a_max = a.cwiseAbs().maxCoeff();
    check_al_divergence(last_change, change, a_max, it, tr.alpha);
    if (change <= tol * (1.0 + a_max) || change >= last_change) break;
    last_change = change;
  }
  return it;
}

}  // namespace closedchain
