// closedchain._core: construction, settings and the one-evaluation Python entry points.

#pragma once

#include <chrono>
#include <limits>
#include <string>

#include "core_data.hpp"
#include "core_methods.hpp"
#include "core_model.hpp"
#include "core_partitioning.hpp"
#include "core_rows.hpp"
#include "settings.hpp"

namespace closedchain {

// -- declarations ------------------------------------------------------------

/// Settings: the method and the run's options, the solver settings (cond_max, Baumgarte
/// gains, the augmented Lagrangian's), the simulation settings (settings.hpp); the kept
/// factor of M + alpha J^T J is dropped.
void configure(CoreModel &model, CoreData &data, const RunOptions &run,
               const SolverSettings &solver, const SimulationSettings &sim);

/// tau: None, a constant (nv,) array or a callable tau(t, q, v).
void set_tau(CoreModel &model, bp::object tau);

/// (phi, J, gamma) at (q, v); gamma includes the Baumgarte terms when configured.
bp::tuple py_rows(const CoreModel &model, CoreData &data, const Vec &q, const Vec &v);

/// (a, lam) at (q, v) with generalized force tau: one whole evaluation.
bp::tuple py_forward(const CoreModel &model, CoreData &data, const Vec &q, const Vec &v,
                     const Vec &tau);

/// a at (q, v) for n_eval repetitions inside C++ (the per-evaluation cost in the loop).
Vec py_repeat(const CoreModel &model, CoreData &data, const Vec &q, const Vec &v, const Vec &tau,
              int n);

/// Mean wall time [ns] of each stage of one evaluation over n repetitions
/// (profiling): the sequence of solve(), with a clock between its stages.
bp::dict py_profile(const CoreModel &model, CoreData &data, const Vec &q, const Vec &v,
                    const Vec &tau, int n);

// -- definitions -------------------------------------------------------------

inline void configure(CoreModel &model, CoreData &data, const RunOptions &run,
                      const SolverSettings &solver, const SimulationSettings &sim) {
  const std::string &m = run.method;
  if (m == "kkt")
    model.method = KKT;
  else if (m == "schur")
    model.method = SCHUR;
  else if (m == "nullspace")
    model.method = NULLSPACE;
  else if (m == "augmented-lagrangian")
    model.method = AUGMENTED_LAGRANGIAN;
  else if (m == "reduced")
    model.method = REDUCED;
  else
    throw BadArgument{"compiled core: unknown method '" + m +
                      "'; compiled: kkt, schur, nullspace, augmented-lagrangian, reduced"};
  model.method_name = m;
  model.cond_max = solver.cond_max;
  model.baumgarte = solver.baumgarte;
  if (model.baumgarte) {
    model.baumgarte_alpha = solver.baumgarte_alpha;
    model.baumgarte_beta = solver.baumgarte_beta;
  }
  model.projection_tol = sim.projection_tol;
  model.projection_iters = sim.projection_iters;
  model.project_velocities = sim.project_velocities;
  model.singular_cond = sim.singular_cond;
  model.drift_limit = sim.drift_limit;
  model.al_penalty = solver.al_penalty;
  model.al_tol = solver.al_tol;
  model.al_max_iter = solver.al_max_iter;
  model.stage_projects = run.stage_projects;
  model.singular_zone = sim.singular_zone;
  model.stage_zone = sim.stage_singular_zone;
  model.singular_robust = run.singular_robust;
  model.dropped_tol = sim.dropped_row_tol;
  model.dropped_ratio = sim.dropped_row_ratio;
  configure_partitioning(model, data, run, sim);
  invalidate_kinematics(data);  // the kept factor of M + alpha J^T J has the old al_penalty
}

inline void set_tau(CoreModel &model, bp::object tau) {
  model.tau_function = bp::object();
  model.tau_mode = 0;
  if (tau.is_none()) return;
  if (PyCallable_Check(tau.ptr())) {
    model.tau_function = tau;
    model.np_asarray = bp::import("numpy").attr("asarray");
    model.tau_mode = 2;
    return;
  }
  Vec c = bp::extract<Vec>(tau);
  if (c.size() != model.nv) throw BadArgument{"tau must have shape (nv,)"};
  model.tau_constant = c;
  model.tau_mode = 1;
}

inline bp::tuple py_rows(const CoreModel &model, CoreData &data, const Vec &q, const Vec &v) {
  check_sizes(model, q, v);
  eval_terms(model, data, q, v);
  return bp::make_tuple(Vec(data.phi), Mat(data.J), Vec(data.gamma));
}

inline bp::tuple py_forward(const CoreModel &model, CoreData &data, const Vec &q, const Vec &v,
                            const Vec &tau) {
  check_sizes(model, q, v);
  if (tau.size() != model.nv) throw BadArgument{"tau must have shape (nv,)"};
  invalidate_kinematics(data);  // one whole evaluation per call
  solve(model, data, q, v, tau, std::numeric_limits<double>::quiet_NaN());
  return bp::make_tuple(Vec(data.a), Vec(data.lam));
}

inline Vec py_repeat(const CoreModel &model, CoreData &data, const Vec &q, const Vec &v,
                     const Vec &tau, int n) {
  check_sizes(model, q, v);
  for (int i = 0; i < n; ++i) {
    invalidate_kinematics(data);  // a whole evaluation each time (not the kinematics' reuse)
    solve(model, data, q, v, tau, std::numeric_limits<double>::quiet_NaN());
  }
  return data.a;
}

inline bp::dict py_profile(const CoreModel &model, CoreData &data, const Vec &q, const Vec &v,
                           const Vec &tau, int n) {
  check_sizes(model, q, v);
  using clock = std::chrono::steady_clock;
  double acc[4] = {0, 0, 0, 0};
  clock::time_point last;
  auto mark = [&](int stage) {
    const clock::time_point now = clock::now();
    acc[stage] += std::chrono::duration<double, std::nano>(now - last).count();
    last = now;
  };
  for (int i = 0; i < n; ++i) {
    invalidate_kinematics(data);
    last = clock::now();
    eval_terms(model, data, q, v, mark);
    dispatch(model, data, q, tau, std::numeric_limits<double>::quiet_NaN());
    mark(3);
  }
  bp::dict d;
  const char *names[4] = {"tree", "frames", "rows", "solve"};
  for (int k = 0; k < 4; ++k) d[names[k]] = acc[k] / n;
  return d;
}

}  // namespace closedchain
