// closedchain._core: the fixed-step loops: Euler, semi-implicit Euler and rk4 (with stage
// projection near singular positions); ALI3-P is in ali3p.hpp.
// (Functions over (CoreModel, CoreData): their declarations, then their definitions.)

#pragma once

#include <pinocchio/algorithm/joint-configuration.hpp>

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

#include "core_chart.hpp"
#include "core_data.hpp"
#include "core_methods.hpp"
#include "core_model.hpp"
#include "core_partitioning.hpp"
#include "core_projection.hpp"
#include "core_recording.hpp"
#include "core_rows.hpp"
#include "gil.hpp"

namespace closedchain {

// -- declarations ------------------------------------------------------------

/// The crossing time in steps from the start that the indicator at the start, midpoint
/// and end points to, inf when none is ahead (fixed.crossing_estimate): rho = s |t - tau|
/// fitted by least squares for tau in [0, 0.5), [0.5, 1) and [1, inf), the signs of
/// t - tau at the samples known in each; the fit in its interval with the smallest
/// residual is taken.
double crossing_estimate(double r0, double r1, double r2);

/// Distance [steps] of a crossing at tau from the evaluation points of a retake of one
/// (double: two) grid steps split at h1 (h1 = span: one substep) (fixed._plan_points).
double plan_distance(double tau, bool twice, double h1);

/// false when the plain step keeps its points at least `zone` steps from a crossing at
/// tau; else true with the retake (twice, h1) whose points are farthest from it, ties
/// to the single step (fixed.retake_plan).
bool retake_plan(double tau, double zone, bool &twice, double &h1);

/// One rk4 step of length h from (q, v) with accelerations a0 at t, every stage and
/// the end projected; (qn, vn) the end, qm the projected stage-2 (midpoint) state.
void rk4_projected(const CoreModel &model, CoreData &data, double t, const Vec &q, const Vec &v,
                   const Vec &a0, double h, Vec &qn, Vec &vn, Vec &qm);

/// The state at t = t0 + s h of the substep (q0, v0, a0) -> (q1, v1, a1) of length h
/// by cubic Hermite interpolation, q projected onto phi = 0, recorded (v is not
/// projected: near the crossing that is the ill-conditioned step avoided).
void record_interpolated(const CoreModel &model, CoreData &data, Samples &S, double t, double s,
                         double h, const Vec &q0, const Vec &v0, const Vec &a0, const Vec &q1,
                         const Vec &v1, const Vec &a1);

/// rk4 with every stage projected and the retake rule near singular positions (simulate/
/// fixed.py, _run_rk4_stage_projected), recording at the steps where out[k] is set.
bp::dict run_rk4_stage_projected(const CoreModel &model, CoreData &data, const Vec &q0,
                                 const Vec &v0, double dt, long n_steps,
                                 const std::vector<char> &out, bp::object progress);

/// rk4's stage buffers of run_fixed, sized once per run.
struct Rk4Stages {
  /// Buffers of shapes (nq,) (qs) and (nv,) (the others).
  explicit Rk4Stages(const CoreModel &model);
  /// A stage's state; the increment of q along a stage's rate.
  Vec qs, vs, dv;
  /// The stages' rates of q (in the chart about the step's q) and of v.
  Vec k1v, k1a, k2v, k2a, k3v, k3a, k4v, k4a;
};

/// One rk4 stage of the step from (q, v) at t: the state at t + c along the previous
/// stage's rates (kv_prev, ka_prev), projected (stage projection) or completed
/// (partitioning), and its rates (kv, ka).
void rk4_stage(const CoreModel &model, CoreData &data, double t, const Vec &q, const Vec &v,
               double c, const Vec &kv_prev, const Vec &ka_prev, Vec &kv, Vec &ka, Rk4Stages &st);

/// One step of length dt of euler, semi-implicit Euler or rk4 from (q, v) at t with the
/// accelerations data.a there, to (qn, vn).
void explicit_step(const CoreModel &model, CoreData &data, int integrator, double t, double dt,
                   const Vec &q, const Vec &v, Vec &qn, Vec &vn, Rk4Stages &st);

/// Integrate with a fixed step dt for n_steps, recording at the steps in `out`.
bp::dict run_fixed(const CoreModel &model, CoreData &data, int integrator, const Vec &q0,
                   const Vec &v0, double dt, long n_steps, const Eigen::VectorXi &out_steps,
                   bool projects, bp::object progress);

// -- definitions -------------------------------------------------------------

inline double crossing_estimate(double r0, double r1, double r2) {
  const double far = std::numeric_limits<double>::infinity();
  if (std::max({r0, r1, r2}) >= RANK_INDICATOR_CAP) return far;
  const double t[3] = {0.0, 0.5, 1.0}, r[3] = {r0, r1, r2};
  const double lo[3] = {0.0, 0.5, 1.0};
  const double hi[3] = {0.5, 1.0, std::numeric_limits<double>::infinity()};
  const double sg[3][3] = {{-1, 1, 1}, {-1, -1, 1}, {-1, -1, -1}};
  double best = std::numeric_limits<double>::infinity(), best_res = best;
  for (int h = 0; h < 3; ++h) {
    // r_i = sg_i t_i x0 - sg_i x1 (x0 = s, x1 = s tau): 2 x 2 normal equations
    double a00 = 0, a01 = 0, a11 = 0, b0 = 0, b1 = 0;
    for (int i = 0; i < 3; ++i) {
      const double c0 = sg[h][i] * t[i], c1 = -sg[h][i];
      a00 += c0 * c0;
      a01 += c0 * c1;
      a11 += c1 * c1;
      b0 += c0 * r[i];
      b1 += c1 * r[i];
    }
    const double det = a00 * a11 - a01 * a01;
    const double slope = (a11 * b0 - a01 * b1) / det, st = (a00 * b1 - a01 * b0) / det;
    if (!(slope > 0.0)) continue;
    const double tau = st / slope;
    if (!(lo[h] <= tau && tau < hi[h])) continue;
    double res = 0.0;
    for (int i = 0; i < 3; ++i) {
      const double e = sg[h][i] * t[i] * slope - sg[h][i] * st - r[i];
      res += e * e;
    }
    if (res < best_res && std::sqrt(res) <= CROSSING_FIT_RTOL * std::max({r0, r1, r2})) {
      best = tau;
      best_res = res;
    }
  }
  return best;
}

inline double plan_distance(double tau, bool twice, double h1) {
  const double end = twice ? 2.0 : 1.0;
  if (h1 >= end) return std::min(std::abs(end / 2 - tau), std::abs(end - tau));
  const double pts[4] = {h1 / 2, h1, (h1 + end) / 2, end};
  double d = std::numeric_limits<double>::infinity();
  for (double p : pts) d = std::min(d, std::abs(p - tau));
  return d;
}

inline bool retake_plan(double tau, double zone, bool &twice, double &h1) {
  if (std::min(std::abs(0.5 - tau), std::abs(1.0 - tau)) >= zone) return false;
  double best_d = -1.0;
  for (int dbl = 0; dbl < 2; ++dbl) {
    for (int k = 1; k < RETAKE_GRID + dbl; ++k) {
      const double f = (dbl ? 2.0 : 1.0) * k / RETAKE_GRID;
      const double d = plan_distance(tau, dbl != 0, f);
      if (d > best_d) {
        best_d = d;
        twice = dbl != 0;
        h1 = f;
      }
    }
  }
  return true;
}

inline void rk4_projected(const CoreModel &model, CoreData &data, double t, const Vec &q,
                          const Vec &v, const Vec &a0, double h, Vec &qn, Vec &vn, Vec &qm) {
  data.dv = (h / 2) * v;
  pinocchio::integrate(model.tree, q, data.dv, qm);
  data.vs = v + (h / 2) * a0;
  project(model, data, qm, data.vs, true);
  // the retake rule's midpoint indicator, while J is at qm (no kinematics pass later)
  if (model.stage_zone > 0) data.midpoint_indicator = rank_indicator(model, data, qm);
  check_stage_regular(model, data, qm, t + h / 2);
  accel(model, data, t + h / 2, qm, data.vs);
  chart_rate(model, data, q, data.dv, data.vs,
             data.k2v);  // the stages' rates in the chart about q (run_fixed)
  data.k2a = data.a;
  data.dv = (h / 2) * data.k2v;
  pinocchio::integrate(model.tree, q, data.dv, data.qs);
  data.vs = v + (h / 2) * data.k2a;
  project(model, data, data.qs, data.vs, true);
  check_stage_regular(model, data, data.qs, t + h / 2);
  accel(model, data, t + h / 2, data.qs, data.vs);
  chart_rate(model, data, q, data.dv, data.vs, data.k3v);
  data.k3a = data.a;
  data.dv = h * data.k3v;
  pinocchio::integrate(model.tree, q, data.dv, data.qs);
  data.vs = v + h * data.k3a;
  project(model, data, data.qs, data.vs, true);
  check_stage_regular(model, data, data.qs, t + h);
  accel(model, data, t + h, data.qs, data.vs);
  chart_rate(model, data, q, data.dv, data.vs, data.k4v);
  data.k4a = data.a;
  data.dv = (h / 6) * (v + 2 * data.k2v + 2 * data.k3v + data.k4v);
  pinocchio::integrate(model.tree, q, data.dv, qn);
  vn = v + (h / 6) * (a0 + 2 * data.k2a + 2 * data.k3a + data.a);
  check_finite(model, qn, vn, t + h);
  project(model, data, qn, vn, true);
}

inline void record_interpolated(const CoreModel &model, CoreData &data, Samples &S, double t,
                                double s, double h, const Vec &q0, const Vec &v0, const Vec &a0,
                                const Vec &q1, const Vec &v1, const Vec &a1) {
  const double h00 = 2 * s * s * s - 3 * s * s + 1, h10 = s * s * s - 2 * s * s + s;
  const double h01 = -2 * s * s * s + 3 * s * s, h11 = s * s * s - s * s;
  pinocchio::difference(model.tree, q0, q1, data.dv);
  data.dv = h10 * h * v0 + h01 * data.dv + h11 * h * v1;
  pinocchio::integrate(model.tree, q0, data.dv, data.qs);
  data.k2v = h00 * v0 + h10 * h * a0 + h01 * v1 + h11 * h * a1;
  data.vs = data.k2v;
  project(model, data, data.qs, data.vs);
  check_regular(model, data, data.qs, t);
  accel(model, data, t, data.qs, data.k2v);
  record(model, data, S, t, data.qs, data.k2v);
}

inline bp::dict run_rk4_stage_projected(const CoreModel &model, CoreData &data, const Vec &q0,
                                        const Vec &v0, double dt, long n_steps,
                                        const std::vector<char> &out, bp::object progress) {
  Samples S;
  Vec q = q0, v = v0, a(model.nv), qn(model.nq), vn(model.nv), qm(model.nq), q1(model.nq),
      v1(model.nv), a1(model.nv);
  data.dv.resize(model.nv);
  data.vs.resize(model.nv);
  data.qs.resize(model.nq);
  data.k2v.resize(model.nv);
  data.k2a.resize(model.nv);
  data.k3v.resize(model.nv);
  data.k3a.resize(model.nv);
  data.k4v.resize(model.nv);
  data.a2.resize(model.nv);
  GilRelease nogil;  // until the samples become Python objects (gil.hpp)
  double t = 0.0;
  accel(model, data, t, q, v);
  a = data.a;
  if (out[0]) record(model, data, S, t, q, v);
  long splits = 0;
  double rho_start = rank_indicator(model, data, q);
  for (long k = 1; k <= n_steps; ++k) {
    rk4_projected(model, data, t, q, v, a, dt, qn, vn, qm);
    double rho_new = rank_indicator(model, data, qn);
    bool twice = false;
    double f = 0.0;
    if (model.stage_zone > 0 &&
        retake_plan(crossing_estimate(rho_start, data.midpoint_indicator, rho_new),
                    model.stage_zone, twice, f)) {
      const double span = twice ? 2.0 : 1.0;
      double h1 = f * dt, h2 = span * dt - f * dt;
      if (f < span) {
        rk4_projected(model, data, t, q, v, a, h1, q1, v1, qm);
        check_regular(model, data, q1, t + h1);
        accel(model, data, t + h1, q1, v1);
        a1 = data.a;
        rk4_projected(model, data, t + h1, q1, v1, a1, h2, qn, vn, qm);
      } else {  // one substep of two grid steps
        h1 = 0.0;
        h2 = span * dt;
        q1 = q;
        v1 = v;
        a1 = a;
        rk4_projected(model, data, t, q, v, a, h2, qn, vn, qm);
      }
      rho_new = rank_indicator(model, data, qn);
      ++splits;
      if (twice) {
        if (out[k]) {  // the skipped grid point, from the substep holding it
          if (h1 >= dt) {
            record_interpolated(model, data, S, k * dt, dt / h1, h1, q, v, a, q1, v1, a1);
          } else {
            check_regular(model, data, qn, t + 2 * dt);
            accel(model, data, t + 2 * dt, qn, vn);
            data.a2 = data.a;
            record_interpolated(model, data, S, k * dt, (dt - h1) / h2, h2, q1, v1, a1, qn, vn,
                                data.a2);
          }
        }
        poll(k, k * dt, progress);
        if (k == n_steps) break;  // the step beyond t_final only served the output
        ++k;
      }
    }
    t = k * dt;
    check_regular(model, data, qn, t);
    q = qn;
    v = vn;
    accel(model, data, t, q, v);
    a = data.a;
    rho_start = rho_new;
    if (out[k]) record(model, data, S, t, q, v);
    poll(k, t, progress);
  }
  nogil.restore();
  bp::dict d = samples_dict(model, data, S, n_steps);
  d["singular_splits"] = splits;
  return d;
}

inline Rk4Stages::Rk4Stages(const CoreModel &model)
    : qs(model.nq),
      vs(model.nv),
      dv(model.nv),
      k1v(model.nv),
      k1a(model.nv),
      k2v(model.nv),
      k2a(model.nv),
      k3v(model.nv),
      k3a(model.nv),
      k4v(model.nv),
      k4a(model.nv) {}

inline void rk4_stage(const CoreModel &model, CoreData &data, double t, const Vec &q, const Vec &v,
                      double c, const Vec &kv_prev, const Vec &ka_prev, Vec &kv, Vec &ka,
                      Rk4Stages &st) {
  st.dv = c * kv_prev;
  pinocchio::integrate(model.tree, q, st.dv, st.qs);
  st.vs = v + c * ka_prev;
  if (model.stage_projects)
    project(model, data, st.qs, st.vs, true);
  else if (model.partitions)
    complete(model, data, st.qs, st.vs, t + c);
  accel(model, data, t + c, st.qs, st.vs);
  chart_rate(model, data, q, st.dv, st.vs, kv);  // the chart about q (simulate/chart.py)
  ka = data.a;
}

inline void explicit_step(const CoreModel &model, CoreData &data, int integrator, double t,
                          double dt, const Vec &q, const Vec &v, Vec &qn, Vec &vn, Rk4Stages &st) {
  if (integrator == EULER) {
    st.dv = dt * v;
    pinocchio::integrate(model.tree, q, st.dv, qn);
    vn = v + dt * data.a;
  } else if (integrator == SEMI_IMPLICIT) {
    vn = v + dt * data.a;
    st.dv = dt * vn;
    pinocchio::integrate(model.tree, q, st.dv, qn);
  } else {
    st.k1v = v;
    st.k1a = data.a;
    rk4_stage(model, data, t, q, v, dt / 2, st.k1v, st.k1a, st.k2v, st.k2a, st);
    rk4_stage(model, data, t, q, v, dt / 2, st.k2v, st.k2a, st.k3v, st.k3a, st);
    rk4_stage(model, data, t, q, v, dt, st.k3v, st.k3a, st.k4v, st.k4a, st);
    st.dv = (dt / 6) * (st.k1v + 2 * st.k2v + 2 * st.k3v + st.k4v);
    pinocchio::integrate(model.tree, q, st.dv, qn);
    vn = v + (dt / 6) * (st.k1a + 2 * st.k2a + 2 * st.k3a + st.k4a);
  }
}

inline bp::dict run_fixed(const CoreModel &model, CoreData &data, int integrator, const Vec &q0,
                          const Vec &v0, double dt, long n_steps, const Eigen::VectorXi &out_steps,
                          bool projects, bp::object progress) {
  check_sizes(model, q0, v0);
  invalidate_kinematics(data);  // nothing kept from before the run (data.M, the factor of P)
  if (integrator < EULER || integrator > RK4) throw BadArgument{"run_fixed: unknown integrator"};
  data.n_evals = 0;
  Samples S;
  const std::vector<char> out = output_mask(out_steps, n_steps);
  // Every run starts from its own configuration: a previous partitioning run's
  // data.rows_only left set would skip the stage-projected loop's singularity check.
  begin_partitioning(model, data, true);
  if (integrator == RK4 && model.stage_projects && projects && model.nc)
    return run_rk4_stage_projected(model, data, q0, v0, dt, n_steps, out, progress);
  Vec q = q0, v = v0, qn(model.nq), vn(model.nv);
  Rk4Stages stages(model);
  GilRelease nogil;  // until the samples become Python objects (gil.hpp)
  double t = 0.0;
  if (model.partitions) complete(model, data, q, v, t);
  accel(model, data, t, q, v);
  if (out[0]) record(model, data, S, t, q, v);
  for (long k = 1; k <= n_steps; ++k) {
    explicit_step(model, data, integrator, t, dt, q, v, qn, vn, stages);
    t = k * dt;
    check_finite(model, qn, vn, t);
    if (projects)
      project(model, data, qn, vn, model.stage_projects);
    else if (model.partitions)
      partition_step(model, data, qn, vn, t);
    check_regular(model, data, qn, t);  // partitioning: the rows only (Problem.check_rows)
    q = qn;
    v = vn;
    accel(model, data, t, q, v);
    if (out[k]) record(model, data, S, t, q, v);
    poll(k, t, progress);
  }
  nogil.restore();
  return samples_dict(model, data, S, n_steps);
}

}  // namespace closedchain
