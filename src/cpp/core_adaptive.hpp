// closedchain._core: the adaptive loops (RK45, DOP853 with scipy's error control) and the
// chart of q when nq != nv.
// (Functions over (CoreModel, CoreData): their declarations, then their definitions.)

#pragma once

#include <pinocchio/algorithm/joint-configuration.hpp>

#include <algorithm>
#include <cmath>
#include <limits>
#include <string>
#include <vector>

#include "core_chart.hpp"
#include "core_data.hpp"
#include "core_fixed.hpp"
#include "core_methods.hpp"
#include "core_model.hpp"
#include "core_partitioning.hpp"
#include "core_projection.hpp"
#include "core_recording.hpp"
#include "core_rows.hpp"
#include "gil.hpp"
#include "rk_coefficients.hpp"

namespace closedchain {

// -- declarations ------------------------------------------------------------

/// Root mean square of x (scipy's norm of the error estimate).
double rms(const Vec &x);

/// The right-hand side dy/dt = f(t, y) of the adaptive loops: y = (q or the chart's x, v),
/// or (q_I, v_I) with partitioning (fun_partitioned).
void fun(const CoreModel &model, CoreData &data, double t, const Vec &y, Eigen::Ref<Vec> f);

/// The state of one adaptive run (scipy's RungeKutta): the tableau, the tolerances, the
/// integrated state y and its rate f, the stages, the dense-output coefficients and the
/// samples. y is (q or the chart's x, v), or (q_I, v_I) with partitioning.
struct AdaptiveRun {
  /// The tableau of `integrator` (RK45 or DOP853), the tolerances (rtol at least 100 eps,
  /// scipy's validate_tol) and the output times t_eval (None: every step).
  AdaptiveRun(const CoreModel &model, int integrator, double rtol, double atol,
              bp::object t_eval_obj);

  /// DOP853 (else RK45); its stages; the step-size exponent -1 / (error order + 1).
  bool dop;
  int n_stages;
  double error_exponent;
  /// Relative and absolute tolerances.
  double rtol, atol;
  /// The integrator's name, for messages.
  std::string name;
  /// Size of the integrated positions (nv, or nv - nc with partitioning) and of y.
  int ns, n;
  /// Output at the times `pending` (the next one pending[ip]), else at every step.
  bool dense;
  std::vector<double> pending;
  std::size_t ip = 0;
  /// Time [s] of y, end of the step being taken, its length and the next step's size.
  double t = 0.0, t_new = 0.0, h = 0.0, h_abs = 0.0;
  /// State and rate at t and at t_new; error scale; work vectors (shape (n,)).
  Vec y, y_new, f, f_new, scale, dy, ye, tmp, e5, e3;
  /// The full state (q, v) completed from y (partitioning), the output's (q, v), the
  /// chart coordinates of a projected q.
  Vec qc, vc, q_out, v_out, x_out;
  /// The stages' rates, shape (n, stages); the dense-output coefficients of y and of q_D.
  Mat K, F, FD;
  /// The samples recorded.
  Samples samples;
};

/// The run's initial state y: (q0, v0), in the chart when nq != nv, or (q_I, v_I) after
/// completing (q0, v0) with partitioning.
void adaptive_start(const CoreModel &model, CoreData &data, AdaptiveRun &run, const Vec &q0,
                    const Vec &v0);

/// Evaluate and record the state y at t (completed with partitioning).
void adaptive_output(const CoreModel &model, CoreData &data, AdaptiveRun &run, double t,
                     const Vec &y);

/// The first step's size [s] (scipy's select_initial_step) from y and f at run.t.
double initial_step(const CoreModel &model, CoreData &data, AdaptiveRun &run, double t_final);

/// The Runge-Kutta stages of the step of length run.h from (run.t, run.y): run.K, y_new and
/// f_new (rk_step), the stages' v_D with partitioning.
void rk_stages(const CoreModel &model, CoreData &data, AdaptiveRun &run);

/// The error norm of the step just taken (scipy's _estimate_error_norm; DOP853's with
/// its 5th- and 3rd-order estimates).
double error_norm(AdaptiveRun &run);

/// Take one step of scipy's RungeKutta._step_impl: steps of size run.h_abs until one is
/// accepted; run.t_new, run.h of the step taken, run.h_abs the next step's size.
/// SimulationFailure when the step size falls below the spacing of numbers at t.
void accepted_step(const CoreModel &model, CoreData &data, AdaptiveRun &run, double t_final);

/// DOP853's dense-output coefficients of the step (its three extra stages), of q_D too with
/// partitioning (from the stages' v_D).
void dop853_dense_coefficients(const CoreModel &model, CoreData &data, AdaptiveRun &run,
                               double t_old);

/// RK45's dense-output coefficients Q = K^T P of the step, of q_D too with partitioning.
void rk45_dense_coefficients(const CoreModel &model, CoreData &data, AdaptiveRun &run);

/// The interpolated state at the fraction x of the step into run.ye, and the guess of q_D
/// for its dependent solve (data.guess_qD) with partitioning.
void dense_state(const CoreModel &model, CoreData &data, AdaptiveRun &run, double x);

/// Record the output times within the step from t_old to run.t_new by dense output (from
/// the unprojected step).
void dense_outputs(const CoreModel &model, CoreData &data, AdaptiveRun &run, double t_old);

/// After an accepted step (y at run.t): check that it is finite, project it (projects),
/// re-centre the chart, and check the step (check_regular).
void finish_step(const CoreModel &model, CoreData &data, AdaptiveRun &run, double t_final,
                 bool projects);

/// Integrate with RK45 or DOP853 (scipy's RungeKutta: the same error control, step-size
/// rule and dense output) from (q0, v0) at t = 0 to t_final, recording at every step or at
/// the times t_eval; projects: project onto the constraint manifold after every step.
bp::dict run_adaptive(const CoreModel &model, CoreData &data, int integrator, const Vec &q0,
                      const Vec &v0, double t_final, double rtol, double atol,
                      bp::object t_eval_obj, bool projects, bp::object progress);

/// The state of one rk43 run (simulate/rk43.py): the tolerances, the times the steps land
/// on, the state at t and at the end of the step being taken, the step size and the run's
/// counters.
struct Rk43Run {
  /// The tolerances, the first trial step h0 [s] and the stops: every time of t_eval > 0
  /// (None: t_final alone).
  Rk43Run(const CoreModel &model, double t_final, double rtol, double atol, double h0,
          bp::object t_eval_obj, bool record_all);

  /// Relative and absolute tolerances of the error estimate.
  double rtol, atol;
  /// The times [s] the steps land on, in order; the start is recorded (t_eval is None or
  /// starts at 0); every step end is recorded (t_eval None or record_all).
  std::vector<double> stops;
  bool record_start = true, every = true;
  /// Time [s] of (q, v, a) and the next trial step [s]; the end [s] of an accepted
  /// DOP853 trial (dop853-rk43).
  double t = 0.0, h, t_far_end = 0.0;
  /// rk43_accept records the step's end (dop853-rk43 records it after the outputs
  /// within the step).
  bool record_steps = true;
  /// The state at t: q (nq,), v and a (nv,).
  Vec q, v, a;
  /// The state at the end of the step being taken.
  Vec qn, vn, an;
  /// The end of the first substep of a retake around a singular position.
  Vec q1, v1, a1;
  /// rk4_projected's projected midpoint q; the chart rate at the step's end; the position
  /// part of the error estimate.
  Vec qm, k5v, ex;
  /// The rank indicator at q.
  double rho_start = 0.0;
  /// Largest accepted error norm; sum of the accepted steps' largest position errors.
  double err_max = 0.0, err_sum = 0.0;
  /// Accepted steps, rejected trials, steps retaken around a singular position; with
  /// dop853-rk43, its DOP853 steps and the rk43 steps kept within the indicator's cap.
  long steps = 0, rejected = 0, splits = 0, far_steps = 0, zone_steps = 0;
  /// The samples recorded.
  Samples samples;
};

/// One trial of rk43 from run.t: its error norm (scipy's weighted RMS), the largest
/// position error [rad or m], the rank indicator at its end, and the retake around a
/// singular position it plans (retake_plan: twice, the first substep f [steps], span).
struct Rk43Trial {
  /// Error norm (accepted at most 1); largest position error [rad or m]; rank indicator
  /// at the trial's end.
  double err = 0.0, exm = 0.0, rho_new = 0.0;
  /// A retake is planned; it spans two steps; it is split in two substeps.
  bool plan = false, twice = false, sub = false;
  /// The first substep [steps] and the retake's length [steps].
  double f = 0.0, span = 1.0;
};

/// The step-size factor after a trial with error norm err (rk43.py: SAFETY err^(-1/4)
/// within [MIN_FACTOR, MAX_FACTOR]).
double rk43_factor(double err);

/// One projected rk4 step from (qa, va, aa) at t of length h with its estimate
/// (rk43._Estimator.step): (qb, vb, ab) at the end, err in scipy's weighted RMS norm of
/// (h / 6) (k4 - k5), exm the largest position error [rad or m]; returns the rank
/// indicator at the projected midpoint.
double rk43_step(const CoreModel &model, CoreData &data, Rk43Run &run, double t, const Vec &qa,
                 const Vec &va, const Vec &aa, double h, Vec &qb, Vec &vb, Vec &ab, double &err,
                 double &exm);

/// The state at t = 0: the stage buffers sized, (q0, v0) evaluated, recorded unless t_eval
/// starts later, and the rank indicator there.
void rk43_start(const CoreModel &model, CoreData &data, Rk43Run &run, const Vec &q0,
                const Vec &v0);

/// Retake the step around a singular position as trial.plan says: one step of span steps
/// or two substeps split at trial.f; false when the step must be re-planned (two steps
/// would pass t_stop: run.h halved to end there).
bool rk43_retake(const CoreModel &model, CoreData &data, Rk43Run &run, double t_stop,
                 Rk43Trial &trial);

/// Accept the trial: check the substep's and the step's ends (check_regular), move the
/// state to the end, record it, and the next step size (kept for a step within the
/// indicator's cap, in_zone).
void rk43_accept(const CoreModel &model, CoreData &data, Rk43Run &run, const Rk43Trial &trial,
                 double t_stop, bool clipped, double proposed, bool in_zone,
                 const bp::object &progress);

struct Dop853Far;

/// One trial step toward t_stop (clipped to land on it); true when accepted, false when
/// rejected (run.h reduced) or re-planned. SimulationFailure when the step falls below the
/// spacing of the times. far: dop853-rk43's DOP853 state (its steps near a singular
/// position: the step bounded by Dop853Far::near_step, kept whatever its estimate within
/// the indicator's cap), or nullptr (rk43).
bool rk43_try_step(const CoreModel &model, CoreData &data, Rk43Run &run, double t_stop,
                   const bp::object &progress, const Dop853Far *far = nullptr);

/// The DOP853 trials of dop853-rk43 (simulate/dop853_rk43.py, Dop853Far): the tolerances,
/// the next trial step, the rank indicator's steepest rate over the last trial and its
/// uncapped value at the last accepted DOP853 end, the stages' rates.
struct Dop853Far {
  /// The tolerances and the first trial step h0 [s].
  Dop853Far(const CoreModel &model, double rtol, double atol, double h0);
  /// Relative and absolute tolerances.
  double rtol, atol;
  /// The next trial step [s]; the step being taken was rejected before.
  double h;
  bool rejected = false;
  /// The indicator's steepest rate over the last trial [1/s].
  double rate = 0.0;
  /// Time [s] and uncapped indicator of the last accepted DOP853 end.
  double start_t = std::numeric_limits<double>::quiet_NaN(), start_rho = 0.0;
  /// The stages' position rates (chart about the step's start) and accelerations, shape
  /// (nv, 16): the 12 stages, the step's end, the dense output's three extra stages.
  Mat kx, ka;
  /// A stage's chart coordinates and velocity; its configuration; error estimate work;
  /// the step's end in the chart about its start.
  Vec x, vs, qs, ex, ev, xn;
  /// The dense output's coefficients of x and v, shape (nv, 7), and an output's state.
  Mat fx, fv;
  Vec xo, vo, qo;
  /// The indicator's samples of the trial: times [s] and values, and their number.
  double sample_t[4] = {0, 0, 0, 0}, sample_r[4] = {0, 0, 0, 0};
  int n_samples = 0;
  /// An rk43 step [s]: h at most NEAR_ENTRY_FRACTION cap / rate.
  double near_step(double h_near) const;
  /// Add a sample and return the steepest rate between consecutive samples [1/s].
  double add_sample(double t, double r);
};

/// Outcomes of a DOP853 trial: the indicator fell below its cap (take an rk43 step),
/// rejected, accepted.
enum FarOutcome { FAR_NEAR = 0, FAR_REJECTED = 1, FAR_ACCEPTED = 2 };

/// One DOP853 trial from run's state toward t_land [s] (Dop853Far.trial): the end in run.qn,
/// vn, an and the estimate in trial when accepted.
FarOutcome dop853_far_trial(const CoreModel &model, CoreData &data, Rk43Run &run,
                            Dop853Far &far, double t_land, Rk43Trial &trial);

/// The dense output of the DOP853 step of length h just accepted from (q, v) at t (its
/// three extra stages; far.xn the end's chart coordinates, far.vo the velocity's change).
void dop853_far_dense(const CoreModel &model, CoreData &data, const Vec &q, const Vec &v,
                      double t, double h, Dop853Far &far);

/// Record the dense output at the fraction theta of the step from (q, v): q and v
/// projected as at a step's end, its accelerations.
void dop853_far_output(const CoreModel &model, CoreData &data, Rk43Run &run, Dop853Far &far,
                       const Vec &q, const Vec &v, double t_out, double theta);

/// dop853-rk43 (simulate/dop853_rk43.py, step for step): DOP853 steps where the rank
/// indicator is at its cap, rk43 steps near singular positions at tolerances at least
/// (NEAR_RTOL, NEAR_ATOL); every step end recorded, and the times t_eval (None: none)
/// within the steps (DOP853's dense output, rk43's cubic Hermite), their samples listed
/// in "outputs".
bp::dict run_dop853_rk43(const CoreModel &model, CoreData &data, const Vec &q0, const Vec &v0,
                         double t_final, double rtol, double atol, double h0,
                         bp::object t_eval_obj, bp::object progress);

/// rk43 (simulate/rk43.py, step for step): rk4 with stage projection and the retakes near
/// singular positions, its step chosen by the embedded third-order estimate
/// (h / 6) (k4 - k5); first trial step h0 [s]; the steps land on every time of t_eval (or
/// t_final), recorded there, and at every step end with record_all.
bp::dict run_rk43(const CoreModel &model, CoreData &data, const Vec &q0, const Vec &v0,
                  double t_final, double rtol, double atol, double h0, bp::object t_eval_obj,
                  bool record_all, bp::object progress);

// -- definitions -------------------------------------------------------------

inline double rms(const Vec &x) { return x.norm() / std::sqrt(static_cast<double>(x.size())); }

inline void fun(const CoreModel &model, CoreData &data, double t, const Vec &y, Eigen::Ref<Vec> f) {
  if (model.partitions) {
    fun_partitioned(model, data, t, y, f);
    return;
  }
  accel(model, data, t, chart_q(model, data, y.head(model.nv)), y.tail(model.nv));
  if (data.chart)
    chart_rate(model, data, data.chart_centre, y.head(model.nv), y.tail(model.nv),
               f.head(model.nv));
  else
    f.head(model.nv) = y.tail(model.nv);
  f.tail(model.nv) = data.a;
}

inline AdaptiveRun::AdaptiveRun(const CoreModel &model, int integrator, double relative_tol,
                                double absolute_tol, bp::object t_eval_obj)
    : dop(integrator == DOP853),
      n_stages(dop ? dop853::N_STAGES : rk45::N_STAGES),
      error_exponent(-1.0 / ((dop ? 7 : 4) + 1)),
      rtol(std::max(relative_tol, 100 * std::numeric_limits<double>::epsilon())),  // validate_tol
      atol(absolute_tol),
      name(dop ? "DOP853" : "RK45"),
      ns(model.partitions ? model.nv - model.nc : model.nv),
      n(2 * ns),
      dense(!t_eval_obj.is_none()) {
  if (dense) {
    Vec te = bp::extract<Vec>(t_eval_obj);
    pending.assign(te.data(), te.data() + te.size());
  }
  y.resize(n);
  y_new.resize(n);
  f.resize(n);
  f_new.resize(n);
  scale.resize(n);
  dy.resize(n);
  ye.resize(n);
  tmp.resize(n);
  e5.resize(n);
  e3.resize(n);
  qc.resize(model.nv);
  vc.resize(model.nv);
  q_out.resize(model.nq);
  v_out.resize(model.nv);
  x_out.resize(model.nv);
  K.resize(n, dop ? dop853::N_STAGES_EXTENDED : n_stages + 1);
  F.resize(n, dop853::INTERPOLATOR_POWER);
  FD.resize(model.nc, model.partitions ? dop853::INTERPOLATOR_POWER : 0);
}

inline void adaptive_start(const CoreModel &model, CoreData &data, AdaptiveRun &run, const Vec &q0,
                           const Vec &v0) {
  begin_partitioning(model, data, false);
  chart_start(model, data, q0);  // partitioning needs nq == nv (refused in Python): no chart then
  if (model.partitions) {
    run.qc = q0;
    run.vc = v0;
    complete(model, data, run.qc, run.vc, 0.0);
    data.warm_q = q0;  // the dependent solves start from the last evaluation's q
    pack(model, data, run.qc, run.vc, run.y);
  } else {
    run.y.head(model.nv) = data.chart ? Vec::Zero(model.nv) : q0;
    run.y.tail(model.nv) = v0;
  }
  data.stage_dependent_v = Mat::Zero(model.nc, run.K.cols());
}

inline void adaptive_output(const CoreModel &model, CoreData &data, AdaptiveRun &run, double t,
                            const Vec &yy) {
  if (model.partitions) {
    unpack(model, data, yy, t, run.qc, run.vc);
    accel(model, data, t, run.qc, run.vc);
    record(model, data, run.samples, t, run.qc, run.vc);
    return;
  }
  run.q_out = chart_q(model, data, yy.head(model.nv));
  run.v_out = yy.tail(model.nv);
  accel(model, data, t, run.q_out, run.v_out);
  record(model, data, run.samples, t, run.q_out, run.v_out);
}

inline double initial_step(const CoreModel &model, CoreData &data, AdaptiveRun &run,
                           double t_final) {
  const double t = run.t;
  double interval = std::abs(t_final - t);
  run.scale = run.atol + run.y.cwiseAbs().array() * run.rtol;
  double d0 = rms(run.y.cwiseQuotient(run.scale)), d1 = rms(run.f.cwiseQuotient(run.scale));
  double h0 = (d0 < 1e-5 || d1 < 1e-5) ? 1e-6 : 0.01 * d0 / d1;
  h0 = std::min(h0, interval);
  Vec y1 = run.y + h0 * run.f;
  Vec f1(run.n);
  fun(model, data, t + h0, y1, f1);
  double d2 = rms((f1 - run.f).cwiseQuotient(run.scale)) / h0;
  const int error_order = run.dop ? 7 : 4;
  double h1 = (d1 <= 1e-15 && d2 <= 1e-15)
                  ? std::max(1e-6, h0 * 1e-3)
                  : std::pow(0.01 / std::max(d1, d2), 1.0 / (error_order + 1));
  return std::min(std::min(100 * h0, h1), interval);
}

inline void rk_stages(const CoreModel &model, CoreData &data, AdaptiveRun &run) {
  const bool dop = run.dop;
  const int n_stages = run.n_stages;
  const double t = run.t, h = run.h;
  run.K.col(0) = run.f;
  if (model.partitions) data.stage_dependent_v.col(0) = data.start_dependent_v;
  for (int s = 1; s < n_stages; ++s) {
    run.dy.setZero();
    for (int j = 0; j < s; ++j) {
      double c = dop ? dop853::A[s][j] : rk45::A[s][j];
      if (c != 0.0) run.dy += c * run.K.col(j);
    }
    run.ye = run.y + h * run.dy;
    if (model.partitions) stage_guess(model, data, dop ? dop853::A[s] : rk45::A[s], s, h);
    fun(model, data, t + (dop ? dop853::C[s] : rk45::C[s]) * h, run.ye, run.K.col(s));
    if (model.partitions) data.stage_dependent_v.col(s) = data.vD_last;
  }
  run.dy.setZero();
  for (int j = 0; j < n_stages; ++j) {
    double b = dop ? dop853::B[j] : rk45::B[j];
    if (b != 0.0) run.dy += b * run.K.col(j);
  }
  run.y_new = run.y + h * run.dy;
  if (model.partitions) stage_guess(model, data, dop ? dop853::B : rk45::B, n_stages, h);
  fun(model, data, t + h, run.y_new, run.f_new);
  if (model.partitions) data.stage_dependent_v.col(n_stages) = data.vD_last;
  run.K.col(n_stages) = run.f_new;
}

inline double error_norm(AdaptiveRun &run) {
  const int n_stages = run.n_stages;
  const double h = run.h;
  run.scale = run.atol + run.y.cwiseAbs().cwiseMax(run.y_new.cwiseAbs()).array() * run.rtol;
  if (run.dop) {
    run.e5.setZero();
    run.e3.setZero();
    for (int j = 0; j <= n_stages; ++j) {
      run.e5 += dop853::E5[j] * run.K.col(j);
      run.e3 += dop853::E3[j] * run.K.col(j);
    }
    run.e5 = run.e5.cwiseQuotient(run.scale);
    run.e3 = run.e3.cwiseQuotient(run.scale);
    double n5 = run.e5.squaredNorm(), n3 = run.e3.squaredNorm();
    if (n5 == 0 && n3 == 0) return 0.0;
    return std::abs(h) * n5 / std::sqrt((n5 + 0.01 * n3) * run.n);
  }
  run.tmp.setZero();
  for (int j = 0; j <= n_stages; ++j) run.tmp += rk45::E[j] * run.K.col(j);
  run.tmp *= h;
  return rms(run.tmp.cwiseQuotient(run.scale));
}

inline void accepted_step(const CoreModel &model, CoreData &data, AdaptiveRun &run,
                          double t_final) {
  constexpr double SAFETY = 0.9, MIN_FACTOR = 0.2, MAX_FACTOR = 10.0;
  const double t = run.t;
  double min_step = 10 * std::abs(std::nextafter(t, std::numeric_limits<double>::infinity()) - t);
  if (run.h_abs < min_step) run.h_abs = min_step;
  bool accepted = false, rejected = false;
  run.t_new = t;
  run.h = 0.0;
  while (!accepted) {
    if (run.h_abs < min_step)
      throw SimulationFailure{model.name + ": integrator " + run.name +
                                  " failed at t = " + fmt("%.9g", t) +
                                  " s: Required step size is less than spacing between "
                                  "numbers.",
                              t};
    run.h = run.h_abs;
    run.t_new = t + run.h;
    if (run.t_new - t_final > 0) run.t_new = t_final;
    run.h = run.t_new - t;
    run.h_abs = std::abs(run.h);
    rk_stages(model, data, run);
    const double err = error_norm(run);
    if (err < 1) {
      double factor =
          err == 0 ? MAX_FACTOR : std::min(MAX_FACTOR, SAFETY * std::pow(err, run.error_exponent));
      if (rejected) factor = std::min(1.0, factor);
      run.h_abs *= factor;
      accepted = true;
    } else {
      run.h_abs *= std::max(MIN_FACTOR, SAFETY * std::pow(err, run.error_exponent));
      rejected = true;
    }
  }
}

inline void dop853_dense_coefficients(const CoreModel &model, CoreData &data, AdaptiveRun &run,
                                      double t_old) {
  const int n_stages = run.n_stages;
  const double h = run.h;
  for (int s = n_stages + 1, e = 0; e < 3; ++s, ++e) {
    run.dy.setZero();
    for (int j = 0; j < s; ++j)
      if (dop853::A_EXTRA[e][j] != 0.0) run.dy += dop853::A_EXTRA[e][j] * run.K.col(j);
    run.ye = run.y + h * run.dy;
    if (model.partitions) stage_guess(model, data, dop853::A_EXTRA[e], s, h);
    fun(model, data, t_old + dop853::C_EXTRA[e] * h, run.ye, run.K.col(s));
    if (model.partitions) data.stage_dependent_v.col(s) = data.vD_last;
  }
  run.F.col(0) = run.y_new - run.y;
  run.F.col(1) = h * run.K.col(0) - run.F.col(0);
  run.F.col(2) = 2 * run.F.col(0) - h * (run.f_new + run.K.col(0));
  for (int i = 0; i < 4; ++i) {
    run.tmp.setZero();
    for (int j = 0; j < dop853::N_STAGES_EXTENDED; ++j)
      if (dop853::D[i][j] != 0.0) run.tmp += dop853::D[i][j] * run.K.col(j);
    run.F.col(3 + i) = h * run.tmp;
  }
  if (!(model.partitions && model.nc)) return;
  const Mat &V = data.stage_dependent_v;
  run.FD.col(0) = data.qD_end - data.qD0;
  run.FD.col(1) = h * V.col(0) - run.FD.col(0);
  run.FD.col(2) = 2 * run.FD.col(0) - h * (V.col(n_stages) + V.col(0));
  for (int i = 0; i < 4; ++i) {
    run.FD.col(3 + i).setZero();
    for (int j = 0; j < dop853::N_STAGES_EXTENDED; ++j)
      if (dop853::D[i][j] != 0.0) run.FD.col(3 + i) += (h * dop853::D[i][j]) * V.col(j);
  }
}

inline void rk45_dense_coefficients(const CoreModel &model, CoreData &data, AdaptiveRun &run) {
  const int n_stages = run.n_stages;
  for (int i = 0; i < 4; ++i) {  // Q = K^T P
    run.tmp.setZero();
    for (int j = 0; j <= n_stages; ++j)
      if (rk45::P[j][i] != 0.0) run.tmp += rk45::P[j][i] * run.K.col(j);
    run.F.col(i) = run.tmp;
    if (model.partitions && model.nc) {
      run.FD.col(i).setZero();
      for (int j = 0; j <= n_stages; ++j)
        if (rk45::P[j][i] != 0.0) run.FD.col(i) += rk45::P[j][i] * data.stage_dependent_v.col(j);
    }
  }
}

inline void dense_state(const CoreModel &model, CoreData &data, AdaptiveRun &run, double x) {
  const bool guess = model.partitions && model.nc;
  const double h = run.h;
  if (run.dop) {
    run.ye.setZero();
    if (guess) data.guess_qD.setZero();
    for (int i = dop853::INTERPOLATOR_POWER - 1, r = 0; i >= 0; --i, ++r) {
      run.ye += run.F.col(i);
      run.ye *= (r % 2 == 0) ? x : 1 - x;
      if (guess) {
        data.guess_qD += run.FD.col(i);
        data.guess_qD *= (r % 2 == 0) ? x : 1 - x;
      }
    }
    run.ye += run.y;
    if (guess) data.guess_qD += data.qD0;
  } else {
    double p = x;
    run.ye = run.y;
    if (guess) data.guess_qD = data.qD0;
    for (int i = 0; i < 4; ++i, p *= x) {
      run.ye += (h * p) * run.F.col(i);
      if (guess) data.guess_qD += (h * p) * run.FD.col(i);
    }
  }
  data.use_out_guess = guess;
}

inline void dense_outputs(const CoreModel &model, CoreData &data, AdaptiveRun &run, double t_old) {
  if (!(run.dense && run.ip < run.pending.size() && run.pending[run.ip] <= run.t_new)) return;
  if (run.dop)
    dop853_dense_coefficients(model, data, run, t_old);
  else
    rk45_dense_coefficients(model, data, run);
  while (run.ip < run.pending.size() && run.pending[run.ip] <= run.t_new * (1 + 1e-15)) {
    dense_state(model, data, run, (run.pending[run.ip] - t_old) / run.h);
    adaptive_output(model, data, run, run.pending[run.ip], run.ye);
    ++run.ip;
  }
}

inline void finish_step(const CoreModel &model, CoreData &data, AdaptiveRun &run, double t_final,
                        bool projects) {
  const double t = run.t;
  if (model.partitions) {
    data.qD0 = data.qD_end;
    check_finite(model, run.y.head(run.ns), run.y.tail(run.ns), t);
  } else {
    run.q_out = chart_q(model, data, run.y.head(model.nv));
    run.v_out = run.y.tail(model.nv);
    check_finite(model, run.q_out, run.v_out, t);
  }
  if (projects) {
    project(model, data, run.q_out, run.v_out);
    if (data.chart) pinocchio::difference(model.tree, data.chart_centre, run.q_out, run.x_out);
    run.y.head(model.nv) = data.chart ? run.x_out : run.q_out;
    run.y.tail(model.nv) = run.v_out;
    fun(model, data, t, run.y, run.f);
  }
  if (model.partitions) {
    unpack(model, data, run.y, t, run.qc, run.vc);
    check_regular(model, data, run.qc, t);
  } else {
    if (data.chart && t < t_final && chart_recentre(model, data, run.y.head(model.nv)))
      fun(model, data, t, run.y, run.f);
    check_regular(model, data, run.q_out, t);
  }
}

inline bp::dict run_adaptive(const CoreModel &model, CoreData &data, int integrator, const Vec &q0,
                             const Vec &v0, double t_final, double rtol, double atol,
                             bp::object t_eval_obj, bool projects, bp::object progress) {
  check_sizes(model, q0, v0);
  invalidate_kinematics(data);  // nothing kept from before the run (data.M, the factor of P)
  if (integrator != RK45 && integrator != DOP853)
    throw BadArgument{"run_adaptive: unknown integrator"};
  data.n_evals = 0;
  AdaptiveRun run(model, integrator, rtol, atol, t_eval_obj);
  GilRelease nogil;  // until the samples become Python objects (gil.hpp)
  adaptive_start(model, data, run, q0, v0);
  if (!run.dense || (run.ip < run.pending.size() && run.pending[run.ip] <= 0.0)) {
    adaptive_output(model, data, run, 0.0, run.y);
    if (run.dense) ++run.ip;
  }
  fun(model, data, run.t, run.y, run.f);
  if (model.partitions) step_start_from_last(data);
  run.h_abs = initial_step(model, data, run, t_final);  // scipy's select_initial_step
  long steps = 0;
  while (run.t < t_final) {
    accepted_step(model, data, run, t_final);  // one step of scipy's RungeKutta._step_impl
    ++steps;
    const double t_old = run.t;
    if (model.partitions) {  // the dependent state at y_new and its rate: the next step's start
      data.qD_end = data.qD_new;  // (data.qD0 stays the step start's for the dense-output stages)
      data.start_dependent_v = data.stage_dependent_v.col(run.n_stages);
    }
    dense_outputs(model, data, run, t_old);  // the t_eval within the step, unprojected
    run.t = run.t_new;
    run.y = run.y_new;
    run.f = run.f_new;
    finish_step(model, data, run, t_final, projects);
    if (!run.dense) adaptive_output(model, data, run, run.t, run.y);
    poll(steps, run.t, progress);
    // det(J_D) sign and re-partitioning; a new partition restarts the integrator
    // from (t, y) with the step size it proposed (as the numpy loop restarts scipy's).
    if (model.partitions &&
        adaptive_partition_check(model, data, run.t, t_final, run.y, run.qc, run.vc)) {
      fun(model, data, run.t, run.y, run.f);
      step_start_from_last(data);
    }
  }
  nogil.restore();
  return samples_dict(model, data, run.samples, steps);
}

inline Rk43Run::Rk43Run(const CoreModel &model, double t_final, double relative_tol,
                        double absolute_tol, double h0, bp::object t_eval_obj, bool record_all)
    : rtol(relative_tol), atol(absolute_tol), h(h0) {
  if (t_eval_obj.is_none()) {
    stops.push_back(t_final);
  } else {
    Vec te = bp::extract<Vec>(t_eval_obj);
    record_start = te.size() && te[0] <= 0.0;
    for (Eigen::Index i = 0; i < te.size(); ++i)
      if (te[i] > 0.0) stops.push_back(te[i]);
  }
  every = t_eval_obj.is_none() || record_all;
  const int nq = model.nq, nv = model.nv;
  for (Vec *x : {&q, &qn, &q1, &qm}) x->resize(nq);
  for (Vec *x : {&v, &a, &vn, &an, &v1, &a1, &k5v, &ex}) x->resize(nv);
}

inline double rk43_factor(double err) {
  if (err == 0.0) return RK43_MAX_FACTOR;
  return std::min(RK43_MAX_FACTOR,
                  std::max(RK43_MIN_FACTOR, RK43_SAFETY * std::pow(err, RK43_ERROR_EXPONENT)));
}

inline double rk43_step(const CoreModel &model, CoreData &data, Rk43Run &run, double t,
                        const Vec &qa, const Vec &va, const Vec &aa, double h, Vec &qb, Vec &vb,
                        Vec &ab, double &err, double &exm) {
  rk4_projected(model, data, t, qa, va, aa, h, qb, vb, run.qm);
  const double mid = data.midpoint_indicator;
  accel(model, data, t + h, qb, vb);
  ab = data.a;
  pinocchio::difference(model.tree, qa, qb, data.dv);
  chart_rate(model, data, qa, data.dv, vb, run.k5v);
  run.ex = (h / 6) * (data.k4v - run.k5v);
  double sum = 0.0;  // positions in the chart about qa: 0 at the start, data.dv at the end
  for (int i = 0; i < model.nv; ++i) {
    const double sx = run.atol + run.rtol * std::abs(data.dv[i]);
    const double sv = run.atol + run.rtol * std::max(std::abs(va[i]), std::abs(vb[i]));
    const double ev = (h / 6) * (data.k4a[i] - ab[i]);
    sum += (run.ex[i] / sx) * (run.ex[i] / sx) + (ev / sv) * (ev / sv);
  }
  err = model.nv ? std::sqrt(sum / (2.0 * model.nv)) : 0.0;
  exm = model.nv ? run.ex.cwiseAbs().maxCoeff() : 0.0;
  return mid;
}

inline void rk43_start(const CoreModel &model, CoreData &data, Rk43Run &run, const Vec &q0,
                       const Vec &v0) {
  for (Vec *b : {&data.dv, &data.vs, &data.k2v, &data.k2a, &data.k3v, &data.k3a, &data.k4v,
                 &data.k4a})
    b->resize(model.nv);
  data.qs.resize(model.nq);
  run.q = q0;
  run.v = v0;
  accel(model, data, run.t, run.q, run.v);
  run.a = data.a;
  if (run.record_start) record(model, data, run.samples, run.t, run.q, run.v);
  run.rho_start = rank_indicator(model, data, run.q);
}

inline bool rk43_retake(const CoreModel &model, CoreData &data, Rk43Run &run, double t_stop,
                        Rk43Trial &trial) {
  const double t = run.t, h = run.h;
  trial.span = trial.twice ? 2.0 : 1.0;
  if (trial.twice && t + 2.0 * h > t_stop * (1.0 + 1e-15)) {
    run.h = 0.5 * (t_stop - t);  // re-plan with two steps ending at the stop
    return false;
  }
  if (trial.f < trial.span) {
    double e1 = 0.0, m1 = 0.0, e2 = 0.0, m2 = 0.0;
    rk43_step(model, data, run, t, run.q, run.v, run.a, trial.f * h, run.q1, run.v1, run.a1, e1,
              m1);
    trial.sub = true;
    rk43_step(model, data, run, t + trial.f * h, run.q1, run.v1, run.a1,
              (trial.span - trial.f) * h, run.qn, run.vn, run.an, e2, m2);
    trial.err = std::max(e1, e2);
    trial.exm = m1 + m2;
  } else {  // one substep of two steps
    rk43_step(model, data, run, t, run.q, run.v, run.a, trial.span * h, run.qn, run.vn, run.an,
              trial.err, trial.exm);
  }
  trial.rho_new = rank_indicator(model, data, run.qn);
  return true;
}

inline void rk43_accept(const CoreModel &model, CoreData &data, Rk43Run &run,
                        const Rk43Trial &trial, double t_stop, bool clipped, double proposed,
                        bool in_zone, const bp::object &progress) {
  const double h = run.h, span = trial.span;
  if (trial.plan) ++run.splits;
  if (trial.sub) check_regular(model, data, run.q1, run.t + trial.f * h);
  run.t = (clipped || run.t + span * h >= t_stop) ? t_stop : run.t + span * h;
  check_regular(model, data, run.qn, run.t);
  run.q = run.qn;
  run.v = run.vn;
  run.a = run.an;
  run.rho_start = trial.rho_new;
  ++run.steps;
  run.zone_steps += in_zone;
  if (!in_zone) {
    run.err_max = std::max(run.err_max, trial.err);
    run.err_sum += trial.exm;
  }
  // data.a, data.lam: the last evaluation's, at q
  if (run.record_steps && (run.every || run.t == t_stop))
    record(model, data, run.samples, run.t, run.q, run.v);
  poll(run.steps, run.t, progress);
  if (!in_zone) run.h *= rk43_factor(trial.err);
  if (clipped) run.h = std::max(run.h, proposed);
}

inline bool rk43_try_step(const CoreModel &model, CoreData &data, Rk43Run &run, double t_stop,
                          const bp::object &progress, const Dop853Far *far) {
  if (far) run.h = far->near_step(run.h);  // near a singular position: steps that see it
  const double proposed = run.h, t = run.t;
  const bool clipped = t + run.h >= t_stop * (1.0 - 1e-15);
  if (clipped) run.h = t_stop - t;
  if (!(run.h > 10 * std::abs(std::nextafter(t, t_stop) - t)))
    throw SimulationFailure{model.name + ": integrator rk43 failed at t = " + fmt("%.9g", t) +
                                " s: the step fell below the spacing of the times",
                            t};
  Rk43Trial trial;
  const double rho_mid = rk43_step(model, data, run, t, run.q, run.v, run.a, run.h, run.qn,
                                   run.vn, run.an, trial.err, trial.exm);
  trial.rho_new = rank_indicator(model, data, run.qn);
  if (model.stage_zone > 0)
    trial.plan = retake_plan(crossing_estimate(run.rho_start, rho_mid, trial.rho_new),
                             model.stage_zone, trial.twice, trial.f);
  if (trial.plan && !rk43_retake(model, data, run, t_stop, trial)) return false;
  // dop853-rk43 within the indicator's cap: the step is kept, its size too (an estimate
  // there measures what the crossing amplifies, not the step's error).
  const bool in_zone = far && std::min(run.rho_start, trial.rho_new) < RANK_INDICATOR_CAP;
  if (trial.err > 1.0 && !in_zone) {
    ++run.rejected;
    run.h *= rk43_factor(trial.err);
    return false;
  }
  rk43_accept(model, data, run, trial, t_stop, clipped, proposed, in_zone, progress);
  return true;
}

inline bp::dict run_rk43(const CoreModel &model, CoreData &data, const Vec &q0, const Vec &v0,
                         double t_final, double rtol, double atol, double h0,
                         bp::object t_eval_obj, bool record_all, bp::object progress) {
  check_sizes(model, q0, v0);
  invalidate_kinematics(data);  // nothing kept from before the run (M, the factor of P)
  if (!(h0 > 0.0) || !(t_final > 0.0) || !(rtol > 0.0) || !(atol > 0.0))
    throw BadArgument{"run_rk43: t_final, rtol, atol and h0 must be > 0"};
  data.n_evals = 0;
  begin_partitioning(model, data, true);  // as run_fixed: the stage-projected loop's checks
  Rk43Run run(model, t_final, rtol, atol, h0, t_eval_obj, record_all);
  GilRelease nogil;  // until the samples become Python objects (gil.hpp)
  rk43_start(model, data, run, q0, v0);
  for (const double t_stop : run.stops)
    while (run.t < t_stop) rk43_try_step(model, data, run, t_stop, progress, nullptr);
  nogil.restore();
  bp::dict d = samples_dict(model, data, run.samples, run.steps);
  d["singular_splits"] = run.splits;
  d["rejected_steps"] = run.rejected;
  d["error_estimate_max"] = run.err_max;
  d["error_estimate_sum"] = run.err_sum;
  return d;
}

inline Dop853Far::Dop853Far(const CoreModel &model, double relative_tol, double absolute_tol,
                            double h0)
    : rtol(relative_tol), atol(absolute_tol), h(h0) {
  kx.resize(model.nv, dop853::N_STAGES_EXTENDED);
  ka.resize(model.nv, dop853::N_STAGES_EXTENDED);
  fx.resize(model.nv, dop853::INTERPOLATOR_POWER);
  fv.resize(model.nv, dop853::INTERPOLATOR_POWER);
  for (Vec *b : {&x, &vs, &ex, &ev, &xn, &xo, &vo}) b->resize(model.nv);
  qs.resize(model.nq);
  qo.resize(model.nq);
}

inline double Dop853Far::near_step(double h_near) const {
  return rate > 0.0 ? std::min(h_near, NEAR_ENTRY_FRACTION * RANK_INDICATOR_CAP / rate) : h_near;
}

inline double Dop853Far::add_sample(double t, double r) {
  sample_t[n_samples] = t;
  sample_r[n_samples] = r;
  ++n_samples;
  double steepest = 0.0;
  for (int i = 0; i + 1 < n_samples; ++i)
    if (sample_t[i + 1] > sample_t[i])
      steepest = std::max(steepest,
                          std::abs(sample_r[i + 1] - sample_r[i]) / (sample_t[i + 1] - sample_t[i]));
  return steepest;
}

/// Sets data.method_override for a scope (kkt in dop853-rk43's DOP853 trials).
struct MethodOverride {
  MethodOverride(CoreData &d, int method) : data(d) { data.method_override = method; }
  ~MethodOverride() { data.method_override = -1; }
  MethodOverride(const MethodOverride &) = delete;
  MethodOverride &operator=(const MethodOverride &) = delete;
  CoreData &data;
};

inline FarOutcome dop853_far_trial(const CoreModel &model, CoreData &data, Rk43Run &run,
                                   Dop853Far &far, double t_land, Rk43Trial &trial) {
  constexpr double UNCAPPED = std::numeric_limits<double>::infinity();
  // Far from singular positions the augmented Lagrangian converges to kkt's solution:
  // kkt's solve, at about half the cost (dop853_rk43.py).
  MethodOverride solve_by(data, model.method == AUGMENTED_LAGRANGIAN ? KKT : -1);
  const double t = run.t;
  const bool loops = model.nc > 0;
  if (loops && far.start_t != t) {  // the start was an rk43 step's end
    far.start_t = t;
    far.start_rho = rank_indicator(model, data, run.q, UNCAPPED);
  }
  far.n_samples = 0;
  far.add_sample(far.start_t, far.start_rho);
  if (loops && far.rate > 0.0) far.h = std::min(far.h, FAR_RHO_FRACTION * far.start_rho / far.rate);
  double h = far.h;
  const bool clipped = t + h >= t_land * (1.0 - 1e-15);
  if (clipped) h = t_land - t;
  if (!(h > 10 * std::abs(std::nextafter(t, t_land) - t)))
    throw SimulationFailure{model.name + ": integrator dop853-rk43 failed at t = " +
                                fmt("%.9g", t) + " s: the step fell below the spacing of the times",
                            t};
  far.kx.col(0) = run.v;
  far.ka.col(0) = run.a;
  for (int s = 1; s < dop853::N_STAGES; ++s) {
    far.x.setZero();
    far.vs = run.v;
    for (int j = 0; j < s; ++j) {
      const double c = h * dop853::A[s][j];
      if (c == 0.0) continue;
      far.x += c * far.kx.col(j);
      far.vs += c * far.ka.col(j);
    }
    pinocchio::integrate(model.tree, run.q, far.x, far.qs);
    accel(model, data, t + dop853::C[s] * h, far.qs, far.vs);
    far.ka.col(s) = data.a;
    chart_rate(model, data, run.q, far.x, far.vs, far.kx.col(s));
    if (loops && (s == FAR_INDICATOR_STAGE_A || s == FAR_INDICATOR_STAGE_B)) {
      const double r = rank_indicator(model, data, far.qs, UNCAPPED);
      const double rate = far.add_sample(t + dop853::C[s] * h, r);
      if (r < RANK_INDICATOR_CAP) {
        far.rate = rate;
        return FAR_NEAR;
      }
    }
  }
  far.x.setZero();
  run.vn = run.v;
  for (int j = 0; j < dop853::N_STAGES; ++j) {
    const double c = h * dop853::B[j];
    if (c == 0.0) continue;
    far.x += c * far.kx.col(j);
    run.vn += c * far.ka.col(j);
  }
  pinocchio::integrate(model.tree, run.q, far.x, run.qn);
  const double t_new = clipped ? t_land : t + h;
  check_finite(model, run.qn, run.vn, t_new);
  project(model, data, run.qn, run.vn, false);  // J regular: the minimum-norm correction
  double r_new = RANK_INDICATOR_CAP;
  if (loops) {
    r_new = rank_indicator(model, data, run.qn, UNCAPPED);
    far.rate = far.add_sample(t_new, r_new);
    if (r_new < RANK_INDICATOR_CAP) return FAR_NEAR;
  }
  accel(model, data, t_new, run.qn, run.vn);
  run.an = data.a;
  pinocchio::difference(model.tree, run.q, run.qn, far.xn);  // the chart about q
  chart_rate(model, data, run.q, far.xn, run.vn, far.kx.col(dop853::N_STAGES));
  far.ka.col(dop853::N_STAGES) = run.an;
  // One weight for the positions, scipy's per velocity (dop853_rk43.py).
  const double sx = far.atol + far.rtol * (model.nv ? far.xn.cwiseAbs().maxCoeff() : 0.0);
  far.vs = far.atol + far.rtol * run.v.cwiseAbs().cwiseMax(run.vn.cwiseAbs()).array();
  double n5 = 0.0, n3 = 0.0;
  for (const double *E : {dop853::E5, dop853::E3}) {
    far.ex.setZero();
    far.ev.setZero();
    for (int j = 0; j <= dop853::N_STAGES; ++j) {
      if (E[j] == 0.0) continue;
      far.ex += E[j] * far.kx.col(j);
      far.ev += E[j] * far.ka.col(j);
    }
    const double n =
        far.ex.squaredNorm() / (sx * sx) + far.ev.cwiseQuotient(far.vs).squaredNorm();
    if (E == dop853::E5) {
      n5 = n;
      trial.exm = model.nv ? h * far.ex.cwiseAbs().maxCoeff() : 0.0;
    } else {
      n3 = n;
    }
  }
  const double err = (n5 == 0.0 && n3 == 0.0)
                         ? 0.0
                         : h * n5 / std::sqrt((n5 + 0.01 * n3) * (2.0 * model.nv));
  if (err > 1.0) {
    far.h = h * std::max(FAR_MIN_FACTOR, FAR_SAFETY * std::pow(err, FAR_ERROR_EXPONENT));
    far.rejected = true;
    return FAR_REJECTED;
  }
  const double proposed = far.h;
  double factor =
      err == 0.0 ? FAR_MAX_FACTOR
                 : std::min(FAR_MAX_FACTOR, FAR_SAFETY * std::pow(err, FAR_ERROR_EXPONENT));
  if (far.rejected) factor = std::min(1.0, factor);
  far.h = h * factor;
  if (clipped) far.h = std::max(far.h, proposed);
  far.rejected = false;
  if (loops) {
    far.start_t = t_new;
    far.start_rho = r_new;
  }
  trial.err = err;
  trial.rho_new = std::min(r_new, RANK_INDICATOR_CAP);
  trial.span = 1.0;
  run.t_far_end = t_new;
  return FAR_ACCEPTED;
}

inline void dop853_far_dense(const CoreModel &model, CoreData &data, const Vec &q,
                             const Vec &v, double t, double h, Dop853Far &far) {
  MethodOverride solve_by(data, model.method == AUGMENTED_LAGRANGIAN ? KKT : -1);
  for (int e = 0, s = dop853::N_STAGES + 1; e < 3; ++e, ++s) {
    far.x.setZero();
    far.vs = v;
    for (int j = 0; j < s; ++j) {
      const double c = h * dop853::A_EXTRA[e][j];
      if (c == 0.0) continue;
      far.x += c * far.kx.col(j);
      far.vs += c * far.ka.col(j);
    }
    pinocchio::integrate(model.tree, q, far.x, far.qs);
    accel(model, data, t + dop853::C_EXTRA[e] * h, far.qs, far.vs);
    far.ka.col(s) = data.a;
    chart_rate(model, data, q, far.x, far.vs, far.kx.col(s));
  }
  // y = (x, v), y_old = (0, v), y_new = (xn, vn) (scipy's Dop853DenseOutput)
  const int end = dop853::N_STAGES;
  far.fx.col(0) = far.xn;
  far.fv.col(0) = far.vo;  // vn - v: set by the caller in far.vo
  far.fx.col(1) = h * far.kx.col(0) - far.fx.col(0);
  far.fv.col(1) = h * far.ka.col(0) - far.fv.col(0);
  far.fx.col(2) = 2 * far.fx.col(0) - h * (far.kx.col(end) + far.kx.col(0));
  far.fv.col(2) = 2 * far.fv.col(0) - h * (far.ka.col(end) + far.ka.col(0));
  for (int i = 0; i < 4; ++i) {
    far.fx.col(3 + i).setZero();
    far.fv.col(3 + i).setZero();
    for (int j = 0; j < dop853::N_STAGES_EXTENDED; ++j) {
      const double c = h * dop853::D[i][j];
      if (c == 0.0) continue;
      far.fx.col(3 + i) += c * far.kx.col(j);
      far.fv.col(3 + i) += c * far.ka.col(j);
    }
  }
}

inline void dop853_far_output(const CoreModel &model, CoreData &data, Rk43Run &run,
                              Dop853Far &far, const Vec &q, const Vec &v, double t_out,
                              double theta) {
  far.xo.setZero();
  far.vo.setZero();
  for (int i = dop853::INTERPOLATOR_POWER - 1, r = 0; i >= 0; --i, ++r) {
    far.xo += far.fx.col(i);
    far.vo += far.fv.col(i);
    const double w = (r % 2 == 0) ? theta : 1.0 - theta;
    far.xo *= w;
    far.vo *= w;
  }
  far.vo += v;
  pinocchio::integrate(model.tree, q, far.xo, far.qo);
  project(model, data, far.qo, far.vo, false);
  check_regular(model, data, far.qo, t_out);
  MethodOverride solve_by(data, model.method == AUGMENTED_LAGRANGIAN ? KKT : -1);
  accel(model, data, t_out, far.qo, far.vo);
  record(model, data, run.samples, t_out, far.qo, far.vo);
}

inline bp::dict run_dop853_rk43(const CoreModel &model, CoreData &data, const Vec &q0,
                                const Vec &v0, double t_final, double rtol, double atol,
                                double h0, bp::object t_eval_obj, bp::object progress) {
  check_sizes(model, q0, v0);
  invalidate_kinematics(data);  // nothing kept from before the run (M, the factor of P)
  if (!(h0 > 0.0) || !(t_final > 0.0) || !(rtol > 0.0) || !(atol > 0.0))
    throw BadArgument{"run_dop853_rk43: t_final, rtol, atol and h0 must be > 0"};
  data.n_evals = 0;
  data.method_override = -1;
  begin_partitioning(model, data, true);  // as run_rk43
  std::vector<double> outs;  // the output times (none: every step end is one)
  if (!t_eval_obj.is_none()) {
    Vec te = bp::extract<Vec>(t_eval_obj);
    outs.assign(te.data(), te.data() + te.size());
  }
  const bool dense = !t_eval_obj.is_none();
  Rk43Run run(model, t_final, std::max(rtol, NEAR_RTOL), std::max(atol, NEAR_ATOL), h0,
              bp::object(), true);
  run.record_steps = false;
  Dop853Far far(model, rtol, atol, h0);
  std::vector<long> out_index;  // the samples at output times
  Vec q_old(model.nq), v_old(model.nv), a_old(model.nv);
  GilRelease nogil;  // until the samples become Python objects (gil.hpp)
  rk43_start(model, data, run, q0, v0);  // records t = 0
  std::size_t io = 0;
  if (dense && io < outs.size() && outs[io] <= 0.0) {
    out_index.push_back(0);
    ++io;
  }
  while (run.t < t_final) {
    const double t_old = run.t;
    q_old = run.q;
    v_old = run.v;
    a_old = run.a;
    bool far_step = false, accepted = false;
    double h_step = 0.0;
    if (run.rho_start >= RANK_INDICATOR_CAP) {
      Rk43Trial trial;
      const FarOutcome out = dop853_far_trial(model, data, run, far, t_final, trial);
      if (out == FAR_REJECTED) {
        ++run.rejected;
        continue;
      }
      if (out == FAR_ACCEPTED) {
        run.t = run.t_far_end;
        h_step = run.t - t_old;
        check_regular(model, data, run.qn, run.t);
        run.q = run.qn;
        run.v = run.vn;
        run.a = run.an;
        run.rho_start = trial.rho_new;
        ++run.steps;
        ++run.far_steps;
        run.err_max = std::max(run.err_max, trial.err);
        run.err_sum += trial.exm;
        far_step = accepted = true;
      }
    }
    if (!far_step) accepted = rk43_try_step(model, data, run, t_final, progress, &far);
    if (!accepted) continue;
    // The outputs within (t_old, run.t), then the step's end (data.a, data.lam at it
    // unless an output was evaluated since).
    bool evaluated = false;
    bool prepared = false;
    while (dense && io < outs.size() && outs[io] < run.t) {
      if (outs[io] > t_old) {
        if (far_step) {
          if (!prepared) {
            far.vo = run.v - v_old;
            dop853_far_dense(model, data, q_old, v_old, t_old, h_step, far);
            prepared = true;
          }
          dop853_far_output(model, data, run, far, q_old, v_old, outs[io],
                            (outs[io] - t_old) / h_step);
        } else {
          record_interpolated(model, data, run.samples, outs[io], (outs[io] - t_old) / (run.t - t_old),
                              run.t - t_old, q_old, v_old, a_old, run.q, run.v, run.a);
        }
        out_index.push_back(static_cast<long>(run.samples.t.size()) - 1);
        evaluated = true;
      }
      ++io;
    }
    if (evaluated) {
      MethodOverride solve_by(data, far_step && model.method == AUGMENTED_LAGRANGIAN ? KKT : -1);
      accel(model, data, run.t, run.q, run.v);
    }
    record(model, data, run.samples, run.t, run.q, run.v);
    if (dense && io < outs.size() && outs[io] == run.t) {
      out_index.push_back(static_cast<long>(run.samples.t.size()) - 1);
      ++io;
    }
    if (far_step) poll(run.steps, run.t, progress);
  }
  nogil.restore();
  bp::dict d = samples_dict(model, data, run.samples, run.steps);
  d["singular_splits"] = run.splits;
  d["rejected_steps"] = run.rejected;
  d["error_estimate_max"] = run.err_max;
  d["error_estimate_sum"] = run.err_sum;
  d["far_steps"] = run.far_steps;
  d["zone_steps"] = run.zone_steps;
  bp::list outputs;
  for (const long k : out_index) outputs.append(k);
  d["outputs"] = outputs;
  return d;
}

}  // namespace closedchain
