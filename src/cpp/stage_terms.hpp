// closedchain._core: the two halves of tree_terms_at_kinematics (tree_terms.hpp) for
// the stage projection (included by expose-core.cpp after tree_terms.hpp).
//
// At a stage of rk4 with stage projection the mass-orthogonal velocity step needs M
// at the projected q, and the evaluation that follows needs h and gamma at the same
// q and the projected v: M is computed once (mass_at_kinematics) and the evaluation
// runs the velocity-dependent part only (bias_at_kinematics), where the
// tree_terms_at_kinematics of each would run the forward and backward passes twice.
// Both need the kinematics at q in data (liMi, oMi, J: joint_kinematics(plan, model,
// data, q)); revolute joints take tree_terms' revolute path (plan), the others
// Pinocchio's visitor. Both are tree_terms' own passes (motion_pass, backward with
// only M or only h): M, h, ov, oa, of and the composite inertias are the same bits.

#pragma once

#include "tree_terms.hpp"

namespace closedchain {

/// M (full, symmetric, armature included) at the kinematics in data: tree_terms' M
/// without the velocity pass; data.oYcrb left composite (as tree_terms leaves it).
inline void mass_at_kinematics(const TreePlan &plan, const pinocchio::Model &model,
                               pinocchio::Data &data, Eigen::MatrixXd &M) {
  data.oYcrb[0].setZero();
  for (pinocchio::JointIndex i = 1; i < (pinocchio::JointIndex)model.njoints; ++i)
    data.oYcrb[i] = data.oMi[i].act(model.inertias[i]);
  Eigen::VectorXd no_h;  // not written (size 0: no allocation)
  tree_terms_detail::backward<true, false>(plan, model, data, M, no_h);
}

/// h = nonLinearEffects(q, v) and data.ov, data.oa, data.of at the kinematics in data
/// (tree_terms_at_kinematics without M).
template <typename ConfigVectorType, typename TangentVectorType>
void bias_at_kinematics(const TreePlan &plan, const pinocchio::Model &model,
                        pinocchio::Data &data, const Eigen::MatrixBase<ConfigVectorType> &q,
                        const Eigen::MatrixBase<TangentVectorType> &v, Eigen::VectorXd &h) {
  tree_terms_detail::motion_pass(plan, model, data, q, v);
  Eigen::MatrixXd no_M;  // not written (size 0: no allocation)
  tree_terms_detail::backward<false, true>(plan, model, data, no_M, h);
}

}  // namespace closedchain
