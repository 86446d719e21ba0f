// closedchain._core: the reduced method and the coordinate-partitioning stabilization.
// (Member functions of Core, declared in core.hpp.)

#pragma once

#include <pinocchio/algorithm/joint-configuration.hpp>

#include <algorithm>
#include <cmath>
#include <limits>

#include "core.hpp"

namespace closedchain {

inline void Core::init_partitioning() {
  const int m = std::max(nv_ - nc_, 0);
  JD_ = Mat::Zero(nc_, nc_);
  lu_jd_.resize(nc_);
  reduced_basis_ = Mat::Zero(nv_, m);
  mass_reduced_basis_ = Mat::Zero(nv_, m);
  reduced_offset_ = Vec::Zero(nv_);
  reduced_force_ = Vec::Zero(nv_);
  independent_a_ = Vec::Zero(m);
  svd_jd_ = Eigen::JacobiSVD<Mat>(nc_, nc_);
  svd_jd_uv_ = Eigen::JacobiSVD<Mat>(nc_, nc_, Eigen::ComputeFullU | Eigen::ComputeFullV);
  phi_n_ = Vec::Zero(nc_);
  phi_best_ = Vec::Zero(nc_);
  step_c_ = Vec::Zero(nc_);
  q_try_ = Vec::Zero(nq_);
  q_best_ = Vec::Zero(nq_);
  dv_n_ = Vec::Zero(nv_);
  warm_q_ = Vec::Zero(nq_);
  fun_q_ = Vec::Zero(nq_);
  fun_v_ = Vec::Zero(nv_);
  Xwarm_ = Mat::Zero(nc_, m);
  qD0_ = start_dependent_v_ = qD_end_ = qD_new_ = vD_last_ = guess_qD_ = Vec::Zero(nc_);
  independent_dq_ = Vec::Zero(m);
  unpack_q_ = Vec::Zero(nq_);
  unpack_v_ = Vec::Zero(nv_);
  unpack_warm_ = Vec::Zero(nq_);
  unpack_y_ = Vec::Zero(2 * m);
  std::vector<int> ind(m);
  for (int i = 0; i < m; ++i) ind[i] = nc_ + i;  // until set_partition
  set_indices(ind, red_ind_, red_dep_);
  ind0_ = ind_ = red_ind_;
  dep_ = red_dep_;
}

inline void Core::set_indices(std::vector<int> ind, std::vector<int> &ind_out,
                              std::vector<int> &dep_out) {
  std::sort(ind.begin(), ind.end());
  ind_out = ind;
  dep_out.clear();
  for (int i = 0; i < nv_; ++i)
    if (!std::binary_search(ind.begin(), ind.end(), i)) dep_out.push_back(i);
}

inline std::vector<int> Core::checked_indices(const Eigen::VectorXi &ind, const std::string &what) {
  const int m = nv_ - nc_;
  std::vector<int> v(ind.data(), ind.data() + ind.size());
  std::vector<int> s = v;
  std::sort(s.begin(), s.end());
  bool ok = static_cast<int>(v.size()) == m &&
            std::adjacent_find(s.begin(), s.end()) == s.end() &&
            (s.empty() || (s.front() >= 0 && s.back() < nv_));
  if (!ok)
    throw BadArgument{what + " must be " + std::to_string(m) +
                      " distinct velocity indices in 0.." + std::to_string(nv_ - 1) +
                      " (the mobility)"};
  return v;
}

inline void Core::set_partition(const Eigen::VectorXi &ind, bp::list names) {
  if (bp::len(names) != nv_) throw BadArgument{"Core.set_partition: one name per coordinate"};
  set_indices(checked_indices(ind, "independent_idx_v"), red_ind_, red_dep_);
  coordinate_names_.clear();
  for (int i = 0; i < nv_; ++i) coordinate_names_.push_back(bp::extract<std::string>(names[i]));
  red_what_ = "J_D (constraint-Jacobian columns of the dependent coordinates " +
              join_names(red_dep_) + ")";
  reduced_basis_.setZero();
  for (std::size_t k = 0; k < red_ind_.size(); ++k) reduced_basis_(red_ind_[k], k) = 1.0;
  ind0_ = ind_ = red_ind_;
  dep_ = red_dep_;
}

inline void Core::set_alignment(const Eigen::VectorXi &fid_p, const Eigen::VectorXi &fid_s,
                                const Mat &u, const Eigen::VectorXi &loop, bp::list loop_names) {
  const Eigen::Index n = fid_p.size();
  if (fid_s.size() != n || u.rows() != n || loop.size() != n || (n && u.cols() != 3))
    throw BadArgument{"Core.set_alignment: tables of inconsistent shapes"};
  align_.clear();
  align_names_.clear();
  for (long i = 0; i < bp::len(loop_names); ++i)
    align_names_.push_back(bp::extract<std::string>(loop_names[i]));
  for (Eigen::Index i = 0; i < n; ++i) {
    if (fid_p[i] < 0 || fid_p[i] >= static_cast<int>(model_.nframes) || fid_s[i] < 0 ||
        fid_s[i] >= static_cast<int>(model_.nframes) || loop[i] < 0 ||
        loop[i] >= static_cast<int>(align_names_.size()))
      throw BadArgument{"Core.set_alignment: frame or loop index out of range"};
    align_.push_back({frame_index(fid_p[i]), frame_index(fid_s[i]), u.row(i).transpose(),
                      loop[i]});
  }
  if (R_.size() != fids_.size()) frame_buffers();  // a frame not among the rows' frames
  invalidate_kinematics();
}

inline void Core::configure_partitioning(const RunOptions &run, const SimulationSettings &sim) {
  dependent_tol_ = sim.dependent_tol;
  repartition_cond_ = sim.repartition_cond;
  partition_singular_cond_ = sim.partition_singular_cond;
  partitions_ = run.partitions;
  rows_only_ = false;  // set by begin_partitioning for the run
  pivot_tie_rtol_ = PIVOT_TIE_RTOL;
  if (run.independent.size() > 0) ind0_ = checked_indices(run.independent, "independent");
}

inline std::string Core::join_names(const std::vector<int> &idx) const {
  std::string s;
  for (std::size_t k = 0; k < idx.size(); ++k) {
    if (k) s += ", ";
    s += idx[k] < static_cast<int>(coordinate_names_.size()) ? coordinate_names_[idx[k]]
                                                               : std::to_string(idx[k]);
  }
  return s;
}

inline void Core::gather_JD(const std::vector<int> &dep) {
  for (int c = 0; c < nc_; ++c) JD_.col(c) = J_.col(dep[c]);
}

inline void Core::solve_reduced(const RefV &q, const Vec &tau, double t) {
  const int m = nv_ - nc_;
  reduced_force_ = tau - h_;
  if (nc_) {
    gather_JD(red_dep_);
    const double rcond = lu_jd_.factor(JD_) ? lu_jd_.rcond() : 0.0;
    const double cond = rcond > 0.0 ? 1.0 / rcond : std::numeric_limits<double>::infinity();
    if (!(cond <= cond_max_))
      singular(q, red_what_, cond,
               "this partition cannot describe the motion here (seed Problem 4): "
               "re-partition with choose_partition(mech, q), or the configuration is a "
               "singularity of the mechanism",
               t);
    for (int k = 0; k < m; ++k) {
      tmp_c_ = J_.col(red_ind_[k]);
      lu_jd_.solve(tmp_c_);
      for (int i = 0; i < nc_; ++i) reduced_basis_(red_dep_[i], k) = -tmp_c_[i];
    }
    tmp_c_ = gamma_;
    lu_jd_.solve(tmp_c_);
    for (int i = 0; i < nc_; ++i) reduced_offset_[red_dep_[i]] = -tmp_c_[i];
    reduced_force_.noalias() -= M_ * reduced_offset_;
  }
  if (m) {
    mass_reduced_basis_.noalias() = M_ * reduced_basis_;
    reduced_mass_.noalias() = reduced_basis_.transpose() * mass_reduced_basis_;
    llt_r_.compute(reduced_mass_);
    check_rcond(q, "the reduced mass matrix S^T M S",
                llt_r_.info() == Eigen::Success ? llt_r_.rcond() : 0.0, t);
    independent_a_.noalias() = reduced_basis_.transpose() * reduced_force_;
    llt_r_.solveInPlace(independent_a_);
    a_.noalias() = reduced_basis_ * independent_a_;
    a_ += reduced_offset_;
    if (!nc_) return;
    reduced_force_.noalias() -= mass_reduced_basis_ * independent_a_;
  } else {
    a_ = reduced_offset_;
  }
  for (int i = 0; i < nc_; ++i) tmp_c_[i] = reduced_force_[red_dep_[i]];
  lu_jd_.solve_transposed(tmp_c_);
  lam_ = tmp_c_;
}

inline void Core::newton_dependent(Vec &q, double t) {
  if (nc_ == 0) return;
  constexpr int MAX_ITER = 20, MAX_HALVINGS = 12;
  constexpr double FALLBACK_RCOND = 1e-2, CONTRACTION = 0.25;
  const double tol = dependent_tol_;
  eval_phi_J(q);
  phi_n_ = phi_;
  double res = phi_n_.cwiseAbs().maxCoeff();
  for (int it = 0; it < MAX_ITER && !(res <= tol); ++it) {
    eval_phi_J(q);
    gather_JD(dep_);
    const double sq = phi_n_.squaredNorm();
    bool have = false;
    double best_sq = 0.0, best_res = 0.0;
    for (int pass = 0; pass < 2; ++pass) {
      // a regular J_D (rcond above eps nc; the factors' bound shows it cheaply
      // away from singular J_D): lstsq's solution is the LU solution
      const double eps_n = std::numeric_limits<double>::epsilon() * nc_;
      if (pass == 0 && lu_jd_.factor(JD_) &&
          (lu_jd_.anorm * lu_jd_.inverse_norm_bound() * eps_n < 1.0 ||
           lu_jd_.rcond() > eps_n)) {
        step_c_ = -phi_n_;
        lu_jd_.solve(step_c_);  // = lstsq's solution for a regular J_D
      } else {
        // lstsq with rcond: singular values below rcond s_max dropped (rcond None:
        // eps nc, numpy's default)
        const double rc = pass == 0 ? std::numeric_limits<double>::epsilon() * nc_
                                    : FALLBACK_RCOND;
        svd_jd_uv_.compute(JD_, Eigen::ComputeFullU | Eigen::ComputeFullV);
        const Vec &sv = svd_jd_uv_.singularValues();
        step_c_.setZero();
        for (Eigen::Index i = 0; i < sv.size(); ++i)
          if (sv[i] > rc * sv[0])
            step_c_ -= (svd_jd_uv_.matrixU().col(i).dot(phi_n_) / sv[i]) *
                       svd_jd_uv_.matrixV().col(i);
      }
      dv_n_.setZero();
      for (int i = 0; i < nc_; ++i) dv_n_[dep_[i]] = step_c_[i];
      double alpha = 1.0;
      for (int k = 0; k < MAX_HALVINGS; ++k) {
        dq_ = alpha * dv_n_;
        if (vector_space_)
          q_try_ = q + dq_;  // pinocchio::integrate on revolute/prismatic joints: q + dq
        else
          pinocchio::integrate(model_, q, dq_, q_try_);
        eval_phi_J_trial(q_try_);
        const double res_try = phi_.cwiseAbs().maxCoeff(), sq_try = phi_.squaredNorm();
        if (sq_try < sq || res_try <= tol) {
          if (!have || sq_try < best_sq) {
            have = true;
            best_sq = sq_try;
            best_res = res_try;
            q_best_ = q_try_;
            phi_best_ = phi_;
          }
          break;
        }
        alpha *= 0.5;
      }
      if (have && (best_res <= tol || best_sq <= CONTRACTION * sq)) break;
    }
    if (!have) break;
    q = q_best_;
    phi_n_ = phi_best_;
    res = best_res;
  }
  if (!(res <= tol))
    throw SimulationFailure{"at t = " + fmt("%.9g", t) +
                                " s the dependent coordinates could not be solved: assembly "
                                "did not converge: max |phi| = " +
                                fmt("%.3e", res) + " > tol " + fmt("%.1e", tol),
                            t};
  if (align_.empty()) return;
  eval_phi_J(q);  // the placements at q (from the memo unless a later trial moved them)
  std::string bad;
  int last = -1;
  for (const Align &al : align_) {
    if (al.loop == last) continue;  // that loop is already reported
    // the frames' rotations of placements() at q (the same products as oMi * placement)
    if ((R_[al.p] * al.u).dot(R_[al.s] * al.u) <= 0.0) {
      bad += (bad.empty() ? "" : ", ") + align_names_[al.loop];
      last = al.loop;
    }
  }
  if (!bad.empty())
    throw SimulationFailure{
        "at t = " + fmt("%.9g", t) +
            " s the dependent coordinates could not be solved: assembly reached phi = 0 on "
            "a spurious closure of loop(s) " + bad +
            ": the cut-joint frames are turned by 180 degrees against each other; start "
            "from a guess closer to the intended assembly",
        t};
}

inline void Core::complete(Vec &q, Vec &v, double t) {
  if (nc_ == 0) return;
  newton_dependent(q, t);
  eval_phi_J(q);
  gather_JD(dep_);
  if (!lu_jd_.factor(JD_))
    throw SingularError{name_ + ": at t = " + fmt("%.9g", t) + " s J_D of the dependent " +
                            "coordinates " + join_names(dep_) + " is singular at q = " +
                            vec_str(q) + "; " + PASSING_HINT,
                        std::numeric_limits<double>::infinity(), t, Vec(q)};
  tmp_c_.setZero();
  for (int i : ind_) tmp_c_.noalias() += v[i] * J_.col(i);
  lu_jd_.solve(tmp_c_);
  for (int i = 0; i < nc_; ++i) v[dep_[i]] = -tmp_c_[i];
}

inline double Core::cond_JD(const Vec &q) {
  if (nc_ == 0) return 1.0;
  eval_phi_J(q);
  gather_JD(dep_);
  svd_jd_.compute(JD_);
  const Vec &sv = svd_jd_.singularValues();
  return sv[nc_ - 1] > 0 ? sv[0] / sv[nc_ - 1] : std::numeric_limits<double>::infinity();
}

inline std::vector<int> Core::tie_pivots() const {
  Mat A = J_;
  std::vector<char> taken(nv_, 0);
  std::vector<int> piv;
  Vec norms(nv_), u;
  for (int k = 0; k < nc_; ++k) {
    const int r = nc_ - k;
    double mx = -1.0;
    for (int j = 0; j < nv_; ++j) {
      norms[j] = taken[j] ? -1.0 : A.col(j).tail(r).norm();
      mx = std::max(mx, norms[j]);
    }
    int p = 0;
    while (!(norms[p] >= (1.0 - pivot_tie_rtol_) * mx)) ++p;
    piv.push_back(p);
    taken[p] = 1;
    u = A.col(p).tail(r);
    u[0] += std::copysign(u.norm(), u[0]);
    const double un = u.norm();
    if (un > 0.0) {
      u /= un;
      A.bottomRows(r) -= 2.0 * u * (u.transpose() * A.bottomRows(r));
    }
  }
  std::sort(piv.begin(), piv.end());
  return piv;
}

inline bool Core::repartition(const Vec &q, double t) {
  eval_phi_J(q);
  const std::vector<int> dep = tie_pivots();
  gather_JD(dep);
  svd_jd_.compute(JD_);
  const Vec &sv = svd_jd_.singularValues();
  const double cond =
      sv[nc_ - 1] > 0 ? sv[0] / sv[nc_ - 1] : std::numeric_limits<double>::infinity();
  if (!(cond <= partition_singular_cond_))
    throw SingularError{name_ + ": at t = " + fmt("%.9g", t) +
                            " s the best-conditioned J_D of any partition of the coordinates "
                            "is singular at q = " + vec_str(q) + " (condition number " +
                            fmt("%.3e", cond) + " > partition_singular_cond " +
                            fmt("%.1e", partition_singular_cond_) +
                            "); no partition has a regular J_D: a singular configuration; " +
                            PASSING_HINT,
                        cond, t, Vec(q)};
  if (dep == dep_) return false;
  dep_ = dep;
  ind_.clear();
  for (int i = 0; i < nv_; ++i)
    if (!std::binary_search(dep_.begin(), dep_.end(), i)) ind_.push_back(i);
  rep_t_.push_back(t);
  rep_ind_.insert(rep_ind_.end(), ind_.begin(), ind_.end());
  return true;
}

inline void Core::begin_partitioning(bool fixed_step) {
  rep_t_.clear();
  rep_ind_.clear();
  sign0_ = 0.0;
  rows_only_ = partitions_ && fixed_step;  // fixed.py checks the rows only
  predictor_valid_ = unpack_valid_ = false;
  if (!partitions_) return;
  if (nq_ != nv_) throw BadArgument{"stabilization partitioning needs nq == nv"};
  set_indices(ind0_, ind_, dep_);
}

inline void Core::partition_step(Vec &q, Vec &v, double t) {
  complete(q, v, t);
  if (cond_JD(q) > repartition_cond_) repartition(q, t);
}

inline void Core::pack(const Vec &q, const Vec &v, Vec &y) const {
  const int m = static_cast<int>(ind_.size());
  for (int k = 0; k < m; ++k) {
    y[k] = q[ind_[k]];
    y[m + k] = v[ind_[k]];
  }
}

inline bool Core::unpack(const Vec &y, double t, Vec &q, Vec &v) {
  const int m = static_cast<int>(ind_.size());
  const bool guess = use_out_guess_;
  use_out_guess_ = false;
  if (unpack_valid_ && y == unpack_y_ && warm_q_ == unpack_warm_) {
    q = unpack_q_;
    v = unpack_v_;
    return false;
  }
  q = warm_q_;
  v.setZero();
  for (int k = 0; k < m; ++k) {
    q[ind_[k]] = y[k];
    v[ind_[k]] = y[m + k];
  }
  if (guess) {  // a dense output's q_D (run_adaptive)
    for (int i = 0; i < nc_; ++i) q[dep_[i]] = guess_qD_[i];
  } else if (predictor_valid_ && nc_) {
    for (int k = 0; k < m; ++k) independent_dq_[k] = y[k] - warm_q_[ind_[k]];
    tmp_c_.noalias() = Xwarm_ * independent_dq_;
    for (int i = 0; i < nc_; ++i) q[dep_[i]] -= tmp_c_[i];
  }
  complete(q, v, t);
  unpack_y_ = y;
  unpack_warm_ = warm_q_;
  unpack_q_ = q;
  unpack_v_ = v;
  unpack_valid_ = true;
  return true;
}

inline void Core::fun_partitioned(double t, const Vec &y, Eigen::Ref<Vec> f) {
  const int m = static_cast<int>(ind_.size());
  if (use_guess_) {  // the stage's guess of q_D (stage_guess)
    use_guess_ = false;
    fun_q_ = warm_q_;
    fun_v_.setZero();
    for (int k = 0; k < m; ++k) {
      fun_q_[ind_[k]] = y[k];
      fun_v_[ind_[k]] = y[m + k];
    }
    for (int i = 0; i < nc_; ++i) fun_q_[dep_[i]] = guess_qD_[i];
    complete(fun_q_, fun_v_, t);
  } else if (!unpack(y, t, fun_q_, fun_v_) && nc_) {
    eval_phi_J(fun_q_);
    gather_JD(dep_);
    lu_jd_.factor(JD_);
  }
  for (int i = 0; i < nc_; ++i) {
    vD_last_[i] = fun_v_[dep_[i]];
    qD_new_[i] = fun_q_[dep_[i]];
  }
  // the tangent at the new warm start: lu_jd_ holds J_D(fun_q_) from complete, J_ is J(fun_q_)
  if (nc_) {
    for (int k = 0; k < m; ++k) {
      tmp_c_ = J_.col(ind_[k]);
      lu_jd_.solve(tmp_c_);
      Xwarm_.col(k) = tmp_c_;
    }
    predictor_valid_ = true;
  }
  accel(t, fun_q_, fun_v_);
  warm_q_ = fun_q_;
  for (int k = 0; k < m; ++k) {
    f[k] = fun_v_[ind_[k]];
    f[m + k] = a_[ind_[k]];
  }
}

inline bool Core::adaptive_partition_check(double t, double t_final, Vec &y, Vec &q, Vec &v) {
  unpack(y, t, q, v);
  if (nc_ == 0) return false;
  eval_phi_J(q);
  gather_JD(dep_);
  lu_jd_.factor(JD_);
  const double sign = lu_jd_.det_sign();
  if (sign0_ == 0.0) sign0_ = sign;
  if (sign * sign0_ <= 0.0) {
    const double cond = cond_JD(q);
    throw SingularError{name_ + ": at t = " + fmt("%.9g", t) +
                            " s det(J_D) changed sign within the last step, ending at q = " +
                            vec_str(q) + " (condition number " + fmt("%.3e", cond) +
                            " of J_D at the step's end); the motion crossed a singular "
                            "configuration, which adaptive partitioning cannot follow; use a "
                            "fixed-step integrator; " + PASSING_HINT,
                        cond, t, Vec(q)};
  }
  if (!(cond_JD(q) > repartition_cond_ && t < t_final && repartition(q, t))) return false;
  warm_q_ = q;
  predictor_valid_ = unpack_valid_ = false;  // made for the old partition
  gather_JD(dep_);  // J_ is still that of q
  lu_jd_.factor(JD_);
  sign0_ = lu_jd_.det_sign();
  pack(q, v, y);
  return true;
}

inline void Core::stage_guess(const double *a, int s, double h) {
  guess_qD_ = qD0_;
  for (int j = 0; j < s; ++j)
    if (a[j] != 0.0) guess_qD_.noalias() += (h * a[j]) * stage_dependent_v_.col(j);
  use_guess_ = nc_ > 0;
}

inline void Core::step_start_from_last() {
  qD0_ = qD_new_;
  start_dependent_v_ = vD_last_;
}

inline bp::list Core::repartitions_list() const {
  bp::list out;
  const std::size_t m = ind_.size();
  for (std::size_t i = 0; i < rep_t_.size(); ++i) {
    bp::list ind;
    for (std::size_t k = 0; k < m; ++k) ind.append(rep_ind_[i * m + k]);
    out.append(bp::make_tuple(rep_t_[i], ind));
  }
  return out;
}

inline bp::tuple Core::py_partition() const {
  bp::list ind, dep;
  for (int i : ind_) ind.append(i);
  for (int i : dep_) dep.append(i);
  return bp::make_tuple(ind, dep);
}

}  // namespace closedchain
