// closedchain._core: the sparsity of M and J and the band paths (products over the
// structure, band Cholesky of M + alpha J^T J and J J^T).
// (Functions over (CoreModel, CoreData): their declarations, then their definitions.)

#pragma once

#include <algorithm>
#include <cmath>

#include "banded.hpp"
#include "core_data.hpp"
#include "core_model.hpp"
#include "core_rows.hpp"

namespace closedchain {

// -- declarations ------------------------------------------------------------

/// Choose the band paths (closedchain.compiled.make_core, from PenalizedSolver and
/// NormalSolver): banded_p factorizes M + alpha J^T J in the order perm (perm[k] =
/// the column at position k) as a band, banded_n the normal equations J J^T in the
/// natural row order. Returns the half bandwidths (b_p, b_n) of the structure in
/// those orders (the Python side's bandwidths, checked by the tests).
bp::tuple set_band(CoreModel &model, CoreData &data, const Eigen::VectorXi &perm, bool banded_p,
                   bool banded_n);

/// M(i, c) structurally nonzero: one of the two joints supports the other.
bool M_structural(const CoreModel &model, int i, int c);

/// The joint whose velocities hold column c (0: none).
pinocchio::JointIndex col_joint(const CoreModel &model, int c);

/// Rows r and s2 of J have a structural column in common.
bool rows_share_column(const CoreModel &model, int r, int s2);

/// y = J x over each row's column hull.
void j_mul(const CoreModel &model, const CoreData &data, const Vec &x, Vec &y);

/// x = J^T y (x overwritten).
void jt_mul(const CoreModel &model, const CoreData &data, const Vec &y, Vec &x);

/// x += J^T y over each row's column hull.
void jt_mul_add(const CoreModel &model, const CoreData &data, const Vec &y, Vec &x);

/// y -= M x over each row's hull.
void m_mul_sub(const CoreModel &model, const CoreData &data, const Vec &x, Vec &y);

/// sum of J_ij^2
double j_squared_norm(const CoreModel &model, const CoreData &data);

/// Factorize P = M + alpha J^T J as a band in the order model.perm.
bool factor_penalized_band(const CoreModel &model, CoreData &data, double alpha);

/// x <- P^-1 x on the band factor.
void solve_penalized_band(const CoreModel &model, CoreData &data, Vec &x);

/// Factorize P = M + alpha J^T J with the caller's alpha (dense: Cholesky of P's lower
/// triangle; band: factor_penalized_band); the factor of solve_al's alpha is dropped.
/// Returns false when P is not positive definite.
bool factor_penalized(const CoreModel &model, CoreData &data, double alpha);

/// x <- P^-1 x with the factor of factor_penalized (or al_factor).
void solve_penalized(const CoreModel &model, CoreData &data, Vec &x);

/// Assemble J J^T + eps I as a band (natural row order), eps = rel_reg max(tr(J J^T), 1)
/// / nc (0: none), and factorize it.
bool factor_normal_band(const CoreModel &model, CoreData &data, double rel_reg);

/// J J^T + eps I as a band in data.normal_band (natural row order), eps as in
/// factor_normal_band; not factorized.
void assemble_normal_band(const CoreModel &model, CoreData &data, double rel_reg);

// -- definitions -------------------------------------------------------------

inline bp::tuple set_band(CoreModel &model, CoreData &data, const Eigen::VectorXi &perm,
                          bool banded_p, bool banded_n) {
  if (perm.size() != model.nv) throw BadArgument{"Core.set_band: perm must have shape (nv,)"};
  model.perm.assign(perm.data(), perm.data() + model.nv);
  model.perm_inverse.assign(model.nv, -1);
  for (int k = 0; k < model.nv; ++k) {
    if (model.perm[k] < 0 || model.perm[k] >= model.nv || model.perm_inverse[model.perm[k]] >= 0)
      throw BadArgument{"Core.set_band: perm must be a permutation of range(nv)"};
    model.perm_inverse[model.perm[k]] = k;
  }
  model.perm_identity = true;
  for (int k = 0; k < model.nv; ++k)
    model.perm_identity = model.perm_identity && model.perm[k] == k;
  int b_p = 0;  // M's pattern and J^T J's, in the order perm
  for (int i = 0; i < model.nv; ++i)
    for (int c = model.mlo[i]; c <= model.mhi[i]; ++c)
      if (M_structural(model, i, c))
        b_p = std::max(b_p, std::abs(model.perm_inverse[i] - model.perm_inverse[c]));
  for (int r = 0; r < model.nc; ++r)
    for (int x = model.jcol_start[r]; x < model.jcol_start[r + 1]; ++x)
      for (int y = model.jcol_start[r]; y < model.jcol_start[r + 1]; ++y)
        b_p = std::max(
            b_p, std::abs(model.perm_inverse[model.jcols[x]] - model.perm_inverse[model.jcols[y]]));
  int b_n = 0;  // rows sharing a column
  for (int r = 0; r < model.nc; ++r)
    for (int s2 = 0; s2 < r; ++s2)
      if (r - s2 > b_n && rows_share_column(model, r, s2)) b_n = r - s2;
  model.penalized_bandwidth = b_p;
  model.normal_bandwidth = b_n;
  model.banded_penalized = banded_p && model.nc > 0;
  model.banded_normal = banded_n && model.nc > 0;
  if (model.banded_penalized) {
    data.penalized_band.resize(model.nv, b_p);
    data.band_work = Vec::Zero(model.nv);
  }
  if (model.banded_normal) data.normal_band.resize(model.nc, b_n);
  invalidate_kinematics(data);
  return bp::make_tuple(b_p, b_n);
}

inline bool M_structural(const CoreModel &model, int i, int c) {
  const pinocchio::JointIndex ji = col_joint(model, i), jc = col_joint(model, c);
  const auto &si = model.tree.supports[ji], &sc = model.tree.supports[jc];
  return std::find(si.begin(), si.end(), jc) != si.end() ||
         std::find(sc.begin(), sc.end(), ji) != sc.end();
}

inline pinocchio::JointIndex col_joint(const CoreModel &model, int c) {
  for (pinocchio::JointIndex j = 1; j < static_cast<pinocchio::JointIndex>(model.tree.njoints); ++j)
    if (c >= model.tree.joints[j].idx_v() &&
        c < model.tree.joints[j].idx_v() + model.tree.joints[j].nv())
      return j;
  return 0;
}

inline bool rows_share_column(const CoreModel &model, int r, int s2) {
  for (int x = model.jcol_start[r]; x < model.jcol_start[r + 1]; ++x)
    for (int y = model.jcol_start[s2]; y < model.jcol_start[s2 + 1]; ++y)
      if (model.jcols[x] == model.jcols[y]) return true;
  return false;
}

inline void j_mul(const CoreModel &model, const CoreData &data, const Vec &x, Vec &y) {
  for (int r = 0; r < model.nc; ++r) {
    const int lo = model.jlo[r], len = model.jhi[r] - model.jlo[r] + 1;
    y[r] = len > 0 ? data.J.row(r).segment(lo, len).dot(x.segment(lo, len)) : 0.0;
  }
}

inline void jt_mul(const CoreModel &model, const CoreData &data, const Vec &y, Vec &x) {
  x.setZero();
  jt_mul_add(model, data, y, x);
}

inline void jt_mul_add(const CoreModel &model, const CoreData &data, const Vec &y, Vec &x) {
  for (int r = 0; r < model.nc; ++r) {
    const int lo = model.jlo[r], len = model.jhi[r] - model.jlo[r] + 1;
    if (len > 0) x.segment(lo, len) += y[r] * data.J.row(r).segment(lo, len).transpose();
  }
}

inline void m_mul_sub(const CoreModel &model, const CoreData &data, const Vec &x, Vec &y) {
  for (int i = 0; i < model.nv; ++i) {
    const int lo = model.mlo[i], len = model.mhi[i] - model.mlo[i] + 1;
    y[i] -= data.M.row(i).segment(lo, len).dot(x.segment(lo, len));
  }
}

inline double j_squared_norm(const CoreModel &model, const CoreData &data) {
  double s = 0.0;
  for (int r = 0; r < model.nc; ++r) {
    const int lo = model.jlo[r], len = model.jhi[r] - model.jlo[r] + 1;
    if (len > 0) s += data.J.row(r).segment(lo, len).squaredNorm();
  }
  return s;
}

inline bool factor_penalized_band(const CoreModel &model, CoreData &data, double alpha) {
  const int b = data.penalized_band.bandwidth();
  Mat &A = data.penalized_band.A;
  for (int j = 0; j < model.nv; ++j)
    for (int k = 0; k <= b; ++k)
      A(k, j) = j + k < model.nv ? data.M(model.perm[j + k], model.perm[j]) : 0.0;
  for (int r = 0; r < model.nc; ++r)
    for (int x = model.jcol_start[r]; x < model.jcol_start[r + 1]; ++x) {
      const int cx = model.jcols[x], px = model.perm_inverse[cx];
      const double ax = alpha * data.J(r, cx);
      for (int y = model.jcol_start[r]; y < model.jcol_start[r + 1]; ++y) {
        const int cy = model.jcols[y], py = model.perm_inverse[cy];
        if (px >= py) A(px - py, py) += ax * data.J(r, cy);
      }
    }
  return data.penalized_band.factor();
}

inline void solve_penalized_band(const CoreModel &model, CoreData &data, Vec &x) {
  if (model.perm_identity) {
    data.penalized_band.solve_in_place(x);
    return;
  }
  for (int k = 0; k < model.nv; ++k) data.band_work[k] = x[model.perm[k]];
  data.penalized_band.solve_in_place(data.band_work);
  for (int k = 0; k < model.nv; ++k) x[model.perm[k]] = data.band_work[k];
}

inline bool factor_penalized(const CoreModel &model, CoreData &data, double alpha) {
  data.P_factored = false;
  if (model.banded_penalized) return factor_penalized_band(model, data, alpha);
  if (model.nc)
    data.P.triangularView<Eigen::Lower>() = data.J.transpose() * data.J;
  else
    data.P.setZero();
  data.P.triangularView<Eigen::Lower>() = alpha * data.P + data.M;
  return data.llt_p.compute(data.P);
}

inline void solve_penalized(const CoreModel &model, CoreData &data, Vec &x) {
  if (model.banded_penalized)
    solve_penalized_band(model, data, x);
  else
    data.llt_p.solveInPlace(x);
}

inline bool factor_normal_band(const CoreModel &model, CoreData &data, double rel_reg) {
  assemble_normal_band(model, data, rel_reg);
  return data.normal_band.factor();
}

inline void assemble_normal_band(const CoreModel &model, CoreData &data, double rel_reg) {
  const int b = data.normal_band.bandwidth();
  Mat &A = data.normal_band.A;
  for (int j = 0; j < model.nc; ++j)
    for (int k = 0; k <= b; ++k) {
      const int i = j + k;
      double v = 0.0;
      if (i < model.nc) {
        const int lo = std::max(model.jlo[i], model.jlo[j]),
                  hi = std::min(model.jhi[i], model.jhi[j]);
        if (hi >= lo)
          v = data.J.row(i).segment(lo, hi - lo + 1).dot(data.J.row(j).segment(lo, hi - lo + 1));
      }
      A(k, j) = v;
    }
  if (rel_reg != 0.0)
    A.row(0).array() += rel_reg * std::max(A.row(0).sum(), 1.0) / static_cast<double>(model.nc);
}

}  // namespace closedchain
