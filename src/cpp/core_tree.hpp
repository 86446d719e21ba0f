// closedchain._core: the tree path of the kkt and augmented-lagrangian methods over
// (CoreModel, CoreData): a tree with few loop rows solved in O(nv) for the tree plus a
// dense nc x nc solve for the rows, M never formed (tree_solve.hpp factors it by the
// articulated-body recursion, tree_rows.hpp holds the rows' algebra and its formulas).
//
// Chosen per mechanism (CoreModel::tree_path: nv > TREE_SOLVE_MIN_NV and nc <= nv /
// TREE_SOLVE_NV_PER_ROW, set at construction) where the method's solve is chosen
// (dispatch, core_methods.hpp) and, for the stage projection's velocity step, in project
// (core_projection.hpp); CoreModel::tree_solves() says whether a configured core takes it.
// The factorization, W, D and the factors of D and of I / alpha + D are made once per
// configuration (data.J_at) and shared by the evaluation and the projection there.
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

/// M factored by the articulated-body recursion, then W = M^-1 J^T and D = J W, at the
/// kinematics of the last evaluation (data.J_at), unless already (data.tree_factored).
/// SingularError naming M when a subtree is massless.
void tree_factor_at_J(const CoreModel &model, CoreData &data, const RefV &q, double t);

/// The factor of D for kkt, unless already (data.delassus_factored): a cheap upper bound of
/// cond_1(D) first, and where it exceeds cond_max D's cond_2 from its eigenvalues
/// (SingularError naming the Delassus matrix J M^-1 J^T). After tree_factor_at_J.
void tree_factor_kkt(const CoreModel &model, CoreData &data, const RefV &q, double t);

/// The factor of I / alpha + D for the augmented Lagrangian, unless already
/// (data.tree_penalized): alpha starts at the dense path's al_penalty tr(M) / tr(J^T J)
/// and is lowered by its rule (al_lowered_penalty) while the factor's smallest relative
/// pivot is below AL_PIVOT_MIN, at most AL_MAX_PENALTY_LOWERINGS times (then
/// SingularError). After tree_factor_at_J.
void tree_penalize(const CoreModel &model, CoreData &data, const RefV &q, double t);

/// kkt or the augmented Lagrangian on the tree path (tree_rows.hpp's formulas): data.a and
/// data.lam at the last evaluation with generalized force tau, shape (nv,) [N, N m].
void solve_tree(const CoreModel &model, CoreData &data, const RefV &q, const Vec &tau,
                double t);

/// project()'s mass-orthogonal velocity step on the tree path: v, shape (nv,), onto J v = 0
/// by the dual augmented-Lagrangian iteration with right-hand side M v (a_f = v), at the
/// kinematics of eval_phi_J(q).
void tree_project_velocity(const CoreModel &model, CoreData &data, const RefV &q, Vec &v);

/// 1/2 v^T M v [J] by the Newton-Euler product (tree_mass_mul) at the configuration of the
/// last tree factorization (data.tree_factored). v: shape (nv,).
double tree_kinetic_energy(const CoreModel &model, CoreData &data, const Vec &v);

// -- definitions -------------------------------------------------------------

inline void set_tree_path(CoreModel &model, CoreData &data, bool on) {
  model.tree_path = on;
  invalidate_kinematics(data);
}

inline void tree_factor_at_J(const CoreModel &model, CoreData &data, const RefV &q, double t) {
  if (data.tree_factored) return;
  if (!tree_factor(model.tree, data.tree, data.mass_factor))
    singular(model, q, "the mass matrix M", std::numeric_limits<double>::infinity(),
             "it is not positive definite (a massless subtree)", t);
  tree_delassus(model.tree, data.tree, data.mass_factor, data.J, data.tree_rows);
  data.tree_factored = true;
}

inline void tree_factor_kkt(const CoreModel &model, CoreData &data, const RefV &q, double t) {
  if (data.delassus_factored) return;
  if (!(tree_factor_delassus(data.tree_rows, INVERSE_BOUND_MARGIN) <= model.cond_max)) {
    data.eig.compute(data.tree_rows.D, Eigen::EigenvaluesOnly);  // reads the lower triangle
    const Vec &ev = data.eig.eigenvalues();
    check_rcond(model, q, "the Delassus matrix J M^-1 J^T",
                ev.size() && ev[0] > 0.0 ? ev[0] / ev[ev.size() - 1] : 0.0, RANK_LOSS_HINT, t);
  }
  data.delassus_factored = true;
}

inline void tree_penalize(const CoreModel &model, CoreData &data, const RefV &q, double t) {
  if (data.tree_penalized) return;
  TreeRows &rows = data.tree_rows;
  double alpha = model.al_penalty * data.mass_factor.trace /
                 std::max(data.J.squaredNorm(), std::numeric_limits<double>::min());
  for (rows.lowerings = 0;; ++rows.lowerings) {  // al_factor's rule, on I / alpha + D
    const double pivot = tree_factor_penalized(rows, alpha);
    if (pivot >= AL_PIVOT_MIN) break;
    if (rows.lowerings == AL_MAX_PENALTY_LOWERINGS) penalized_singular(model, q, alpha, t);
    alpha = al_lowered_penalty(alpha, pivot);
  }
  rows.alpha = alpha;
  data.tree_penalized = true;
}

inline void solve_tree(const CoreModel &model, CoreData &data, const RefV &q, const Vec &tau,
                       double t) {
  const bool penalized = model.method == AUGMENTED_LAGRANGIAN;
  tree_factor_at_J(model, data, q, t);
  if (penalized)
    tree_penalize(model, data, q, t);
  else
    tree_factor_kkt(model, data, q, t);
  data.rhs_v = tau - data.h;
  tree_free_motion(model.tree, data.tree, data.mass_factor, data.J, data.tree_rows, data.rhs_v,
                   data.gamma, data.a);
  if (!penalized) return tree_kkt(data.tree_rows, data.a, data.lam);
  tree_al_iterate(data.tree_rows, model.al_max_iter * (1 + data.tree_rows.lowerings), model.al_tol,
                  data.a, data.lam);
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
