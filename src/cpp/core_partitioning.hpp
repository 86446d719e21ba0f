// closedchain._core: the reduced method and the coordinate-partitioning stabilization.
// (Functions over (CoreModel, CoreData): their declarations, then their definitions.)

#pragma once

#include <pinocchio/algorithm/joint-configuration.hpp>

#include <algorithm>
#include <cmath>
#include <limits>
#include <string>

#include "closure_newton.hpp"
#include "core_data.hpp"
#include "core_methods.hpp"
#include "core_model.hpp"
#include "core_rows.hpp"
#include "errors.hpp"
#include "settings.hpp"

namespace closedchain {

// -- declarations ------------------------------------------------------------

/// `ind` as a vector, checked: nv - nc distinct indices in 0..nv-1 (BadArgument naming
/// `what` otherwise).
std::vector<int> checked_indices(const CoreModel &model, const Eigen::VectorXi &ind,
                                 const std::string &what);

/// The reduced method's partition (mech.independent_idx_v) and the names of the
/// velocity coordinates (for the J_D messages).
void set_partition(CoreModel &model, CoreData &data, const Eigen::VectorXi &ind, bp::list names);

/// The loops' alignment checks (ConstraintLayer.alignment_vectors): phi = 0 is a
/// spurious closure when (R_p u).(R_s u) <= 0 for a vector u of loop loop[i].
void set_alignment(CoreModel &model, CoreData &data, const Eigen::VectorXi &fid_p,
                   const Eigen::VectorXi &fid_s, const Mat &u, const Eigen::VectorXi &loop,
                   bp::list loop_names);

/// The partitioning settings of configure (SimulationSettings.dependent_tol,
/// repartition_cond, partition_singular_cond; RunOptions.partitions, independent).
void configure_partitioning(CoreModel &model, CoreData &data, const RunOptions &run,
                            const SimulationSettings &sim);

/// The names of the coordinates idx, comma separated (their indices without names).
std::string join_names(const CoreModel &model, const std::vector<int> &idx);

/// The dependent solve's iteration limit, halvings of a step, rcond of its fallback step
/// and the contraction of |phi|^2 that makes the full step enough (closure.solve_closure).
constexpr int DEPENDENT_MAX_ITER = 20, DEPENDENT_MAX_HALVINGS = 12;
constexpr double DEPENDENT_FALLBACK_RCOND = 1e-2, DEPENDENT_CONTRACTION = 0.25;

/// The Gauss-Newton step of the dependent solve into data.step_c, -J_D^+ phi_n: by LU where
/// J_D is regular (pass 0), else lstsq's solution with rcond eps nc (pass 0) or
/// DEPENDENT_FALLBACK_RCOND (pass 1: without J_D's weak directions).
void dependent_step(const CoreModel &model, CoreData &data, int pass);

/// Halve the step data.step_c from q until accept_trial (closure_newton.hpp: the trial point
/// lowers |phi|^2 below sq or meets tol; the best so far in best, data.q_best, data.phi_best).
void dependent_line_search(const CoreModel &model, CoreData &data, const Vec &q, double sq,
                           double tol, TrialBest &best);

/// The names of the loops whose alignment check fails at q, comma separated (empty when
/// every loop is aligned or none is checked): phi = 0 there is a spurious closure, the
/// cut-joint frames turned by 180 degrees against each other, (R_p u) . (R_s u) <= 0
/// (ConstraintLayer.misaligned_loops). The one alignment check of the core: the dependent
/// solve's (check_alignment) and the assembly's (closure_newton.hpp).
std::string misaligned_loops(const CoreModel &model, CoreData &data, const RefV &q);

/// SimulationFailure when the assembly at q is a spurious closure of a loop
/// (misaligned_loops).
void check_alignment(const CoreModel &model, CoreData &data, const Vec &q, double t);

/// Gauss-Newton on phi(q) = 0 moving the dependent coordinates data.dependent only, to
/// dependent_tol (closure.solve_closure with AssemblySettings(tol=dependent_tol,
/// max_iter=20): the full step, then, unless it contracts the sum of squares by
/// 1/4, the step without J_D's directions below 1e-2 of its largest singular
/// value; each with up to 12 halvings; the lower one is taken). nq == nv, so the
/// held coordinates stay exact under pinocchio::integrate. Every trial point is
/// evaluated with its J (one kinematics pass, computeJointJacobians): the accepted
/// one's J serves the next iteration and v_D from the memo of eval_phi_J.
void newton_dependent(const CoreModel &model, CoreData &data, Vec &q, double t);

/// Problem.complete: q_D from phi = 0 (q_I held, q the guess), v_D = -J_D^-1 J_I v_I.
void complete(const CoreModel &model, CoreData &data, Vec &q, Vec &v, double t);

/// cond_2(J_D(q)) of the stabilization's partition (np.linalg.cond).
double cond_JD(const CoreModel &model, CoreData &data, const Vec &q);

/// The pivot columns of Householder QR of data.J, each the lowest-index column whose
/// remaining norm is within pivot_tie_rtol of the largest (closure._tie_pivots), sorted.
/// Only when re-partitioning is considered: allocates.
std::vector<int> tie_pivots(const CoreModel &model, const CoreData &data);

/// Problem.repartition: the dependent set of column-pivoted QR of J (Wehage-Haug, ties
/// to the lowest index); true when it changed. SingularError when its J_D is above
/// partition_singular_cond.
bool repartition(const CoreModel &model, CoreData &data, const Vec &q, double t);

/// The start of a run: the stabilization's partition from configure ("independent").
void begin_partitioning(const CoreModel &model, CoreData &data, bool fixed_step);

/// After a fixed step (fixed.py): complete (q, v), re-partition when cond(J_D) is large.
void partition_step(const CoreModel &model, CoreData &data, Vec &q, Vec &v, double t);

/// y = (q_I, v_I) of the state (q, v) in the current partition.
void pack(const CoreModel &model, const CoreData &data, const Vec &q, const Vec &v, Vec &y);

/// (q, v) of the partitioned state y = (q_I, v_I), the dependent solve warm-started
/// from the last evaluation's q (adaptive.py's unpack).
///
/// Two savings over the numpy loop, same solution to dependent_tol: the guess of q_D
/// follows the tangent, q_D = warm_D - (J_D^-1 J_I)(warm) (q_I - warm_I) (the numpy
/// loop starts from warm_D: one Newton iteration more per evaluation; a dense
/// output of run_adaptive passes q_D from the step's own interpolant instead,
/// data.use_out_guess: one iteration where the tangent took two to four), and the
/// state of the last call is reused when y and the warm start are the same (each
/// step unpacks its end state three times: checks, output, re-partitioning).
/// Returns false when the result came from that memo (data.J and data.lu_jd are then not
/// necessarily those of q).
bool unpack(const CoreModel &model, CoreData &data, const Vec &y, double t, Vec &q, Vec &v);

/// fun with partitioning: (q, v) completed from y = (q_I, v_I) (a stage's guess, or
/// unpack), the tangent predictor at the new warm start, f = (v_I, a_I).
void fun_partitioned(const CoreModel &model, CoreData &data, double t, const Vec &y,
                     Eigen::Ref<Vec> f);

/// After an adaptive step (adaptive.py): stop when det(J_D) changed sign since the
/// first step (or the last re-partition); re-partition when cond(J_D) is large and
/// t < t_final, then y is the new partition's state. Returns true on re-partition.
bool adaptive_partition_check(const CoreModel &model, CoreData &data, double t, double t_final,
                              Vec &y, Vec &q, Vec &v);

/// The guess of q_D at a Runge-Kutta stage with coefficients a[0..s-1]: the dependent
/// coordinates integrated with the stage's own weights, q_D0 + h sum_j a_j v_D,j
/// (v_D,j of the earlier stages): accurate to the step's truncation error, so the
/// dependent solve needs one Newton iteration (the numpy loop starts from the last
/// evaluation's q_D, and from the tangent predictor of unpack here elsewhere).
void stage_guess(const CoreModel &model, CoreData &data, const double *a, int s, double h);

/// The step start (t, y) is the last evaluation's: its q_D and v_D.
void step_start_from_last(CoreData &data);

/// The run's re-partitions as a list of (t, independent indices).
bp::list repartitions_list(const CoreData &data);

/// (independent, dependent) velocity indices of the stabilization's partition.
bp::tuple py_partition(const CoreData &data);

// -- definitions -------------------------------------------------------------

inline std::vector<int> checked_indices(const CoreModel &model, const Eigen::VectorXi &ind,
                                        const std::string &what) {
  const int m = model.nv - model.nc;
  std::vector<int> v(ind.data(), ind.data() + ind.size());
  std::vector<int> s = v;
  std::sort(s.begin(), s.end());
  bool ok = static_cast<int>(v.size()) == m && std::adjacent_find(s.begin(), s.end()) == s.end() &&
            (s.empty() || (s.front() >= 0 && s.back() < model.nv));
  if (!ok)
    throw BadArgument{what + " must be " + std::to_string(m) + " distinct velocity indices in 0.." +
                      std::to_string(model.nv - 1) + " (the mobility)"};
  return v;
}

inline void set_partition(CoreModel &model, CoreData &data, const Eigen::VectorXi &ind,
                          bp::list names) {
  if (bp::len(names) != model.nv) throw BadArgument{"Core.set_partition: one name per coordinate"};
  split_indices(model.nv, checked_indices(model, ind, "independent_idx_v"),
                model.method_independent, model.method_dependent);
  model.coordinate_names.clear();
  for (int i = 0; i < model.nv; ++i)
    model.coordinate_names.push_back(bp::extract<std::string>(names[i]));
  model.method_jd_label = "J_D (constraint-Jacobian columns of the dependent coordinates " +
                          join_names(model, model.method_dependent) + ")";
  data.reduced_basis.setZero();
  for (std::size_t k = 0; k < model.method_independent.size(); ++k)
    data.reduced_basis(model.method_independent[k], k) = 1.0;
  model.start_independent = data.independent = model.method_independent;
  data.dependent = model.method_dependent;
}

inline void set_alignment(CoreModel &model, CoreData &data, const Eigen::VectorXi &fid_p,
                          const Eigen::VectorXi &fid_s, const Mat &u, const Eigen::VectorXi &loop,
                          bp::list loop_names) {
  const Eigen::Index n = fid_p.size();
  if (fid_s.size() != n || u.rows() != n || loop.size() != n || (n && u.cols() != 3))
    throw BadArgument{"Core.set_alignment: tables of inconsistent shapes"};
  model.alignments.clear();
  model.loop_names.clear();
  for (long i = 0; i < bp::len(loop_names); ++i)
    model.loop_names.push_back(bp::extract<std::string>(loop_names[i]));
  for (Eigen::Index i = 0; i < n; ++i) {
    if (fid_p[i] < 0 || fid_p[i] >= static_cast<int>(model.tree.nframes) || fid_s[i] < 0 ||
        fid_s[i] >= static_cast<int>(model.tree.nframes) || loop[i] < 0 ||
        loop[i] >= static_cast<int>(model.loop_names.size()))
      throw BadArgument{"Core.set_alignment: frame or loop index out of range"};
    model.alignments.push_back(
        {model.frame_index(fid_p[i]), model.frame_index(fid_s[i]), u.row(i).transpose(), loop[i]});
  }
  if (data.frame_R.size() != model.frame_ids.size()) {  // a frame not among the rows' frames
    model.frame_supports();
    data.resize_frames(model);
  }
  invalidate_kinematics(data);
}

inline void configure_partitioning(CoreModel &model, CoreData &data, const RunOptions &run,
                                   const SimulationSettings &sim) {
  model.dependent_tol = sim.dependent_tol;
  model.repartition_cond = sim.repartition_cond;
  model.partition_singular_cond = sim.partition_singular_cond;
  model.partitions = run.partitions;
  data.rows_only = false;  // set by begin_partitioning for the run
  model.pivot_tie_rtol = PIVOT_TIE_RTOL;
  if (run.independent.size() > 0)
    model.start_independent = checked_indices(model, run.independent, "independent");
}

inline std::string join_names(const CoreModel &model, const std::vector<int> &idx) {
  std::string s;
  for (std::size_t k = 0; k < idx.size(); ++k) {
    if (k) s += ", ";
    s += idx[k] < static_cast<int>(model.coordinate_names.size()) ? model.coordinate_names[idx[k]]
                                                                  : std::to_string(idx[k]);
  }
  return s;
}

inline void dependent_step(const CoreModel &model, CoreData &data, int pass) {
  // a regular J_D (rcond above eps nc; the factors' bound shows it cheaply
  // away from singular J_D): lstsq's solution is the LU solution
  const double eps_n = std::numeric_limits<double>::epsilon() * model.nc;
  if (pass == 0 && data.lu_jd.factor(data.JD) &&
      (data.lu_jd.anorm * data.lu_jd.inverse_norm_bound() * eps_n < 1.0 ||
       data.lu_jd.rcond() > eps_n)) {
    data.step_c = -data.phi_n;
    data.lu_jd.solve(data.step_c);  // = lstsq's solution for a regular J_D
    return;
  }
  // lstsq with rcond: singular values below rcond s_max dropped (rcond None:
  // eps nc, numpy's default)
  const double rc =
      pass == 0 ? std::numeric_limits<double>::epsilon() * model.nc : DEPENDENT_FALLBACK_RCOND;
  data.svd_jd_uv.compute(data.JD, Eigen::ComputeFullU | Eigen::ComputeFullV);
  gauss_newton_svd_step(data.svd_jd_uv, data.phi_n, rc, data.step_c);
}

inline void dependent_line_search(const CoreModel &model, CoreData &data, const Vec &q, double sq,
                                  double tol, TrialBest &best) {
  data.dv_n.setZero();
  for (int i = 0; i < model.nc; ++i) data.dv_n[data.dependent[i]] = data.step_c[i];
  double alpha = 1.0;
  for (int k = 0; k < DEPENDENT_MAX_HALVINGS; ++k, alpha *= 0.5) {
    data.dq = alpha * data.dv_n;
    integrate_trial(model, q, data.dq, data.q_try);
    eval_phi_J_trial(model, data, data.q_try);
    if (accept_trial(data, data.q_try, sq, tol, best, data.q_best, data.phi_best)) return;
  }
}

inline void newton_dependent(const CoreModel &model, CoreData &data, Vec &q, double t) {
  if (model.nc == 0) return;
  const double tol = model.dependent_tol;
  eval_phi_J(model, data, q);
  data.phi_n = data.phi;
  double res = max_abs_nan(data.phi_n);
  for (int it = 0; it < DEPENDENT_MAX_ITER && !(res <= tol); ++it) {
    eval_phi_J(model, data, q);
    gather_JD(model, data, data.dependent);
    const double sq = data.phi_n.squaredNorm();
    TrialBest best;
    for (int pass = 0; pass < 2; ++pass) {
      dependent_step(model, data, pass);
      dependent_line_search(model, data, q, sq, tol, best);
      if (best.have && (best.res <= tol || best.sq <= DEPENDENT_CONTRACTION * sq)) break;
    }
    if (!best.have) break;
    q = data.q_best;
    data.phi_n = data.phi_best;
    res = best.res;
  }
  if (!(res <= tol))
    throw SimulationFailure{"at t = " + fmt("%.9g", t) +
                                " s the dependent coordinates could not be solved: assembly "
                                "did not converge: max |phi| = " +
                                fmt("%.3e", res) + " > tol " + fmt("%.1e", tol),
                            t};
  check_alignment(model, data, q, t);
}

inline std::string misaligned_loops(const CoreModel &model, CoreData &data, const RefV &q) {
  std::string bad;
  if (model.alignments.empty()) return bad;
  // the placements at q (from the memo unless a later trial moved them)
  eval_phi_J(model, data, q);
  int last = -1;
  for (const LoopAlignment &al : model.alignments) {
    if (al.loop == last) continue;  // that loop is already reported
    // the frames' rotations of placements() at q (the same products as oMi * placement)
    if ((data.frame_R[al.p] * al.u).dot(data.frame_R[al.s] * al.u) <= 0.0) {
      bad += (bad.empty() ? "" : ", ") + model.loop_names[al.loop];
      last = al.loop;
    }
  }
  return bad;
}

inline void check_alignment(const CoreModel &model, CoreData &data, const Vec &q, double t) {
  const std::string bad = misaligned_loops(model, data, q);
  if (!bad.empty())
    throw SimulationFailure{
        "at t = " + fmt("%.9g", t) +
            " s the dependent coordinates could not be solved: assembly reached phi = 0 on "
            "a spurious closure of loop(s) " +
            bad +
            ": the cut-joint frames are turned by 180 degrees against each other; start "
            "from a guess closer to the intended assembly",
        t};
}

inline void complete(const CoreModel &model, CoreData &data, Vec &q, Vec &v, double t) {
  if (model.nc == 0) return;
  newton_dependent(model, data, q, t);
  eval_phi_J(model, data, q);
  gather_JD(model, data, data.dependent);
  if (!data.lu_jd.factor(data.JD))
    throw SingularError{model.name + ": at t = " + fmt("%.9g", t) + " s J_D of the dependent " +
                            "coordinates " + join_names(model, data.dependent) +
                            " is singular at q = " + vec_str(q) + "; " + PASSING_HINT,
                        std::numeric_limits<double>::infinity(), t, Vec(q)};
  data.tmp_c.setZero();
  for (int i : data.independent) data.tmp_c.noalias() += v[i] * data.J.col(i);
  data.lu_jd.solve(data.tmp_c);
  for (int i = 0; i < model.nc; ++i) v[data.dependent[i]] = -data.tmp_c[i];
}

inline double cond_JD(const CoreModel &model, CoreData &data, const Vec &q) {
  if (model.nc == 0) return 1.0;
  eval_phi_J(model, data, q);
  gather_JD(model, data, data.dependent);
  data.svd_jd.compute(data.JD);
  const Vec &sv = data.svd_jd.singularValues();
  return sv[model.nc - 1] > 0 ? sv[0] / sv[model.nc - 1] : std::numeric_limits<double>::infinity();
}

inline std::vector<int> tie_pivots(const CoreModel &model, const CoreData &data) {
  Mat A = data.J;
  std::vector<char> taken(model.nv, 0);
  std::vector<int> piv;
  Vec norms(model.nv), u;
  for (int k = 0; k < model.nc; ++k) {
    const int r = model.nc - k;
    double mx = -1.0;
    for (int j = 0; j < model.nv; ++j) {
      norms[j] = taken[j] ? -1.0 : A.col(j).tail(r).norm();
      mx = std::max(mx, norms[j]);
    }
    int p = 0;
    while (!(norms[p] >= (1.0 - model.pivot_tie_rtol) * mx)) ++p;
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

inline bool repartition(const CoreModel &model, CoreData &data, const Vec &q, double t) {
  eval_phi_J(model, data, q);
  const std::vector<int> dep = tie_pivots(model, data);
  gather_JD(model, data, dep);
  data.svd_jd.compute(data.JD);
  const Vec &sv = data.svd_jd.singularValues();
  const double cond =
      sv[model.nc - 1] > 0 ? sv[0] / sv[model.nc - 1] : std::numeric_limits<double>::infinity();
  if (!(cond <= model.partition_singular_cond))
    throw SingularError{
        model.name + ": at t = " + fmt("%.9g", t) +
            " s the best-conditioned J_D of any partition of the coordinates "
            "is singular at q = " +
            vec_str(q) + " (condition number " + fmt("%.3e", cond) + " > partition_singular_cond " +
            fmt("%.1e", model.partition_singular_cond) +
            "); no partition has a regular J_D: a singular configuration; " + PASSING_HINT,
        cond, t, Vec(q)};
  if (dep == data.dependent) return false;
  data.dependent = dep;
  data.independent.clear();
  for (int i = 0; i < model.nv; ++i)
    if (!std::binary_search(data.dependent.begin(), data.dependent.end(), i))
      data.independent.push_back(i);
  data.rep_t.push_back(t);
  data.rep_ind.insert(data.rep_ind.end(), data.independent.begin(), data.independent.end());
  return true;
}

inline void begin_partitioning(const CoreModel &model, CoreData &data, bool fixed_step) {
  data.rep_t.clear();
  data.rep_ind.clear();
  data.sign0 = 0.0;
  data.rows_only = model.partitions && fixed_step;  // fixed.py checks the rows only
  data.predictor_valid = data.unpack_valid = false;
  if (!model.partitions) return;
  if (model.nq != model.nv) throw BadArgument{"stabilization partitioning needs nq == nv"};
  split_indices(model.nv, model.start_independent, data.independent, data.dependent);
}

inline void partition_step(const CoreModel &model, CoreData &data, Vec &q, Vec &v, double t) {
  complete(model, data, q, v, t);
  if (cond_JD(model, data, q) > model.repartition_cond) repartition(model, data, q, t);
}

inline void pack(const CoreModel &model, const CoreData &data, const Vec &q, const Vec &v, Vec &y) {
  const int m = static_cast<int>(data.independent.size());
  for (int k = 0; k < m; ++k) {
    y[k] = q[data.independent[k]];
    y[m + k] = v[data.independent[k]];
  }
}

inline bool unpack(const CoreModel &model, CoreData &data, const Vec &y, double t, Vec &q, Vec &v) {
  const int m = static_cast<int>(data.independent.size());
  const bool guess = data.use_out_guess;
  data.use_out_guess = false;
  if (data.unpack_valid && y == data.unpack_y && data.warm_q == data.unpack_warm) {
    q = data.unpack_q;
    v = data.unpack_v;
    return false;
  }
  q = data.warm_q;
  v.setZero();
  for (int k = 0; k < m; ++k) {
    q[data.independent[k]] = y[k];
    v[data.independent[k]] = y[m + k];
  }
  if (guess) {  // a dense output's q_D (run_adaptive)
    for (int i = 0; i < model.nc; ++i) q[data.dependent[i]] = data.guess_qD[i];
  } else if (data.predictor_valid && model.nc) {
    for (int k = 0; k < m; ++k) data.independent_dq[k] = y[k] - data.warm_q[data.independent[k]];
    data.tmp_c.noalias() = data.Xwarm * data.independent_dq;
    for (int i = 0; i < model.nc; ++i) q[data.dependent[i]] -= data.tmp_c[i];
  }
  complete(model, data, q, v, t);
  data.unpack_y = y;
  data.unpack_warm = data.warm_q;
  data.unpack_q = q;
  data.unpack_v = v;
  data.unpack_valid = true;
  return true;
}

inline void fun_partitioned(const CoreModel &model, CoreData &data, double t, const Vec &y,
                            Eigen::Ref<Vec> f) {
  const int m = static_cast<int>(data.independent.size());
  if (data.use_guess) {  // the stage's guess of q_D (stage_guess)
    data.use_guess = false;
    data.fun_q = data.warm_q;
    data.fun_v.setZero();
    for (int k = 0; k < m; ++k) {
      data.fun_q[data.independent[k]] = y[k];
      data.fun_v[data.independent[k]] = y[m + k];
    }
    for (int i = 0; i < model.nc; ++i) data.fun_q[data.dependent[i]] = data.guess_qD[i];
    complete(model, data, data.fun_q, data.fun_v, t);
  } else if (!unpack(model, data, y, t, data.fun_q, data.fun_v) && model.nc) {
    eval_phi_J(model, data, data.fun_q);
    gather_JD(model, data, data.dependent);
    data.lu_jd.factor(data.JD);
  }
  for (int i = 0; i < model.nc; ++i) {
    data.vD_last[i] = data.fun_v[data.dependent[i]];
    data.qD_new[i] = data.fun_q[data.dependent[i]];
  }
  // the tangent at the new warm start: data.lu_jd holds J_D(data.fun_q) from complete, data.J is
  // J(data.fun_q)
  if (model.nc) {
    for (int k = 0; k < m; ++k) {
      data.tmp_c = data.J.col(data.independent[k]);
      data.lu_jd.solve(data.tmp_c);
      data.Xwarm.col(k) = data.tmp_c;
    }
    data.predictor_valid = true;
  }
  accel(model, data, t, data.fun_q, data.fun_v);
  data.warm_q = data.fun_q;
  for (int k = 0; k < m; ++k) {
    f[k] = data.fun_v[data.independent[k]];
    f[m + k] = data.a[data.independent[k]];
  }
}

inline bool adaptive_partition_check(const CoreModel &model, CoreData &data, double t,
                                     double t_final, Vec &y, Vec &q, Vec &v) {
  unpack(model, data, y, t, q, v);
  if (model.nc == 0) return false;
  eval_phi_J(model, data, q);
  gather_JD(model, data, data.dependent);
  data.lu_jd.factor(data.JD);
  const double sign = data.lu_jd.det_sign();
  if (data.sign0 == 0.0) data.sign0 = sign;
  if (sign * data.sign0 <= 0.0) {
    const double cond = cond_JD(model, data, q);
    throw SingularError{model.name + ": at t = " + fmt("%.9g", t) +
                            " s det(J_D) changed sign within the last step, ending at q = " +
                            vec_str(q) + " (condition number " + fmt("%.3e", cond) +
                            " of J_D at the step's end); the motion crossed a singular "
                            "configuration, which adaptive partitioning cannot follow; use a "
                            "fixed-step integrator; " +
                            PASSING_HINT,
                        cond, t, Vec(q)};
  }
  if (!(cond_JD(model, data, q) > model.repartition_cond && t < t_final &&
        repartition(model, data, q, t)))
    return false;
  data.warm_q = q;
  data.predictor_valid = data.unpack_valid = false;  // made for the old partition
  gather_JD(model, data, data.dependent);            // data.J is still that of q
  data.lu_jd.factor(data.JD);
  data.sign0 = data.lu_jd.det_sign();
  pack(model, data, q, v, y);
  return true;
}

inline void stage_guess(const CoreModel &model, CoreData &data, const double *a, int s, double h) {
  data.guess_qD = data.qD0;
  for (int j = 0; j < s; ++j)
    if (a[j] != 0.0) data.guess_qD.noalias() += (h * a[j]) * data.stage_dependent_v.col(j);
  data.use_guess = model.nc > 0;
}

inline void step_start_from_last(CoreData &data) {
  data.qD0 = data.qD_new;
  data.start_dependent_v = data.vD_last;
}

inline bp::list repartitions_list(const CoreData &data) {
  bp::list out;
  const std::size_t m = data.independent.size();
  for (std::size_t i = 0; i < data.rep_t.size(); ++i) {
    bp::list ind;
    for (std::size_t k = 0; k < m; ++k) ind.append(data.rep_ind[i * m + k]);
    out.append(bp::make_tuple(data.rep_t[i], ind));
  }
  return out;
}

inline bp::tuple py_partition(const CoreData &data) {
  bp::list ind, dep;
  for (int i : data.independent) ind.append(i);
  for (int i : data.dependent) dep.append(i);
  return bp::make_tuple(ind, dep);
}

}  // namespace closedchain
