// closedchain._core: the ALI3-P integrator (Ali3pLoop) and its entry point run_ali3p.
//
// Index-3 augmented Lagrangian integrated by the implicit trapezoidal rule with
// Newton iterations, then mass-orthogonal projections of the velocities and
// accelerations (Bayo & Ledesma 1996; Cuadrado, Cardenal, Morer & Bayo 2000):
// the algorithm of closedchain/simulate/ali3p.py, step for step (same predictor,
// multiplier update, stopping rules, projections, singular-zone rule and output),
// on the core's pieces: the single tree pass (eval_terms), the rows, and the band
// Cholesky of P = M + alpha J^T J (set_band) when the numpy backend uses one.
//
// Ali3pLoop works on a (CoreModel, CoreData) pair (the last evaluation's M, h, J, phi,
// gamma, the products on the structure and the factor of P); one object per run owns
// the run's own vectors, sized once (no allocation inside the steps).

#pragma once

#include <pinocchio/algorithm/joint-configuration.hpp>

#include <Eigen/Dense>
#include <boost/python.hpp>

#include <algorithm>
#include <cmath>
#include <limits>
#include <string>
#include <vector>

#include "al_iteration.hpp"
#include "common.hpp"
#include "constants.hpp"
#include "core_data.hpp"
#include "core_methods.hpp"
#include "core_model.hpp"
#include "core_projection.hpp"
#include "core_recording.hpp"
#include "core_rows.hpp"
#include "core_structure.hpp"
#include "errors.hpp"
#include "gil.hpp"
#include "settings.hpp"

namespace closedchain {

/// One ALI3-P run on a (CoreModel, CoreData) pair: the trapezoidal steps, their Newton
/// iterations and projections, and the run's own vectors.
class Ali3pLoop {
 public:
  using Vec = Eigen::VectorXd;

  /// The run's vectors sized once for the model; s: SimulationSettings.ali3p_*.
  Ali3pLoop(const CoreModel &model, CoreData &data, const Ali3pSettings &s)
      : model_(model), data_(data), settings_(s) {
    const int nq = model_.nq, nv = model_.nv, nc = model_.nc;
    displacement_.setZero(nv);
    newton_step_.setZero(nv);
    residual_.setZero(nv);
    tau_.setZero(nv);
    scaled_lam_.setZero(nc);
    zero_c_.setZero(nc);
    work_c_.setZero(nc);
    projection_lam_.setZero(nc);
    q_interp_.setZero(nq);
    v_interp_.setZero(nv);
    a_interp_.setZero(nv);
    work_v_.setZero(nv);
    j_product_.setZero(nc);
  }

  /// One trapezoidal step of length h ending at t_new from (q, v, a) with the
  /// multiplier estimate lam_star (updated in place): the end state into
  /// (qn, vn, an) and its multipliers into lam (ali3p.py, advance).
  void advance(double t_new, const Vec &q, const Vec &v, const Vec &a, Vec &lam_star, double h,
               Vec &qn, Vec &vn, Vec &an, Vec &lam) {
    const int nc = model_.nc;
    tau_ = tau_at(model_, data_, t_new, q, v);
    const double hh = h * h / 4.0;
    scaled_lam_ = hh * lam_star;
    displacement_ = h * v + (0.5 * h * h) * a;  // predictor: Taylor to second order
    bool converged = false;
    double last = std::numeric_limits<double>::infinity(), size = 0.0;
    for (int it = 0; it < settings_.max_iter; ++it) {
      pinocchio::integrate(model_.tree, q, displacement_, qn);
      vn = (2.0 / h) * displacement_ - v;
      an = (4.0 / (h * h)) * displacement_ - (4.0 / h) * v - a;
      eval_terms(model_, data_, qn, vn);
      // lambda*_{i+1} = lambda*_i + alpha phi(q_{i+1})
      if (nc && it) scaled_lam_ += alpha_ * data_.phi;
      // f = h^2/4 (M a + h - tau) + J^T (mu + alpha phi)
      m_mul(an, residual_);
      residual_ += data_.h - tau_;
      residual_ *= hh;
      if (nc) {
        work_c_ = scaled_lam_ + alpha_ * data_.phi;
        jt_mul_add(work_c_, residual_);
      }
      factor(qn, t_new);
      if (converged) break;
      newton_step_ = -residual_;
      solve(newton_step_);
      displacement_ += newton_step_;
      ++newton_iterations_;
      size = newton_step_.cwiseAbs().maxCoeff();
      // Below ali3p_tol, iterate on while the corrections still shrink (the approximate
      // tangent converges linearly), and until J^T phi is below ali3p_phi_tol.
      converged = size <= settings_.tol &&
                  (size <= settings_.tol * ALI3P_TOL_FLOOR || size > ALI3P_STALL * last);
      if (converged && nc) {
        jt_mul(data_.phi, residual_);
        converged = residual_.cwiseAbs().maxCoeff() <= settings_.phi_tol;
      }
      last = size;
    }
    if (!converged)
      throw SimulationFailure{
          model_.name + ": ALI3-P Newton iterations did not converge at t = " + fmt("%.9g", t_new) +
              " s (last correction " + fmt("%.3e", size) + " > ali3p_tol " +
              fmt("%.1e", settings_.tol) + " after " + std::to_string(settings_.max_iter) +
              " iterations); use a smaller dt",
          t_new};
    check_finite(model_, qn, vn, t_new);
    if (!nc) {
      lam.resize(0);
      return;
    }
    lam = (4.0 / (h * h)) * (scaled_lam_ + alpha_ * data_.phi);
    // Mass-orthogonal projections with the factorization of P at q_{n+1}.
    m_mul(vn, residual_);
    project(residual_, zero_c_, vn);
    // gamma = Jdot v at (q_{n+1}, projected v): M and J at the same q are unchanged.
    eval_terms(model_, data_, qn, vn);
    m_mul(an, residual_);
    project(residual_, data_.gamma, an);
    lam_star = (4.0 / (h * h)) * scaled_lam_;
  }

  /// Integrate from (q0, v0) at the fixed step dt for n_steps, recording at the steps k
  /// with out[k] (ali3p.py, run_ali3p); the samples, the splits around singular positions,
  /// the Newton iterations and alpha.
  bp::dict run(const Vec &q0, const Vec &v0, double dt, long n_steps, const std::vector<char> &out,
               bp::object progress) {
    const int nq = model_.nq, nv = model_.nv, nc = model_.nc;
    Samples S;
    GilRelease nogil;  // until the samples become Python objects (gil.hpp)
    Vec q = q0, v = v0, a(nv), qn(nq), vn(nv), an(nv), q1(nq), v1(nv), a1(nv);
    Vec lam_star(nc), lam(nc), lam1(nc), dq(nv);
    double t = 0.0;
    data_.n_evals = 0;
    accel(model_, data_, t, q, v);  // M, J at q0 from its evaluation
    a = data_.a;
    alpha_ = nc ? settings_.penalty * mass_at_J(model_, data_).trace() /
                      std::max(data_.J.squaredNorm(), std::numeric_limits<double>::min())
                : 0.0;
    // The multiplier estimate, warm-started from the method's multipliers.
    lam = data_.lam;
    if (out[0]) record(model_, data_, S, t, q, v);
    // Singular positions: steps never end within singular_zone steps of a crossing
    // (ali3p.py, run_ali3p): its time is extrapolated from the rank indicator at the
    // last two states (before the first step: q(-dt) by Taylor's expansion), and a step
    // that would end near it is taken with the next one as 1.5 + 0.5 steps.
    const double zone = model_.singular_zone;
    const double sigma_min = std::sqrt(ALI3P_ENFORCED / settings_.penalty);
    long splits = 0;
    lam_star = lam;
    double rho_now = indicator(q);
    dq = -dt * v + (0.5 * dt * dt) * a;
    pinocchio::integrate(model_.tree, q, dq, qn);
    double rho_prev = indicator(qn);
    double gap = 1.0;
    for (long k = 1; k <= n_steps; ++k) {
      // The crossing [steps after t] and the zone around it: singular_zone steps, or
      // where the indicator is predicted below sigma_min.
      double tc = std::numeric_limits<double>::infinity(), zone_k = zone;
      if (rho_now < rho_prev) {
        const double slope = (rho_prev - rho_now) / gap;
        tc = rho_now / slope;
        if (zone > 0.0) zone_k = std::max(zone, std::min(ALI3P_ZONE_MAX, sigma_min / slope));
      }
      gap = 1.0;
      if (std::abs(tc - 1.0) < zone_k) {
        const double h1 = (tc <= 1.0 ? ALI3P_SPLIT : 2.0 - ALI3P_SPLIT) * dt, h2 = 2.0 * dt - h1;
        advance(t + h1, q, v, a, lam_star, h1, q1, v1, a1, lam1);
        advance(t + 2 * dt, q1, v1, a1, lam_star, h2, qn, vn, an, lam);
        ++splits;
        gap = 2.0;
        if (out[k]) {
          if (h1 > dt)
            record_hermite(S, k * dt, dt / h1, h1, q, v, a, q1, v1, a1, lam1);
          else
            record_hermite(S, k * dt, (dt - h1) / h2, h2, q1, v1, a1, qn, vn, an, lam);
        }
        poll(k, k * dt, progress);
        if (k == n_steps) break;  // the step beyond t_final only served the output
        ++k;
      } else {
        advance(k * dt, q, v, a, lam_star, dt, qn, vn, an, lam);
      }
      q.swap(qn);
      v.swap(vn);
      a.swap(an);
      t = k * dt;
      rho_prev = rho_now;
      rho_now = indicator(q);  // J at q from advance's last evaluation
      if (out[k]) {
        set_solution(a, lam);
        record(model_, data_, S, t, q, v);
      }
      poll(k, t, progress);
    }
    nogil.restore();
    bp::dict d = samples_dict(model_, data_, S, n_steps);
    d["singular_splits"] = splits;
    d["newton_iterations"] = newton_iterations_;
    d["ali3p_alpha"] = alpha_;
    return d;
  }

 private:
  /// (data_.a, data_.lam) = (a, lam): the solution record() writes.
  void set_solution(const Vec &a, const Vec &lam) {
    data_.a = a;
    data_.lam = lam;
  }

  /// The rank indicator of J at q (rank_indicator, core_projection.hpp: on the band of J J^T where
  /// there is one).
  double indicator(const Vec &q) { return rank_indicator(model_, data_, q); }

  /// f = M x (the band path: over M's structural hulls).
  void m_mul(const Vec &x, Vec &f) {
    if (model_.banded_penalized) {
      f.setZero();
      closedchain::m_mul_sub(model_, data_, x, f);
      f = -f;
    } else {
      f.noalias() = mass_at_J(model_, data_) * x;
    }
  }

  /// x += J^T y
  void jt_mul_add(const Vec &y, Vec &x) {
    if (model_.banded_penalized) {
      closedchain::jt_mul_add(model_, data_, y, x);
    } else {
      x.noalias() += data_.J.transpose() * y;
    }
  }

  /// x = J^T y
  void jt_mul(const Vec &y, Vec &x) {
    x.setZero();
    jt_mul_add(y, x);
  }

  /// y = J x
  void j_mul(const Vec &x, Vec &y) {
    if (model_.banded_penalized)
      closedchain::j_mul(model_, data_, x, y);
    else
      y.noalias() = data_.J * x;
  }

  /// Factorize P = M + alpha J^T J at the last evaluation (at q, for the error); the
  /// data's own factor (its solve_al's alpha) is gone.
  void factor(const Vec &q, double t) {
    mass_at_J(model_, data_);  // M itself (the tree path does not form it)
    if (!factor_penalized(model_, data_, alpha_))
      singular(model_, q, "the penalized mass matrix M + alpha J^T J",
               std::numeric_limits<double>::infinity(),
               "it is not positive definite (alpha = " + fmt("%.3g", alpha_) +
                   "): M is singular (a massless subtree) or so ill-conditioned that alpha "
                   "J^T J swamps it; lower SimulationSettings.ali3p_penalty",
               t);
  }

  /// x <- P^-1 x
  void solve(Vec &x) { solve_penalized(model_, data_, x); }

  /// al_iterate's products (al_iteration.hpp) on the dense path: Eigen's matrix-vector
  /// kernels into the loop's own vectors (the band path: core_methods.hpp's BandAlOps).
  struct DenseOps {
    /// The loop whose products and factor of P these are.
    Ali3pLoop &l;
    /// y += J x.
    void add_j(const Vec &x, Vec &y) {
      l.j_mul(x, l.j_product_);
      y += l.j_product_;
    }
    /// y -= M x.
    void sub_m(const Vec &x, Vec &y) {
      l.m_mul(x, l.work_v_);
      y -= l.work_v_;
    }
    /// x -= J^T y.
    void sub_jt(const Vec &y, Vec &x) {
      l.jt_mul(y, l.work_v_);
      x -= l.work_v_;
    }
    /// x -= s J^T y.
    void sub_scaled_jt(double s, const Vec &y, Vec &x) {
      l.jt_mul(y, l.work_v_);
      x -= s * l.work_v_;
    }
    /// x <- P^-1 x.
    void solve(Vec &x) { l.solve(x); }
  };

  /// The mass-orthogonal projection min (x - x*)^T M (x - x*) s.t. J x + g = 0 with
  /// rhs = M x*, by the augmented-Lagrangian iteration (al_iterate) with P at alpha_
  /// until max |dx| <= al_tol (1 + max |x|) (solve_augmented_lagrangian, no polish).
  void project(const Vec &rhs, const Vec &g, Vec &x) {
    if (model_.banded_penalized) {
      BandAlOps ops{model_, data_};
      al_iterate(ops, alpha_, rhs, g, model_.al_max_iter, model_.al_tol, x, projection_lam_,
                 newton_step_, work_c_);
    } else {
      DenseOps ops{*this};
      al_iterate(ops, alpha_, rhs, g, model_.al_max_iter, model_.al_tol, x, projection_lam_,
                 newton_step_, work_c_);
    }
  }

  /// Record the state at t = t0 + s h of the substep (q0, v0, a0) -> (q1, v1, a1) of
  /// length h by cubic Hermite interpolation, with the end's multipliers lam
  /// (ali3p.py, _record_hermite: not projected, a linear).
  void record_hermite(Samples &S, double t, double s, double h, const Vec &q0, const Vec &v0,
                      const Vec &a0, const Vec &q1, const Vec &v1, const Vec &a1, const Vec &lam) {
    const double h00 = 2 * s * s * s - 3 * s * s + 1, h10 = s * s * s - 2 * s * s + s;
    const double h01 = -2 * s * s * s + 3 * s * s, h11 = s * s * s - s * s;
    pinocchio::difference(model_.tree, q0, q1, work_v_);
    work_v_ = h10 * h * v0 + h01 * work_v_ + h11 * h * v1;
    pinocchio::integrate(model_.tree, q0, work_v_, q_interp_);
    v_interp_ = h00 * v0 + h10 * h * a0 + h01 * v1 + h11 * h * a1;
    a_interp_ = a0 + s * (a1 - a0);
    set_solution(a_interp_, lam);
    record(model_, data_, S, t, q_interp_, v_interp_);
  }

  /// The mechanism and the data its evaluations write.
  const CoreModel &model_;
  CoreData &data_;
  /// SimulationSettings.ali3p_* of the run.
  Ali3pSettings settings_;
  /// The penalty alpha of P = M + alpha J^T J, fixed for the run.
  double alpha_ = 0.0;
  /// Newton iterations of the run.
  long newton_iterations_ = 0;
  /// advance's Newton state (nv): the displacement q_{n+1} - q_n in the tangent space, the
  /// last correction, the residual (and M v, M a of the projections), the generalized force.
  Vec displacement_, newton_step_, residual_, tau_;
  /// (nc): h^2/4 lambda* of the step, zeros (g of the velocity projection), work, the
  /// projections' multipliers.
  Vec scaled_lam_, zero_c_, work_c_, projection_lam_;
  /// record_hermite's interpolated state (q, v, a); nv and nc work vectors of the products.
  Vec q_interp_, v_interp_, a_interp_, work_v_, j_product_;
};

/// The ALI3-P integrator (ali3p.hpp) at the fixed step dt for n_steps, recording at
/// the steps in out_steps with the settings s (SimulationSettings.ali3p_*).
bp::dict run_ali3p(const CoreModel &model, CoreData &data, const Vec &q0, const Vec &v0, double dt,
                   long n_steps, const Eigen::VectorXi &out_steps, const Ali3pSettings &s,
                   bp::object progress);

inline bp::dict run_ali3p(const CoreModel &model, CoreData &data, const Vec &q0, const Vec &v0,
                          double dt, long n_steps, const Eigen::VectorXi &out_steps,
                          const Ali3pSettings &s, bp::object progress) {
  check_sizes(model, q0, v0);
  invalidate_kinematics(data);  // nothing kept from before the run (data.M, the factor of P)
  if (!(dt > 0.0) || n_steps < 0 || s.max_iter < 1)
    throw BadArgument{"run_ali3p: dt > 0, n_steps >= 0 and ali3p_max_iter >= 1 required"};
  const std::vector<char> out = output_mask(out_steps, n_steps);
  return Ali3pLoop(model, data, s).run(q0, v0, dt, n_steps, out, progress);
}

}  // namespace closedchain
