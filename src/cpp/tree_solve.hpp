// closedchain._core: products with M and M^-1 of a kinematic tree in O(nv), by the
// articulated-body algorithm (Featherstone, Rigid Body Dynamics Algorithms, 2008,
// section 7.3) with zero velocity and no gravity, every quantity in the world frame
// (as Pinocchio's aba: no transform between a joint and its parent). A serial chain's
// M is dense, so its Cholesky factor costs O(nv^3) and the CRBA that forms it
// O(nv^2); this factors M implicitly in O(nv) per configuration and applies M^-1 to a
// vector in O(nv):
//
//   factor (children first), with S_i = data.J's columns of joint i (world) and
//   Y_i = oMi I_i the body's world spatial inertia:
//     IA_i = Y_i + sum over children c of (IA_c - U_c D_c^-1 U_c^T),
//     U_i = IA_i S_i,   D_i = S_i^T U_i + diag(armature_i);
//   x <- M^-1 x:
//     backward:  u_i = x_i - S_i^T p_i,   p_parent += p_i + U_i D_i^-1 u_i,
//     forward:   x_i = D_i^-1 (u_i - U_i^T a_parent),   a_i = a_parent + S_i x_i;
//   y = M x (the recursive Newton-Euler algorithm at zero velocity and gravity):
//     forward:   a_i = a_parent + S_i x_i,   f_i = Y_i a_i,
//     backward:  y_i = S_i^T f_i + armature_i x_i,   f_parent += f_i.
//
// tr(M) = sum_i tr(S_i^T Ic_i S_i) + sum armature, Ic_i the composite inertia of
// joint i's subtree, comes with the factorization (the augmented Lagrangian's penalty).
//
// Free functions over (pinocchio::Model, pinocchio::Data, TreeFactor), Pinocchio's
// style: the Data holds the kinematics of the configuration (data.oMi and the world
// joint Jacobian columns data.J, as tree_terms.hpp's passes leave them), TreeFactor the
// factorization and its scratch, sized once for the model (no allocation per call).
// Used by the tree path of the forward-dynamics methods (tree_rows.hpp, core_tree.hpp);
// tests/test_tree_solve.py checks it against the dense solves.

#pragma once

#include <pinocchio/multibody/data.hpp>
#include <pinocchio/multibody/model.hpp>

#include <Eigen/Cholesky>
#include <Eigen/Dense>
#include <Eigen/StdVector>

#include <vector>

namespace closedchain {

/// The articulated-body factorization of a tree's M at one configuration (the data of
/// tree_factor, tree_solve_in_place and tree_mass_mul): one 6 x 6 block per joint.
struct TreeFactor {
  /// A spatial (6 x 6) matrix.
  using Matrix6 = Eigen::Matrix<double, 6, 6>;
  /// A spatial vector.
  using Vector6 = Eigen::Matrix<double, 6, 1>;
  /// One T per joint, aligned for Eigen's fixed-size types.
  template <class T>
  using Aligned = std::vector<T, Eigen::aligned_allocator<T>>;

  /// Empty buffers.
  TreeFactor() = default;

  /// Buffers for `model` (one 6 x 6 block per joint, U of shape (6, nv)).
  explicit TreeFactor(const pinocchio::Model &model)
      : Y(model.njoints), IA(model.njoints), Ic(model.njoints), Dinv(model.njoints),
        f(model.njoints), acc(model.njoints), U(6, model.nv) {}

  Aligned<Matrix6> Y;     ///< body inertia in the world frame, per joint [kg, kg m, kg m^2]
  Aligned<Matrix6> IA;    ///< articulated-body inertia, per joint
  Aligned<Matrix6> Ic;    ///< composite inertia (for tr(M)), per joint
  Aligned<Matrix6> Dinv;  ///< D_i^-1 (its top-left nv_i x nv_i block), per joint
  Aligned<Vector6> f;     ///< bias forces p_i / forces f_i, per joint (scratch)
  Aligned<Vector6> acc;   ///< spatial accelerations, per joint (scratch)
  Eigen::Matrix<double, 6, Eigen::Dynamic> U;  ///< U_i = IA_i S_i, column by column
  double trace = 0.0;  ///< tr(M) [kg, kg m^2] at the last tree_factor
};

namespace tree_solve_detail {
/// Per-joint blocks of at most 6 columns (fixed storage: no allocation).
using Block = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, 0, 6, 6>;
/// Per-joint vectors of at most 6 entries (fixed storage: no allocation).
using Small = Eigen::Matrix<double, Eigen::Dynamic, 1, 0, 6, 1>;
}  // namespace tree_solve_detail

/// Factor M at the kinematics in `data` (data.oMi and the world joint Jacobian columns
/// data.J of the configuration) into `tf`. Returns false when a D_i is not positive
/// definite (a massless subtree: M is singular).
inline bool tree_factor(const pinocchio::Model &model, const pinocchio::Data &data,
                        TreeFactor &tf) {
  using namespace tree_solve_detail;
  using Vector6 = TreeFactor::Vector6;
  for (pinocchio::JointIndex i = 1; i < (pinocchio::JointIndex)model.njoints; ++i) {
    tf.Y[i] = data.oMi[i].act(model.inertias[i]).matrix();
    tf.IA[i] = tf.Y[i];
    tf.Ic[i] = tf.Y[i];
  }
  tf.trace = 0.0;
  bool ok = true;
  for (pinocchio::JointIndex i = (pinocchio::JointIndex)(model.njoints - 1); i > 0; --i) {
    const int k = model.idx_vs[i], n = model.nvs[i];
    const pinocchio::JointIndex parent = model.parents[i];
    if (n == 1) {  // the common case: one column, D_i a scalar
      const Vector6 s = data.J.col(k);
      const Vector6 u = tf.IA[i] * s;
      tf.U.col(k) = u;
      const double d = s.dot(u) + model.armature[k];
      ok = ok && d > 0.0;
      tf.Dinv[i](0, 0) = 1.0 / d;
      tf.trace += s.dot(tf.Ic[i] * s) + model.armature[k];
      if (parent > 0) {
        tf.IA[parent].noalias() += tf.IA[i] - (u / d) * u.transpose();
        tf.Ic[parent] += tf.Ic[i];
      }
      continue;
    }
    const auto S = data.J.middleCols(k, n);
    auto U = tf.U.middleCols(k, n);
    U.noalias() = tf.IA[i] * S;
    Block D(n, n);
    D.noalias() = S.transpose() * U;
    D.diagonal() += model.armature.segment(k, n);
    Block icS(6, n);
    icS.noalias() = tf.Ic[i] * S;
    for (int c = 0; c < n; ++c) tf.trace += S.col(c).dot(icS.col(c)) + model.armature[k + c];
    Eigen::LLT<Block> llt(D);
    ok = ok && llt.info() == Eigen::Success;
    auto Dinv = tf.Dinv[i].topLeftCorner(n, n);
    Dinv.setIdentity();
    llt.solveInPlace(Dinv);
    if (parent > 0) {
      Block UD(6, n);
      UD.noalias() = U * Dinv;
      tf.IA[parent].noalias() += tf.IA[i] - UD * U.transpose();
      tf.Ic[parent] += tf.Ic[i];
    }
  }
  return ok;
}

/// x <- M^-1 x, x of shape (nv,) [N, N m] -> [m/s^2, rad/s^2], after tree_factor at the
/// kinematics in `data`.
inline void tree_solve_in_place(const pinocchio::Model &model, const pinocchio::Data &data,
                                TreeFactor &tf, Eigen::Ref<Eigen::VectorXd> x) {
  using namespace tree_solve_detail;
  const pinocchio::JointIndex nj = (pinocchio::JointIndex)model.njoints;
  for (pinocchio::JointIndex i = 1; i < nj; ++i) tf.f[i].setZero();
  for (pinocchio::JointIndex i = nj - 1; i > 0; --i) {  // u_i and the bias forces p_i
    const int k = model.idx_vs[i], n = model.nvs[i];
    const pinocchio::JointIndex parent = model.parents[i];
    if (n == 1) {
      x[k] -= data.J.col(k).dot(tf.f[i]);
      if (parent > 0) tf.f[parent] += tf.f[i] + tf.U.col(k) * (tf.Dinv[i](0, 0) * x[k]);
      continue;
    }
    auto xi = x.segment(k, n);
    xi.noalias() -= data.J.middleCols(k, n).transpose() * tf.f[i];
    if (parent > 0) {
      Small du(n);
      du.noalias() = tf.Dinv[i].topLeftCorner(n, n) * xi;
      tf.f[parent] += tf.f[i];
      tf.f[parent].noalias() += tf.U.middleCols(k, n) * du;
    }
  }
  for (pinocchio::JointIndex i = 1; i < nj; ++i) {  // the accelerations
    const int k = model.idx_vs[i], n = model.nvs[i];
    const pinocchio::JointIndex parent = model.parents[i];
    if (n == 1) {
      if (parent > 0) {
        x[k] = tf.Dinv[i](0, 0) * (x[k] - tf.U.col(k).dot(tf.acc[parent]));
        tf.acc[i] = tf.acc[parent] + data.J.col(k) * x[k];
      } else {
        x[k] *= tf.Dinv[i](0, 0);
        tf.acc[i] = data.J.col(k) * x[k];
      }
      continue;
    }
    Small u = x.segment(k, n);
    if (parent > 0) u.noalias() -= tf.U.middleCols(k, n).transpose() * tf.acc[parent];
    x.segment(k, n).noalias() = tf.Dinv[i].topLeftCorner(n, n) * u;
    if (parent > 0)
      tf.acc[i] = tf.acc[parent];
    else
      tf.acc[i].setZero();
    tf.acc[i].noalias() += data.J.middleCols(k, n) * x.segment(k, n);
  }
}

/// y = M x, x and y of shape (nv,) (distinct) [rad/s^2 -> N m], at the configuration of
/// the last tree_factor (its world inertias tf.Y).
inline void tree_mass_mul(const pinocchio::Model &model, const pinocchio::Data &data,
                          TreeFactor &tf, const Eigen::Ref<const Eigen::VectorXd> &x,
                          Eigen::Ref<Eigen::VectorXd> y) {
  const pinocchio::JointIndex nj = (pinocchio::JointIndex)model.njoints;
  for (pinocchio::JointIndex i = 1; i < nj; ++i) {
    const int k = model.idx_vs[i], n = model.nvs[i];
    const pinocchio::JointIndex parent = model.parents[i];
    if (parent > 0)
      tf.acc[i] = tf.acc[parent];
    else
      tf.acc[i].setZero();
    tf.acc[i].noalias() += data.J.middleCols(k, n) * x.segment(k, n);
    tf.f[i].noalias() = tf.Y[i] * tf.acc[i];
  }
  for (pinocchio::JointIndex i = nj - 1; i > 0; --i) {
    const int k = model.idx_vs[i], n = model.nvs[i];
    const pinocchio::JointIndex parent = model.parents[i];
    y.segment(k, n).noalias() = data.J.middleCols(k, n).transpose() * tf.f[i];
    y.segment(k, n) += model.armature.segment(k, n).cwiseProduct(x.segment(k, n));
    if (parent > 0) tf.f[parent] += tf.f[i];
  }
}

}  // namespace closedchain
