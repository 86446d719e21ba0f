// closedchain._core: the adaptive loops (RK45, DOP853 with scipy's error control) and the
// chart of q when nq != nv.
// (Functions over (CoreModel, CoreData): their declarations, then their definitions.)

#pragma once

#include <pinocchio/algorithm/joint-configuration.hpp>

#include <algorithm>
#include <cmath>
#include <limits>

#include "core_chart.hpp"
#include "core_data.hpp"
#include "core_fixed.hpp"
#include "core_methods.hpp"
#include "core_model.hpp"
#include "core_partitioning.hpp"
#include "core_projection.hpp"
#include "core_recording.hpp"
#include "core_rows.hpp"
#include "rk_coefficients.hpp"

namespace closedchain {

// -- declarations ------------------------------------------------------------

/// Root mean square of x (scipy's norm of the error estimate).
double rms(const Vec &x);

/// The right-hand side dy/dt = f(t, y) of the adaptive loops: y = (q or the chart's x, v),
/// or (q_I, v_I) with partitioning (fun_partitioned).
void fun(const CoreModel &model, CoreData &data, double t, const Vec &y, Eigen::Ref<Vec> f);

/// Integrate with RK45 or DOP853 (scipy's RungeKutta: the same error control, step-size
/// rule and dense output) from (q0, v0) at t = 0 to t_final, recording at every step or at
/// the times t_eval; projects: project onto the constraint manifold after every step.
bp::dict run_adaptive(const CoreModel &model, CoreData &data, int integrator, const Vec &q0,
                      const Vec &v0, double t_final, double rtol, double atol,
                      bp::object t_eval_obj, bool projects, bp::object progress);

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

inline bp::dict run_adaptive(const CoreModel &model, CoreData &data, int integrator, const Vec &q0,
                             const Vec &v0, double t_final, double rtol, double atol,
                             bp::object t_eval_obj, bool projects, bp::object progress) {
  check_sizes(model, q0, v0);
  invalidate_kinematics(data);  // nothing kept from before the run (data.M, the factor of P)
  if (integrator != RK45 && integrator != DOP853)
    throw BadArgument{"run_adaptive: unknown integrator"};
  const bool dop = integrator == DOP853;
  const int n_stages = dop ? dop853::N_STAGES : rk45::N_STAGES;
  const int error_order = dop ? 7 : 4;
  const double error_exponent = -1.0 / (error_order + 1);
  const double SAFETY = 0.9, MIN_FACTOR = 0.2, MAX_FACTOR = 10.0;
  const double eps = std::numeric_limits<double>::epsilon();
  if (rtol < 100 * eps) rtol = 100 * eps;  // scipy's validate_tol
  const std::string iname = dop ? "DOP853" : "RK45";
  data.n_evals = 0;
  Samples S;
  begin_partitioning(model, data, false);
  // Partitioning integrates (q_I, v_I) only; (q_D, v_D) follow at every evaluation.
  const int ns = model.partitions ? model.nv - model.nc : model.nv;
  const int n = 2 * ns;
  Vec qc(model.nv), vc(model.nv);
  std::vector<double> pending;
  const bool dense = !t_eval_obj.is_none();
  if (dense) {
    Vec te = bp::extract<Vec>(t_eval_obj);
    pending.assign(te.data(), te.data() + te.size());
  }
  std::size_t ip = 0;
  Vec y(n), y_new(n), f(n), f_new(n), scale(n), dy(n), ye(n), tmp(n), e5(n), e3(n);
  Vec q_out(model.nq), v_out(model.nv), x_out(model.nv);
  chart_start(model, data, q0);  // partitioning needs nq == nv (refused in Python): no chart then
  if (model.partitions) {
    qc = q0;
    vc = v0;
    complete(model, data, qc, vc, 0.0);
    data.warm_q = q0;  // the dependent solves start from the last evaluation's q
    pack(model, data, qc, vc, y);
  } else {
    y.head(model.nv) = data.chart ? Vec::Zero(model.nv) : q0;
    y.tail(model.nv) = v0;
  }
  Mat K(n, dop ? dop853::N_STAGES_EXTENDED : n_stages + 1);
  data.stage_dependent_v = Mat::Zero(model.nc, K.cols());
  Mat F(n, dop853::INTERPOLATOR_POWER);
  // partitioning: the same dense output of q_D from its rates v_D at the stages
  // (data.stage_dependent_v),
  // the guess of the output's dependent solve (as stage_guess for the stages)
  Mat FD(model.nc, model.partitions ? dop853::INTERPOLATOR_POWER : 0);
  auto output = [&](double t, const Vec &yy) {
    if (model.partitions) {
      unpack(model, data, yy, t, qc, vc);
      accel(model, data, t, qc, vc);
      record(model, data, S, t, qc, vc);
      return;
    }
    q_out = chart_q(model, data, yy.head(model.nv));
    v_out = yy.tail(model.nv);
    accel(model, data, t, q_out, v_out);
    record(model, data, S, t, q_out, v_out);
  };
  double t = 0.0;
  if (!dense || (ip < pending.size() && pending[ip] <= 0.0)) {
    output(0.0, y);
    if (dense) ++ip;
  }
  fun(model, data, t, y, f);
  if (model.partitions) step_start_from_last(data);
  // scipy's select_initial_step
  double h_abs;
  {
    double interval = std::abs(t_final - t);
    scale = atol + y.cwiseAbs().array() * rtol;
    double d0 = rms(y.cwiseQuotient(scale)), d1 = rms(f.cwiseQuotient(scale));
    double h0 = (d0 < 1e-5 || d1 < 1e-5) ? 1e-6 : 0.01 * d0 / d1;
    h0 = std::min(h0, interval);
    Vec y1 = y + h0 * f;
    Vec f1(n);
    fun(model, data, t + h0, y1, f1);
    double d2 = rms((f1 - f).cwiseQuotient(scale)) / h0;
    double h1 = (d1 <= 1e-15 && d2 <= 1e-15)
                    ? std::max(1e-6, h0 * 1e-3)
                    : std::pow(0.01 / std::max(d1, d2), 1.0 / (error_order + 1));
    h_abs = std::min(std::min(100 * h0, h1), interval);
  }
  long steps = 0;
  while (t < t_final) {
    // one step of scipy's RungeKutta._step_impl
    double min_step = 10 * std::abs(std::nextafter(t, std::numeric_limits<double>::infinity()) - t);
    if (h_abs < min_step) h_abs = min_step;
    bool accepted = false, rejected = false;
    double t_new = t, h = 0.0;
    while (!accepted) {
      if (h_abs < min_step)
        throw SimulationFailure{model.name + ": integrator " + iname +
                                    " failed at t = " + fmt("%.9g", t) +
                                    " s: Required step size is less than spacing between "
                                    "numbers.",
                                t};
      h = h_abs;
      t_new = t + h;
      if (t_new - t_final > 0) t_new = t_final;
      h = t_new - t;
      h_abs = std::abs(h);
      // rk_step
      K.col(0) = f;
      if (model.partitions) data.stage_dependent_v.col(0) = data.start_dependent_v;
      for (int s = 1; s < n_stages; ++s) {
        dy.setZero();
        for (int j = 0; j < s; ++j) {
          double c = dop ? dop853::A[s][j] : rk45::A[s][j];
          if (c != 0.0) dy += c * K.col(j);
        }
        ye = y + h * dy;
        if (model.partitions) stage_guess(model, data, dop ? dop853::A[s] : rk45::A[s], s, h);
        fun(model, data, t + (dop ? dop853::C[s] : rk45::C[s]) * h, ye, K.col(s));
        if (model.partitions) data.stage_dependent_v.col(s) = data.vD_last;
      }
      dy.setZero();
      for (int j = 0; j < n_stages; ++j) {
        double b = dop ? dop853::B[j] : rk45::B[j];
        if (b != 0.0) dy += b * K.col(j);
      }
      y_new = y + h * dy;
      if (model.partitions) stage_guess(model, data, dop ? dop853::B : rk45::B, n_stages, h);
      fun(model, data, t + h, y_new, f_new);
      if (model.partitions) data.stage_dependent_v.col(n_stages) = data.vD_last;
      K.col(n_stages) = f_new;
      scale = atol + y.cwiseAbs().cwiseMax(y_new.cwiseAbs()).array() * rtol;
      double err;
      if (dop) {
        e5.setZero();
        e3.setZero();
        for (int j = 0; j <= n_stages; ++j) {
          e5 += dop853::E5[j] * K.col(j);
          e3 += dop853::E3[j] * K.col(j);
        }
        e5 = e5.cwiseQuotient(scale);
        e3 = e3.cwiseQuotient(scale);
        double n5 = e5.squaredNorm(), n3 = e3.squaredNorm();
        if (n5 == 0 && n3 == 0)
          err = 0.0;
        else
          err = std::abs(h) * n5 / std::sqrt((n5 + 0.01 * n3) * n);
      } else {
        tmp.setZero();
        for (int j = 0; j <= n_stages; ++j) tmp += rk45::E[j] * K.col(j);
        tmp *= h;
        err = rms(tmp.cwiseQuotient(scale));
      }
      if (err < 1) {
        double factor =
            err == 0 ? MAX_FACTOR : std::min(MAX_FACTOR, SAFETY * std::pow(err, error_exponent));
        if (rejected) factor = std::min(1.0, factor);
        h_abs *= factor;
        accepted = true;
      } else {
        h_abs *= std::max(MIN_FACTOR, SAFETY * std::pow(err, error_exponent));
        rejected = true;
      }
    }
    ++steps;
    const double t_old = t;
    if (model.partitions) {  // the dependent state at y_new and its rate: the next step's start
      data.qD_end = data.qD_new;  // (data.qD0 stays the step start's for the dense-output stages)
      data.start_dependent_v = data.stage_dependent_v.col(n_stages);
    }
    // dense output at the t_eval within the step, from the unprojected step
    if (dense && ip < pending.size() && pending[ip] <= t_new) {
      if (dop) {
        for (int s = n_stages + 1, e = 0; e < 3; ++s, ++e) {
          dy.setZero();
          for (int j = 0; j < s; ++j)
            if (dop853::A_EXTRA[e][j] != 0.0) dy += dop853::A_EXTRA[e][j] * K.col(j);
          ye = y + h * dy;
          if (model.partitions) stage_guess(model, data, dop853::A_EXTRA[e], s, h);
          fun(model, data, t_old + dop853::C_EXTRA[e] * h, ye, K.col(s));
          if (model.partitions) data.stage_dependent_v.col(s) = data.vD_last;
        }
        F.col(0) = y_new - y;
        F.col(1) = h * K.col(0) - F.col(0);
        F.col(2) = 2 * F.col(0) - h * (f_new + K.col(0));
        for (int i = 0; i < 4; ++i) {
          tmp.setZero();
          for (int j = 0; j < dop853::N_STAGES_EXTENDED; ++j)
            if (dop853::D[i][j] != 0.0) tmp += dop853::D[i][j] * K.col(j);
          F.col(3 + i) = h * tmp;
        }
        if (model.partitions && model.nc) {
          FD.col(0) = data.qD_end - data.qD0;
          FD.col(1) = h * data.stage_dependent_v.col(0) - FD.col(0);
          FD.col(2) = 2 * FD.col(0) -
                      h * (data.stage_dependent_v.col(n_stages) + data.stage_dependent_v.col(0));
          for (int i = 0; i < 4; ++i) {
            FD.col(3 + i).setZero();
            for (int j = 0; j < dop853::N_STAGES_EXTENDED; ++j)
              if (dop853::D[i][j] != 0.0)
                FD.col(3 + i) += (h * dop853::D[i][j]) * data.stage_dependent_v.col(j);
          }
        }
      } else {
        for (int i = 0; i < 4; ++i) {  // Q = K^T P
          tmp.setZero();
          for (int j = 0; j <= n_stages; ++j)
            if (rk45::P[j][i] != 0.0) tmp += rk45::P[j][i] * K.col(j);
          F.col(i) = tmp;
          if (model.partitions && model.nc) {
            FD.col(i).setZero();
            for (int j = 0; j <= n_stages; ++j)
              if (rk45::P[j][i] != 0.0) FD.col(i) += rk45::P[j][i] * data.stage_dependent_v.col(j);
          }
        }
      }
      while (ip < pending.size() && pending[ip] <= t_new * (1 + 1e-15)) {
        double x = (pending[ip] - t_old) / h;
        const bool guess = model.partitions && model.nc;
        if (dop) {
          ye.setZero();
          if (guess) data.guess_qD.setZero();
          for (int i = dop853::INTERPOLATOR_POWER - 1, r = 0; i >= 0; --i, ++r) {
            ye += F.col(i);
            ye *= (r % 2 == 0) ? x : 1 - x;
            if (guess) {
              data.guess_qD += FD.col(i);
              data.guess_qD *= (r % 2 == 0) ? x : 1 - x;
            }
          }
          ye += y;
          if (guess) data.guess_qD += data.qD0;
        } else {
          double p = x;
          ye = y;
          if (guess) data.guess_qD = data.qD0;
          for (int i = 0; i < 4; ++i, p *= x) {
            ye += (h * p) * F.col(i);
            if (guess) data.guess_qD += (h * p) * FD.col(i);
          }
        }
        data.use_out_guess = guess;
        output(pending[ip], ye);
        ++ip;
      }
    }
    t = t_new;
    y = y_new;
    f = f_new;
    if (model.partitions) {
      data.qD0 = data.qD_end;
      check_finite(model, y.head(ns), y.tail(ns), t);
    } else {
      q_out = chart_q(model, data, y.head(model.nv));
      v_out = y.tail(model.nv);
      check_finite(model, q_out, v_out, t);
    }
    if (projects) {
      project(model, data, q_out, v_out);
      if (data.chart) pinocchio::difference(model.tree, data.chart_centre, q_out, x_out);
      y.head(model.nv) = data.chart ? x_out : q_out;
      y.tail(model.nv) = v_out;
      fun(model, data, t, y, f);
    }
    if (model.partitions) {
      unpack(model, data, y, t, qc, vc);
      check_regular(model, data, qc, t);
    } else {
      if (data.chart && t < t_final && chart_recentre(model, data, y.head(model.nv)))
        fun(model, data, t, y, f);
      check_regular(model, data, q_out, t);
    }
    if (!dense) output(t, y);
    poll(steps, t, progress);
    // det(J_D) sign and re-partitioning; a new partition restarts the integrator
    // from (t, y) with the step size it proposed (as the numpy loop restarts scipy's).
    if (model.partitions && adaptive_partition_check(model, data, t, t_final, y, qc, vc)) {
      fun(model, data, t, y, f);
      step_start_from_last(data);
    }
  }
  return samples_dict(model, data, S, steps);
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
  Samples S;
  std::vector<double> stops;
  bool record_start = true;
  if (t_eval_obj.is_none()) {
    stops.push_back(t_final);
  } else {
    Vec te = bp::extract<Vec>(t_eval_obj);
    record_start = te.size() && te[0] <= 0.0;
    for (Eigen::Index i = 0; i < te.size(); ++i)
      if (te[i] > 0.0) stops.push_back(te[i]);
  }
  const bool every = t_eval_obj.is_none() || record_all;
  for (Vec *b : {&data.dv, &data.vs, &data.k2v, &data.k2a, &data.k3v, &data.k3a, &data.k4v,
                 &data.k4a})
    b->resize(model.nv);
  data.qs.resize(model.nq);
  const int nq = model.nq, nv = model.nv;
  Vec q = q0, v = v0, a(nv), qn(nq), vn(nv), an(nv), qm(nq), q1(nq), v1(nv), a1(nv);
  Vec k5v(nv), ex(nv);
  auto factor = [](double err) {
    if (err == 0.0) return RK43_MAX_FACTOR;
    return std::min(RK43_MAX_FACTOR,
                    std::max(RK43_MIN_FACTOR, RK43_SAFETY * std::pow(err, RK43_ERROR_EXPONENT)));
  };
  // One projected rk4 step with its estimate (rk43._Estimator.step): (qb, vb, ab) at the
  // end, err in scipy's weighted RMS norm, exm the largest position error [rad or m];
  // returns the rank indicator at the projected midpoint.
  auto step = [&](double t, const Vec &qa, const Vec &va, const Vec &aa, double h, Vec &qb,
                  Vec &vb, Vec &ab, double &err, double &exm) {
    rk4_projected(model, data, t, qa, va, aa, h, qb, vb, qm);
    const double mid = data.midpoint_indicator;
    accel(model, data, t + h, qb, vb);
    ab = data.a;
    pinocchio::difference(model.tree, qa, qb, data.dv);
    chart_rate(model, data, qa, data.dv, vb, k5v);
    ex = (h / 6) * (data.k4v - k5v);
    double sum = 0.0;  // positions in the chart about qa: 0 at the start, data.dv at the end
    for (int i = 0; i < model.nv; ++i) {
      const double sx = atol + rtol * std::abs(data.dv[i]);
      const double sv = atol + rtol * std::max(std::abs(va[i]), std::abs(vb[i]));
      const double ev = (h / 6) * (data.k4a[i] - ab[i]);
      sum += (ex[i] / sx) * (ex[i] / sx) + (ev / sv) * (ev / sv);
    }
    err = model.nv ? std::sqrt(sum / (2.0 * model.nv)) : 0.0;
    exm = model.nv ? ex.cwiseAbs().maxCoeff() : 0.0;
    return mid;
  };
  double t = 0.0;
  accel(model, data, t, q, v);
  a = data.a;
  if (record_start) record(model, data, S, t, q, v);
  double rho_start = rank_indicator(model, data, q);
  double h = h0, err_max = 0.0, err_sum = 0.0;
  long steps = 0, rejected = 0, splits = 0;
  for (const double t_stop : stops) {
    while (t < t_stop) {
      const double proposed = h;
      const bool clipped = t + h >= t_stop * (1.0 - 1e-15);
      if (clipped) h = t_stop - t;
      if (!(h > 10 * std::abs(std::nextafter(t, t_stop) - t)))
        throw SimulationFailure{model.name + ": integrator rk43 failed at t = " + fmt("%.9g", t) +
                                    " s: the step fell below the spacing of the times",
                                t};
      double err = 0.0, exm = 0.0;
      const double rho_mid = step(t, q, v, a, h, qn, vn, an, err, exm);
      double rho_new = rank_indicator(model, data, qn);
      bool plan = false, twice = false, sub = false;
      double f = 0.0, span = 1.0;
      if (model.stage_zone > 0)
        plan = retake_plan(crossing_estimate(rho_start, rho_mid, rho_new), model.stage_zone,
                           twice, f);
      if (plan) {
        span = twice ? 2.0 : 1.0;
        if (twice && t + 2.0 * h > t_stop * (1.0 + 1e-15)) {
          h = 0.5 * (t_stop - t);  // re-plan with two steps ending at the stop
          continue;
        }
        if (f < span) {
          double e1 = 0.0, m1 = 0.0, e2 = 0.0, m2 = 0.0;
          step(t, q, v, a, f * h, q1, v1, a1, e1, m1);
          sub = true;
          step(t + f * h, q1, v1, a1, (span - f) * h, qn, vn, an, e2, m2);
          err = std::max(e1, e2);
          exm = m1 + m2;
        } else {  // one substep of two steps
          step(t, q, v, a, span * h, qn, vn, an, err, exm);
        }
        rho_new = rank_indicator(model, data, qn);
      }
      if (err > 1.0) {
        ++rejected;
        h *= factor(err);
        continue;
      }
      if (plan) ++splits;
      if (sub) check_regular(model, data, q1, t + f * h);
      t = (clipped || t + span * h >= t_stop) ? t_stop : t + span * h;
      check_regular(model, data, qn, t);
      q = qn;
      v = vn;
      a = an;
      rho_start = rho_new;
      ++steps;
      err_max = std::max(err_max, err);
      err_sum += exm;
      // data.a, data.lam: the last evaluation's, at q
      if (every || t == t_stop) record(model, data, S, t, q, v);
      poll(steps, t, progress);
      h *= factor(err);
      if (clipped) h = std::max(h, proposed);
    }
  }
  bp::dict d = samples_dict(model, data, S, steps);
  d["singular_splits"] = splits;
  d["rejected_steps"] = rejected;
  d["error_estimate_max"] = err_max;
  d["error_estimate_sum"] = err_sum;
  return d;
}

}  // namespace closedchain
