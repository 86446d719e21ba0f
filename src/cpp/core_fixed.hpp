// closedchain._core: the fixed-step loops: Euler, semi-implicit Euler, rk4 (with stage
// projection near singular positions) and the ALI3-P entry point.
// (Member functions of Core, declared in core.hpp.)

#pragma once

#include <pinocchio/algorithm/joint-configuration.hpp>

#include <algorithm>
#include <cmath>
#include <limits>

#include "ali3p.hpp"
#include "core.hpp"

namespace closedchain {

inline double Core::crossing_estimate(double r0, double r1, double r2) {
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

inline double Core::plan_distance(double tau, bool twice, double h1) {
  const double end = twice ? 2.0 : 1.0;
  if (h1 >= end) return std::min(std::abs(end / 2 - tau), std::abs(end - tau));
  const double pts[4] = {h1 / 2, h1, (h1 + end) / 2, end};
  double d = std::numeric_limits<double>::infinity();
  for (double p : pts) d = std::min(d, std::abs(p - tau));
  return d;
}

inline bool Core::retake_plan(double tau, double zone, bool &twice, double &h1) {
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

inline void Core::rk4_projected(double t, const Vec &q, const Vec &v, const Vec &a0, double h,
                                Vec &qn, Vec &vn, Vec &qm) {
  dv_ = (h / 2) * v;
  pinocchio::integrate(model_, q, dv_, qm);
  vs_ = v + (h / 2) * a0;
  project(qm, vs_, true);
  // the retake rule's midpoint indicator, while J is at qm (no kinematics pass later)
  if (stage_zone_ > 0) midpoint_indicator_ = rank_indicator(qm);
  check_stage_regular(qm, t + h / 2);
  accel(t + h / 2, qm, vs_);
  chart_rate(q, dv_, vs_, k2v_);  // the stages' rates in the chart about q (run_fixed)
  k2a_ = a_;
  dv_ = (h / 2) * k2v_;
  pinocchio::integrate(model_, q, dv_, qs_);
  vs_ = v + (h / 2) * k2a_;
  project(qs_, vs_, true);
  check_stage_regular(qs_, t + h / 2);
  accel(t + h / 2, qs_, vs_);
  chart_rate(q, dv_, vs_, k3v_);
  k3a_ = a_;
  dv_ = h * k3v_;
  pinocchio::integrate(model_, q, dv_, qs_);
  vs_ = v + h * k3a_;
  project(qs_, vs_, true);
  check_stage_regular(qs_, t + h);
  accel(t + h, qs_, vs_);
  chart_rate(q, dv_, vs_, k4v_);
  k4a_ = a_;
  dv_ = (h / 6) * (v + 2 * k2v_ + 2 * k3v_ + k4v_);
  pinocchio::integrate(model_, q, dv_, qn);
  vn = v + (h / 6) * (a0 + 2 * k2a_ + 2 * k3a_ + a_);
  check_finite(qn, vn, t + h);
  project(qn, vn, true);
}

inline void Core::record_interpolated(Samples &S, double t, double s, double h, const Vec &q0,
                                      const Vec &v0, const Vec &a0, const Vec &q1, const Vec &v1,
                                      const Vec &a1) {
  const double h00 = 2 * s * s * s - 3 * s * s + 1, h10 = s * s * s - 2 * s * s + s;
  const double h01 = -2 * s * s * s + 3 * s * s, h11 = s * s * s - s * s;
  pinocchio::difference(model_, q0, q1, dv_);
  dv_ = h10 * h * v0 + h01 * dv_ + h11 * h * v1;
  pinocchio::integrate(model_, q0, dv_, qs_);
  k2v_ = h00 * v0 + h10 * h * a0 + h01 * v1 + h11 * h * a1;
  vs_ = k2v_;
  project(qs_, vs_);
  check_regular(qs_, t);
  accel(t, qs_, k2v_);
  record(S, t, qs_, k2v_);
}

inline bp::dict Core::run_rk4_stage_projected(const Vec &q0, const Vec &v0, double dt, long n_steps,
                                              const std::vector<char> &out, bp::object progress) {
  Samples S;
  Vec q = q0, v = v0, a(nv_), qn(nq_), vn(nv_), qm(nq_), q1(nq_), v1(nv_), a1(nv_);
  dv_.resize(nv_);
  vs_.resize(nv_);
  qs_.resize(nq_);
  k2v_.resize(nv_);
  k2a_.resize(nv_);
  k3v_.resize(nv_);
  k3a_.resize(nv_);
  k4v_.resize(nv_);
  a2_.resize(nv_);
  double t = 0.0;
  accel(t, q, v);
  a = a_;
  if (out[0]) record(S, t, q, v);
  long splits = 0;
  double rho_start = rank_indicator(q);
  for (long k = 1; k <= n_steps; ++k) {
    rk4_projected(t, q, v, a, dt, qn, vn, qm);
    double rho_new = rank_indicator(qn);
    bool twice = false;
    double f = 0.0;
    if (stage_zone_ > 0 &&
        retake_plan(crossing_estimate(rho_start, midpoint_indicator_, rho_new), stage_zone_,
                    twice, f)) {
      const double span = twice ? 2.0 : 1.0;
      double h1 = f * dt, h2 = span * dt - f * dt;
      if (f < span) {
        rk4_projected(t, q, v, a, h1, q1, v1, qm);
        check_regular(q1, t + h1);
        accel(t + h1, q1, v1);
        a1 = a_;
        rk4_projected(t + h1, q1, v1, a1, h2, qn, vn, qm);
      } else {  // one substep of two grid steps
        h1 = 0.0;
        h2 = span * dt;
        q1 = q;
        v1 = v;
        a1 = a;
        rk4_projected(t, q, v, a, h2, qn, vn, qm);
      }
      rho_new = rank_indicator(qn);
      ++splits;
      if (twice) {
        if (out[k]) {  // the skipped grid point, from the substep holding it
          if (h1 >= dt) {
            record_interpolated(S, k * dt, dt / h1, h1, q, v, a, q1, v1, a1);
          } else {
            check_regular(qn, t + 2 * dt);
            accel(t + 2 * dt, qn, vn);
            a2_ = a_;
            record_interpolated(S, k * dt, (dt - h1) / h2, h2, q1, v1, a1, qn, vn, a2_);
          }
        }
        poll(k, k * dt, progress);
        if (k == n_steps) break;  // the step beyond t_final only served the output
        ++k;
      }
    }
    t = k * dt;
    check_regular(qn, t);
    q = qn;
    v = vn;
    accel(t, q, v);
    a = a_;
    rho_start = rho_new;
    if (out[k]) record(S, t, q, v);
    poll(k, t, progress);
  }
  bp::dict d = samples_dict(S, n_steps);
  d["singular_splits"] = splits;
  return d;
}

inline bp::dict Core::run_fixed(int integrator, const Vec &q0, const Vec &v0, double dt,
                                long n_steps, const Eigen::VectorXi &out_steps, bool projects,
                                bp::object progress) {
  check_sizes(q0, v0);
  invalidate_kinematics();  // nothing kept from before the run (M_, the factor of P)
  if (integrator < EULER || integrator > RK4) throw BadArgument{"run_fixed: unknown integrator"};
  n_evals_ = 0;
  Samples S;
  std::vector<char> out(n_steps + 1, 0);
  for (Eigen::Index i = 0; i < out_steps.size(); ++i)
    if (out_steps[i] >= 0 && out_steps[i] <= n_steps) out[out_steps[i]] = 1;
  // Every run starts from its own configuration: a previous partitioning run's
  // rows_only_ left set would skip the stage-projected loop's singularity check.
  begin_partitioning(true);
  if (integrator == RK4 && stage_projects_ && projects && nc_)
    return run_rk4_stage_projected(q0, v0, dt, n_steps, out, progress);
  Vec q = q0, v = v0, qn(nq_), vn(nv_), qs(nq_), vs(nv_);
  Vec k1v(nv_), k1a(nv_), k2v(nv_), k2a(nv_), k3v(nv_), k3a(nv_), k4v(nv_), k4a(nv_), dv(nv_);
  double t = 0.0;
  if (partitions_) complete(q, v, t);
  accel(t, q, v);
  if (out[0]) record(S, t, q, v);
  for (long k = 1; k <= n_steps; ++k) {
    if (integrator == EULER) {
      dv = dt * v;
      pinocchio::integrate(model_, q, dv, qn);
      vn = v + dt * a_;
    } else if (integrator == SEMI_IMPLICIT) {
      vn = v + dt * a_;
      dv = dt * vn;
      pinocchio::integrate(model_, q, dv, qn);
    } else {
      k1v = v;
      k1a = a_;
      dv = (dt / 2) * k1v;
      pinocchio::integrate(model_, q, dv, qs);
      vs = v + (dt / 2) * k1a;
      if (stage_projects_) project(qs, vs, true);
      else if (partitions_) complete(qs, vs, t + dt / 2);
      accel(t + dt / 2, qs, vs);
      chart_rate(q, dv, vs, k2v);  // the chart about q (simulate/chart.py)
      k2a = a_;
      dv = (dt / 2) * k2v;
      pinocchio::integrate(model_, q, dv, qs);
      vs = v + (dt / 2) * k2a;
      if (stage_projects_) project(qs, vs, true);
      else if (partitions_) complete(qs, vs, t + dt / 2);
      accel(t + dt / 2, qs, vs);
      chart_rate(q, dv, vs, k3v);
      k3a = a_;
      dv = dt * k3v;
      pinocchio::integrate(model_, q, dv, qs);
      vs = v + dt * k3a;
      if (stage_projects_) project(qs, vs, true);
      else if (partitions_) complete(qs, vs, t + dt);
      accel(t + dt, qs, vs);
      chart_rate(q, dv, vs, k4v);
      k4a = a_;
      dv = (dt / 6) * (k1v + 2 * k2v + 2 * k3v + k4v);
      pinocchio::integrate(model_, q, dv, qn);
      vn = v + (dt / 6) * (k1a + 2 * k2a + 2 * k3a + k4a);
    }
    t = k * dt;
    check_finite(qn, vn, t);
    if (projects) project(qn, vn, stage_projects_);
    else if (partitions_) partition_step(qn, vn, t);
    check_regular(qn, t);  // partitioning: the rows only (Problem.check_rows)
    q = qn;
    v = vn;
    accel(t, q, v);
    if (out[k]) record(S, t, q, v);
    poll(k, t, progress);
  }
  return samples_dict(S, n_steps);
}

inline bp::dict Core::run_ali3p(const Vec &q0, const Vec &v0, double dt, long n_steps,
                                const Eigen::VectorXi &out_steps, const Ali3pSettings &s,
                                bp::object progress) {
  check_sizes(q0, v0);
  invalidate_kinematics();  // nothing kept from before the run (M_, the factor of P)
  if (!(dt > 0.0) || n_steps < 0 || s.max_iter < 1)
    throw BadArgument{"run_ali3p: dt > 0, n_steps >= 0 and ali3p_max_iter >= 1 required"};
  std::vector<char> out(n_steps + 1, 0);
  for (Eigen::Index i = 0; i < out_steps.size(); ++i)
    if (out_steps[i] >= 0 && out_steps[i] <= n_steps) out[out_steps[i]] = 1;
  return Ali3pLoop<Core>(*this, s).run(q0, v0, dt, n_steps, out, progress);
}

}  // namespace closedchain
