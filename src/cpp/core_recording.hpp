// closedchain._core: the samples of a run (state, residuals, energy, branch sign) and progress.
// (Functions over (CoreModel, CoreData): their declarations, then their definitions.)

#pragma once

#include <pinocchio/algorithm/energy.hpp>
#include <pinocchio/algorithm/kinematics.hpp>

#include <cmath>
#include <vector>

#include "core_data.hpp"
#include "core_model.hpp"
#include "core_partitioning.hpp"
#include "core_rows.hpp"
#include "core_tree.hpp"
#include "errors.hpp"
#include "gil.hpp"

namespace closedchain {

/// The samples of a run, one entry (or one row of nq, nv or nc entries) per output time.
struct Samples {
  /// Time [s]; max |phi| over the declared rows [m or 1]; max |J v| [m/s or 1/s]; total and
  /// kinetic energy [J]; sign of det(J[:, branch_columns]).
  std::vector<double> t, res, vres, e, ke, branch;
  /// State, accelerations and multipliers, row-major.
  std::vector<double> q, v, a, lam;
};

// -- declarations ------------------------------------------------------------

/// The columns D of J whose sign of det(J[:, D]) is recorded with every sample (the
/// assembly branch, Recorder._add_branch); empty: none recorded.
void set_branch_columns(CoreModel &model, CoreData &data, const Eigen::VectorXi &cols);

/// Sign of det(data.J[:, model.branch_columns]) (data.J at the sample's q): the parity of the row
/// swaps of an LU with partial pivoting times the signs of its pivots, 0 for an
/// exactly zero pivot (numpy.linalg.slogdet's sign).
double branch_sign(const CoreModel &model, CoreData &data);

/// Append the sample at (t, q, v) with the last solve's (a, lam): residuals over every
/// declared row (SimulationFailure beyond drift_limit), energies, branch sign.
void record(const CoreModel &model, CoreData &data, Samples &out, double t, const Vec &q,
            const Vec &v);

/// The row-major values x as a (rows, cols) numpy array.
bp::object sample_matrix(const std::vector<double> &x, long rows, long cols);

/// The dict of a run's samples (t, q, v, a, lam, res, vres, e, ke, branch), steps,
/// evaluations and re-partitions.
bp::dict samples_dict(const CoreModel &model, const CoreData &data, const Samples &s, long steps);

/// Call progress(t) (when given) and, every 64 steps, check for Ctrl-C, holding the GIL
/// for them only (the loops release it: gil.hpp).
void poll(long k, double t, const bp::object &progress);

/// SimulationFailure when q or v is not finite at t.
void check_finite(const CoreModel &model, const Vec &q, const Vec &v, double t);

/// out[k] = 1 for the steps k of out_steps within 0..n_steps: where a fixed-step run records.
std::vector<char> output_mask(const Eigen::VectorXi &out_steps, long n_steps);

// -- definitions -------------------------------------------------------------

inline void set_branch_columns(CoreModel &model, CoreData &data, const Eigen::VectorXi &cols) {
  if (cols.size() != 0 && cols.size() != model.nc)
    throw BadArgument{"Core.set_branch_columns: need nc = " + std::to_string(model.nc) +
                      " columns"};
  for (Eigen::Index i = 0; i < cols.size(); ++i)
    if (cols[i] < 0 || cols[i] >= model.nv)
      throw BadArgument{"Core.set_branch_columns: column out of range"};
  model.branch_columns = cols;
  data.lu_branch.resize(cols.size());
}

inline double branch_sign(const CoreModel &model, CoreData &data) {
  for (Eigen::Index j = 0; j < model.branch_columns.size(); ++j)
    data.lu_branch.A.col(j) = data.J.col(model.branch_columns[j]);
  data.lu_branch.factor_in_place();
  return data.lu_branch.det_sign();
}

inline void record(const CoreModel &model, CoreData &data, Samples &out, double t, const Vec &q,
                   const Vec &v) {
  // data.a and data.lam are those at (t, q, v)
  // res: max |phi| over every declared row (a loop is never reported closed while
  // a dropped row is open); vres: max |J v| over the kept rows.
  double res = 0.0, vres = 0.0;
  int worst = -1;
  if (model.nc || !model.declared_rows.empty()) {
    eval_phi_J(model, data, q);
    if (!model.declared_rows.empty()) {
      declared_phi(model, data);
      for (Eigen::Index r = 0; r < data.declared_residuals.size(); ++r)
        if (!(std::abs(data.declared_residuals[r]) <= res)) {
          res = std::abs(data.declared_residuals[r]);
          worst = static_cast<int>(r);
        }
    } else {
      res = data.phi.cwiseAbs().maxCoeff();
    }
    if (model.nc) {
      data.vel_c.noalias() = data.J * v;
      vres = data.vel_c.cwiseAbs().maxCoeff();
    }
  }
  check_drift(model, res, worst, t);
  // Energies: from the last eval_terms when it was at (q, v) (the loops record
  // right after accel there), else from Pinocchio's own passes. On the tree path (M not
  // formed) the kinetic energy is the Newton-Euler product's, while the factorization is
  // at q.
  double ke, pe;
  const bool tree_ke = model.tree_solves() && !data.M_at_J;
  if (q == data.terms_q && v == data.terms_v &&
      (!tree_ke || (data.tree_mass_factored && data.J_at_valid && q == data.J_at))) {
    ke = tree_ke ? tree_kinetic_energy(model, data, v) : 0.5 * v.dot(data.M.lazyProduct(v));
    pe = data.potential_energy;
  } else {
    // 1/2 sum v_i . I_i v_i + 1/2 v^T diag(armature) v: Pinocchio 4.1's
    // computeKineticEnergy leaves out the armature of revolute joints about unaligned axes.
    pinocchio::forwardKinematics(model.tree, data.tree, q, v);
    ke = model.tree.armature.dot(v.cwiseAbs2());
    for (pinocchio::JointIndex i = 1; i < (pinocchio::JointIndex)model.tree.njoints; ++i)
      ke += model.tree.inertias[i].vtiv(data.tree.v[i]);
    ke *= 0.5;
    pe = pinocchio::computePotentialEnergy(model.tree, data.tree, q);
    invalidate_kinematics(data);  // Pinocchio's passes moved data.tree's placements to q
  }
  out.t.push_back(t);
  out.res.push_back(res);
  out.vres.push_back(vres);
  out.e.push_back(ke + pe);
  out.ke.push_back(ke);
  out.q.insert(out.q.end(), q.data(), q.data() + model.nq);
  out.v.insert(out.v.end(), v.data(), v.data() + model.nv);
  out.a.insert(out.a.end(), data.a.data(), data.a.data() + model.nv);
  out.lam.insert(out.lam.end(), data.lam.data(), data.lam.data() + model.nc);
  if (model.branch_columns.size() && model.nc)
    out.branch.push_back(branch_sign(model, data));  // data.J at q (eval_phi_J)
}

inline bp::object sample_matrix(const std::vector<double> &x, long rows, long cols) {
  Mat m(rows, cols);
  for (long i = 0; i < rows; ++i)
    for (long j = 0; j < cols; ++j) m(i, j) = x[i * cols + j];
  return bp::object(m);
}

inline bp::dict samples_dict(const CoreModel &model, const CoreData &data, const Samples &s,
                             long steps) {
  long n = static_cast<long>(s.t.size());
  bp::dict d;
  d["t"] = sample_matrix(s.t, n, 1);
  d["q"] = sample_matrix(s.q, n, model.nq);
  d["v"] = sample_matrix(s.v, n, model.nv);
  d["a"] = sample_matrix(s.a, n, model.nv);
  d["lam"] = sample_matrix(s.lam, n, model.nc);
  d["res"] = sample_matrix(s.res, n, 1);
  d["vres"] = sample_matrix(s.vres, n, 1);
  d["e"] = sample_matrix(s.e, n, 1);
  d["ke"] = sample_matrix(s.ke, n, 1);
  if (model.branch_columns.size() && model.nc) d["branch"] = sample_matrix(s.branch, n, 1);
  d["steps"] = steps;
  d["evaluations"] = data.n_evals;
  d["repartitions"] = repartitions_list(data);
  return d;
}

inline void poll(long k, double t, const bp::object &progress) {
  const bool signals = (k & 63) == 0;
  if (progress.is_none() && !signals) return;  // no call into Python: the GIL stays free
  GilHeld gil;
  if (!progress.is_none()) progress(t);
  if (signals && PyErr_CheckSignals() != 0) bp::throw_error_already_set();
}

inline void check_finite(const CoreModel &model, const Vec &q, const Vec &v, double t) {
  if (!(q.allFinite() && v.allFinite()))
    throw SimulationFailure{model.name + ": non-finite state at t = " + fmt("%.9g", t) + " s", t};
}

inline std::vector<char> output_mask(const Eigen::VectorXi &out_steps, long n_steps) {
  std::vector<char> out(n_steps + 1, 0);
  for (Eigen::Index i = 0; i < out_steps.size(); ++i)
    if (out_steps[i] >= 0 && out_steps[i] <= n_steps) out[out_steps[i]] = 1;
  return out;
}

}  // namespace closedchain
