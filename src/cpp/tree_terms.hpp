// closedchain._core: M, h, the joints' world placements, world Jacobian columns,
// spatial velocities and bias accelerations of a kinematic tree in one forward and
// one backward pass (included by expose-core.cpp, the production module's only
// translation unit that instantiates Pinocchio's algorithms, and by expose-testing.cpp).
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
//
// Revolute joints (JointModelRX/RY/RZ and RevoluteUnaligned: one angle q, a unit
// axis a fixed in the joint frame) take a path written for that case (TreePlan);
// every other joint type keeps Pinocchio's visitor (calc of its JointModel), so
// a mixed tree runs both, joint by joint, on the same Data fields. Per revolute
// joint, with the joint placement (Rp, pp) in its parent and one sincos:
//   liMi.R = Rp R(a, q) = A2 + cos q A0 + sin q A1   (Rodrigues; A0 = Rp - A2,
//            A1 = Rp [a]x, A2 = (Rp a) a^T, made once),   liMi.p = pp,
//   oMi    = oMi_parent liMi,   J_i = (p_i x w_i, w_i) with w_i = R_parent (Rp a),
//   ov_i = ov_parent + J_i qdot,   oa_i = oa_parent + ov_i x J_i qdot   (c_J = 0),
// and in the backward pass Ag_i = oY_i J_i and M[i, subtree(i)] = J_i . Ag columns
// (6-vector dot products; no dynamic-size block product).

#pragma once

#include <pinocchio/multibody/data.hpp>
#include <pinocchio/multibody/model.hpp>
#include <pinocchio/multibody/visitor.hpp>
#include <pinocchio/spatial/act-on-set.hpp>

#include <pinocchio/math/sincos.hpp>

#include <string>
#include <type_traits>
#include <vector>

namespace closedchain {

// Which joints of a model take the revolute path, and their constants.
class TreePlan {
 public:
  struct Revolute {
    int idx_q = 0, idx_v = 0;
    Eigen::Matrix3d A0, A1, A2;  // liMi.R = A2 + cos q A0 + sin q A1
    Eigen::Vector3d b;           // Rp a: the axis in the parent joint's frame
    Eigen::Vector3d pp;          // the joint placement's translation
  };

  TreePlan() = default;
  explicit TreePlan(const pinocchio::Model &model)
      : revolute_(model.joints.size(), 0), rev_(model.joints.size()) {
    for (std::size_t i = 1; i < model.joints.size(); ++i) {
      const auto &jm = model.joints[i];
      const std::string name = jm.shortname();
      Eigen::Vector3d a;
      if (name == "JointModelRX")
        a = Eigen::Vector3d::UnitX();
      else if (name == "JointModelRY")
        a = Eigen::Vector3d::UnitY();
      else if (name == "JointModelRZ")
        a = Eigen::Vector3d::UnitZ();
      else if (name == "JointModelRevoluteUnaligned")
        a = boost::get<pinocchio::JointModelRevoluteUnaligned>(jm.toVariant()).axis;
      else
        continue;
      Revolute &r = rev_[i];
      r.idx_q = jm.idx_q();
      r.idx_v = jm.idx_v();
      const Eigen::Matrix3d &Rp = model.jointPlacements[i].rotation();
      Eigen::Matrix3d ax;
      ax << 0.0, -a.z(), a.y(), a.z(), 0.0, -a.x(), -a.y(), a.x(), 0.0;
      r.b = Rp * a;
      r.A2 = r.b * a.transpose();
      r.A0 = Rp - r.A2;
      r.A1 = Rp * ax;
      r.pp = model.jointPlacements[i].translation();
      revolute_[i] = 1;
    }
  }

  bool revolute(std::size_t i) const { return revolute_[i] != 0; }
  const Revolute &rev(std::size_t i) const { return rev_[i]; }

 private:
  std::vector<char> revolute_;
  std::vector<Revolute> rev_;
};

namespace tree_terms_detail {

using Model = pinocchio::Model;
using Data = pinocchio::Data;
using Vec3 = Eigen::Vector3d;

// Revolute joint i at q: liMi, oMi and its world Jacobian column data.J.col(idx_v).
template <typename ConfigVectorType>
inline void revolute_kinematics(const TreePlan::Revolute &r, const Model &model, Data &data,
                                pinocchio::JointIndex i,
                                const Eigen::MatrixBase<ConfigVectorType> &q) {
  double s, c;
  pinocchio::SINCOS(q[r.idx_q], &s, &c);
  pinocchio::SE3 &li = data.liMi[i], &oi = data.oMi[i];
  li.rotation() = r.A2 + c * r.A0 + s * r.A1;
  li.translation() = r.pp;
  const pinocchio::JointIndex parent = model.parents[i];
  Vec3 w;
  if (parent > 0) {
    const pinocchio::SE3 &op = data.oMi[parent];
    oi.rotation().noalias() = op.rotation() * li.rotation();
    oi.translation() = op.translation();
    oi.translation().noalias() += op.rotation() * r.pp;
    w.noalias() = op.rotation() * r.b;
  } else {
    oi.rotation() = li.rotation();
    oi.translation() = r.pp;
    w = r.b;
  }
  auto col = data.J.col(r.idx_v);
  col.head<3>() = oi.translation().cross(w);
  col.tail<3>() = w;
}

// Revolute joint i at (q, v) after revolute_kinematics: ov, oa, oYcrb, of.
template <typename TangentVectorType>
inline void revolute_motion(const TreePlan::Revolute &r, const Model &model, Data &data,
                            pinocchio::JointIndex i,
                            const Eigen::MatrixBase<TangentVectorType> &v) {
  const pinocchio::JointIndex parent = model.parents[i];
  const double qd = v[r.idx_v];
  const pinocchio::Motion vJ(Eigen::Matrix<double, 6, 1>(data.J.col(r.idx_v) * qd));
  pinocchio::Motion &ov = data.ov[i], &oa = data.oa[i];
  ov = data.ov[parent] + vJ;
  oa = data.oa[parent] + (ov ^ vJ);
  pinocchio::Inertia &oY = data.oYcrb[i];
  oY = data.oMi[i].act(model.inertias[i]);
  const pinocchio::Force oh = oY * ov;
  data.of[i] = oY * (oa - model.gravity) + ov.cross(oh);
}

// Revolute joint i of the backward pass: Ag column and row i of M over its subtree
// (WithM), h_i (WithH), and the parent's composite inertia (always) and force (WithH).
template <bool WithM, bool WithH>
inline void revolute_backward(const TreePlan::Revolute &r, const Model &model, Data &data,
                              pinocchio::JointIndex i, Eigen::MatrixXd &M, Eigen::VectorXd &h) {
  const pinocchio::JointIndex parent = model.parents[i];
  const Eigen::Index k = r.idx_v, n = data.nvSubtree[i];
  const Eigen::Matrix<double, 6, 1> Ji = data.J.col(k);
  if constexpr (WithM) {
    data.Ag.col(k) = (data.oYcrb[i] * pinocchio::Motion(Ji)).toVector();
    for (Eigen::Index j = 0; j < n; ++j) M(k, k + j) = Ji.dot(data.Ag.col(k + j));
  }
  if constexpr (WithH) h[k] = Ji.dot(data.of[i].toVector());
  data.oYcrb[parent] += data.oYcrb[i];
  if constexpr (WithH) data.of[parent] += data.of[i];
}

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

// Joint i's placements and world Jacobian columns from its calc (jdata.M(), S):
// liMi, oMi = oMi_parent liMi, J_i = oMi S (after calc(q) or calc(q, v)).
template <typename JointModel>
inline void place_joint(const pinocchio::JointModelBase<JointModel> &jmodel,
                        const pinocchio::JointDataBase<typename JointModel::JointDataDerived> &jdata,
                        const Model &model, Data &data) {
  typedef typename pinocchio::SizeDepType<JointModel::NV>::template ColsReturn<
      Data::Matrix6x>::Type ColsBlock;
  const pinocchio::JointIndex i = jmodel.id();
  const pinocchio::JointIndex parent = model.parents[i];
  data.liMi[i] = model.jointPlacements[i] * jdata.M();
  if (parent > 0)
    data.oMi[i] = data.oMi[parent] * data.liMi[i];
  else
    data.oMi[i] = data.liMi[i];
  ColsBlock J_cols = jmodel.jointCols(data.J);
  J_cols = data.oMi[i].act(jdata.S());
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
    jmodel.calc(jdata.derived(), q.derived(), v.derived());
    place_joint(jmodel, jdata, model, data);
    forward_motion(jdata, model, data, jmodel.id());
  }
};

// ForwardStep without the velocity part: calc(q), liMi, oMi, J (the kinematics of
// pinocchio::computeJointJacobians(q)).
template <typename ConfigVectorType>
struct KinematicsStep
    : public pinocchio::fusion::JointUnaryVisitorBase<KinematicsStep<ConfigVectorType>> {
  typedef boost::fusion::vector<const Model &, Data &, const ConfigVectorType &> ArgsType;

  template <typename JointModel>
  static void algo(const pinocchio::JointModelBase<JointModel> &jmodel,
                   pinocchio::JointDataBase<typename JointModel::JointDataDerived> &jdata,
                   const Model &model, Data &data,
                   const Eigen::MatrixBase<ConfigVectorType> &q) {
    jmodel.calc(jdata.derived(), q.derived());
    place_joint(jmodel, jdata, model, data);
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

template <bool WithM, bool WithH>
struct BackwardStep
    : public pinocchio::fusion::JointUnaryVisitorBase<BackwardStep<WithM, WithH>> {
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
    if constexpr (WithM) {
      ColsBlock Ag_cols = jmodel.jointCols(data.Ag);
      pinocchio::motionSet::inertiaAction(data.oYcrb[i], J_cols, Ag_cols);
      M.block(jmodel.idx_v(), jmodel.idx_v(), jmodel.nv(), data.nvSubtree[i]).noalias() =
          J_cols.transpose() * data.Ag.middleCols(jmodel.idx_v(), data.nvSubtree[i]);
    }
    if constexpr (WithH)
      jmodel.jointVelocitySelector(h).noalias() = J_cols.transpose() * data.of[i].toVector();
    data.oYcrb[parent] += data.oYcrb[i];
    if constexpr (WithH) data.of[parent] += data.of[i];
  }
};

// The root's quantities before the forward pass.
inline void start(Data &data) {
  data.ov[0].setZero();
  data.oa[0].setZero();
  data.oYcrb[0].setZero();
  data.of[0].setZero();
}

// The velocity-dependent forward pass (ov, oa, oYcrb, of of every joint, from the
// root) when data holds the kinematics at q (joint_kinematics): revolute joints by
// their own path, the others by Pinocchio's visitor (MotionStep).
template <typename ConfigVectorType, typename TangentVectorType>
inline void motion_pass(const TreePlan &plan, const Model &model, Data &data,
                        const Eigen::MatrixBase<ConfigVectorType> &q,
                        const Eigen::MatrixBase<TangentVectorType> &v) {
  start(data);
  typedef MotionStep<ConfigVectorType, TangentVectorType> Pass1;
  for (pinocchio::JointIndex i = 1; i < (pinocchio::JointIndex)model.njoints; ++i) {
    if (plan.revolute(i))
      revolute_motion(plan.rev(i), model, data, i, v);
    else
      Pass1::run(model.joints[i], data.joints[i],
                 typename Pass1::ArgsType(model, data, q.derived(), v.derived()));
  }
}

// The backward pass after the forward one: M (armature on the diagonal, both
// triangles; WithM) and h (WithH); the composite inertias always (the potential
// energy reads data.oYcrb[0]). The argument not asked for is not touched.
template <bool WithM = true, bool WithH = true>
inline void backward(const TreePlan &plan, const Model &model, Data &data, Eigen::MatrixXd &M,
                     Eigen::VectorXd &h) {
  typedef BackwardStep<WithM, WithH> Step;
  for (pinocchio::JointIndex i = (pinocchio::JointIndex)(model.njoints - 1); i > 0; --i) {
    if (plan.revolute(i))
      revolute_backward<WithM, WithH>(plan.rev(i), model, data, i, M, h);
    else
      Step::run(model.joints[i], typename Step::ArgsType(model, data, M, h));
  }
  if constexpr (WithM) {
    M.diagonal() += model.armature;
    M.triangularView<Eigen::StrictlyLower>() = M.transpose();
  }
}

}  // namespace tree_terms_detail

// M (full, symmetric) and h = nonLinearEffects(q, v) into M, h; data.oMi, data.J
// (world columns), data.ov and data.oa (bias accelerations, a = 0, gravity
// excluded) of every joint. M: (nv, nv), h: (nv,), sized by the caller.
// plan: TreePlan(model).
template <typename ConfigVectorType, typename TangentVectorType>
void tree_terms(const TreePlan &plan, const pinocchio::Model &model, pinocchio::Data &data,
                const Eigen::MatrixBase<ConfigVectorType> &q,
                const Eigen::MatrixBase<TangentVectorType> &v, Eigen::MatrixXd &M,
                Eigen::VectorXd &h) {
  using namespace tree_terms_detail;
  start(data);
  typedef ForwardStep<ConfigVectorType, TangentVectorType> Pass1;
  for (pinocchio::JointIndex i = 1; i < (pinocchio::JointIndex)model.njoints; ++i) {
    if (plan.revolute(i)) {
      revolute_kinematics(plan.rev(i), model, data, i, q);
      revolute_motion(plan.rev(i), model, data, i, v);
    } else {
      Pass1::run(model.joints[i], data.joints[i],
                 typename Pass1::ArgsType(model, data, q.derived(), v.derived()));
    }
  }
  backward(plan, model, data, M, h);
}

// The kinematics at q: liMi, oMi and the world Jacobian columns data.J of every
// joint (what pinocchio::computeJointJacobians(q) computes, the revolute joints by
// the same arithmetic as tree_terms, so the two passes give the same placements).
// only (optional, one flag per joint): recompute only the flagged joints, the others
// keep what data holds (valid when data holds the kinematics at a q that agrees with
// this q on every coordinate of the unflagged joints' supports: the caller's check).
template <typename ConfigVectorType>
void joint_kinematics(const TreePlan &plan, const pinocchio::Model &model,
                      pinocchio::Data &data, const Eigen::MatrixBase<ConfigVectorType> &q,
                      const std::vector<char> *only = nullptr) {
  using namespace tree_terms_detail;
  typedef KinematicsStep<ConfigVectorType> Pass;
  for (pinocchio::JointIndex i = 1; i < (pinocchio::JointIndex)model.njoints; ++i) {
    if (only && !(*only)[i]) continue;
    if (plan.revolute(i))
      revolute_kinematics(plan.rev(i), model, data, i, q);
    else
      Pass::run(model.joints[i], data.joints[i],
                typename Pass::ArgsType(model, data, q.derived()));
  }
}

// tree_terms(q, v) when data already holds the kinematics at q (calc(q), liMi,
// oMi and J of joint_kinematics(plan, model, data, q), e.g. the last
// Newton iterate of the dependent-coordinate solve): the velocity-dependent
// forward quantities and the backward pass only; the same M, h, ov, oa.
template <typename ConfigVectorType, typename TangentVectorType>
void tree_terms_at_kinematics(const TreePlan &plan, const pinocchio::Model &model,
                              pinocchio::Data &data,
                              const Eigen::MatrixBase<ConfigVectorType> &q,
                              const Eigen::MatrixBase<TangentVectorType> &v,
                              Eigen::MatrixXd &M, Eigen::VectorXd &h) {
  tree_terms_detail::motion_pass(plan, model, data, q, v);
  tree_terms_detail::backward(plan, model, data, M, h);
}

}  // namespace closedchain
