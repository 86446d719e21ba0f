// closedchain._core: the constraint rows: cut frames, their placements and motion, phi,
// J, gamma, and the evaluation of the tree terms.
// (Functions over (CoreModel, CoreData): their declarations, then their definitions.)

#pragma once

#include <pinocchio/algorithm/kinematics.hpp>

#include <cmath>
#include <limits>

#include "core_data.hpp"
#include "core_model.hpp"
#include "errors.hpp"
#include "stage_terms.hpp"
#include "tree_terms.hpp"

namespace closedchain {

// -- declarations ------------------------------------------------------------

/// Every declared row (the kept ones and those dropped as redundant), checked at
/// every step: kinds/frames/vectors as for the kept rows, kept[i] = 1 for a row
/// the methods use, labels "loop.kind" for messages.
void set_declared(CoreModel &model, CoreData &data, const Eigen::VectorXi &kinds,
                  const Eigen::VectorXi &fid_p, const Eigen::VectorXi &fid_s, const Mat &vec1,
                  const Mat &vec2, const Eigen::VectorXi &kept, bp::list labels);

/// data.tree's kinematics, data.J and data.M no longer known to be at data.J_at; the factor of
/// M + alpha J^T J dropped.
void invalidate_kinematics(CoreData &data);

/// phi only: placements from the kinematics pass (tree_terms.hpp's joint_kinematics,
/// the same placements as eval_phi_J and eval_terms).
void eval_phi(const CoreModel &model, CoreData &data, const RefV &q);

/// phi and J: joint_kinematics(q) (placements and world joint Jacobians, as
/// pinocchio::computeJointJacobians; revolute joints by tree_terms.hpp's own path).
/// Each step asks several times at one q (projection, regularity check, declared
/// rows, output): the last evaluation is reused while q is the same.
void eval_phi_J(const CoreModel &model, CoreData &data, const RefV &q);

/// eval_phi_J at a trial point of the dependent solve, which moves only the
/// dependent coordinates data.dependent: when the kinematics in data.tree (data.J_at) agree with q
/// on every independent coordinate, the joints whose supports hold no dependent coordinate keep
/// their placements and Jacobian columns (the same values a full pass computes: same inputs, same
/// arithmetic) and only the others are recomputed.
void eval_phi_J_trial(const CoreModel &model, CoreData &data, const Vec &q);

/// M, h, phi, J, gamma at (q, v): one pass over the tree (tree_terms.hpp: M, h,
/// the joints' placements, world Jacobian columns, velocities and bias
/// accelerations), then the cut frames' placements, velocities and classical
/// accelerations, then the rows. `mark(stage)` is called after each stage
/// (0 tree, 1 frames, 2 rows): a no-op, or py_profile's clock.
///
/// When the last kinematics pass was at q (eval_phi_J(q): the dependent solve of
/// the partitioning stabilization ends there), data.tree already holds the joints'
/// placements and Jacobian columns and data.phi, data.J and the frame placements are
/// those of q: only the velocity-dependent part of the tree pass and gamma are
/// computed (tree_terms_at_kinematics; the same arithmetic, the same results); when
/// data.M is at q too (data.M_at_J: the stage projection's velocity step computed it, or an
/// evaluation at q with another v), only h (bias_at_kinematics, stage_terms.hpp),
/// and data.M and the factor of M + alpha J^T J (data.P_factored) stay. On the tree
/// path (model.tree_solves()) M is not formed: data.M_at_J stays false (mass_at_J).
template <class Mark>
void eval_terms(const CoreModel &model, CoreData &data, const RefV &q, const RefV &v, Mark &&mark);

/// eval_terms without a mark (no caller to tell which joints moved).
void eval_terms(const CoreModel &model, CoreData &data, const RefV &q, const RefV &v);

/// data.M at the kinematics in data.tree (those of data.J_at), formed there by the CRBA
/// (mass_at_kinematics) unless it is already (data.M_at_J); when formed, the factor of
/// M + alpha J^T J is dropped and data.terms_q forgotten (record() must not pair this M
/// with data.potential_energy). Where the tree path skipped M (the stage projection's
/// dense path, ALI3-P, inverse dynamics).
const Mat &mass_at_J(const CoreModel &model, CoreData &data);

/// phi of every declared row from the placements of the last kinematics pass.
void declared_phi(const CoreModel &model, CoreData &data);

/// BadArgument unless q has shape (nq,) and v shape (nv,).
void check_sizes(const CoreModel &model, const Vec &q, const Vec &v);

/// World placement (data.frame_R, data.frame_p) of every cut frame from data.tree.oMi, and q
/// (data.rows_q: the coupling rows' coordinates) of that kinematics pass.
void placements(const CoreModel &model, CoreData &data, const RefV &q);

/// phi of `row` from the placements and coordinates of the last kinematics pass.
double row_phi(const CoreData &data, const Row &row);

/// Velocity data.frame_v and classical acceleration data.frame_a (at a = 0) of every cut frame's
/// origin p, world axes (LOCAL_WORLD_ALIGNED), from its joint's world spatial
/// velocity (v_o, w) = data.tree.ov and bias acceleration (a_o, al) = data.tree.oa:
///   v_p = v_o + w x p,   a_p = a_o + al x p + w x v_p   (linear; angular w, al).
void frame_motion(const CoreModel &model, CoreData &data);

/// Row J of `row` from the world Jacobian columns data.tree.J (of the last kinematics
/// pass) and the frame placements. A frame's LOCAL_WORLD_ALIGNED Jacobian at p
/// has, on its joint's support, linear columns J_lin + J_ang x p and angular
/// columns J_ang, so a row c . (linear) + e . (angular) of it is the 6-vector
/// (c, p x c + e) applied to the world columns: the row is that of the
/// predecessor frame minus that of the successor.
///   ROW_TRANSLATION: U^T (Jlin_p - Jlin_s) + (U x d)^T Jang_p,
///   ROW_ROTATION:    (W x U)^T (Jang_s - Jang_p),
///   ROW_COUPLING:    e_j^T - m e_i^T (constant).
template <typename RowXpr>
void row_jacobian(const CoreModel &model, CoreData &data, const Row &row, RowXpr &&out);

/// Fill data.phi, data.J, data.gamma from the per-frame quantities.
void fill_rows(const CoreModel &model, CoreData &data, bool want_phi, bool want_J, bool want_gamma);

/// SimulationFailure when res, the largest |phi| over the declared rows (at declared row
/// `worst`; -1: over the kept rows), is not finite or exceeds drift_limit at t: the state
/// left the constraint manifold.
void check_drift(const CoreModel &model, double res, int worst, double t);

// -- definitions -------------------------------------------------------------

inline void set_declared(CoreModel &model, CoreData &data, const Eigen::VectorXi &kinds,
                         const Eigen::VectorXi &fid_p, const Eigen::VectorXi &fid_s,
                         const Mat &vec1, const Mat &vec2, const Eigen::VectorXi &kept,
                         bp::list labels) {
  const int nd = static_cast<int>(kinds.size());
  if (fid_p.size() != nd || fid_s.size() != nd || vec1.rows() != nd || vec2.rows() != nd ||
      kept.size() != nd || bp::len(labels) != nd || (nd && (vec1.cols() != 3 || vec2.cols() != 3)))
    throw BadArgument{"Core.set_declared: row tables of inconsistent shapes"};
  model.declared_rows.clear();
  model.declared_labels.clear();
  for (int r = 0; r < nd; ++r) {
    model.declared_rows.push_back(model.make_row(r, kinds, fid_p, fid_s, vec1, vec2));
    model.declared_labels.push_back(bp::extract<std::string>(labels[r]));
  }
  model.declared_kept = kept;
  data.declared_residuals = Vec::Zero(nd);
  model.frame_supports();
  data.resize_frames(model);
  invalidate_kinematics(data);
}

inline void invalidate_kinematics(CoreData &data) {
  data.J_at_valid = false;
  data.M_at_J = false;
  data.P_factored = false;
  data.tree_mass_factored = data.tree_factored = data.delassus_factored = false;
  data.tree_penalized = data.tree_range_factored = false;
}

inline void eval_phi(const CoreModel &model, CoreData &data, const RefV &q) {
  invalidate_kinematics(data);
  joint_kinematics(model.tree_plan, model.tree, data.tree, q);
  placements(model, data, q);
  fill_rows(model, data, true, false, false);
}

inline void eval_phi_J(const CoreModel &model, CoreData &data, const RefV &q) {
  if (data.J_at_valid && q == data.J_at) return;
  invalidate_kinematics(data);
  joint_kinematics(model.tree_plan, model.tree, data.tree, q);
  placements(model, data, q);
  fill_rows(model, data, true, true, false);
  data.J_at = q;
  data.J_at_valid = true;
}

inline void eval_phi_J_trial(const CoreModel &model, CoreData &data, const Vec &q) {
  bool same = data.J_at_valid && model.nq == model.nv;  // coordinates are velocity indices
  for (std::size_t k = 0; same && k < data.independent.size(); ++k)
    same = data.J_at[data.independent[k]] == q[data.independent[k]];
  if (!same || q == data.J_at) return eval_phi_J(model, data, q);
  if (data.moved_for !=
      data.dependent) {  // the joints moved by data.dependent (allocates: once per partition)
    data.moved_for = data.dependent;
    data.moved.assign(static_cast<std::size_t>(model.tree.njoints), 0);
    std::vector<char> is_dep(static_cast<std::size_t>(model.nv), 0);
    for (int d : data.dependent) is_dep[static_cast<std::size_t>(d)] = 1;
    for (std::size_t j = 1; j < static_cast<std::size_t>(model.tree.njoints); ++j) {
      char m = data.moved[model.tree.parents[j]];
      for (int c = 0; c < model.tree.nvs[j]; ++c) m |= is_dep[model.tree.idx_vs[j] + c];
      data.moved[j] = m;
    }
  }
  invalidate_kinematics(data);
  joint_kinematics(model.tree_plan, model.tree, data.tree, q, &data.moved);
  placements(model, data, q);
  fill_rows(model, data, true, true, false);
  data.J_at = q;
  data.J_at_valid = true;
}

template <class Mark>
inline void eval_terms(const CoreModel &model, CoreData &data, const RefV &q, const RefV &v,
                       Mark &&mark) {
  const bool tree = model.tree_solves();  // M not formed: the tree path factors it implicitly
  if (data.J_at_valid && q == data.J_at) {
    if (data.M_at_J || tree) {
      bias_at_kinematics(model.tree_plan, model.tree, data.tree, q, v, data.h);
    } else {
      tree_terms_at_kinematics(model.tree_plan, model.tree, data.tree, q, v, data.M, data.h);
      data.M_at_J = true;
      data.P_factored = false;
    }
    mark(0);
    frame_motion(model, data);
    mark(1);
    fill_rows(model, data, false, false, true);
  } else {
    invalidate_kinematics(data);
    if (tree) {  // tree_terms without M: its two halves, the same arithmetic
      joint_kinematics(model.tree_plan, model.tree, data.tree, q);
      bias_at_kinematics(model.tree_plan, model.tree, data.tree, q, v, data.h);
    } else {
      tree_terms(model.tree_plan, model.tree, data.tree, q, v, data.M, data.h);
    }
    mark(0);
    placements(model, data, q);
    frame_motion(model, data);
    mark(1);
    fill_rows(model, data, true, true, true);
  }
  model.passive.subtract_from_bias(q, v, data.h);  // h - tau_passive: springs and damping
  if (model.baumgarte && model.nc) {
    data.tmp_c.noalias() = data.J * v;
    data.gamma += (2.0 * model.baumgarte_alpha) * data.tmp_c +
                  (model.baumgarte_beta * model.baumgarte_beta) * data.phi;
  }
  // data.phi, data.J and the placements are those eval_phi_J(q) would compute; data.M and the
  // potential energy (total mass and centre of mass in data.tree.oYcrb[0]) serve record().
  data.J_at = q;
  data.J_at_valid = true;
  if (!tree) data.M_at_J = true;
  data.terms_q = q;
  data.terms_v = v;
  data.potential_energy =
      -data.tree.oYcrb[0].mass() * model.tree.gravity.linear().dot(data.tree.oYcrb[0].lever());
  mark(2);
}

inline void eval_terms(const CoreModel &model, CoreData &data, const RefV &q, const RefV &v) {
  eval_terms(model, data, q, v, [](int) {});
}

inline const Mat &mass_at_J(const CoreModel &model, CoreData &data) {
  if (!data.M_at_J) {
    mass_at_kinematics(model.tree_plan, model.tree, data.tree, data.M);
    data.M_at_J = true;
    data.P_factored = false;
    data.terms_q.setConstant(std::numeric_limits<double>::quiet_NaN());
  }
  return data.M;
}

inline void declared_phi(const CoreModel &model, CoreData &data) {
  for (std::size_t r = 0; r < model.declared_rows.size(); ++r)
    data.declared_residuals[r] = row_phi(data, model.declared_rows[r]);
}

inline double row_phi(const CoreData &data, const Row &row) {
  switch (row.kind) {
    case ROW_TRANSLATION:
      return (data.frame_R[row.p] * row.n).dot(data.frame_p[row.p] - data.frame_p[row.s]);
    case ROW_ROTATION:
      return (data.frame_R[row.p] * row.n).dot(data.frame_R[row.s] * row.w);
    default:  // ROW_COUPLING: q_j - m q_i - c
      return data.rows_q[row.qj] - row.n[0] * data.rows_q[row.qi] - row.n[1];
  }
}

inline void check_sizes(const CoreModel &model, const Vec &q, const Vec &v) {
  if (q.size() != model.nq || v.size() != model.nv)
    throw BadArgument{"q must have shape (" + std::to_string(model.nq) + ",) and v shape (" +
                      std::to_string(model.nv) + ",)"};
}

inline void placements(const CoreModel &model, CoreData &data, const RefV &q) {
  data.rows_q = q;
  for (std::size_t k = 0; k < model.frame_ids.size(); ++k) {
    const pinocchio::SE3 oMf =
        data.tree.oMi[model.frame_joint[k]] * model.tree.frames[model.frame_ids[k]].placement;
    data.frame_R[k] = oMf.rotation();
    data.frame_p[k] = oMf.translation();
  }
}

inline void frame_motion(const CoreModel &model, CoreData &data) {
  for (std::size_t k = 0; k < model.frame_ids.size(); ++k) {
    const pinocchio::Motion &ov = data.tree.ov[model.frame_joint[k]],
                            &oa = data.tree.oa[model.frame_joint[k]];
    const Vector3d w = ov.angular(), al = oa.angular();
    const Vector3d vp = ov.linear() + w.cross(data.frame_p[k]);
    data.frame_v[k].head<3>() = vp;
    data.frame_v[k].tail<3>() = w;
    data.frame_a[k].head<3>() = oa.linear() + al.cross(data.frame_p[k]) + w.cross(vp);
    data.frame_a[k].tail<3>() = al;
  }
}

template <typename RowXpr>
inline void row_jacobian(const CoreModel &model, CoreData &data, const Row &row, RowXpr &&out) {
  out.setZero();
  if (row.kind == ROW_COUPLING) {
    out(row.vj) += 1.0;
    out(row.vi) -= row.n[0];
    return;
  }
  Eigen::Matrix<double, 6, 1> wp, ws;
  const int P = row.p, S = row.s;
  if (row.kind == ROW_TRANSLATION) {
    const Vector3d U = data.frame_R[P] * row.n;
    wp.head<3>() = U;
    ws.head<3>() = U;
    wp.tail<3>() = data.frame_p[P].cross(U);
    wp.tail<3>() += U.cross(data.frame_p[P] - data.frame_p[S]);
    ws.tail<3>() = data.frame_p[S].cross(U);
  } else {
    const Vector3d WxU = (data.frame_R[S] * row.w).cross(data.frame_R[P] * row.n);
    wp.head<3>().setZero();
    ws.head<3>().setZero();
    wp.tail<3>() = -WxU;
    ws.tail<3>() = -WxU;
  }
  const Data::Matrix6x &Jw = data.tree.J;
  for (Eigen::Index c : model.frame_columns[P]) out(c) += wp.dot(Jw.col(c));
  for (Eigen::Index c : model.frame_columns[S]) out(c) -= ws.dot(Jw.col(c));
}

inline void fill_rows(const CoreModel &model, CoreData &data, bool want_phi, bool want_J,
                      bool want_gamma) {
  for (int r = 0; r < model.nc; ++r) {
    const Row &row = model.rows[r];
    const int P = row.p, S = row.s;
    if (want_J) row_jacobian(model, data, row, data.J.row(r));
    if (row.kind == ROW_COUPLING) {  // linear in q: gamma = 0
      if (want_phi) data.phi[r] = row_phi(data, row);
      if (want_gamma) data.gamma[r] = 0.0;
    } else if (row.kind == ROW_TRANSLATION) {
      const Vector3d d = data.frame_p[P] - data.frame_p[S];
      const Vector3d U = data.frame_R[P] * row.n;
      if (want_phi) data.phi[r] = U.dot(d);
      if (want_gamma) {
        const Vector3d dd = data.frame_a[P].head<3>() - data.frame_a[S].head<3>();
        double g = U.dot(dd);
        const Vector3d wp = data.frame_v[P].tail<3>(), alp = data.frame_a[P].tail<3>();
        const Vector3d Ud = wp.cross(U);
        const Vector3d Udd = alp.cross(U) + wp.cross(Ud);
        const Vector3d ddot = data.frame_v[P].head<3>() - data.frame_v[S].head<3>();
        g += Udd.dot(d) + 2.0 * Ud.dot(ddot);
        data.gamma[r] = g;
      }
    } else {
      const Vector3d U = data.frame_R[P] * row.n, W = data.frame_R[S] * row.w;
      const double UW = U.dot(W);
      if (want_phi) data.phi[r] = UW;
      if (want_gamma) {
        const Vector3d WxU = W.cross(U);
        const Vector3d wp = data.frame_v[P].tail<3>(), ws = data.frame_v[S].tail<3>();
        const double pu = wp.dot(U), pw = wp.dot(W), su = ws.dot(U), sw = ws.dot(W);
        data.gamma[r] = WxU.dot(data.frame_a[S].tail<3>() - data.frame_a[P].tail<3>()) + pu * pw +
                        su * sw - 2.0 * pw * su - (wp - ws).squaredNorm() * UW;
      }
    }
  }
}

inline void check_drift(const CoreModel &model, double res, int worst, double t) {
  if (std::isfinite(res) && res <= model.drift_limit) return;
  throw SimulationFailure{model.name + ": the state left the constraint manifold at t = " +
                              fmt("%.9g", t) + " s (max |phi| = " + fmt("%.3e", res) +
                              " > drift_limit " + fmt("%.1e", model.drift_limit) +
                              (worst >= 0 ? ", row " + model.declared_labels[worst] : "") +
                              "); use a stabilization or a smaller step",
                          t};
}

}  // namespace closedchain
