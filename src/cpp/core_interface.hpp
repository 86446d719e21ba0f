// closedchain._core: construction, settings and the one-evaluation Python entry points.
// (Member functions of Core, declared in core.hpp.)

#pragma once

#include <chrono>
#include <limits>
#include <string>

#include "core.hpp"
#include "lean_data.hpp"

namespace closedchain {

inline Core::Core(bp::object model_obj, const std::string &name, const Eigen::VectorXi &kinds,
                  const Eigen::VectorXi &fid_p, const Eigen::VectorXi &fid_s, const Mat &vec1,
                  const Mat &vec2): model_obj_(model_obj),
      model_(bp::extract<Model &>(model_obj)()),
      data_(lean_data(model_)),  // no nv^3 tensors: see lean_data.cpp
      plan_(model_),
      name_(name) {
  const Model &model = model_;
  nq_ = model.nq;
  nv_ = model.nv;
  nc_ = static_cast<int>(kinds.size());
  if (fid_p.size() != nc_ || fid_s.size() != nc_ || vec1.rows() != nc_ ||
      vec2.rows() != nc_ || (nc_ && (vec1.cols() != 3 || vec2.cols() != 3)))
    throw BadArgument{"Core: row tables of inconsistent shapes"};
  for (int r = 0; r < nc_; ++r) rows_.push_back(make_row(r, kinds, fid_p, fid_s, vec1, vec2));
  if (!model.mimicking_joints.empty())
    throw BadArgument{"compiled core: models with mimic joints are not supported "
                      "(use backend='numpy')"};
  frame_buffers();
  M_ = Mat::Zero(nv_, nv_);
  h_ = Vec::Zero(nv_);
  J_ = Mat::Zero(nc_, nv_);
  phi_ = Vec::Zero(nc_);
  gamma_ = Vec::Zero(nc_);
  a_ = Vec::Zero(nv_);
  lam_ = Vec::Zero(nc_);
  tau_ = Vec::Zero(nv_);
  tau_const_ = Vec::Zero(nv_);
  zero_v_ = Vec::Zero(nv_);
  kkt_.resize(nv_ + nc_);
  kkt_solution_ = Vec::Zero(nv_ + nc_);
  kkt_scale_ = Vec::Ones(nv_ + nc_);
  nullspace_a_ = Vec::Zero(std::max(nv_ - nc_, 0));
  llt_m_ = Eigen::LLT<Mat>(nv_);
  llt_c_ = Eigen::LLT<Mat>(nc_);
  schur_solves_ = Mat::Zero(nv_, nc_ + 1);
  delassus_ = Mat::Zero(nc_, nc_);
  svd_ = Eigen::JacobiSVD<Mat>(nc_, nv_, Eigen::ComputeFullU | Eigen::ComputeFullV);
  llt_r_ = Eigen::LLT<Mat>(nv_ - nc_ > 0 ? nv_ - nc_ : 0);
  reduced_mass_ = Mat::Zero(std::max(nv_ - nc_, 0), std::max(nv_ - nc_, 0));
  JJt_ = Mat::Zero(nc_, nc_);
  eig_ = Eigen::SelfAdjointEigenSolver<Mat>(nc_);
  dq_ = Vec::Zero(nv_);
  tmp_c_ = Vec::Zero(nc_);
  tmp_v_ = Vec::Zero(nv_);
  mv_ = Vec::Zero(nv_);
  zero_c_ = Vec::Zero(nc_);
  al_wc_ = Vec::Zero(nc_);
  al_wv_ = Vec::Zero(nv_);
  rhs_v_ = Vec::Zero(nv_);
  P_ = Mat::Zero(nv_, nv_);
  llt_p_.resize(nv_);
  llt_jj_.resize(nc_);
  J_at_ = Vec::Zero(nq_);
  terms_q_ = Vec::Constant(nq_, std::numeric_limits<double>::quiet_NaN());
  terms_v_ = Vec::Zero(nv_);
  q_prev_ = Vec::Zero(nq_);
  vel_c_ = Vec::Zero(nc_);
  rhs_work_ = Vec::Zero(nv_ + nc_);
  for (std::size_t j = 1; j < model.joints.size(); ++j) {
    const auto &jm = model.joints[j];
    if (jm.nv() > 1 && jm.nq() != jm.nv()) {
      if (jm.nv() > 6) throw BadArgument{"Core: a curved joint with more than 6 velocities"};
      curved_.emplace_back(jm.idx_v(), jm.nv());
    }
  }
  D_chart_ = Mat::Zero(curved_.empty() ? 0 : nv_, curved_.empty() ? 0 : nv_);
  vector_space_ = true;
  for (std::size_t j = 1; j < model.joints.size(); ++j) {
    const std::string jn = model.joints[j].shortname();
    if (!(plan_.revolute(j) || jn == "JointModelPX" || jn == "JointModelPY" ||
          jn == "JointModelPZ" || jn == "JointModelPrismaticUnaligned"))
      vector_space_ = false;
  }
  init_partitioning();
  sparsity();
}

inline void Core::configure(const RunOptions &run, const SolverSettings &solver,
                            const SimulationSettings &sim) {
  const std::string &m = run.method;
  if (m == "kkt")
    method_ = KKT;
  else if (m == "schur")
    method_ = SCHUR;
  else if (m == "nullspace")
    method_ = NULLSPACE;
  else if (m == "augmented-lagrangian")
    method_ = AUGMENTED_LAGRANGIAN;
  else if (m == "reduced")
    method_ = REDUCED;
  else
    throw BadArgument{"compiled core: unknown method '" + m +
                      "'; compiled: kkt, schur, nullspace, augmented-lagrangian, reduced"};
  method_name_ = m;
  cond_max_ = solver.cond_max;
  baumgarte_ = solver.baumgarte;
  if (baumgarte_) {
    alpha_ = solver.baumgarte_alpha;
    beta_ = solver.baumgarte_beta;
  }
  projection_tol_ = sim.projection_tol;
  projection_iters_ = sim.projection_iters;
  project_velocities_ = sim.project_velocities;
  singular_cond_ = sim.singular_cond;
  drift_limit_ = sim.drift_limit;
  al_penalty_ = solver.al_penalty;
  al_tol_ = solver.al_tol;
  al_max_iter_ = solver.al_max_iter;
  stage_projects_ = run.stage_projects;
  singular_zone_ = sim.singular_zone;
  stage_zone_ = sim.stage_singular_zone;
  singular_robust_ = run.singular_robust;
  dropped_tol_ = sim.dropped_row_tol;
  dropped_ratio_ = sim.dropped_row_ratio;
  configure_partitioning(run, sim);
  invalidate_kinematics();  // the kept factor of M + alpha J^T J has the old al_penalty
}

inline void Core::set_tau(bp::object tau) {
  tau_obj_ = bp::object();
  tau_mode_ = 0;
  if (tau.is_none()) return;
  if (PyCallable_Check(tau.ptr())) {
    tau_obj_ = tau;
    np_asarray_ = bp::import("numpy").attr("asarray");
    tau_mode_ = 2;
    return;
  }
  Vec c = bp::extract<Vec>(tau);
  if (c.size() != nv_) throw BadArgument{"tau must have shape (nv,)"};
  tau_const_ = c;
  tau_mode_ = 1;
}

inline bp::tuple Core::py_rows(const Vec &q, const Vec &v) {
  check_sizes(q, v);
  eval_terms(q, v);
  return bp::make_tuple(Vec(phi_), Mat(J_), Vec(gamma_));
}

inline bp::tuple Core::py_forward(const Vec &q, const Vec &v, const Vec &tau) {
  check_sizes(q, v);
  if (tau.size() != nv_) throw BadArgument{"tau must have shape (nv,)"};
  invalidate_kinematics();  // one whole evaluation per call
  solve(q, v, tau, std::numeric_limits<double>::quiet_NaN());
  return bp::make_tuple(Vec(a_), Vec(lam_));
}

inline Vec Core::py_repeat(const Vec &q, const Vec &v, const Vec &tau, int n) {
  check_sizes(q, v);
  for (int i = 0; i < n; ++i) {
    invalidate_kinematics();  // a whole evaluation each time (not the kinematics' reuse)
    solve(q, v, tau, std::numeric_limits<double>::quiet_NaN());
  }
  return a_;
}

inline bp::dict Core::py_profile(const Vec &q, const Vec &v, const Vec &tau, int n) {
  check_sizes(q, v);
  using clock = std::chrono::steady_clock;
  double acc[4] = {0, 0, 0, 0};
  clock::time_point last;
  auto mark = [&](int stage) {
    const clock::time_point now = clock::now();
    acc[stage] += std::chrono::duration<double, std::nano>(now - last).count();
    last = now;
  };
  for (int i = 0; i < n; ++i) {
    invalidate_kinematics();
    last = clock::now();
    eval_terms(q, v, mark);
    dispatch(q, tau, std::numeric_limits<double>::quiet_NaN());
    mark(3);
  }
  bp::dict d;
  const char *names[4] = {"tree", "frames", "rows", "solve"};
  for (int k = 0; k < 4; ++k) d[names[k]] = acc[k] / n;
  return d;
}

}  // namespace closedchain
