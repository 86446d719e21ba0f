// closedchain._core: CoreData, everything an evaluation or a run writes: Pinocchio's Data, the
// last evaluation's terms and rows, the factorizations, the caches that skip repeated work,
// the partitioning state and the integrators' stage buffers. Sized once from a CoreModel
// (no allocation in the hot loop); the functions of every concept header take
// (const CoreModel &, CoreData &).

#pragma once

#include <pinocchio/multibody/data.hpp>

#include <Eigen/Dense>

#include <algorithm>
#include <limits>
#include <vector>

#include "banded.hpp"
#include "common.hpp"
#include "core_model.hpp"
#include "dense_lu.hpp"
#include "lean_data.hpp"
#include "small_llt.hpp"
#include "tree_rows.hpp"
#include "tree_solve.hpp"

namespace closedchain {

/// The workspace of the assembly's Gauss-Newton (closure_newton.hpp), sized by
/// closure_newton_resize for one set of free coordinates and reused by every iteration.
struct ClosureNewtonData {
  /// The free velocity indices it is sized for (empty before the first call).
  std::vector<int> free;
  /// The configuration entries of the joints none of whose velocity coordinates is free,
  /// kept exact (pinocchio::integrate with a zero step may renormalize a continuous joint's
  /// (cos, sin)), and their values in the start.
  std::vector<int> held_q;
  Vec q_held;  ///< The values of the held_q entries in the start.
  /// The free columns of J, shape (nc, n_free).
  Mat J_free;
  Eigen::JacobiSVD<Mat> svd;  ///< The SVD of J_free (thin U and V), once per iteration.
  /// The step of the free coordinates, shape (n_free,); on every coordinate (dv) and times the
  /// line search's alpha (dq), shape (nv,).
  Vec step, dv, dq;
  /// The residuals phi at the iterate and at the best trial point, shape (nc,).
  Vec phi, phi_best;
  /// The trial point and the best one, shape (nq,).
  Vec q_try, q_best;
};

/// The buffers, caches and counters of one mechanism's evaluations and runs.
struct CoreData {
  /// Every buffer sized for `model`.
  explicit CoreData(const CoreModel &model);

  /// Size the per-frame buffers for the model's cut frames (new frames zeroed, set_declared
  /// and set_alignment may add frames).
  void resize_frames(const CoreModel &model);

  // -- the tree and the cut frames ---------------------------------------------------------

  /// Pinocchio's Data of the tree, without the nv^3 second-order tensors (lean_data.cpp).
  Data tree;
  /// eval_phi_J_trial: the dependent set that `moved` was made for, and per joint whether
  /// its support holds one of its coordinates.
  std::vector<int> moved_for;
  std::vector<char> moved;
  /// World placement (rotation, origin [m]) of every cut frame at the last kinematics pass.
  std::vector<Eigen::Matrix3d> frame_R;
  std::vector<Vector3d> frame_p;
  /// The configuration of the last kinematics pass: the coupling rows' coordinates.
  Vec rows_q;
  /// Velocity (linear, angular) and classical acceleration at a = 0 of every cut frame's
  /// origin, world axes [m/s, rad/s; m/s^2, rad/s^2].
  std::vector<Eigen::Matrix<double, 6, 1>> frame_v, frame_a;

  // -- the last evaluation -----------------------------------------------------------------

  /// Mass matrix, shape (nv, nv) [kg, kg m, kg m^2].
  Mat M;
  /// Bias forces h = C(q, v) v + g(q), shape (nv,) [N, N m].
  Vec h;
  /// Constraint residuals phi, shape (nc,) [m or 1].
  Vec phi;
  /// Constraint Jacobian, shape (nc, nv).
  Mat J;
  /// gamma = Jdot v, shape (nc,), Baumgarte terms included.
  Vec gamma;
  /// The last solve's accelerations a, shape (nv,), and multipliers lam, shape (nc,).
  Vec a, lam;
  /// The generalized force of the last tau(t, q, v) call, shape (nv,) [N, N m].
  Vec tau;
  /// Zeros, shape (nv,) (tau when none is set) and shape (nc,) (g of the velocity projection).
  Vec zero_v, zero_c;
  /// phi of every declared row at the last kinematics pass, shape (n_declared,).
  Vec declared_residuals;
  /// The q of the last eval_phi_J (J, phi and the frame placements valid there).
  Vec J_at;
  bool J_at_valid = false;
  /// M is at J_at too (with J_at_valid).
  bool M_at_J = false;
  /// llt_p / penalized_band hold P = M + alpha J^T J of solve_al's alpha.
  bool P_factored = false;
  /// al_factor's penalty alpha and how many times it was lowered (valid while P_factored).
  double al_alpha = 0.0;
  int al_lowerings = 0;
  /// (q, v) of the last eval_terms (M and potential_energy valid there).
  Vec terms_q, terms_v;
  /// Potential energy at terms_q [J] (gravity on the total mass, for record()).
  double potential_energy = 0.0;
  /// Evaluations of the right-hand side since the start of the run.
  long n_evals = 0;

  // -- the methods' factorizations and work vectors ----------------------------------------

  /// J J^T, shape (nc, nc).
  Mat JJt;
  /// solve_schur: M^-1 [J^T, tau - h], shape (nv, nc + 1), and the Delassus matrix
  /// J M^-1 J^T, shape (nc, nc).
  Mat schur_solves, delassus;
  /// The reduced mass matrix N^T M N (solve_nullspace) or S^T M S (solve_reduced), shape
  /// (nv - nc, nv - nc).
  Mat reduced_mass;
  /// solve_nullspace: the accelerations in the null-space basis N, shape (nv - nc,).
  Vec nullspace_a;
  /// solve_kkt: K = [[M, J^T], [J, 0]] and its LU.
  DenseLU kkt;
  /// solve_kkt: the right-hand side [tau - h, -gamma], then the solution [a, lam].
  Vec kkt_solution;
  /// solve_kkt: the equilibration D = diag(d_v, d_c) of K (kkt_equilibration).
  Vec kkt_scale;
  /// solve_kkt: D^-1 (kkt_equilibration), the scaling of K^-1 in its condition estimate.
  Vec kkt_unscale;
  /// Work vectors, shapes (nv,) and (nc,).
  Vec dq, tmp_v, tmp_c;
  /// Cholesky factors of M, of an (nc, nc) matrix (Delassus, J J^T) and of the reduced mass.
  Eigen::LLT<Mat> llt_m, llt_c, llt_r;
  /// Fixed-layout Cholesky of M + alpha J^T J and of J J^T (+ regularization).
  SmallLLT llt_p, llt_jj;
  /// P = M + alpha J^T J (lower triangle), shape (nv, nv).
  Mat P;
  /// solve_al: tau - h, shape (nv,).
  Vec rhs_v;
  /// project: q before the last Gauss-Newton step, shape (nq,); J v, shape (nc,).
  Vec q_prev, vel_c;
  /// project(mass_orth): M v, shape (nv,).
  Vec mv;
  /// BandAlOps' products, shapes (nc,) and (nv,).
  Vec al_wc, al_wv;
  /// Band Cholesky factors of M + alpha J^T J (order perm) and of J J^T.
  BandCholesky penalized_band, normal_band;
  /// solve_penalized_band: the right-hand side in the order perm, shape (nv,).
  Vec band_work;
  /// SVD of J (null space, minimum-norm solutions); eigenvalues of J J^T (cond_J) or of the
  /// tree path's Delassus matrix.
  Eigen::JacobiSVD<Mat> svd;
  Eigen::SelfAdjointEigenSolver<Mat> eig;

  // -- the tree path (core_tree.hpp) -------------------------------------------------------

  /// The articulated-body factorization of M at data.J_at (tree_solve.hpp).
  TreeFactor mass_factor;
  /// W = M^-1 J^T, the Delassus matrix D and the factors of D and of I / alpha + D, the SVD
  /// of J, W_r = M^-1 V_r, G = V_r^T W_r and its factor at data.J_at (tree_rows.hpp).
  TreeRows tree_rows;
  /// mass_factor is at data.J_at; so are W and D; the factor of D (its condition checked);
  /// that of I / alpha + D; the SVD of J, W_r, G and G's factor (tree_factor_range).
  bool tree_mass_factored = false, tree_factored = false, delassus_factored = false,
       tree_penalized = false, tree_range_factored = false;

  // -- the integrators ---------------------------------------------------------------------

  /// rk4_projected's stages: increment, stage state, rates.
  Vec dv, vs, qs, k2v, k2a, k3v, k3a, k4v;
  /// rk4_projected: the fourth stage's accelerations (run_rk43's error estimate).
  Vec k4a;
  /// run_rk4_stage_projected: accelerations at a two-step retake's end.
  Vec a2;
  /// rk4_projected: the rank indicator at the projected midpoint.
  double midpoint_indicator = 0.0;
  /// The method the solves use instead of model.method while set (dop853-rk43's kkt far
  /// from singular positions); -1: model.method.
  int method_override = -1;
  /// The chart of the adaptive loops (nq != nv) is in use; its centre q_c and the q of the
  /// last x, shape (nq,); dIntegrate/dx, shape (nv, nv).
  bool chart = false;
  Vec chart_centre, chart_config;
  Mat chart_D;
  /// record: the LU of J's branch columns.
  DenseLU lu_branch;

  // -- the reduced method and coordinate partitioning --------------------------------------

  /// The stabilization's current partition: independent and dependent velocity indices.
  std::vector<int> independent, dependent;
  /// Fixed-step partitioning: the step checks the rows only.
  bool rows_only = false;
  /// J_D, the columns `dependent` of J, shape (nc, nc), its LU and SVDs.
  Mat JD;
  DenseLU lu_jd;
  Eigen::JacobiSVD<Mat> svd_jd, svd_jd_uv;
  /// (J_D^-1 J_I) at warm_q: the dependent solve's tangent predictor, shape (nc, nv - nc).
  Mat Xwarm;
  /// v_D at the stages of the current adaptive step, shape (nc, n_stages + 1).
  Mat stage_dependent_v;
  /// q_D at the step start, at the step end, of the last evaluation; v_D of the last
  /// evaluation; the guess of the next dependent solve; v_D at the step start (all (nc,)).
  Vec qD0, qD_end, qD_new, vD_last, guess_qD, start_dependent_v;
  /// The next dependent solve starts from guess_qD (a stage; a dense output).
  bool use_guess = false, use_out_guess = false;
  /// unpack: the independent coordinates' distance from warm_q, shape (nv - nc,).
  Vec independent_dq;
  /// unpack's memo: the last y, warm start and result (q, v).
  Vec unpack_y, unpack_warm, unpack_q, unpack_v;
  bool predictor_valid = false, unpack_valid = false;
  /// Sign of det(J_D) at the first step (0: not yet).
  double sign0 = 0.0;
  /// solve_reduced: a = S a_I + c with S (reduced_basis, shape (nv, nv - nc)) and c
  /// (reduced_offset, shape (nv,)); M S, shape (nv, nv - nc).
  Mat reduced_basis, mass_reduced_basis;
  Vec reduced_offset;
  /// solve_reduced: tau - h - M c, shape (nv,), and the independent accelerations a_I,
  /// shape (nv - nc,).
  Vec reduced_force, independent_a;
  /// newton_dependent: residuals, step, trial and best points.
  Vec phi_n, phi_best, step_c, q_try, q_best, dv_n;
  /// The q of the last evaluation: the dependent solves' warm start, shape (nq,).
  Vec warm_q;
  /// fun_partitioned: the full state (q, v) completed from the independent one.
  Vec fun_q, fun_v;
  /// The run's re-partitions: times [s] and the new independent indices (nv - nc each).
  std::vector<double> rep_t;
  std::vector<int> rep_ind;

  // -- the assembly (closure_newton.hpp) ---------------------------------------------------

  /// Gauss-Newton onto phi = 0 moving the free coordinates (closedchain.assemble).
  ClosureNewtonData closure_newton;
};

inline CoreData::CoreData(const CoreModel &model)
    : tree(lean_data(model.tree)),  // no nv^3 tensors: see lean_data.cpp
      mass_factor(model.tree),
      tree_rows(model.nv, model.nc) {
  const int nq = model.nq, nv = model.nv, nc = model.nc, m = std::max(nv - nc, 0);
  resize_frames(model);
  for (Vec *x : {&h, &a, &tau, &zero_v, &dq, &tmp_v, &mv, &al_wv, &rhs_v, &terms_v,
                 &reduced_offset, &reduced_force, &dv_n, &fun_v, &unpack_v})
    *x = Vec::Zero(nv);
  for (Vec *x : {&phi, &gamma, &lam, &tmp_c, &zero_c, &al_wc, &vel_c, &phi_n, &phi_best,
                 &step_c, &qD0, &start_dependent_v, &qD_end, &qD_new, &vD_last, &guess_qD})
    *x = Vec::Zero(nc);
  for (Vec *x : {&rows_q, &J_at, &q_prev, &q_try, &q_best, &warm_q, &fun_q, &unpack_q, &unpack_warm})
    *x = Vec::Zero(nq);
  for (Vec *x : {&nullspace_a, &independent_a, &independent_dq}) *x = Vec::Zero(m);
  terms_q = Vec::Constant(nq, std::numeric_limits<double>::quiet_NaN());
  kkt_solution = Vec::Zero(nv + nc);
  kkt_scale = Vec::Ones(nv + nc);
  kkt_unscale = Vec::Ones(nv + nc);
  unpack_y = Vec::Zero(2 * m);
  M = Mat::Zero(nv, nv);
  P = Mat::Zero(nv, nv);
  J = Mat::Zero(nc, nv);
  JJt = Mat::Zero(nc, nc);
  JD = Mat::Zero(nc, nc);
  delassus = Mat::Zero(nc, nc);
  schur_solves = Mat::Zero(nv, nc + 1);
  reduced_mass = Mat::Zero(m, m);
  reduced_basis = Mat::Zero(nv, m);
  mass_reduced_basis = Mat::Zero(nv, m);
  Xwarm = Mat::Zero(nc, m);
  const int chart_size = model.curved_joints.empty() ? 0 : nv;
  chart_D = Mat::Zero(chart_size, chart_size);
  kkt.resize(nv + nc);
  lu_jd.resize(nc);
  llt_p.resize(nv);
  llt_jj.resize(nc);
  llt_m = Eigen::LLT<Mat>(nv);
  llt_c = Eigen::LLT<Mat>(nc);
  llt_r = Eigen::LLT<Mat>(m);
  eig = Eigen::SelfAdjointEigenSolver<Mat>(nc);
  svd = Eigen::JacobiSVD<Mat>(nc, nv, Eigen::ComputeFullU | Eigen::ComputeFullV);
  svd_jd = Eigen::JacobiSVD<Mat>(nc, nc);
  svd_jd_uv = Eigen::JacobiSVD<Mat>(nc, nc, Eigen::ComputeFullU | Eigen::ComputeFullV);
  independent = model.method_independent;
  dependent = model.method_dependent;
}

inline void CoreData::resize_frames(const CoreModel &model) {
  const std::size_t nf = model.frame_ids.size();
  frame_R.resize(nf);
  frame_p.resize(nf);
  frame_v.resize(nf, Eigen::Matrix<double, 6, 1>::Zero());
  frame_a.resize(nf, Eigen::Matrix<double, 6, 1>::Zero());
}

}  // namespace closedchain
