// closedchain._core: the sparsity of M and J and the band paths (products over the
// structure, band Cholesky of M + alpha J^T J and J J^T).
// (Member functions of Core, declared in core.hpp.)

#pragma once

#include <algorithm>
#include <cmath>

#include "core.hpp"

namespace closedchain {

inline void Core::sparsity() {
  const Model &model = model_;
  auto support_cols = [&](pinocchio::JointIndex j, std::vector<int> &cols) {
    for (pinocchio::JointIndex s : model.supports[j]) {
      if (s == 0) continue;
      for (int c = 0; c < model.joints[s].nv(); ++c) cols.push_back(model.joints[s].idx_v() + c);
    }
  };
  jcol_start_.assign(1, 0);
  jcols_.clear();
  jlo_.assign(nc_, 0);
  jhi_.assign(nc_, nv_ ? nv_ - 1 : 0);
  for (int r = 0; r < nc_; ++r) {
    std::vector<int> cols;
    support_cols(model.frames[fids_[rows_[r].p]].parentJoint, cols);
    support_cols(model.frames[fids_[rows_[r].s]].parentJoint, cols);
    std::sort(cols.begin(), cols.end());
    cols.erase(std::unique(cols.begin(), cols.end()), cols.end());
    jcols_.insert(jcols_.end(), cols.begin(), cols.end());
    jcol_start_.push_back(static_cast<int>(jcols_.size()));
    if (!cols.empty()) {
      jlo_[r] = cols.front();
      jhi_[r] = cols.back();
    } else {  // a row on two frames of the base: J row zero
      jlo_[r] = 0;
      jhi_[r] = -1;
    }
  }
  mlo_.assign(nv_, 0);
  mhi_.assign(nv_, 0);
  for (pinocchio::JointIndex j = 1; j < static_cast<pinocchio::JointIndex>(model.njoints); ++j) {
    int lo = model.joints[j].idx_v(), hi = lo + model.joints[j].nv() - 1;
    for (pinocchio::JointIndex s : model.supports[j])
      if (s != 0) lo = std::min(lo, model.joints[s].idx_v());
    for (pinocchio::JointIndex s : model.subtrees[j])
      hi = std::max(hi, model.joints[s].idx_v() + model.joints[s].nv() - 1);
    for (int c = 0; c < model.joints[j].nv(); ++c) {
      mlo_[model.joints[j].idx_v() + c] = lo;
      mhi_[model.joints[j].idx_v() + c] = hi;
    }
  }
}

inline bp::tuple Core::set_band(const Eigen::VectorXi &perm, bool banded_p, bool banded_n) {
  if (perm.size() != nv_) throw BadArgument{"Core.set_band: perm must have shape (nv,)"};
  perm_.assign(perm.data(), perm.data() + nv_);
  pinv_.assign(nv_, -1);
  for (int k = 0; k < nv_; ++k) {
    if (perm_[k] < 0 || perm_[k] >= nv_ || pinv_[perm_[k]] >= 0)
      throw BadArgument{"Core.set_band: perm must be a permutation of range(nv)"};
    pinv_[perm_[k]] = k;
  }
  perm_identity_ = true;
  for (int k = 0; k < nv_; ++k) perm_identity_ = perm_identity_ && perm_[k] == k;
  int b_p = 0;  // M's pattern and J^T J's, in the order perm
  for (int i = 0; i < nv_; ++i)
    for (int c = mlo_[i]; c <= mhi_[i]; ++c)
      if (M_structural(i, c)) b_p = std::max(b_p, std::abs(pinv_[i] - pinv_[c]));
  for (int r = 0; r < nc_; ++r)
    for (int x = jcol_start_[r]; x < jcol_start_[r + 1]; ++x)
      for (int y = jcol_start_[r]; y < jcol_start_[r + 1]; ++y)
        b_p = std::max(b_p, std::abs(pinv_[jcols_[x]] - pinv_[jcols_[y]]));
  int b_n = 0;  // rows sharing a column
  for (int r = 0; r < nc_; ++r)
    for (int s2 = 0; s2 < r; ++s2)
      if (r - s2 > b_n && rows_share_column(r, s2)) b_n = r - s2;
  penalized_bandwidth_ = b_p;
  normal_bandwidth_ = b_n;
  band_p_ = banded_p && nc_ > 0;
  band_n_ = banded_n && nc_ > 0;
  if (band_p_) {
    penalized_band_.resize(nv_, b_p);
    band_work_ = Vec::Zero(nv_);
  }
  if (band_n_) normal_band_.resize(nc_, b_n);
  invalidate_kinematics();
  return bp::make_tuple(b_p, b_n);
}

inline bool Core::M_structural(int i, int c) const {
  const pinocchio::JointIndex ji = col_joint(i), jc = col_joint(c);
  const auto &si = model_.supports[ji], &sc = model_.supports[jc];
  return std::find(si.begin(), si.end(), jc) != si.end() ||
         std::find(sc.begin(), sc.end(), ji) != sc.end();
}

inline pinocchio::JointIndex Core::col_joint(int c) const {
  for (pinocchio::JointIndex j = 1; j < static_cast<pinocchio::JointIndex>(model_.njoints); ++j)
    if (c >= model_.joints[j].idx_v() && c < model_.joints[j].idx_v() + model_.joints[j].nv())
      return j;
  return 0;
}

inline bool Core::rows_share_column(int r, int s2) const {
  for (int x = jcol_start_[r]; x < jcol_start_[r + 1]; ++x)
    for (int y = jcol_start_[s2]; y < jcol_start_[s2 + 1]; ++y)
      if (jcols_[x] == jcols_[y]) return true;
  return false;
}

inline void Core::j_mul(const Vec &x, Vec &y) const {
  for (int r = 0; r < nc_; ++r) {
    const int lo = jlo_[r], len = jhi_[r] - jlo_[r] + 1;
    y[r] = len > 0 ? J_.row(r).segment(lo, len).dot(x.segment(lo, len)) : 0.0;
  }
}

inline void Core::jt_mul(const Vec &y, Vec &x) const {
  x.setZero();
  jt_mul_add(y, x);
}

inline void Core::jt_mul_add(const Vec &y, Vec &x) const {
  for (int r = 0; r < nc_; ++r) {
    const int lo = jlo_[r], len = jhi_[r] - jlo_[r] + 1;
    if (len > 0) x.segment(lo, len) += y[r] * J_.row(r).segment(lo, len).transpose();
  }
}

inline void Core::m_mul_sub(const Vec &x, Vec &y) const {
  for (int i = 0; i < nv_; ++i) {
    const int lo = mlo_[i], len = mhi_[i] - mlo_[i] + 1;
    y[i] -= M_.row(i).segment(lo, len).dot(x.segment(lo, len));
  }
}

inline double Core::j_squared_norm() const {
  double s = 0.0;
  for (int r = 0; r < nc_; ++r) {
    const int lo = jlo_[r], len = jhi_[r] - jlo_[r] + 1;
    if (len > 0) s += J_.row(r).segment(lo, len).squaredNorm();
  }
  return s;
}

inline bool Core::factor_penalized_band(double alpha) {
  const int b = penalized_band_.bandwidth();
  Mat &A = penalized_band_.A;
  for (int j = 0; j < nv_; ++j)
    for (int k = 0; k <= b; ++k) A(k, j) = j + k < nv_ ? M_(perm_[j + k], perm_[j]) : 0.0;
  for (int r = 0; r < nc_; ++r)
    for (int x = jcol_start_[r]; x < jcol_start_[r + 1]; ++x) {
      const int cx = jcols_[x], px = pinv_[cx];
      const double ax = alpha * J_(r, cx);
      for (int y = jcol_start_[r]; y < jcol_start_[r + 1]; ++y) {
        const int cy = jcols_[y], py = pinv_[cy];
        if (px >= py) A(px - py, py) += ax * J_(r, cy);
      }
    }
  return penalized_band_.factor();
}

inline void Core::solve_penalized_band(Vec &x) {
  if (perm_identity_) {
    penalized_band_.solve_in_place(x);
    return;
  }
  for (int k = 0; k < nv_; ++k) band_work_[k] = x[perm_[k]];
  penalized_band_.solve_in_place(band_work_);
  for (int k = 0; k < nv_; ++k) x[perm_[k]] = band_work_[k];
}

inline bool Core::factor_penalized(double alpha) {
  p_fact_ = false;
  if (band_p_) return factor_penalized_band(alpha);
  if (nc_)
    P_.triangularView<Eigen::Lower>() = J_.transpose() * J_;
  else
    P_.setZero();
  P_.triangularView<Eigen::Lower>() = alpha * P_ + M_;
  return llt_p_.compute(P_);
}

inline void Core::solve_penalized(Vec &x) {
  if (band_p_)
    solve_penalized_band(x);
  else
    llt_p_.solveInPlace(x);
}

inline bool Core::factor_normal_band(double rel_reg) {
  assemble_normal_band(rel_reg);
  return normal_band_.factor();
}

inline void Core::assemble_normal_band(double rel_reg) {
  const int b = normal_band_.bandwidth();
  Mat &A = normal_band_.A;
  for (int j = 0; j < nc_; ++j)
    for (int k = 0; k <= b; ++k) {
      const int i = j + k;
      double v = 0.0;
      if (i < nc_) {
        const int lo = std::max(jlo_[i], jlo_[j]), hi = std::min(jhi_[i], jhi_[j]);
        if (hi >= lo)
          v = J_.row(i).segment(lo, hi - lo + 1).dot(J_.row(j).segment(lo, hi - lo + 1));
      }
      A(k, j) = v;
    }
  if (rel_reg != 0.0)
    A.row(0).array() += rel_reg * std::max(A.row(0).sum(), 1.0) / static_cast<double>(nc_);
}

}  // namespace closedchain
