// closedchain._core: M, h, the joints' world placements, world Jacobian columns,
// spatial velocities and bias accelerations of a kinematic tree in one forward and
// one backward pass (included by core.cpp: the only translation unit that
// instantiates Pinocchio's algorithms).
//
// Pinocchio's crba (WORLD convention) and nonLinearEffects each run their own
// forward pass with its own joint calc (sin/cos), and the frames' bias
// accelerations then need a third quantity (a_gf minus gravity). Here one pass
// per joint i, every quantity in the world frame (Featherstone, Rigid Body
// Dynamics Algorithms, 2008, sections 5.3 and 6.2; Pinocchio's computeAllTerms
// in the same convention):
//   forward, with (S_i, v_J, c_J) of joint i's calc(q, v) and X_i = oMi:
//     J_i   = X_i S_i                              (world Jacobian columns, data.J)
//     ov_i  = ov_parent + X_i v_J                  (spatial velocity, data.ov)
//     oa_i  = oa_parent + X_i c_J + ov_i x X_i v_J (bias acceleration at a = 0, data.oa)
//     oY_i  = X_i I_i                              (body inertia, data.oYcrb)
//     of_i  = oY_i (oa_i - g) + ov_i x* (oY_i ov_i)   (data.of)
//   backward (children first):
//     M[i, subtree(i)] = J_i^T oY_i J_subtree,   h_i = J_i^T of_i,
//     oY_parent += oY_i,   of_parent += of_i,
// and the armature on M's diagonal (as pinocchio::crba). M and h agree with
// crba + nonLinearEffects to round-off; mimic joints are not supported (the
// loader never makes them; the Core refuses such models).

#pragma once

#include <pinocchio/multibody/data.hpp>
#include <pinocchio/multibody/model.hpp>
#include <pinocchio/multibody/visitor.hpp>
#include <pinocchio/spatial/act-on-set.hpp>

#include <type_traits>

namespace closedchain {
namespace tree_terms_detail {

using Model = pinocchio::Model;
using Data = pinocchio::Data;

// The velocity-dependent quantities of joint i (world frame) from its calc's v_J and
// c_J and its placement data.oMi[i]: ov, oa, oYcrb, of (the formulas above).
template <typename JointData>
inline void forward_motion(const pinocchio::JointDataBase<JointData> &jdata, const Model &model,
                           Data &data, pinocchio::JointIndex i) {
  const pinocchio::JointIndex parent = model.parents[i];
  const pinocchio::SE3 &oMi = data.oMi[i];
  const pinocchio::Motion ovJ = oMi.act(jdata.v());
  data.ov[i] = data.ov[parent] + ovJ;
  data.oa[i] = data.oa[parent] + oMi.act(jdata.c()) + (data.ov[i] ^ ovJ);
  data.oYcrb[i] = oMi.act(model.inertias[i]);
  const pinocchio::Force oh = data.oYcrb[i] * data.ov[i];
  data.of[i] = data.oYcrb[i] * (data.oa[i] - model.gravity) + data.ov[i].cross(oh);
}

template <typename ConfigVectorType, typename TangentVectorType>
struct ForwardStep
    : public pinocchio::fusion::JointUnaryVisitorBase<
          ForwardStep<ConfigVectorType, TangentVectorType>> {
  typedef boost::fusion::vector<const Model &, Data &, const ConfigVectorType &,
                                const TangentVectorType &>
      ArgsType;

  template <typename JointModel>
  static void algo(const pinocchio::JointModelBase<JointModel> &jmodel,
                   pinocchio::JointDataBase<typename JointModel::JointDataDerived> &jdata,
                   const Model &model, Data &data,
                   const Eigen::MatrixBase<ConfigVectorType> &q,
                   const Eigen::MatrixBase<TangentVectorType> &v) {
    typedef typename pinocchio::SizeDepType<JointModel::NV>::template ColsReturn<
        Data::Matrix6x>::Type ColsBlock;
    const pinocchio::JointIndex i = jmodel.id();
    const pinocchio::JointIndex parent = model.parents[i];
    jmodel.calc(jdata.derived(), q.derived(), v.derived());
    data.liMi[i] = model.jointPlacements[i] * jdata.M();
    if (parent > 0)
      data.oMi[i] = data.oMi[parent] * data.liMi[i];
    else
      data.oMi[i] = data.liMi[i];
    ColsBlock J_cols = jmodel.jointCols(data.J);
    J_cols = data.oMi[i].act(jdata.S());
    forward_motion(jdata, model, data, i);
  }
};

// The velocity-dependent part of ForwardStep at (q, v) when the kinematics at q
// (calc(q), liMi, oMi, J: pinocchio::computeJointJacobians(q)) are already in data:
// the joint's velocity from calc(Blank, v) where its bias c is structurally zero
// (revolute, prismatic, helical, planar, spherical, translation, free-flyer: v_J
// = S qdot, the same arithmetic as calc(q, v)), else from the full calc(q, v) (c
// depends on q and v: spherical-ZYX, universal, ellipsoid, composite).
template <typename ConfigVectorType, typename TangentVectorType>
struct MotionStep
    : public pinocchio::fusion::JointUnaryVisitorBase<
          MotionStep<ConfigVectorType, TangentVectorType>> {
  typedef boost::fusion::vector<const Model &, Data &, const ConfigVectorType &,
                                const TangentVectorType &>
      ArgsType;

  template <typename JointModel>
  static void algo(const pinocchio::JointModelBase<JointModel> &jmodel,
                   pinocchio::JointDataBase<typename JointModel::JointDataDerived> &jdata,
                   const Model &model, Data &data,
                   const Eigen::MatrixBase<ConfigVectorType> &q,
                   const Eigen::MatrixBase<TangentVectorType> &v) {
    typedef typename pinocchio::traits<typename JointModel::JointDerived>::Bias_t Bias;
    if constexpr (std::is_same<Bias, pinocchio::MotionZeroTpl<double, 0>>::value)
      jmodel.calc(jdata.derived(), pinocchio::Blank(), v.derived());
    else
      jmodel.calc(jdata.derived(), q.derived(), v.derived());
    forward_motion(jdata, model, data, jmodel.id());
  }
};

struct BackwardStep : public pinocchio::fusion::JointUnaryVisitorBase<BackwardStep> {
  typedef boost::fusion::vector<const Model &, Data &, Eigen::MatrixXd &, Eigen::VectorXd &>
      ArgsType;

  template <typename JointModel>
  static void algo(const pinocchio::JointModelBase<JointModel> &jmodel, const Model &model,
                   Data &data, Eigen::MatrixXd &M, Eigen::VectorXd &h) {
    typedef typename pinocchio::SizeDepType<JointModel::NV>::template ColsReturn<
        Data::Matrix6x>::Type ColsBlock;
    const pinocchio::JointIndex i = jmodel.id();
    const pinocchio::JointIndex parent = model.parents[i];
    ColsBlock J_cols = jmodel.jointCols(data.J);
    ColsBlock Ag_cols = jmodel.jointCols(data.Ag);
    pinocchio::motionSet::inertiaAction(data.oYcrb[i], J_cols, Ag_cols);
    M.block(jmodel.idx_v(), jmodel.idx_v(), jmodel.nv(), data.nvSubtree[i]).noalias() =
        J_cols.transpose() * data.Ag.middleCols(jmodel.idx_v(), data.nvSubtree[i]);
    jmodel.jointVelocitySelector(h).noalias() = J_cols.transpose() * data.of[i].toVector();
    data.oYcrb[parent] += data.oYcrb[i];
    data.of[parent] += data.of[i];
  }
};

// The root's quantities before the forward pass.
inline void start(Data &data) {
  data.ov[0].setZero();
  data.oa[0].setZero();
  data.oYcrb[0].setZero();
  data.of[0].setZero();
}

// The backward pass after the forward one: M (armature on the diagonal, both
// triangles) and h.
inline void backward(const Model &model, Data &data, Eigen::MatrixXd &M, Eigen::VectorXd &h) {
  for (pinocchio::JointIndex i = (pinocchio::JointIndex)(model.njoints - 1); i > 0; --i)
    BackwardStep::run(model.joints[i], BackwardStep::ArgsType(model, data, M, h));
  M.diagonal() += model.armature;
  M.triangularView<Eigen::StrictlyLower>() = M.transpose();
}

}  // namespace tree_terms_detail

// M (full, symmetric) and h = nonLinearEffects(q, v) into M, h; data.oMi, data.J
// (world columns), data.ov and data.oa (bias accelerations, a = 0, gravity
// excluded) of every joint. M: (nv, nv), h: (nv,), sized by the caller.
template <typename ConfigVectorType, typename TangentVectorType>
void tree_terms(const pinocchio::Model &model, pinocchio::Data &data,
                const Eigen::MatrixBase<ConfigVectorType> &q,
                const Eigen::MatrixBase<TangentVectorType> &v, Eigen::MatrixXd &M,
                Eigen::VectorXd &h) {
  using namespace tree_terms_detail;
  start(data);
  typedef ForwardStep<ConfigVectorType, TangentVectorType> Pass1;
  for (pinocchio::JointIndex i = 1; i < (pinocchio::JointIndex)model.njoints; ++i)
    Pass1::run(model.joints[i], data.joints[i],
               typename Pass1::ArgsType(model, data, q.derived(), v.derived()));
  backward(model, data, M, h);
}

// tree_terms(q, v) when data already holds the kinematics at q (calc(q), liMi,
// oMi and J of pinocchio::computeJointJacobians(model, data, q), e.g. the last
// Newton iterate of the dependent-coordinate solve): the velocity-dependent
// forward quantities and the backward pass only; the same M, h, ov, oa.
template <typename ConfigVectorType, typename TangentVectorType>
void tree_terms_at_kinematics(const pinocchio::Model &model, pinocchio::Data &data,
                              const Eigen::MatrixBase<ConfigVectorType> &q,
                              const Eigen::MatrixBase<TangentVectorType> &v,
                              Eigen::MatrixXd &M, Eigen::VectorXd &h) {
  using namespace tree_terms_detail;
  start(data);
  typedef MotionStep<ConfigVectorType, TangentVectorType> Pass1;
  for (pinocchio::JointIndex i = 1; i < (pinocchio::JointIndex)model.njoints; ++i)
    Pass1::run(model.joints[i], data.joints[i],
               typename Pass1::ArgsType(model, data, q.derived(), v.derived()));
  backward(model, data, M, h);
}

}  // namespace closedchain
