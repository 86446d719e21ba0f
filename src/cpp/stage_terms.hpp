// closedchain._core: the two halves of tree_terms_at_kinematics (tree_terms.hpp) for
// the stage projection (included by core.cpp after tree_terms.hpp).
//
// At a stage of rk4 with stage projection the mass-orthogonal velocity step needs M
// at the projected q, and the evaluation that follows needs h and gamma at the same
// q and the projected v: M is computed once (mass_at_kinematics) and the evaluation
// runs the velocity-dependent part only (bias_at_kinematics), where the
// tree_terms_at_kinematics of each would run the forward and backward passes twice.
// Both need the kinematics at q in data (liMi, oMi, J: joint_kinematics(plan, model,
// data, q)); revolute joints take tree_terms' revolute path (plan), the others
// Pinocchio's visitor. Every quantity is computed with
// the arithmetic of tree_terms (the same forward_motion and backward formulas, in the
// same order): M, h, ov, oa, of and the composite inertias are the same bits.

#pragma once

#include "tree_terms.hpp"

namespace closedchain {
namespace stage_terms_detail {

using Model = pinocchio::Model;
using Data = pinocchio::Data;

// The backward step of tree_terms restricted to M (and the composite inertias).
struct MassBackwardStep : public pinocchio::fusion::JointUnaryVisitorBase<MassBackwardStep> {
  typedef boost::fusion::vector<const Model &, Data &, Eigen::MatrixXd &> ArgsType;

  template <typename JointModel>
  static void algo(const pinocchio::JointModelBase<JointModel> &jmodel, const Model &model,
                   Data &data, Eigen::MatrixXd &M) {
    typedef typename pinocchio::SizeDepType<JointModel::NV>::template ColsReturn<
        Data::Matrix6x>::Type ColsBlock;
    const pinocchio::JointIndex i = jmodel.id();
    ColsBlock J_cols = jmodel.jointCols(data.J);
    ColsBlock Ag_cols = jmodel.jointCols(data.Ag);
    pinocchio::motionSet::inertiaAction(data.oYcrb[i], J_cols, Ag_cols);
    M.block(jmodel.idx_v(), jmodel.idx_v(), jmodel.nv(), data.nvSubtree[i]).noalias() =
        J_cols.transpose() * data.Ag.middleCols(jmodel.idx_v(), data.nvSubtree[i]);
    data.oYcrb[model.parents[i]] += data.oYcrb[i];
  }
};

// The backward step of tree_terms restricted to h (the composite inertias too: the
// potential energy reads data.oYcrb[0]).
struct BiasBackwardStep : public pinocchio::fusion::JointUnaryVisitorBase<BiasBackwardStep> {
  typedef boost::fusion::vector<const Model &, Data &, Eigen::VectorXd &> ArgsType;

  template <typename JointModel>
  static void algo(const pinocchio::JointModelBase<JointModel> &jmodel, const Model &model,
                   Data &data, Eigen::VectorXd &h) {
    typedef typename pinocchio::SizeDepType<JointModel::NV>::template ColsReturn<
        Data::Matrix6x>::Type ColsBlock;
    const pinocchio::JointIndex i = jmodel.id();
    const pinocchio::JointIndex parent = model.parents[i];
    ColsBlock J_cols = jmodel.jointCols(data.J);
    jmodel.jointVelocitySelector(h).noalias() = J_cols.transpose() * data.of[i].toVector();
    data.oYcrb[parent] += data.oYcrb[i];
    data.of[parent] += data.of[i];
  }
};

}  // namespace stage_terms_detail

// M (full, symmetric, armature included) at the kinematics in data: tree_terms' M
// without the velocity pass; data.oYcrb left composite (as tree_terms leaves it).
inline void mass_at_kinematics(const TreePlan &plan, const pinocchio::Model &model,
                               pinocchio::Data &data, Eigen::MatrixXd &M) {
  using namespace stage_terms_detail;
  data.oYcrb[0].setZero();
  for (pinocchio::JointIndex i = 1; i < (pinocchio::JointIndex)model.njoints; ++i)
    data.oYcrb[i] = data.oMi[i].act(model.inertias[i]);
  for (pinocchio::JointIndex i = (pinocchio::JointIndex)(model.njoints - 1); i > 0; --i) {
    if (plan.revolute(i)) {  // tree_terms_detail::revolute_backward without h
      const pinocchio::JointIndex parent = model.parents[i];
      const Eigen::Index k = plan.rev(i).idx_v, n = data.nvSubtree[i];
      const Eigen::Matrix<double, 6, 1> Ji = data.J.col(k);
      data.Ag.col(k) = (data.oYcrb[i] * pinocchio::Motion(Ji)).toVector();
      for (Eigen::Index j = 0; j < n; ++j) M(k, k + j) = Ji.dot(data.Ag.col(k + j));
      data.oYcrb[parent] += data.oYcrb[i];
    } else {
      MassBackwardStep::run(model.joints[i], MassBackwardStep::ArgsType(model, data, M));
    }
  }
  M.diagonal() += model.armature;
  M.triangularView<Eigen::StrictlyLower>() = M.transpose();
}

// h = nonLinearEffects(q, v) and data.ov, data.oa, data.of at the kinematics in data
// (tree_terms_at_kinematics without M).
template <typename ConfigVectorType, typename TangentVectorType>
void bias_at_kinematics(const TreePlan &plan, const pinocchio::Model &model,
                        pinocchio::Data &data, const Eigen::MatrixBase<ConfigVectorType> &q,
                        const Eigen::MatrixBase<TangentVectorType> &v, Eigen::VectorXd &h) {
  tree_terms_detail::motion_pass(plan, model, data, q, v);
  for (pinocchio::JointIndex i = (pinocchio::JointIndex)(model.njoints - 1); i > 0; --i) {
    if (plan.revolute(i)) {  // tree_terms_detail::revolute_backward without M
      const pinocchio::JointIndex parent = model.parents[i];
      h[plan.rev(i).idx_v] = data.J.col(plan.rev(i).idx_v).dot(data.of[i].toVector());
      data.oYcrb[parent] += data.oYcrb[i];
      data.of[parent] += data.of[i];
    } else {
      stage_terms_detail::BiasBackwardStep::run(
          model.joints[i], stage_terms_detail::BiasBackwardStep::ArgsType(model, data, h));
    }
  }
}

}  // namespace closedchain
