// closedchain._core: the constraint rows: cut frames, their placements and motion, phi,
// J, gamma, and the evaluation of the tree terms.
// (Member functions of Core, declared in core.hpp.)

#pragma once

#include <pinocchio/algorithm/kinematics.hpp>

#include <limits>

#include "core.hpp"
#include "stage_terms.hpp"
#include "tree_terms.hpp"

namespace closedchain {

inline void Core::set_declared(const Eigen::VectorXi &kinds, const Eigen::VectorXi &fid_p,
                               const Eigen::VectorXi &fid_s, const Mat &vec1, const Mat &vec2,
                               const Eigen::VectorXi &kept, bp::list labels) {
  const int nd = static_cast<int>(kinds.size());
  if (fid_p.size() != nd || fid_s.size() != nd || vec1.rows() != nd || vec2.rows() != nd ||
      kept.size() != nd || bp::len(labels) != nd || (nd && (vec1.cols() != 3 || vec2.cols() != 3)))
    throw BadArgument{"Core.set_declared: row tables of inconsistent shapes"};
  drows_.clear();
  dlabels_.clear();
  for (int r = 0; r < nd; ++r) {
    drows_.push_back(make_row(r, kinds, fid_p, fid_s, vec1, vec2));
    dlabels_.push_back(bp::extract<std::string>(labels[r]));
  }
  dkept_ = kept;
  dphi_ = Vec::Zero(nd);
  frame_buffers();
  invalidate_kinematics();
}

inline void Core::invalidate_kinematics() {
  J_at_valid_ = false;
  m_at_J_ = false;
  p_fact_ = false;
}

inline void Core::eval_phi(const RefV &q) {
  invalidate_kinematics();
  joint_kinematics(plan_, model_, data_, q);
  placements();
  rows(true, false, false);
}

inline void Core::eval_phi_J(const RefV &q) {
  if (J_at_valid_ && q == J_at_) return;
  invalidate_kinematics();
  joint_kinematics(plan_, model_, data_, q);
  placements();
  rows(true, true, false);
  J_at_ = q;
  J_at_valid_ = true;
}

inline void Core::eval_phi_J_trial(const Vec &q) {
  bool same = J_at_valid_ && nq_ == nv_;  // coordinates are velocity indices
  for (std::size_t k = 0; same && k < ind_.size(); ++k) same = J_at_[ind_[k]] == q[ind_[k]];
  if (!same || q == J_at_) return eval_phi_J(q);
  if (moved_for_ != dep_) {  // the joints moved by dep_ (allocates: once per partition)
    moved_for_ = dep_;
    moved_.assign(static_cast<std::size_t>(model_.njoints), 0);
    std::vector<char> is_dep(static_cast<std::size_t>(nv_), 0);
    for (int d : dep_) is_dep[static_cast<std::size_t>(d)] = 1;
    for (std::size_t j = 1; j < static_cast<std::size_t>(model_.njoints); ++j) {
      char m = moved_[model_.parents[j]];
      for (int c = 0; c < model_.nvs[j]; ++c) m |= is_dep[model_.idx_vs[j] + c];
      moved_[j] = m;
    }
  }
  invalidate_kinematics();
  joint_kinematics(plan_, model_, data_, q, &moved_);
  placements();
  rows(true, true, false);
  J_at_ = q;
  J_at_valid_ = true;
}

template <class Mark>
inline void Core::eval_terms(const RefV &q, const RefV &v, Mark &&mark) {
  if (J_at_valid_ && q == J_at_) {
    if (m_at_J_) {
      bias_at_kinematics(plan_, model_, data_, q, v, h_);
    } else {
      tree_terms_at_kinematics(plan_, model_, data_, q, v, M_, h_);
      m_at_J_ = true;
      p_fact_ = false;
    }
    mark(0);
    frame_motion();
    mark(1);
    rows(false, false, true);
  } else {
    invalidate_kinematics();
    tree_terms(plan_, model_, data_, q, v, M_, h_);
    mark(0);
    placements();
    frame_motion();
    mark(1);
    rows(true, true, true);
  }
  if (baumgarte_ && nc_) {
    tmp_c_.noalias() = J_ * v;
    gamma_ += (2.0 * alpha_) * tmp_c_ + (beta_ * beta_) * phi_;
  }
  // phi_, J_ and the placements are those eval_phi_J(q) would compute; M_ and the
  // potential energy (total mass and centre of mass in data_.oYcrb[0]) serve record().
  J_at_ = q;
  J_at_valid_ = true;
  m_at_J_ = true;
  terms_q_ = q;
  terms_v_ = v;
  potential_energy_ = -data_.oYcrb[0].mass() * model_.gravity.linear().dot(data_.oYcrb[0].lever());
  mark(2);
}

inline void Core::eval_terms(const RefV &q, const RefV &v) {
  eval_terms(q, v, [](int) {});
}

inline void Core::declared_phi() {
  for (std::size_t r = 0; r < drows_.size(); ++r) {
    const Row &row = drows_[r];
    if (row.kind != 2) {
      const Vector3d d = p_[row.p] - p_[row.s];
      dphi_[r] = row.kind == 0 ? row.n.dot(d) : (R_[row.p] * row.n).dot(d);
    } else {
      dphi_[r] = (R_[row.p] * row.n).dot(R_[row.s] * row.w);
    }
  }
}

inline Row Core::make_row(int r, const Eigen::VectorXi &kinds, const Eigen::VectorXi &fid_p,
                          const Eigen::VectorXi &fid_s, const Mat &vec1, const Mat &vec2) {
  if (kinds[r] < 0 || kinds[r] > 2) throw BadArgument{"Core: row kind must be 0, 1 or 2"};
  for (int f : {fid_p[r], fid_s[r]})
    if (f < 0 || f >= static_cast<int>(model_.nframes))
      throw BadArgument{"Core: frame id out of range"};
  Row row;
  row.kind = kinds[r];
  row.p = frame_index(fid_p[r]);
  row.s = frame_index(fid_s[r]);
  row.n = vec1.row(r).transpose();
  row.w = vec2.row(r).transpose();
  return row;
}

inline int Core::frame_index(int fid) {
  for (std::size_t k = 0; k < fids_.size(); ++k)
    if (fids_[k] == static_cast<pinocchio::FrameIndex>(fid)) return static_cast<int>(k);
  fids_.push_back(static_cast<pinocchio::FrameIndex>(fid));
  return static_cast<int>(fids_.size() - 1);
}

inline void Core::check_sizes(const Vec &q, const Vec &v) const {
  if (q.size() != nq_ || v.size() != nv_)
    throw BadArgument{"q must have shape (" + std::to_string(nq_) + ",) and v shape (" +
                      std::to_string(nv_) + ",)"};
}

inline void Core::frame_buffers() {
  const std::size_t nf = fids_.size();
  R_.resize(nf);
  p_.resize(nf);
  vf_.resize(nf, Eigen::Matrix<double, 6, 1>::Zero());
  af_.resize(nf, Eigen::Matrix<double, 6, 1>::Zero());
  fjoint_.resize(nf);
  fcols_.resize(nf);
  for (std::size_t k = 0; k < nf; ++k) {
    const pinocchio::JointIndex j = model_.frames[fids_[k]].parentJoint;
    fjoint_[k] = j;
    fcols_[k].clear();
    for (pinocchio::JointIndex s : model_.supports[j]) {
      if (s == 0) continue;
      for (int c = 0; c < model_.nvs[s]; ++c) fcols_[k].push_back(model_.idx_vs[s] + c);
    }
  }
}

inline void Core::placements() {
  for (std::size_t k = 0; k < fids_.size(); ++k) {
    const pinocchio::SE3 oMf = data_.oMi[fjoint_[k]] * model_.frames[fids_[k]].placement;
    R_[k] = oMf.rotation();
    p_[k] = oMf.translation();
  }
}

inline void Core::frame_motion() {
  for (std::size_t k = 0; k < fids_.size(); ++k) {
    const pinocchio::Motion &ov = data_.ov[fjoint_[k]], &oa = data_.oa[fjoint_[k]];
    const Vector3d w = ov.angular(), al = oa.angular();
    const Vector3d vp = ov.linear() + w.cross(p_[k]);
    vf_[k].head<3>() = vp;
    vf_[k].tail<3>() = w;
    af_[k].head<3>() = oa.linear() + al.cross(p_[k]) + w.cross(vp);
    af_[k].tail<3>() = al;
  }
}

template <typename RowXpr>
inline void Core::row_jacobian(const Row &row, RowXpr &&out) {
  Eigen::Matrix<double, 6, 1> wp, ws;
  const int P = row.p, S = row.s;
  if (row.kind != 2) {
    const Vector3d U = row.kind == 0 ? row.n : Vector3d(R_[P] * row.n);
    wp.head<3>() = U;
    ws.head<3>() = U;
    wp.tail<3>() = p_[P].cross(U);
    if (row.kind == 1) wp.tail<3>() += U.cross(p_[P] - p_[S]);
    ws.tail<3>() = p_[S].cross(U);
  } else {
    const Vector3d WxU = (R_[S] * row.w).cross(R_[P] * row.n);
    wp.head<3>().setZero();
    ws.head<3>().setZero();
    wp.tail<3>() = -WxU;
    ws.tail<3>() = -WxU;
  }
  out.setZero();
  const Data::Matrix6x &Jw = data_.J;
  for (Eigen::Index c : fcols_[P]) out(c) += wp.dot(Jw.col(c));
  for (Eigen::Index c : fcols_[S]) out(c) -= ws.dot(Jw.col(c));
}

inline void Core::rows(bool want_phi, bool want_J, bool want_gamma) {
  for (int r = 0; r < nc_; ++r) {
    const Row &row = rows_[r];
    const int P = row.p, S = row.s;
    if (want_J) row_jacobian(row, J_.row(r));
    if (row.kind != 2) {
      const Vector3d d = p_[P] - p_[S];
      const Vector3d U = row.kind == 0 ? row.n : Vector3d(R_[P] * row.n);
      if (want_phi) phi_[r] = U.dot(d);
      if (want_gamma) {
        const Vector3d dd = af_[P].head<3>() - af_[S].head<3>();
        double g = U.dot(dd);
        if (row.kind == 1) {
          const Vector3d wp = vf_[P].tail<3>(), alp = af_[P].tail<3>();
          const Vector3d Ud = wp.cross(U);
          const Vector3d Udd = alp.cross(U) + wp.cross(Ud);
          const Vector3d ddot = vf_[P].head<3>() - vf_[S].head<3>();
          g += Udd.dot(d) + 2.0 * Ud.dot(ddot);
        }
        gamma_[r] = g;
      }
    } else {
      const Vector3d U = R_[P] * row.n, W = R_[S] * row.w;
      const double UW = U.dot(W);
      if (want_phi) phi_[r] = UW;
      if (want_gamma) {
        const Vector3d WxU = W.cross(U);
        const Vector3d wp = vf_[P].tail<3>(), ws = vf_[S].tail<3>();
        const double pu = wp.dot(U), pw = wp.dot(W), su = ws.dot(U), sw = ws.dot(W);
        gamma_[r] = WxU.dot(af_[S].tail<3>() - af_[P].tail<3>()) + pu * pw + su * sw -
                    2.0 * pw * su - (wp - ws).squaredNorm() * UW;
      }
    }
  }
}

}  // namespace closedchain
