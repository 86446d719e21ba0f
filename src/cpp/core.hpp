// closedchain._core: class Core, the simulator facade the Python bindings use: one
// mechanism's CoreModel (what is fixed once it is built and configured) and CoreData (every
// buffer and cache), and one member per bound entry point, each forwarding to the free
// function of its concept header:
//
//   core_model.hpp, core_data.hpp   the model and the data
//   core_rows.hpp                   cut frames, phi, J, gamma, the tree terms (eval_terms)
//   core_structure.hpp              sparsity, band paths, products over the structure
//   core_methods.hpp                KKT, Schur, null space, augmented Lagrangian, reduced
//   core_tree.hpp                   the tree path of every method but schur
//   core_projection.hpp             projection and the checks of every step
//   core_partitioning.hpp           coordinate partitioning (dependent solve, re-partitioning)
//   closure_newton.hpp              the assembly's Gauss-Newton onto phi = 0 (free coordinates)
//   core_recording.hpp              the samples of a run
//   core_chart.hpp                  the chart of q when nq != nv
//   core_fixed.hpp                  euler, semi-implicit, rk4 (with stage projection)
//   core_adaptive.hpp               RK45, DOP853 (scipy's error control, dense output), rk43, dop853-rk43
//   ali3p.hpp                       ALI3-P
//   core_interface.hpp              settings and the one-evaluation entry points

#pragma once

#include <Eigen/Dense>
#include <boost/python.hpp>

#include <string>

#include "ali3p.hpp"
#include "closure_newton.hpp"
#include "common.hpp"
#include "core_adaptive.hpp"
#include "core_data.hpp"
#include "core_fixed.hpp"
#include "core_interface.hpp"
#include "core_model.hpp"
#include "core_partitioning.hpp"
#include "core_recording.hpp"
#include "core_rows.hpp"
#include "core_structure.hpp"
#include "core_tree.hpp"
#include "settings.hpp"

namespace closedchain {

/// The compiled constraint rows, dynamics methods and integration loops of one mechanism.
class Core {
 public:
  /// Build from the Pinocchio model and the constraint layer's row table (CoreModel's
  /// constructor), with every buffer sized once.
  Core(bp::object model_obj, const std::string &name, const Eigen::VectorXi &kinds,
       const Eigen::VectorXi &fid_p, const Eigen::VectorXi &fid_s, const Mat &vec1, const Mat &vec2)
      : model_(model_obj, name, kinds, fid_p, fid_s, vec1, vec2), data_(model_) {}

  /// Settings: the method and the run's options, the solver settings (cond_max, Baumgarte
  /// gains, the augmented Lagrangian's), the simulation settings (configure).
  void configure(const RunOptions &run, const SolverSettings &solver,
                 const SimulationSettings &sim) {
    closedchain::configure(model_, data_, run, solver, sim);
  }

  /// tau: None, a constant (nv,) array or a callable tau(t, q, v) (set_tau).
  void set_tau(bp::object tau) { closedchain::set_tau(model_, tau); }

  /// The joint springs (indices into q and v, stiffness, reference) and the damping per
  /// velocity coordinate (shape (nv,) or (0,)): tau_passive = -K (q - q_ref) - D v.
  void set_passive(const Eigen::VectorXi &idx_q, const Eigen::VectorXi &idx_v, const Vec &k,
                   const Vec &ref, const Vec &damping) {
    model_.passive.set(model_.nq, model_.nv, idx_q, idx_v, k, ref, damping);
  }

  /// Every declared row, kept[i] = 1 for the rows the methods use (set_declared).
  void set_declared(const Eigen::VectorXi &kinds, const Eigen::VectorXi &fid_p,
                    const Eigen::VectorXi &fid_s, const Mat &vec1, const Mat &vec2,
                    const Eigen::VectorXi &kept, bp::list labels) {
    closedchain::set_declared(model_, data_, kinds, fid_p, fid_s, vec1, vec2, kept, labels);
  }

  /// The band paths; returns their half bandwidths (set_band).
  bp::tuple set_band(const Eigen::VectorXi &perm, bool banded_p, bool banded_n) {
    return closedchain::set_band(model_, data_, perm, banded_p, banded_n);
  }

  /// True when the configured method takes the tree path (CoreModel::tree_solves).
  bool tree_solves() const { return model_.tree_solves(); }

  /// Allow the tree path (chosen at construction by size) or not (set_tree_path).
  void set_tree_path(bool on) { closedchain::set_tree_path(model_, data_, on); }

  /// (banded_p, banded_n, b_p, b_n) as set by set_band.
  bp::tuple band_info() const {
    return bp::make_tuple(model_.banded_penalized, model_.banded_normal,
                          model_.penalized_bandwidth, model_.normal_bandwidth);
  }

  /// (phi, J, gamma) at (q, v) (py_rows).
  bp::tuple py_rows(const Vec &q, const Vec &v) {
    return closedchain::py_rows(model_, data_, q, v);
  }

  /// (a, lam) at (q, v) with force tau (py_forward).
  bp::tuple py_forward(const Vec &q, const Vec &v, const Vec &tau) {
    return closedchain::py_forward(model_, data_, q, v, tau);
  }

  /// a at (q, v) after n evaluations inside C++ (py_repeat).
  Vec py_repeat(const Vec &q, const Vec &v, const Vec &tau, int n) {
    return closedchain::py_repeat(model_, data_, q, v, tau, n);
  }

  /// Mean time [ns] of each stage of one evaluation (py_profile).
  bp::dict py_profile(const Vec &q, const Vec &v, const Vec &tau, int n) {
    return closedchain::py_profile(model_, data_, q, v, tau, n);
  }

  /// Record the sign of det(J[:, cols]) with every sample (set_branch_columns).
  void set_branch_columns(const Eigen::VectorXi &cols) {
    closedchain::set_branch_columns(model_, data_, cols);
  }

  /// euler, semi-implicit or rk4 at the fixed step dt (run_fixed).
  bp::dict run_fixed(int integrator, const Vec &q0, const Vec &v0, double dt, long n_steps,
                     const Eigen::VectorXi &out_steps, bool projects, bp::object progress) {
    return closedchain::run_fixed(model_, data_, integrator, q0, v0, dt, n_steps, out_steps,
                                  projects, progress);
  }

  /// ALI3-P at the fixed step dt with the settings SimulationSettings.ali3p_* (run_ali3p).
  bp::dict run_ali3p(const Vec &q0, const Vec &v0, double dt, long n_steps,
                     const Eigen::VectorXi &out_steps, const Ali3pSettings &settings,
                     bp::object progress) {
    return closedchain::run_ali3p(model_, data_, q0, v0, dt, n_steps, out_steps, settings,
                                  progress);
  }

  /// RK45 or DOP853 to t_final (run_adaptive).
  bp::dict run_adaptive(int integrator, const Vec &q0, const Vec &v0, double t_final, double rtol,
                        double atol, bp::object t_eval_obj, bool projects, bp::object progress) {
    return closedchain::run_adaptive(model_, data_, integrator, q0, v0, t_final, rtol, atol,
                                     t_eval_obj, projects, progress);
  }

  /// rk4 with stage projection, its step chosen by the embedded third-order estimate, to
  /// t_final (run_rk43).
  bp::dict run_rk43(const Vec &q0, const Vec &v0, double t_final, double rtol, double atol,
                    double h0, bp::object t_eval_obj, bool record_all, bp::object progress) {
    return closedchain::run_rk43(model_, data_, q0, v0, t_final, rtol, atol, h0, t_eval_obj,
                                 record_all, progress);
  }

  /// dop853-rk43: DOP853 far from singular positions, rk43 near them, to t_final
  /// (run_dop853_rk43).
  bp::dict run_dop853_rk43(const Vec &q0, const Vec &v0, double t_final, double rtol,
                           double atol, double h0, bp::object t_eval, bp::object progress) {
    return closedchain::run_dop853_rk43(model_, data_, q0, v0, t_final, rtol, atol, h0, t_eval,
                                        progress);
  }

  /// The reduced method's partition and the coordinates' names (set_partition).
  void set_partition(const Eigen::VectorXi &ind, bp::list names) {
    closedchain::set_partition(model_, data_, ind, names);
  }

  /// The loops' alignment checks of the dependent solve (set_alignment).
  void set_alignment(const Eigen::VectorXi &fid_p, const Eigen::VectorXi &fid_s, const Mat &u,
                     const Eigen::VectorXi &loop, bp::list loop_names) {
    closedchain::set_alignment(model_, data_, fid_p, fid_s, u, loop, loop_names);
  }

  /// (independent, dependent) velocity indices of the stabilization's partition.
  bp::tuple py_partition() const { return closedchain::py_partition(data_); }

  /// Number of kept constraint rows.
  int nc() const { return model_.nc; }

  /// The mechanism, its structure and settings (the per-call entry points, percall.hpp).
  const CoreModel &model() const { return model_; }

  /// The buffers of its evaluations (the per-call entry points, percall.hpp).
  CoreData &data() { return data_; }

  /// Right-hand side evaluations of the last run.
  long n_evals() const { return data_.n_evals; }

 private:
  /// The mechanism, its structure and settings.
  CoreModel model_;
  /// Every buffer and cache of its evaluations and runs.
  CoreData data_;
};

}  // namespace closedchain
