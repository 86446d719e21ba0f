// closedchain._core: the samples of a run (state, residuals, energy, branch sign) and progress.
// (Member functions of Core, declared in core.hpp.)

#pragma once

#include <pinocchio/algorithm/energy.hpp>

#include <cmath>

#include "core.hpp"

namespace closedchain {

inline void Core::set_branch_columns(const Eigen::VectorXi &cols) {
  if (cols.size() != 0 && cols.size() != nc_)
    throw BadArgument{"Core.set_branch_columns: need nc = " + std::to_string(nc_) + " columns"};
  for (Eigen::Index i = 0; i < cols.size(); ++i)
    if (cols[i] < 0 || cols[i] >= nv_)
      throw BadArgument{"Core.set_branch_columns: column out of range"};
  branch_cols_ = cols;
  lu_branch_.resize(cols.size());
}

inline double Core::branch_sign() {
  for (Eigen::Index j = 0; j < branch_cols_.size(); ++j)
    lu_branch_.A.col(j) = J_.col(branch_cols_[j]);
  lu_branch_.factor_in_place();
  return lu_branch_.det_sign();
}

inline void Core::record(Samples &out, double t, const Vec &q, const Vec &v) {
  // a_ and lam_ are those at (t, q, v)
  // res: max |phi| over every declared row (a loop is never reported closed while
  // a dropped row is open); vres: max |J v| over the kept rows.
  double res = 0.0, vres = 0.0;
  int worst = -1;
  if (nc_ || !drows_.empty()) {
    eval_phi_J(q);
    if (!drows_.empty()) {
      declared_phi();
      for (Eigen::Index r = 0; r < dphi_.size(); ++r)
        if (!(std::abs(dphi_[r]) <= res)) {
          res = std::abs(dphi_[r]);
          worst = static_cast<int>(r);
        }
    } else {
      res = phi_.cwiseAbs().maxCoeff();
    }
    if (nc_) {
      vel_c_.noalias() = J_ * v;
      vres = vel_c_.cwiseAbs().maxCoeff();
    }
  }
  if (!std::isfinite(res) || res > drift_limit_)
    throw SimulationFailure{
        name_ + ": the state left the constraint manifold at t = " + fmt("%.9g", t) +
            " s (max |phi| = " + fmt("%.3e", res) + " > drift_limit " +
            fmt("%.1e", drift_limit_) + (worst >= 0 ? ", row " + dlabels_[worst] : "") +
            "); use a stabilization or a smaller step",
        t};
  // Energies: from the last eval_terms when it was at (q, v) (the loops record
  // right after accel there), else from Pinocchio's own passes.
  double ke, pe;
  if (q == terms_q_ && v == terms_v_) {
    ke = 0.5 * v.dot(M_.lazyProduct(v));
    pe = potential_energy_;
  } else {
    ke = pinocchio::computeKineticEnergy(model_, data_, q, v);
    pe = pinocchio::computePotentialEnergy(model_, data_, q);
    invalidate_kinematics();  // Pinocchio's passes moved data_'s placements to q
  }
  out.t.push_back(t);
  out.res.push_back(res);
  out.vres.push_back(vres);
  out.e.push_back(ke + pe);
  out.ke.push_back(ke);
  out.q.insert(out.q.end(), q.data(), q.data() + nq_);
  out.v.insert(out.v.end(), v.data(), v.data() + nv_);
  out.a.insert(out.a.end(), a_.data(), a_.data() + nv_);
  out.lam.insert(out.lam.end(), lam_.data(), lam_.data() + nc_);
  if (branch_cols_.size() && nc_) out.branch.push_back(branch_sign());  // J_ at q (eval_phi_J)
}

inline bp::object Core::block(const std::vector<double> &x, long rows, long cols) {
  Mat m(rows, cols);
  for (long i = 0; i < rows; ++i)
    for (long j = 0; j < cols; ++j) m(i, j) = x[i * cols + j];
  return bp::object(m);
}

inline bp::dict Core::samples_dict(const Samples &s, long steps) {
  long n = static_cast<long>(s.t.size());
  bp::dict d;
  d["t"] = block(s.t, n, 1);
  d["q"] = block(s.q, n, nq_);
  d["v"] = block(s.v, n, nv_);
  d["a"] = block(s.a, n, nv_);
  d["lam"] = block(s.lam, n, nc_);
  d["res"] = block(s.res, n, 1);
  d["vres"] = block(s.vres, n, 1);
  d["e"] = block(s.e, n, 1);
  d["ke"] = block(s.ke, n, 1);
  if (branch_cols_.size() && nc_) d["branch"] = block(s.branch, n, 1);
  d["steps"] = steps;
  d["evaluations"] = n_evals_;
  d["repartitions"] = repartitions_list();
  return d;
}

inline void Core::poll(long k, double t, const bp::object &progress) {
  if (!progress.is_none()) progress(t);
  if ((k & 63) == 0 && PyErr_CheckSignals() != 0) bp::throw_error_already_set();
}

inline void Core::check_finite(const Vec &q, const Vec &v, double t) {
  if (!(q.allFinite() && v.allFinite()))
    throw SimulationFailure{name_ + ": non-finite state at t = " + fmt("%.9g", t) + " s", t};
}

}  // namespace closedchain
