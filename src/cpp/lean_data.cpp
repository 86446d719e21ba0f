// closedchain._core: a Pinocchio Data without the second-order derivative tensors.
//
// pinocchio::DataTpl(const Model&) in Pinocchio 4.1 (src/multibody/data.hxx)
// allocates and zeroes four nv x nv x nv tensors (d2tau_dqdq, d2tau_dvdv,
// d2tau_dqdv, d2tau_dadq: 32 nv^3 bytes; setZero() touches every page, so
// Linux overcommit does not help), used only by
// computeRNEASecondOrderDerivatives. A 1000-dof chain would need 32 GB for
// them. lean_data() builds the same Data member by member (a transcription of
// that constructor for the pinned pin 4.1.0, checked field by field against it
// by closedchain._core_testing._lean_data_matches_full) and leaves those four tensors empty: every other
// algorithm reads the same fields it would read in a full Data. Calling
// computeRNEASecondOrderDerivatives on it is undefined: closedchain never does.

#include "lean_data.hpp"

#include <pinocchio/multibody/data.hpp>
#include <pinocchio/multibody/model.hpp>
#include <pinocchio/algorithm/joint-configuration.hpp>

#include <algorithm>

// lastChild and contact_chol are deprecated members that Pinocchio still fills.
#pragma GCC diagnostic ignored "-Wdeprecated-declarations"

namespace closedchain {

namespace {

using Model = pinocchio::Model;
using Data = pinocchio::Data;
using Scalar = Data::Scalar;
using SE3 = Data::SE3;
using Motion = Data::Motion;
using Force = Data::Force;
using Inertia = Data::Inertia;
using MatrixXs = Data::MatrixXs;
using VectorXs = Data::VectorXs;
using RowVectorXs = Data::RowVectorXs;
using RowMatrixXs = Data::RowMatrixXs;
using Vector3 = Data::Vector3;
using Matrix3x = Data::Matrix3x;
using Matrix6x = Data::Matrix6x;
using Matrix6 = Data::Matrix6;
using MatrixXb = Data::MatrixXb;
using BodyRegressorType = Data::BodyRegressorType;
using pinocchio::neutral;
using JointModelMimic = pinocchio::JointModelMimicTpl<Scalar, 0, pinocchio::JointCollectionDefaultTpl>;

// Data::computeLastChild (private in Pinocchio).
void compute_last_child(const Model& model, Data& d) {
  std::fill(d.lastChild.begin(), d.lastChild.end(), -1);
  for (int i = model.njoints - 1; i >= 0; --i) {
    if (d.lastChild[(std::size_t)i] == -1) d.lastChild[(std::size_t)i] = i;
    const std::size_t parent = model.parents[(std::size_t)i];
    d.lastChild[parent] = std::max<int>(d.lastChild[(std::size_t)i], d.lastChild[parent]);
  }
}

// Data::computeNvSubtree (private in Pinocchio).
void compute_nv_subtree(const Model& model, Data& d) {
  for (int i = model.njoints - 1; i >= 0; --i) {
    const std::size_t parent = model.parents[(std::size_t)i];
    d.nvSubtree[(std::size_t)i] += model.joints[(std::size_t)i].nv();
    d.nvSubtree[parent] += d.nvSubtree[(std::size_t)i];
  }
  for (const auto mimicking_id : model.mimicking_joints) {
    const auto& sub = model.subtrees[mimicking_id];
    std::size_t j = 1;
    bool found = false;
    for (; j < sub.size(); j++) {
      if (model.nvs[sub[j]] != 0) {
        found = true;
        break;
      }
    }
    d.mimic_subtree_joint.push_back((sub.size() == 1 || !found) ? 0 : sub[j]);
  }
}

// Walk up from joint id while its mimic-ness equals skip_mimic (0 is the universe).
std::size_t walk_up(const Model& model, std::size_t id, bool skip_mimic) {
  while (id > 0 && (boost::get<JointModelMimic>(&model.joints[id]) != nullptr) == skip_mimic)
    id = model.parents[id];
  return id;
}

// Data::computeParents_fromRow (private in Pinocchio).
void compute_parents_from_row(const Model& model, Data& d) {
  for (std::size_t joint = 1; joint < (std::size_t)model.njoints; joint++) {
    const std::size_t parent = model.parents[joint];
    const int idx_vj = model.joints[joint].idx_v();
    const int nvx_j = model.joints[joint].nvExtended();
    const std::size_t ivx_j = (std::size_t)model.joints[joint].idx_vExtended();
    const auto row_end = [&](std::size_t id) {
      return id > 0 ? model.joints[id].idx_vExtended() + model.joints[id].nvExtended() - 1 : -1;
    };
    d.parents_fromRow[ivx_j] = row_end(parent);
    d.non_mimic_parents_fromRow[ivx_j] = row_end(walk_up(model, parent, true));
    d.mimic_parents_fromRow[ivx_j] = row_end(walk_up(model, parent, false));
    d.nvSubtree_fromRow[ivx_j] = d.nvSubtree[joint];
    d.start_idx_v_fromRow[(std::size_t)idx_vj] = idx_vj;
    d.end_idx_v_fromRow[(std::size_t)idx_vj] = idx_vj + nvx_j - 1;
    d.idx_vExtended_to_idx_v_fromRow[ivx_j] = idx_vj;
    for (int row = 1; row < nvx_j; ++row) {
      const std::size_t r = ivx_j + (std::size_t)row;
      d.parents_fromRow[r] = (int)r - 1;
      d.mimic_parents_fromRow[r] = (int)r - 1;
      d.non_mimic_parents_fromRow[r] = (int)r - 1;
      d.nvSubtree_fromRow[r] = d.nvSubtree[joint] - row;
      d.start_idx_v_fromRow[r] = d.start_idx_v_fromRow[ivx_j];
      d.end_idx_v_fromRow[r] = d.end_idx_v_fromRow[ivx_j];
      d.idx_vExtended_to_idx_v_fromRow[r] = d.idx_vExtended_to_idx_v_fromRow[ivx_j] + row;
    }
  }
}

// Data::computeSupports_fromRow (private in Pinocchio).
void compute_supports_from_row(const Model& model, Data& d) {
  for (std::size_t joint_id = 1; joint_id < (std::size_t)model.njoints; joint_id++) {
    const int nvj = model.joints[joint_id].nv();
    const int idx_vj = model.joints[joint_id].idx_v();
    const int parent_row = d.parents_fromRow[(std::size_t)idx_vj];
    if (parent_row >= 0)
      d.supports_fromRow[(std::size_t)idx_vj] = d.supports_fromRow[(std::size_t)parent_row];
    d.supports_fromRow[(std::size_t)idx_vj].push_back(idx_vj);
    for (int row = 1; row < nvj; ++row) {
      d.supports_fromRow[(std::size_t)(idx_vj + row)] = d.supports_fromRow[(std::size_t)(idx_vj + row - 1)];
      d.supports_fromRow[(std::size_t)(idx_vj + row)].push_back(idx_vj + row);
    }
  }
}

// The fields of the kinematics and the spatial quantities of the joints (q_in ... liMi).
void init_kinematics(const Model& model, Data& d) {
  d.q_in = decltype(d.q_in)(neutral(model));
  d.v_in = decltype(d.v_in)(VectorXs::Zero(model.nv));
  d.a_in = decltype(d.a_in)(VectorXs::Zero(model.nv));
  d.tau_in = decltype(d.tau_in)(VectorXs::Zero(model.nv));
  d.a = decltype(d.a)((std::size_t)model.njoints, Motion::Zero());
  d.oa = decltype(d.oa)((std::size_t)model.njoints, Motion::Zero());
  d.oa_drift = decltype(d.oa_drift)((std::size_t)model.njoints, Motion::Zero());
  d.oa_augmented = decltype(d.oa_augmented)((std::size_t)model.njoints, Motion::Zero());
  d.a_gf = decltype(d.a_gf)((std::size_t)model.njoints, Motion::Zero());
  d.oa_gf = decltype(d.oa_gf)((std::size_t)model.njoints, Motion::Zero());
  d.v = decltype(d.v)((std::size_t)model.njoints, Motion::Zero());
  d.ov = decltype(d.ov)((std::size_t)model.njoints, Motion::Zero());
  d.f = decltype(d.f)((std::size_t)model.njoints, Force::Zero());
  d.of = decltype(d.of)((std::size_t)model.njoints, Force::Zero());
  d.of_augmented = decltype(d.of_augmented)((std::size_t)model.njoints, Force::Zero());
  d.h = decltype(d.h)((std::size_t)model.njoints, Force::Zero());
  d.oh = decltype(d.oh)((std::size_t)model.njoints, Force::Zero());
  d.oMi = decltype(d.oMi)((std::size_t)model.njoints, SE3::Identity());
  d.liMi = decltype(d.liMi)((std::size_t)model.njoints, SE3::Identity());
}

// The fields of the dynamics: generalized forces, frames, CRBA, ABA and centroidal terms (tau ... Fcrb).
void init_dynamics(const Model& model, Data& d) {
  d.tau = decltype(d.tau)(VectorXs::Zero(model.nv));
  d.nle = decltype(d.nle)(VectorXs::Zero(model.nv));
  d.g = decltype(d.g)(VectorXs::Zero(model.nv));
  d.oMf = decltype(d.oMf)((std::size_t)model.nframes, SE3::Identity());
  d.Ycrb = decltype(d.Ycrb)((std::size_t)model.njoints, Inertia::Zero());
  d.dYcrb = decltype(d.dYcrb)((std::size_t)model.njoints, Inertia::Zero());
  d.M = decltype(d.M)(MatrixXs::Zero(model.nv, model.nv));
  d.Minv = decltype(d.Minv)(MatrixXs::Zero(model.nv, model.nv));
  d.C = decltype(d.C)(MatrixXs::Zero(model.nv, model.nv));
  d.dHdq = decltype(d.dHdq)(Matrix6x::Zero(6, model.nv));
  d.dFdq = decltype(d.dFdq)(Matrix6x::Zero(6, model.nv));
  d.dFdv = decltype(d.dFdv)(Matrix6x::Zero(6, model.nv));
  d.dFda = decltype(d.dFda)(Matrix6x::Zero(6, model.nv));
  d.SDinv = decltype(d.SDinv)(Matrix6x::Zero(6, model.nv));
  d.UDinv = decltype(d.UDinv)(Matrix6x::Zero(6, model.nv));
  d.IS = decltype(d.IS)(MatrixXs::Zero(6, model.nv));
  d.vxI = decltype(d.vxI)((std::size_t)model.njoints, Inertia::Matrix6::Zero());
  d.Ivx = decltype(d.Ivx)((std::size_t)model.njoints, Inertia::Matrix6::Zero());
  d.B = decltype(d.B)((std::size_t)model.njoints, Inertia::Matrix6::Zero());
  d.oinertias = decltype(d.oinertias)((std::size_t)model.njoints, Inertia::Zero());
  d.oYcrb = decltype(d.oYcrb)((std::size_t)model.njoints, Inertia::Zero());
  d.doYcrb = decltype(d.doYcrb)((std::size_t)model.njoints, Inertia::Matrix6::Zero());
  d.ddq = decltype(d.ddq)(VectorXs::Zero(model.nv));
  d.Yaba = decltype(d.Yaba)((std::size_t)model.njoints, Inertia::Matrix6::Zero());
  d.oYaba = decltype(d.oYaba)((std::size_t)model.njoints, Inertia::Matrix6::Zero());
  d.oYaba_augmented = decltype(d.oYaba_augmented)((std::size_t)model.njoints, Inertia::Matrix6::Zero());
  d.oL = decltype(d.oL)((std::size_t)model.njoints, Inertia::Matrix6::Zero());
  d.oK = decltype(d.oK)((std::size_t)model.njoints, Inertia::Matrix6::Zero());
  d.u = decltype(d.u)(VectorXs::Zero(model.nv));
  d.Ag = decltype(d.Ag)(Matrix6x::Zero(6, model.nv));
  d.dAg = decltype(d.dAg)(Matrix6x::Zero(6, model.nv));
  d.hg = decltype(d.hg)(Force::Zero());
  d.dhg = decltype(d.dhg)(Force::Zero());
  d.Ig = decltype(d.Ig)(Inertia::Zero());
  d.Fcrb = decltype(d.Fcrb)((std::size_t)model.njoints, Matrix6x::Zero(6, model.nv));
}

// The fields of the index maps of the tree and its rows (lastChild ... nvSubtree_fromRow).
void init_tree_indices(const Model& model, Data& d) {
  d.lastChild = decltype(d.lastChild)((std::size_t)model.njoints, -1);
  d.nvSubtree = decltype(d.nvSubtree)((std::size_t)model.njoints, 0);
  d.start_idx_v_fromRow = decltype(d.start_idx_v_fromRow)((std::size_t)model.nvExtended, -1);
  d.end_idx_v_fromRow = decltype(d.end_idx_v_fromRow)((std::size_t)model.nvExtended, -1);
  d.idx_vExtended_to_idx_v_fromRow = decltype(d.idx_vExtended_to_idx_v_fromRow)((std::size_t)model.nvExtended, -1);
  d.U = decltype(d.U)(MatrixXs::Identity(model.nv, model.nv));
  d.D = decltype(d.D)(VectorXs::Zero(model.nv));
  d.Dinv = decltype(d.Dinv)(VectorXs::Zero(model.nv));
  d.tmp = decltype(d.tmp)(VectorXs::Zero(model.nv));
  d.parents_fromRow = decltype(d.parents_fromRow)((std::size_t)model.nvExtended, -1);
  d.mimic_parents_fromRow = decltype(d.mimic_parents_fromRow)((std::size_t)model.nvExtended, -1);
  d.non_mimic_parents_fromRow = decltype(d.non_mimic_parents_fromRow)((std::size_t)model.nvExtended, -1);
  d.supports_fromRow = decltype(d.supports_fromRow)((std::size_t)model.nv);
  d.nvSubtree_fromRow = decltype(d.nvSubtree_fromRow)((std::size_t)model.nvExtended, -1);
}

// The fields of Jacobians, their derivatives and the first-order dynamics derivatives, centre of mass and energies (J ... mechanical_energy).
void init_derivatives(const Model& model, Data& d) {
  d.J = decltype(d.J)(Matrix6x::Zero(6, model.nvExtended));
  d.dJ = decltype(d.dJ)(Matrix6x::Zero(6, model.nvExtended));
  d.ddJ = decltype(d.ddJ)(Matrix6x::Zero(6, model.nvExtended));
  d.psid = decltype(d.psid)(Matrix6x::Zero(6, model.nv));
  d.psidd = decltype(d.psidd)(Matrix6x::Zero(6, model.nv));
  d.dVdq = decltype(d.dVdq)(Matrix6x::Zero(6, model.nv));
  d.dAdq = decltype(d.dAdq)(Matrix6x::Zero(6, model.nv));
  d.dAdv = decltype(d.dAdv)(Matrix6x::Zero(6, model.nv));
  d.dtau_dq = decltype(d.dtau_dq)(RowMatrixXs::Zero(model.nv, model.nv));
  d.dtau_dv = decltype(d.dtau_dv)(RowMatrixXs::Zero(model.nv, model.nv));
  d.ddq_dq = decltype(d.ddq_dq)(RowMatrixXs::Zero(model.nv, model.nv));
  d.ddq_dv = decltype(d.ddq_dv)(RowMatrixXs::Zero(model.nv, model.nv));
  d.ddq_dtau = decltype(d.ddq_dtau)(RowMatrixXs::Zero(model.nv, model.nv));
  d.iMf = decltype(d.iMf)((std::size_t)model.njoints, SE3::Identity());
  d.com = decltype(d.com)((std::size_t)model.njoints, Vector3::Zero());
  d.vcom = decltype(d.vcom)((std::size_t)model.njoints, Vector3::Zero());
  d.acom = decltype(d.acom)((std::size_t)model.njoints, Vector3::Zero());
  d.mass = decltype(d.mass)((std::size_t)model.njoints, (Scalar)(-1));
  d.Jcom = decltype(d.Jcom)(Matrix3x::Zero(3, model.nv));
  d.kinetic_energy = decltype(d.kinetic_energy)(Scalar(0));
  d.potential_energy = decltype(d.potential_energy)(Scalar(0));
  d.mechanical_energy = decltype(d.mechanical_energy)(Scalar(0));
}

// The fields of the contact and constraint quantities (JMinvJt ... impulse_c).
void init_contacts(const Model& model, Data& d) {
  d.JMinvJt = decltype(d.JMinvJt)();
  d.llt_JMinvJt = decltype(d.llt_JMinvJt)();
  d.lambda_c = decltype(d.lambda_c)();
  d.lambda_c_prox = decltype(d.lambda_c_prox)();
  d.diff_lambda_c = decltype(d.diff_lambda_c)();
  d.sDUiJt = decltype(d.sDUiJt)(MatrixXs::Zero(model.nv, model.nv));
  d.torque_residual = decltype(d.torque_residual)(VectorXs::Zero(model.nv));
  d.dq_after = decltype(d.dq_after)(VectorXs::Zero(model.nv));
  d.impulse_c = decltype(d.impulse_c)();
}

// The fields of the regressors (staticRegressor ... potentialEnergyRegressor).
void init_regressors(const Model& model, Data& d) {
  d.staticRegressor = decltype(d.staticRegressor)(Matrix3x::Zero(3, 4 * (model.njoints - 1)));
  d.bodyRegressor = decltype(d.bodyRegressor)(BodyRegressorType::Zero());
  d.jointTorqueRegressor = decltype(d.jointTorqueRegressor)(MatrixXs::Zero(model.nv, 10 * (model.njoints - 1)));
  d.kineticEnergyRegressor = decltype(d.kineticEnergyRegressor)(RowVectorXs::Zero(10 * (model.njoints - 1)));
  d.potentialEnergyRegressor = decltype(d.potentialEnergyRegressor)(RowVectorXs::Zero(10 * (model.njoints - 1)));
}

// The fields of the constrained-dynamics solver's quantities (KA ... joint_apparent_inertia).
void init_constraint_solver(const Model& model, Data& d) {
  d.KA = decltype(d.KA)((std::size_t)model.njoints, Matrix6x::Zero(6, 0));
  d.LA = decltype(d.LA)((std::size_t)model.njoints, MatrixXs::Zero(0, 0));
  d.lA = decltype(d.lA)((std::size_t)model.njoints, VectorXs::Zero(0));
  d.lambdaA = decltype(d.lambdaA)((std::size_t)model.njoints, VectorXs::Zero(0));
  d.par_cons_ind = decltype(d.par_cons_ind)((std::size_t)model.njoints, 0);
  d.a_bias = decltype(d.a_bias)((std::size_t)model.njoints, Motion::Zero());
  d.KAS = decltype(d.KAS)((std::size_t)model.njoints, MatrixXs::Zero(0, 0));
  d.kinematic_hessians = decltype(d.kinematic_hessians)(6, model.nv, model.nv);
  d.constraint_chol = decltype(d.constraint_chol)();
  d.contact_chol = d.constraint_chol;  // the deprecated alias, a copy as in Pinocchio
  d.extended_motion_propagator = decltype(d.extended_motion_propagator)((std::size_t)model.njoints, Matrix6::Zero());
  d.extended_motion_propagator2 = decltype(d.extended_motion_propagator2)((std::size_t)model.njoints, Matrix6::Zero());
  d.spatial_inv_inertia = decltype(d.spatial_inv_inertia)((std::size_t)model.njoints, Matrix6::Zero());
  d.accumulation_descendant = decltype(d.accumulation_descendant)((std::size_t)model.njoints, 0);
  d.accumulation_ancestor = decltype(d.accumulation_ancestor)((std::size_t)model.njoints, 0);
  d.constraints_supported_dim = decltype(d.constraints_supported_dim)((std::size_t)model.njoints, 0);
  d.constraints_supported = decltype(d.constraints_supported)((std::size_t)model.njoints);
  d.constraints_on_joint = decltype(d.constraints_on_joint)((std::size_t)model.njoints);
  d.joint_neighbours = decltype(d.joint_neighbours)((std::size_t)model.njoints);
  d.joint_cross_coupling = decltype(d.joint_cross_coupling)(model.njoints, model.njoints);
  d.joint_coupling_info = decltype(d.joint_coupling_info)(MatrixXb::Zero(model.njoints, model.njoints));
  d.projected_joint_cross_coupling = decltype(d.projected_joint_cross_coupling)(model.njoints, model.njoints);
  d.joint_apparent_inertia = decltype(d.joint_apparent_inertia)(std::size_t(model.njoints), std::size_t(PINOCCHIO_SQUARE(*std::max_element(model.nvs.begin(), model.nvs.end()))));
}

// The constructor's body: the joints' data, the zeroed matrices and the index maps.
void init_joints(const Model& model, Data& d) {
  d.joints.reserve((std::size_t)model.njoints);
  for (std::size_t i = 0; i < (std::size_t)model.njoints; ++i) {
    d.joints.push_back(model.joints[i].createData());
    const auto joint_nv = model.nvs[i];
    d.joint_apparent_inertia.push_back(joint_nv, joint_nv);
    d.joint_apparent_inertia.back().setZero();
  }
  d.joints_augmented = d.joints;
  d.M.setZero();
  d.Minv.setZero();
  compute_last_child(model, d);
  compute_nv_subtree(model, d);
  compute_parents_from_row(model, d);
  compute_supports_from_row(model, d);
  d.a_gf[0] = -model.gravity;
  d.kinematic_hessians.setZero();

}

}  // namespace

Data lean_data(const Model& model) {
  Data d;
  // The member initializer list of DataTpl(const Model&), in its order, then its body.
  init_kinematics(model, d);
  init_dynamics(model, d);
  init_tree_indices(model, d);
  init_derivatives(model, d);
  init_contacts(model, d);
  init_regressors(model, d);
  init_constraint_solver(model, d);
  init_joints(model, d);
  return d;
}

}  // namespace closedchain
