// closedchain._core: the tree path of the forward-dynamics methods over (CoreModel,
// CoreData): a tree with few loop rows solved in O(nv) for the tree plus a dense nc x nc
// solve for the rows, M never formed (tree_solve.hpp factors it by the articulated-body
// recursion, tree_rows.hpp holds the rows' algebra and its formulas): kkt and the augmented
// Lagrangian on W = M^-1 J^T and D = J W, null space and reduced coordinates in their
// range-space form on W_r = M^-1 V_r and G = V_r^T W_r (tree_rows.hpp's tree_range).
//
// Chosen per mechanism (CoreModel::tree_path: nv > TREE_SOLVE_MIN_NV and nc <= nv /
// TREE_SOLVE_NV_PER_ROW, set at construction) where the method's solve is chosen
// (dispatch, core_methods.hpp) and, for the stage projection's velocity step, in project
// (core_projection.hpp); CoreModel::tree_solves() says whether a configured core takes it.
// The factorization, W, D, W_r, G and the factors of D, of I / alpha + D and of G are made
// once per configuration (data.J_at) and shared by the evaluation and the projection there.
// (Functions over (CoreModel, CoreData): their declarations, then their definitions.)

#pragma once

#include <algorithm>
#include <limits>

#include "constants.hpp"
#include "core_data.hpp"
#include "core_methods.hpp"
#include "core_model.hpp"
#include "tree_rows.hpp"
#include "tree_solve.hpp"

namespace closedchain {

// -- declarations ------------------------------------------------------------

/// Allow the tree path (on) or not (off: the dense or band path) after construction chose
/// it by size (tests and benchmarks compare the two); the kept factorizations are dropped.
void set_tree_path(CoreModel &model, CoreData &data, bool on);

/// M factored by the articulated-body recursion at the kinematics of the last evaluation
/// (data.J_at), unless already (data.tree_mass_factored). SingularError naming M when a
/// subtree is massless.
void tree_factor_mass(const CoreModel &model, CoreData &data, const RefV &q, double t);

/// tree_factor_mass, then W = M^-1 J^T and D = J W, unless already (data.tree_factored).
void tree_factor_at_J(const CoreModel &model, CoreData &data, const RefV &q, double t);

/// The symmetric positive definite A (lower triangle, shape (nc, nc)) factored into llt:
/// a cheap upper bound of cond_1(A) first, and where it exceeds cond_max A's cond_2 from its
/// eigenvalues (check_rcond's SingularError naming `what`, with `hint`).
void tree_factor_checked(const CoreModel &model, CoreData &data, const RefV &q, const Mat &A,
                         SmallLLT &llt, const char *what, const char *hint, double t);

/// The factor of D for kkt (tree_factor_checked, naming the Delassus matrix J M^-1 J^T),
/// unless already (data.delassus_factored). After tree_factor_at_J.
void tree_factor_kkt(const CoreModel &model, CoreData &data, const RefV &q, double t);

/// The factor of I / alpha + D for the augmented Lagrangian, unless already
/// (data.tree_penalized): alpha starts at the dense path's al_penalty tr(M) / tr(J^T J)
/// and is chosen by its rule (al_choose_penalty) on I / alpha + D's pivots. After
/// tree_factor_at_J.
void tree_penalize(const CoreModel &model, CoreData &data, const RefV &q, double t);

/// The range-space form's factors (tree_rows.hpp's tree_range) unless already
/// (data.tree_range_factored): the thin SVD of J (with the null-space method's check of
/// cond(J) where check_rank), tree_factor_mass, W_r = M^-1 V_r and G's factor
/// (tree_factor_checked, naming G as the tree path's).
void tree_factor_range(const CoreModel &model, CoreData &data, const RefV &q, bool check_rank,
                       double t);

/// The configured method on the tree path (tree_rows.hpp's formulas): data.a and data.lam
/// at the last evaluation with generalized force tau, shape (nv,) [N, N m].
void solve_tree(const CoreModel &model, CoreData &data, const RefV &q, const Vec &tau,
                double t);

/// The null-space method in its range-space form (tree_range): a = a_f - W_r mu with
/// c_r = -Sigma^-1 U^T gamma, lam = U Sigma^-1 mu. After tree_free_motion's a = a_f.
void tree_nullspace(CoreData &data);

/// Reduced coordinates in the range-space form (tree_range): the dependent offset
/// c = [0; -J_D^-1 gamma], c_r = V_r^T c, a = a_f - W_r mu, lam = J_D^-T (V_r mu)_D; J_D
/// checked as on the dense path (factor_method_JD). After tree_free_motion's a = a_f.
void tree_reduced(const CoreModel &model, CoreData &data);

/// project()'s mass-orthogonal velocity step on the tree path: v, shape (nv,), onto J v = 0
/// by the dual augmented-Lagrangian iteration with right-hand side M v (a_f = v), at the
/// kinematics of eval_phi_J(q).
void tree_project_velocity(const CoreModel &model, CoreData &data, const RefV &q, Vec &v);

/// 1/2 v^T M v [J] by the Newton-Euler product (tree_mass_mul) at the configuration of the
/// last tree factorization (data.tree_mass_factored). v: shape (nv,).
double tree_kinetic_energy(const CoreModel &model, CoreData &data, const Vec &v);

// -- definitions -------------------------------------------------------------

inline void set_tree_path(CoreModel &model, CoreData &data, bool on) {
  model.tree_path = on;
  invalidate_kinematics(data);
}

inline void tree_factor_mass(const CoreModel &model, CoreData &data, const RefV &q, double t) {
  if (data.tree_mass_factored) return;
  if (!tree_factor(model.tree, data.tree, data.mass_factor))
    singular(model, q, "the mass matrix M", std::numeric_limits<double>::infinity(),
             "it is not positive definite (a massless subtree)", t);
  data.tree_mass_factored = true;
}

inline void tree_factor_at_J(const CoreModel &model, CoreData &data, const RefV &q, double t) {
  if (data.tree_factored) return;
  tree_factor_mass(model, data, q, t);
  tree_delassus(model.tree, data.tree, data.mass_factor, data.J, data.tree_rows);
  data.tree_factored = true;
}

inline void tree_factor_checked(const CoreModel &model, CoreData &data, const RefV &q,
                                const Mat &A, SmallLLT &llt, const char *what, const char *hint,
                                double t) {
  if (factor_cond_bound(A, llt, INVERSE_BOUND_MARGIN) <= model.cond_max) return;
  data.eig.compute(A, Eigen::EigenvaluesOnly);  // reads the lower triangle
  const Vec &ev = data.eig.eigenvalues();
  check_rcond(model, q, what, ev.size() && ev[0] > 0.0 ? ev[0] / ev[ev.size() - 1] : 0.0, hint,
              t);
}

inline void tree_factor_kkt(const CoreModel &model, CoreData &data, const RefV &q, double t) {
  if (data.delassus_factored) return;
  tree_factor_checked(model, data, q, data.tree_rows.D, data.tree_rows.llt_d,
                      "the Delassus matrix J M^-1 J^T", RANK_LOSS_HINT, t);
  data.delassus_factored = true;
}

inline void tree_penalize(const CoreModel &model, CoreData &data, const RefV &q, double t) {
  if (data.tree_penalized) return;
  TreeRows &rows = data.tree_rows;
  rows.alpha = al_choose_penalty(
      model, q, t,
      model.al_penalty * data.mass_factor.trace /
          std::max(data.J.squaredNorm(), std::numeric_limits<double>::min()),
      [&](double alpha) { return tree_factor_penalized(rows, alpha); }, rows.lowerings);
  data.tree_penalized = true;
}

inline void tree_factor_range(const CoreModel &model, CoreData &data, const RefV &q,
                              bool check_rank, double t) {
  if (data.tree_range_factored) return;
  TreeRows &rows = data.tree_rows;
  rows.svd.compute(data.J, Eigen::ComputeThinU | Eigen::ComputeThinV);
  if (check_rank) check_jacobian_rank(model, q, rows.svd.singularValues(), t);
  tree_factor_mass(model, data, q, t);
  tree_range(model.tree, data.tree, data.mass_factor, rows);
  tree_factor_checked(model, data, q, rows.G, rows.llt_g,
                      "the tree path's range-space matrix V_r^T M^-1 V_r", MASS_HINT, t);
  data.tree_range_factored = true;
}

inline void solve_tree(const CoreModel &model, CoreData &data, const RefV &q, const Vec &tau,
                       double t) {
  const Method method = active_method(model, data);
  const bool range = method == NULLSPACE || method == REDUCED;
  if (!range) {
    tree_factor_at_J(model, data, q, t);
    if (method == AUGMENTED_LAGRANGIAN)
      tree_penalize(model, data, q, t);
    else
      tree_factor_kkt(model, data, q, t);
  } else if (model.nc) {  // the checks in the dense path's order: J_D or J, then M, then G
    if (method == REDUCED) factor_method_JD(model, data, q, t);
    tree_factor_range(model, data, q, method == NULLSPACE, t);
  } else {
    tree_factor_mass(model, data, q, t);
  }
  data.rhs_v = tau - data.h;
  tree_free_motion(model.tree, data.tree, data.mass_factor, data.J, data.tree_rows, data.rhs_v,
                   data.gamma, data.a);
  if (!model.nc) return;  // a = a_f
  switch (method) {
    case NULLSPACE:
      return tree_nullspace(data);
    case REDUCED:
      return tree_reduced(model, data);
    case AUGMENTED_LAGRANGIAN:
      tree_al_iterate(data.tree_rows, model.al_max_iter * (1 + data.tree_rows.lowerings),
                      model.al_tol, data.a, data.lam);
      return;
    default:
      return tree_kkt(data.tree_rows, data.a, data.lam);
  }
}

inline void tree_nullspace(CoreData &data) {
  TreeRows &rows = data.tree_rows;
  const Vec &s = rows.svd.singularValues();
  rows.b.noalias() = rows.svd.matrixU().transpose().lazyProduct(data.gamma);
  rows.b.array() /= -s.array();  // c_r = V_r^T a_p = -Sigma^-1 U^T gamma
  tree_range_solve(rows, rows.b, data.a);
  rows.r.array() /= s.array();
  data.lam.noalias() = rows.svd.matrixU().lazyProduct(rows.r);
}

inline void tree_reduced(const CoreModel &model, CoreData &data) {
  TreeRows &rows = data.tree_rows;
  const Mat &Vr = rows.svd.matrixV();
  const std::vector<int> &dep = model.method_dependent;
  data.tmp_c = data.gamma;
  data.lu_jd.solve(data.tmp_c);  // -c on the dependent coordinates
  rows.b.setZero();
  for (int i = 0; i < model.nc; ++i) rows.b -= Vr.row(dep[i]).transpose() * data.tmp_c[i];
  tree_range_solve(rows, rows.b, data.a);
  for (int i = 0; i < model.nc; ++i) data.tmp_c[i] = Vr.row(dep[i]).dot(rows.r);
  data.lu_jd.solve_transposed(data.tmp_c);
  data.lam = data.tmp_c;
}

inline void tree_project_velocity(const CoreModel &model, CoreData &data, const RefV &q, Vec &v) {
  const double t = std::numeric_limits<double>::quiet_NaN();
  tree_factor_at_J(model, data, q, t);
  tree_penalize(model, data, q, t);
  data.tree_rows.b.noalias() = data.J.lazyProduct(v);  // rhs = M v: a_f = v, g = 0
  tree_al_iterate(data.tree_rows, model.al_max_iter * (1 + data.tree_rows.lowerings),
                  model.al_tol, v, data.lam);
}

inline double tree_kinetic_energy(const CoreModel &model, CoreData &data, const Vec &v) {
  tree_mass_mul(model.tree, data.tree, data.mass_factor, v, data.tree_rows.da);
  return 0.5 * v.dot(data.tree_rows.da);
}

}  // namespace closedchain
