// closedchain._core: class Core, the compiled constraint rows, dynamics methods and
// integration loops of one mechanism. Its member functions are defined by concept in
// core_interface.hpp (construction, settings, one evaluation), core_rows.hpp (cut
// frames, phi, J, gamma, the tree terms), core_structure.hpp (sparsity and band paths),
// core_methods.hpp (KKT, Schur, null space, augmented Lagrangian), core_projection.hpp
// (projection and the checks of each step), core_partitioning.hpp (the reduced method
// and coordinate partitioning), core_recording.hpp (samples), core_fixed.hpp and
// core_adaptive.hpp (the integration loops); core_all.hpp includes them all.
//
// Every constraint row is one of three smooth scalar functions of the cut
// frames c1 (predecessor, R_p, p_p) and c2 (successor, R_s, p_s):
//   kind 0  translation along a world axis n:   phi = n . (p_p - p_s)
//   kind 1  translation along n fixed in c1:    phi = (R_p n) . (p_p - p_s)
//   kind 2  rotation, u in c1 and w in c2:      phi = (R_p u) . (R_s w)
// with exact J (derivative along pinocchio::integrate) and gamma = Jdot v, the
// formulas of closedchain/constraints.py.

#pragma once

#include <pinocchio/multibody/data.hpp>
#include <pinocchio/multibody/model.hpp>

#include <Eigen/Dense>
#include <boost/python.hpp>

#include <string>
#include <utility>
#include <vector>

#include "banded.hpp"
#include "common.hpp"
#include "constants.hpp"
#include "dense_lu.hpp"
#include "errors.hpp"
#include "settings.hpp"
#include "small_llt.hpp"
#include "tree_terms.hpp"

namespace closedchain {

struct Row {
  int kind;  // 0 world translation, 1 translation along n in c1, 2 rotation
  int p, s;  // indices into the Core's frame list
  Vector3d n;  // n (kinds 0, 1) or u (kind 2)
  Vector3d w;  // w (kind 2)
};

class Core {
 public:
  Core(bp::object model_obj, const std::string &name, const Eigen::VectorXi &kinds,
       const Eigen::VectorXi &fid_p, const Eigen::VectorXi &fid_s, const Mat &vec1,
       const Mat &vec2);

  /// Structural nonzeros, from the kinematic tree: row r of J is nonzero only on the
  /// columns of the joints supporting its two frames (jcols_ from jcol_start_[r],
  /// sorted; hull [jlo_[r], jhi_[r]]), row i of M on those of the joints that support
  /// or are supported by i's joint (hull [mlo_[i], mhi_[i]]). The rules of
  /// closedchain/dynamics/augmented_lagrangian.py (structure, row_structure).
  void sparsity();

  /// Choose the band paths (closedchain.compiled.make_core, from PenalizedSolver and
  /// NormalSolver): banded_p factorizes M + alpha J^T J in the order perm (perm[k] =
  /// the column at position k) as a band, banded_n the normal equations J J^T in the
  /// natural row order. Returns the half bandwidths (b_p, b_n) of the structure in
  /// those orders (the Python side's bandwidths, checked by the tests).
  bp::tuple set_band(const Eigen::VectorXi &perm, bool banded_p, bool banded_n);

  /// M(i, c) structurally nonzero: one of the two joints supports the other.
  bool M_structural(int i, int c) const;

  pinocchio::JointIndex col_joint(int c) const;

  bool rows_share_column(int r, int s2) const;

  bp::tuple band_info() const {
    return bp::make_tuple(band_p_, band_n_, penalized_bandwidth_, normal_bandwidth_);
  }

  // -- products on the structure (the band paths) ------------------------------

  /// y = J x over each row's column hull.
  void j_mul(const Vec &x, Vec &y) const;

  /// x = J^T y (x overwritten).
  void jt_mul(const Vec &y, Vec &x) const;

  /// x += J^T y over each row's column hull.
  void jt_mul_add(const Vec &y, Vec &x) const;

  /// y -= M x over each row's hull.
  void m_mul_sub(const Vec &x, Vec &y) const;

  /// sum of J_ij^2
  double j_squared_norm() const;

  /// Factorize P = M + alpha J^T J as a band in the order perm_.
  bool factor_penalized_band(double alpha);

  /// x <- P^-1 x on the band factor.
  void solve_penalized_band(Vec &x);

  /// Factorize P = M + alpha J^T J with the caller's alpha (dense: Cholesky of P's lower
  /// triangle; band: factor_penalized_band); the factor of solve_al's alpha is dropped.
  /// Returns false when P is not positive definite.
  bool factor_penalized(double alpha);

  /// x <- P^-1 x with the factor of factor_penalized (or al_factor).
  void solve_penalized(Vec &x);

  /// Assemble J J^T + eps I as a band (natural row order), eps = rel_reg max(tr(J J^T), 1)
  /// / nc (0: none), and factorize it.
  bool factor_normal_band(double rel_reg);

  void assemble_normal_band(double rel_reg);

  int nc() const { return nc_; }
  long n_evals() const { return n_evals_; }
  void reset_evals() { n_evals_ = 0; }

  // -- the state of the last evaluation, read by the ALI3-P loop (ali3p.hpp) ----

  /// The Pinocchio model (by reference: the Python object holds it).
  const Model &model() const { return model_; }
  /// Configuration size nq and velocity size nv of the model.
  int nq() const { return nq_; }
  int nv() const { return nv_; }
  /// The mechanism's name, the first word of every error message.
  const std::string &name() const { return name_; }
  /// Mass matrix M, shape (nv, nv), at the last evaluation [kg, kg m, kg m^2].
  const Mat &mass_matrix() const { return M_; }
  /// Bias forces h = C(q, v) v + g(q), shape (nv,), at the last evaluation [N, N m].
  const Vec &bias_forces() const { return h_; }
  /// Constraint residuals phi, shape (nc,), at the last evaluation [m or 1].
  const Vec &phi() const { return phi_; }
  /// Constraint Jacobian J, shape (nc, nv), at the last evaluation.
  const Mat &jacobian() const { return J_; }
  /// gamma = Jdot v, shape (nc,), at the last evaluation (Baumgarte terms included).
  const Vec &gamma() const { return gamma_; }
  /// Accelerations a, shape (nv,), and multipliers lam, shape (nc,), of the last solve.
  const Vec &accelerations() const { return a_; }
  const Vec &multipliers() const { return lam_; }
  /// Replace the last solve's (a, lam), e.g. by an integrator's own, before record().
  void set_solution(const Vec &a, const Vec &lam) {
    a_ = a;
    lam_ = lam;
  }
  /// SimulationSettings.singular_zone [steps].
  double singular_zone() const { return singular_zone_; }
  /// True when M + alpha J^T J is factored as a band (set_band's banded_p).
  bool banded_penalized() const { return band_p_; }
  /// The augmented-Lagrangian iteration's limit and tolerance (al_max_iter, al_tol).
  int al_max_iter() const { return al_max_iter_; }
  double al_tol() const { return al_tol_; }

  /// Settings: the method and the run's options, the solver settings (cond_max,
  /// Baumgarte gains, the augmented Lagrangian's), the simulation settings.
  void configure(const RunOptions &run, const SolverSettings &solver,
                 const SimulationSettings &sim);

  /// Every declared row (the kept ones and those dropped as redundant), checked at
  /// every step: kinds/frames/vectors as for the kept rows, kept[i] = 1 for a row
  /// the methods use, labels "loop.kind" for messages.
  void set_declared(const Eigen::VectorXi &kinds, const Eigen::VectorXi &fid_p,
                    const Eigen::VectorXi &fid_s, const Mat &vec1, const Mat &vec2,
                    const Eigen::VectorXi &kept, bp::list labels);

  /// tau: None, a constant (nv,) array or a callable tau(t, q, v).
  void set_tau(bp::object tau);

  // -- constraint rows ------------------------------------------------------

  /// data_'s kinematics, J_ and M_ no longer known to be at J_at_; the factor of
  /// M + alpha J^T J dropped.
  void invalidate_kinematics();

  /// phi only: placements from the kinematics pass (tree_terms.hpp's joint_kinematics,
  /// the same placements as eval_phi_J and eval_terms).
  void eval_phi(const RefV &q);

  /// phi and J: joint_kinematics(q) (placements and world joint Jacobians, as
  /// pinocchio::computeJointJacobians; revolute joints by tree_terms.hpp's own path).
  /// Each step asks several times at one q (projection, regularity check, declared
  /// rows, output): the last evaluation is reused while q is the same.
  void eval_phi_J(const RefV &q);

  /// eval_phi_J at a trial point of the dependent solve, which moves only the
  /// dependent coordinates dep_: when the kinematics in data_ (J_at_) agree with q on
  /// every independent coordinate, the joints whose supports hold no dependent
  /// coordinate keep their placements and Jacobian columns (the same values a full
  /// pass computes: same inputs, same arithmetic) and only the others are recomputed.
  void eval_phi_J_trial(const Vec &q);

  /// M, h, phi, J, gamma at (q, v): one pass over the tree (tree_terms.hpp: M, h,
  /// the joints' placements, world Jacobian columns, velocities and bias
  /// accelerations), then the cut frames' placements, velocities and classical
  /// accelerations, then the rows. `mark(stage)` is called after each stage
  /// (0 tree, 1 frames, 2 rows): a no-op, or py_profile's clock.
  ///
  /// When the last kinematics pass was at q (eval_phi_J(q): the dependent solve of
  /// the partitioning stabilization ends there), data_ already holds the joints'
  /// placements and Jacobian columns and phi_, J_ and the frame placements are
  /// those of q: only the velocity-dependent part of the tree pass and gamma are
  /// computed (tree_terms_at_kinematics; the same arithmetic, the same results); when
  /// M_ is at q too (m_at_J_: the stage projection's velocity step computed it, or an
  /// evaluation at q with another v), only h (bias_at_kinematics, stage_terms.hpp),
  /// and M_ and the factor of M + alpha J^T J (p_fact_) stay.
  template <class Mark>
  void eval_terms(const RefV &q, const RefV &v, Mark &&mark);

  void eval_terms(const RefV &q, const RefV &v);

  // -- forward dynamics -------------------------------------------------------

  /// Accelerations a_ and multipliers lam_ at (q, v) with generalized force tau.
  void solve(const RefV &q, const RefV &v, const Vec &tau, double t);

  void dispatch(const RefV &q, const Vec &tau, double t);

  /// Augmented Lagrangian at the acceleration level (closedchain/dynamics/
  /// augmented_lagrangian.py, Bayo & Ledesma 1996): P = M + alpha J^T J with
  /// alpha = rho tr(M) / tr(J^T J), lowered where P's Cholesky cannot take it
  /// (al_factor); from lam_0 = 0,
  ///   a_1 = P^-1 (tau - h - alpha J^T gamma),  lam_1 = alpha (J a_1 + gamma),
  ///   a_{k+1} = a_k + P^-1 (tau - h - M a_k - J^T (lam_k + alpha (J a_k + gamma))),
  ///   lam_{k+1} = lam_k + alpha (J a_{k+1} + gamma),
  /// until max |a_{k+1} - a_k| <= al_tol (1 + max |a_{k+1}|); then lam is polished by
  /// the regularized normal equations J J^T dlam = J (tau - h - M a - J^T lam).
  void solve_al(const RefV &q, const Vec &tau, double t);

  // solve_al for nv <= AL_FIXED_MAX (the 4-bar: nv 3, nc 2) on fixed-size matrices:
  // the same iteration (al_iterate), penalty, acceptance test of P's Cholesky and
  // multiplier polish, with Eigen's unrolled fixed-size products and small_llt.hpp's
  // FixedLDLT in place of the dynamic-size ones (on the 4-bar the solve is the larger
  // part of one evaluation's cost). The results differ from the dynamic path by
  // round-off. P is factored here each time (a few dozen operations);
  // the factor kept for the stage projection (p_fact_, llt_p_) is left as it is.
  // Returns false when (nv, nc) is not among the sizes compiled.
  static constexpr int AL_FIXED_MAX = 6;

  template <int NV, int NC>
  bool solve_al_small(const RefV &q, double t);

  // al_iterate's products (al_iteration.hpp) for the dense path: coefficient-based
  // (lazyProduct; small dynamic sizes, no BLAS-style kernels) on P's SmallLLT.
  struct DenseAlOps {
    Core &c;
    void add_j(const Vec &x, Vec &y) { y.noalias() += c.J_.lazyProduct(x); }
    void sub_m(const Vec &x, Vec &y) { y.noalias() -= c.M_.lazyProduct(x); }
    void sub_jt(const Vec &y, Vec &x) { x.noalias() -= c.J_.transpose().lazyProduct(y); }
    void sub_scaled_jt(double s, const Vec &y, Vec &x) {
      x.noalias() -= s * c.J_.transpose().lazyProduct(y);
    }
    void solve(Vec &x) { c.llt_p_.solveInPlace(x); }
  };

  // ... and for the band path (set_band): the products over the structural hulls, P's
  // band Cholesky in the order perm_ (O(nv) per iterate for a chain of loops).
  struct BandAlOps {
    Core &c;
    void add_j(const Vec &x, Vec &y) {
      c.j_mul(x, c.al_wc_);
      y += c.al_wc_;
    }
    void sub_m(const Vec &x, Vec &y) { c.m_mul_sub(x, y); }
    void sub_jt(const Vec &y, Vec &x) {
      c.jt_mul(y, c.al_wv_);
      x -= c.al_wv_;
    }
    void sub_scaled_jt(double s, const Vec &y, Vec &x) {
      c.jt_mul(y, c.al_wv_);
      x -= s * c.al_wv_;
    }
    void solve(Vec &x) { c.solve_penalized_band(x); }
  };

  /// P = M + alpha J^T J at the last evaluation, factored (dense SmallLLT of P's lower
  /// triangle, or the band Cholesky) unless the factor of these M_ and J_ is kept
  /// (p_fact_); returns alpha. alpha starts at al_penalty tr(M) / tr(J^T J) and is
  /// lowered (al_lowered_penalty, al_lowerings_ times) while the Cholesky fails or
  /// shows a relative pivot below AL_PIVOT_MIN (constants.hpp; numpy's
  /// PenalizedSolver.factor_relative).
  double al_factor(const RefV &q, double t);

  /// The error of a P that is not positive definite at the lowest alpha.
  [[noreturn]] void penalized_singular(const RefV &q, double alpha, double t);

  /// The augmented-Lagrangian iteration (al_iterate) at the last evaluation: x and
  /// lam_ with M x + J^T lam = rhs, J x + g = 0 (to al_tol), no multiplier polish;
  /// from_x: start from x as given (al_iterate).
  void al_solve(const RefV &q, double t, const Vec &rhs, const Vec &g, Vec &x,
                bool from_x = false);

  [[noreturn]] void singular(const RefV &q, const std::string &what, double cond,
                             const std::string &hint, double t);

  void check_rcond(const RefV &q, const std::string &what, double rcond, double t);

  void solve_kkt(const RefV &q, const Vec &tau, double t);

  void solve_schur(const RefV &q, const Vec &tau, double t);

  void solve_nullspace(const RefV &q, const Vec &tau, double t);

  /// The generalized force at (t, q, v) into tau_.
  const Vec &tau_at(double t, const RefV &q, const RefV &v);

  /// The right-hand side of a simulation: a_ (and lam_) at (t, q, v).
  void accel(double t, const RefV &q, const RefV &v);

  // -- Python entry points of one evaluation ---------------------------------

  bp::tuple py_rows(const Vec &q, const Vec &v);

  bp::tuple py_forward(const Vec &q, const Vec &v, const Vec &tau);

  /// a at (q, v) for n_eval repetitions inside C++ (the per-evaluation cost in the loop).
  Vec py_repeat(const Vec &q, const Vec &v, const Vec &tau, int n);

  /// Mean wall time [ns] of each stage of one evaluation over n repetitions
  /// (profiling): the sequence of solve(), with a clock between its stages.
  bp::dict py_profile(const Vec &q, const Vec &v, const Vec &tau, int n);

  // -- stabilization and checks ----------------------------------------------

  /// cond_2(J) from the eigenvalues of J J^T.
  double cond_J();

  /// True when cond_2(J) < limit is certain, in O(nc b^2) on the band of A = J J^T
  /// (band_n_): lambda_max(A) <= ||A||_1, and A - (||A||_1 / limit^2) I is positive
  /// definite (its Cholesky factor exists) iff lambda_min(A) > ||A||_1 / limit^2
  /// (Sylvester's law of inertia), which gives cond_2(J)^2 = lambda_max / lambda_min
  /// < limit^2. False means "not certain": cond_J() decides (only within a factor
  /// sqrt(||A||_1 / lambda_max) <= sqrt(nc) of the limit, i.e. near singular positions).
  bool cond_J_below(double limit);

  /// The step's checks at q (Problem.check_regular and LoopClosure.check_rows of the
  /// numpy backend), plus the drift limit over every declared row at every step:
  /// - every declared row (dropped ones too) within drift_limit, else SimulationFailure
  ///   naming the row;
  /// - a dropped row open by more than max(dropped_row_tol, dropped_row_ratio x the kept
  ///   rows' residual), or kept rows degenerate (cond(J) > singular_cond while there are
  ///   dropped rows): RowCheckRequired (the Python side re-selects the rows);
  /// - unless singular_robust, cond(J) > singular_cond: SingularError.
  void check_regular(const RefV &q, double t);

  /// cond(J) of the kept rows at a projected stage point q of rk4_projected (unless
  /// singular_robust): above singular_cond, check_regular's SingularError (an adaptive
  /// step's ends can straddle a singular position that its stages come close to),
  /// unless the declared rows stay regular (the step's end re-selects the rows).
  void check_stage_regular(const RefV &q, double t);

  /// Throw check_regular's SingularError: cond(J) = cond > singular_cond at (t, q).
  [[noreturn]] void throw_singular_J(const RefV &q, double t, double cond);

  /// Condition number of the nc largest singular values of the declared rows' J at the
  /// last eval_phi_J (LoopClosure.check_rows): above singular_cond the mechanism itself
  /// is singular there, no re-selection of rows helps.
  double declared_cond();

  /// phi of every declared row from the placements of the last kinematics pass.
  void declared_phi();

  /// Minimum-norm solution x of J x = b (J full row rank): J^T (J J^T)^-1 b.
  /// Where J J^T is ill-conditioned (J nearly rank-deficient, e.g. passing a singular
  /// position with stage projection) it is numpy.linalg.lstsq's minimum-norm solution
  /// from the SVD, singular values below eps max(nc, nv) s_max treated as zero.
  /// The test "the estimate rcond of J J^T exceeds MIN_NORM_RCOND" is decided by an
  /// upper bound of cond_1 from the Cholesky factor where it can (rcond >= 1 / that
  /// bound), so Eigen's estimator runs only near singular positions.
  void min_norm(const Vec &b, Vec &x);

  /// numpy.linalg.lstsq's minimum-norm solution of J x = b (dense SVD of J: only where
  /// J J^T is ill-conditioned, i.e. within a step or two of a singular position).
  void min_norm_svd(const Vec &b, Vec &x);

  /// Gauss-Newton (minimum-norm) projection of q onto phi = 0, then v onto J v = 0.
  /// With mass_orth (the stage projection; problem.project's mass_orthogonal) v is
  /// projected in the metric of M: the augmented-Lagrangian iteration (al_solve) at q
  /// with right-hand side M v and g = 0. Only where the run passes singular positions
  /// (singular_robust_), as problem.project. M_ (mass_at_kinematics: no velocity pass)
  /// and the factor of M + alpha J^T J are then those of q and stay for the evaluation
  /// at q that follows (eval_terms: the bias forces only; solve_al: no second
  /// factorization); lam_ is overwritten.
  void project(Vec &q, Vec &v, bool mass_orth = false);

  // -- the reduced method and coordinate partitioning ---------------------------
  //
  // Same math as closedchain/dynamics/reduced.py (the method) and simulate/problem.py,
  // fixed.py, adaptive.py (the stabilization). Two partitions are kept: the method's,
  // mech.independent_idx_v for the whole run (as the numpy method), and the
  // stabilization's, which re-partitioning changes.

  void init_partitioning();

  /// ind: the independent velocity indices; dep: the others, both sorted.
  void set_indices(std::vector<int> ind, std::vector<int> &ind_out, std::vector<int> &dep_out);

  std::vector<int> checked_indices(const Eigen::VectorXi &ind, const std::string &what);

  /// The reduced method's partition (mech.independent_idx_v) and the names of the
  /// velocity coordinates (for the J_D messages).
  void set_partition(const Eigen::VectorXi &ind, bp::list names);

  /// The loops' alignment checks (ConstraintLayer.alignment_vectors): phi = 0 is a
  /// spurious closure when (R_p u).(R_s u) <= 0 for a vector u of loop loop[i].
  void set_alignment(const Eigen::VectorXi &fid_p, const Eigen::VectorXi &fid_s, const Mat &u,
                     const Eigen::VectorXi &loop, bp::list loop_names);

  void configure_partitioning(const RunOptions &run, const SimulationSettings &sim);

  std::string join_names(const std::vector<int> &idx) const;

  /// J_D: the columns dep of J_ into JD_.
  void gather_JD(const std::vector<int> &dep);

  /// Reduced coordinates (dynamics/reduced.py): a = S a_I + c with S = [I; -J_D^-1 J_I],
  /// c = [0; -J_D^-1 gamma]; (S^T M S) a_I = S^T (tau - h - M c); lam = J_D^-T (tau - h - M a)_D.
  void solve_reduced(const RefV &q, const Vec &tau, double t);

  /// Gauss-Newton on phi(q) = 0 moving the dependent coordinates dep_ only, to
  /// dependent_tol (closure.solve_closure with AssemblySettings(tol=dependent_tol,
  /// max_iter=20): the full step, then, unless it contracts the sum of squares by
  /// 1/4, the step without J_D's directions below 1e-2 of its largest singular
  /// value; each with up to 12 halvings; the lower one is taken). nq == nv, so the
  /// held coordinates stay exact under pinocchio::integrate. Every trial point is
  /// evaluated with its J (one kinematics pass, computeJointJacobians): the accepted
  /// one's J serves the next iteration and v_D from the memo of eval_phi_J.
  void newton_dependent(Vec &q, double t);

  /// Problem.complete: q_D from phi = 0 (q_I held, q the guess), v_D = -J_D^-1 J_I v_I.
  void complete(Vec &q, Vec &v, double t);

  /// cond_2(J_D(q)) of the stabilization's partition (np.linalg.cond).
  double cond_JD(const Vec &q);

  /// The pivot columns of Householder QR of J_, each the lowest-index column whose
  /// remaining norm is within pivot_tie_rtol of the largest (closure._tie_pivots), sorted.
  /// Only when re-partitioning is considered: allocates.
  std::vector<int> tie_pivots() const;

  /// Problem.repartition: the dependent set of column-pivoted QR of J (Wehage-Haug, ties
  /// to the lowest index); true when it changed. SingularError when its J_D is above
  /// partition_singular_cond.
  bool repartition(const Vec &q, double t);

  /// The start of a run: the stabilization's partition from configure ("independent").
  void begin_partitioning(bool fixed_step);

  /// After a fixed step (fixed.py): complete (q, v), re-partition when cond(J_D) is large.
  void partition_step(Vec &q, Vec &v, double t);

  void pack(const Vec &q, const Vec &v, Vec &y) const;

  /// (q, v) of the partitioned state y = (q_I, v_I), the dependent solve warm-started
  /// from the last evaluation's q (adaptive.py's unpack).
  ///
  /// Two savings over the numpy loop, same solution to dependent_tol: the guess of q_D
  /// follows the tangent, q_D = warm_D - (J_D^-1 J_I)(warm) (q_I - warm_I) (the numpy
  /// loop starts from warm_D: one Newton iteration more per evaluation; a dense
  /// output of run_adaptive passes q_D from the step's own interpolant instead,
  /// use_out_guess_: one iteration where the tangent took two to four), and the
  /// state of the last call is reused when y and the warm start are the same (each
  /// step unpacks its end state three times: checks, output, re-partitioning).
  /// Returns false when the result came from that memo (J_ and lu_jd_ are then not
  /// necessarily those of q).
  bool unpack(const Vec &y, double t, Vec &q, Vec &v);

  void fun_partitioned(double t, const Vec &y, Eigen::Ref<Vec> f);

  /// After an adaptive step (adaptive.py): stop when det(J_D) changed sign since the
  /// first step (or the last re-partition); re-partition when cond(J_D) is large and
  /// t < t_final, then y is the new partition's state. Returns true on re-partition.
  bool adaptive_partition_check(double t, double t_final, Vec &y, Vec &q, Vec &v);

  /// The guess of q_D at a Runge-Kutta stage with coefficients a[0..s-1]: the dependent
  /// coordinates integrated with the stage's own weights, q_D0 + h sum_j a_j v_D,j
  /// (v_D,j of the earlier stages): accurate to the step's truncation error, so the
  /// dependent solve needs one Newton iteration (the numpy loop starts from the last
  /// evaluation's q_D, and from the tangent predictor of unpack here elsewhere).
  void stage_guess(const double *a, int s, double h);

  /// The step start (t, y) is the last evaluation's: its q_D and v_D.
  void step_start_from_last();

  bp::list repartitions_list() const;

  bp::tuple py_partition() const;

  // -- recording ---------------------------------------------------------------

  struct Samples {
    std::vector<double> t, res, vres, e, ke, branch;
    std::vector<double> q, v, a, lam;
  };

  /// The columns D of J whose sign of det(J[:, D]) is recorded with every sample (the
  /// assembly branch, Recorder._add_branch); empty: none recorded.
  void set_branch_columns(const Eigen::VectorXi &cols);

  /// Sign of det(J_[:, branch_cols_]) (J_ at the sample's q): the parity of the row
  /// swaps of an LU with partial pivoting times the signs of its pivots, 0 for an
  /// exactly zero pivot (numpy.linalg.slogdet's sign).
  double branch_sign();

  void record(Samples &out, double t, const Vec &q, const Vec &v);

  static bp::object block(const std::vector<double> &x, long rows, long cols);

  bp::dict samples_dict(const Samples &s, long steps);

  void poll(long k, double t, const bp::object &progress);

  void check_finite(const Vec &q, const Vec &v, double t);

  // -- rk4 with stage projection near singular positions -----------------------
  // (simulate/fixed.py, _run_rk4_stage_projected: the same rule, step for step)

  /// sqrt(mu / mean eigenvalue of J J^T) at q, capped: mu the Rayleigh quotient after
  /// RANK_INDICATOR_ITERS inverse iterations from the ones vector (fixed.rank_indicator).
  /// With a narrow row band (set_band's banded_n) J J^T is factorized as a band and
  /// x^T J J^T x = |J^T x|^2: O(nc) instead of the dense product and Cholesky, O(nc^3)
  /// (the same quantity to round-off; also the ALI3-P loop's indicator).
  double rank_indicator(const Vec &q);

  /// The crossing time in steps from the start that the indicator at the start, midpoint
  /// and end points to, inf when none is ahead (fixed.crossing_estimate): rho = s |t - tau|
  /// fitted by least squares for tau in [0, 0.5), [0.5, 1) and [1, inf), the signs of
  /// t - tau at the samples known in each; the fit in its interval with the smallest
  /// residual is taken.
  static double crossing_estimate(double r0, double r1, double r2);

  /// Distance [steps] of a crossing at tau from the evaluation points of a retake of one
  /// (double: two) grid steps split at h1 (h1 = span: one substep) (fixed._plan_points).
  static double plan_distance(double tau, bool twice, double h1);

  /// false when the plain step keeps its points at least `zone` steps from a crossing at
  /// tau; else true with the retake (twice, h1) whose points are farthest from it, ties
  /// to the single step (fixed.retake_plan).
  static bool retake_plan(double tau, double zone, bool &twice, double &h1);

  /// One rk4 step of length h from (q, v) with accelerations a0 at t, every stage and
  /// the end projected; (qn, vn) the end, qm the projected stage-2 (midpoint) state.
  void rk4_projected(double t, const Vec &q, const Vec &v, const Vec &a0, double h, Vec &qn,
                     Vec &vn, Vec &qm);

  /// The state at t = t0 + s h of the substep (q0, v0, a0) -> (q1, v1, a1) of length h
  /// by cubic Hermite interpolation, q projected onto phi = 0, recorded (v is not
  /// projected: near the crossing that is the ill-conditioned step avoided).
  void record_interpolated(Samples &S, double t, double s, double h, const Vec &q0,
                           const Vec &v0, const Vec &a0, const Vec &q1, const Vec &v1,
                           const Vec &a1);

  bp::dict run_rk4_stage_projected(const Vec &q0, const Vec &v0, double dt, long n_steps,
                                   const std::vector<char> &out, bp::object progress);

  // -- fixed-step integration ----------------------------------------------------

  /// Integrate with a fixed step dt for n_steps, recording at the steps in `out`.
  bp::dict run_fixed(int integrator, const Vec &q0, const Vec &v0, double dt, long n_steps,
                     const Eigen::VectorXi &out_steps, bool projects, bp::object progress);

  /// The ALI3-P integrator (ali3p.hpp) at the fixed step dt for n_steps, recording at
  /// the steps in out_steps with the settings (SimulationSettings.ali3p_*).
  bp::dict run_ali3p(const Vec &q0, const Vec &v0, double dt, long n_steps,
                     const Eigen::VectorXi &out_steps, const Ali3pSettings &settings,
                     bp::object progress);

  // -- adaptive explicit Runge-Kutta (scipy's RK45 / DOP853, same error control) --

  double rms(const Vec &x) const { return x.norm() / std::sqrt(static_cast<double>(x.size())); }

  /// The chart of the adaptive loops when nq != nv (simulate/chart.py): the state
  /// holds x with q = integrate(q_c, x), dx/dt = D(x)^-1 v, D = dIntegrate/dx.
  void chart_start(const Vec &q0);

  /// out = D(x)^-1 v for q = integrate(q_c, x): the identity but on the blocks of
  /// the joints whose integrate is not x + v (free-flyer, spherical, planar).
  void chart_rate(const Vec &q_c, const Eigen::Ref<const Vec> &x, const Eigen::Ref<const Vec> &v,
                  Eigen::Ref<Vec> out);

  /// The configuration of state y's position part (y itself without a chart).
  RefV chart_q(const Eigen::Ref<const Vec> &x);

  /// Re-centre the chart when a curved joint's block exceeds RECENTRE_NORM.
  bool chart_recentre(Eigen::Ref<Vec> x);

  void fun(double t, const Vec &y, Eigen::Ref<Vec> f);

  bp::dict run_adaptive(int integrator, const Vec &q0, const Vec &v0, double t_final,
                        double rtol, double atol, bp::object t_eval_obj, bool projects,
                        bp::object progress);

  /// rk43 (simulate/rk43.py, step for step): rk4 with stage projection and the retakes
  /// near singular positions, its step chosen by the embedded third-order estimate
  /// (h / 6) (k4 - k5); first trial step h0 [s]; the steps land on every time of
  /// t_eval (or t_final), recorded there, and at every step end with record_all.
  bp::dict run_rk43(const Vec &q0, const Vec &v0, double t_final, double rtol, double atol,
                    double h0, bp::object t_eval_obj, bool record_all, bp::object progress);

 private:
  /// Row r of a row table (kind, frames, vectors as the layer's RowTable), checked.
  Row make_row(int r, const Eigen::VectorXi &kinds, const Eigen::VectorXi &fid_p,
               const Eigen::VectorXi &fid_s, const Mat &vec1, const Mat &vec2);

  int frame_index(int fid);

  void check_sizes(const Vec &q, const Vec &v) const;

  /// Per cut frame: the parent joint and the columns of its support, sized buffers.
  void frame_buffers();

  /// World placement (R_, p_) of every cut frame from data_.oMi.
  void placements();

  /// Velocity vf_ and classical acceleration af_ (at a = 0) of every cut frame's
  /// origin p, world axes (LOCAL_WORLD_ALIGNED), from its joint's world spatial
  /// velocity (v_o, w) = data_.ov and bias acceleration (a_o, al) = data_.oa:
  ///   v_p = v_o + w x p,   a_p = a_o + al x p + w x v_p   (linear; angular w, al).
  void frame_motion();

  /// Row J of `row` from the world Jacobian columns data_.J (of the last kinematics
  /// pass) and the frame placements. A frame's LOCAL_WORLD_ALIGNED Jacobian at p
  /// has, on its joint's support, linear columns J_lin + J_ang x p and angular
  /// columns J_ang, so a row c . (linear) + e . (angular) of it is the 6-vector
  /// (c, p x c + e) applied to the world columns: the row is that of the
  /// predecessor frame minus that of the successor.
  ///   kinds 0, 1: U^T (Jlin_p - Jlin_s) + [kind 1] (U x d)^T Jang_p,
  ///   kind 2:     (W x U)^T (Jang_s - Jang_p).
  template <typename RowXpr>
  void row_jacobian(const Row &row, RowXpr &&out);

  /// Fill phi_, J_, gamma_ from the per-frame quantities.
  void rows(bool want_phi, bool want_J, bool want_gamma);

  bp::object model_obj_;  // keeps the Python model alive
  const Model &model_;
  Data data_;
  TreePlan plan_;  // which joints take tree_terms.hpp's revolute path
  bool vector_space_ = false;  // only revolute and prismatic joints: integrate is q + dq
  std::vector<int> moved_for_;  // eval_phi_J_trial: the dep_ that moved_ was made for
  std::vector<char> moved_;     // per joint: its support holds a coordinate of moved_for_
  std::string name_;
  int nq_ = 0, nv_ = 0, nc_ = 0;
  std::vector<Row> rows_;
  std::vector<pinocchio::FrameIndex> fids_;
  std::vector<pinocchio::JointIndex> fjoint_;  // parent joint of each of fids_
  std::vector<std::vector<Eigen::Index>> fcols_;  // its support's columns
  std::vector<Eigen::Matrix3d> R_;
  std::vector<Vector3d> p_;
  std::vector<Eigen::Matrix<double, 6, 1>> vf_, af_;
  Mat M_, J_, JJt_;
  /// solve_schur: M^-1 [J^T, tau - h], shape (nv, nc + 1).
  Mat schur_solves_;
  /// solve_schur: the Delassus matrix J M^-1 J^T, shape (nc, nc).
  Mat delassus_;
  /// The reduced mass matrix, shape (nv - nc, nv - nc): N^T M N (solve_nullspace) or
  /// S^T M S (solve_reduced).
  Mat reduced_mass_;
  /// solve_nullspace: the accelerations in the null-space basis N, shape (nv - nc,).
  Vec nullspace_a_;
  DenseLU kkt_;  // K of the kkt method
  Vec h_, phi_, gamma_, a_, lam_, tau_, tau_const_, zero_v_, dq_, tmp_c_, tmp_v_;
  /// solve_kkt: the right-hand side [tau - h, -gamma], then the solution [a, lam].
  Vec kkt_solution_;
  /// solve_kkt: the equilibration D = diag(d_v, d_c) of K (dynamics/kkt.py kkt_scaling).
  Vec kkt_scale_;
  Eigen::LLT<Mat> llt_m_, llt_c_, llt_r_;
  SmallLLT llt_p_, llt_jj_;  // M + alpha J^T J; J J^T (+ regularization)
  Mat P_;
  Vec rhs_v_, q_prev_, vel_c_, rhs_work_;
  Vec dv_, vs_, qs_, k2v_, k2a_, k3v_, k3a_, k4v_;  // rk4_projected's stages
  Vec k4a_;  // rk4_projected: the fourth stage's accelerations (run_rk43's estimate)
  Vec a2_;  // run_rk4_stage_projected: accelerations at a two-step retake's end
  Vec mv_;  // project(mass_orth): M v
  Vec zero_c_;  // project(mass_orth): g = 0
  Vec al_wc_, al_wv_;  // BandAlOps' products
  /// rk4_projected: the rank indicator at the projected midpoint.
  double midpoint_indicator_ = 0.0;
  // Structure (sparsity) and the band paths (set_band).
  std::vector<int> jcol_start_, jcols_, jlo_, jhi_, mlo_, mhi_;
  std::vector<int> perm_, pinv_;
  bool perm_identity_ = true, band_p_ = false, band_n_ = false;
  /// Half bandwidths of M + alpha J^T J in the order perm_ and of J J^T (set_band).
  int penalized_bandwidth_ = 0, normal_bandwidth_ = 0;
  /// Band Cholesky factors of M + alpha J^T J (order perm_) and of J J^T.
  BandCholesky penalized_band_, normal_band_;
  /// solve_penalized_band: the right-hand side in the order perm_, shape (nv,).
  Vec band_work_;
  Eigen::JacobiSVD<Mat> svd_;
  Eigen::SelfAdjointEigenSolver<Mat> eig_;
  Method method_ = KKT;
  std::string method_name_ = "kkt";
  double cond_max_ = 1e12;
  bool baumgarte_ = false;
  double alpha_ = 0.0, beta_ = 0.0;
  double projection_tol_ = 1e-13;
  int projection_iters_ = 10;
  bool project_velocities_ = true;
  double singular_cond_ = 1e3;
  double drift_limit_ = 1e-2;
  double al_penalty_ = 1e11, al_tol_ = 1e-13;
  int al_max_iter_ = 30;
  bool stage_projects_ = false, singular_robust_ = false;
  double singular_zone_ = 0.0;  // SimulationSettings.singular_zone
  double stage_zone_ = 0.0;     // SimulationSettings.stage_singular_zone
  double dropped_tol_ = 1e-9, dropped_ratio_ = 100.0;
  std::vector<Row> drows_;  // every declared row
  std::vector<std::string> dlabels_;
  Eigen::VectorXi dkept_;
  Vec dphi_;
  // chart of the adaptive loops (nq != nv): centre, q of the last x, curved joints' blocks
  bool chart_ = false;
  Vec q_c_, q_x_;
  std::vector<std::pair<int, int>> curved_;
  Mat D_chart_;
  Vec J_at_;  // the q of the last eval_phi_J (J_, phi_ and the placements valid there)
  bool J_at_valid_ = false;
  bool m_at_J_ = false;  // M_ at J_at_ too (with J_at_valid_)
  /// al_factor's alpha and how many times it was lowered (valid while p_fact_).
  double al_alpha_ = 0.0;
  int al_lowerings_ = 0;
  bool p_fact_ = false;  // llt_p_ / penalized_band_ hold P = M_ + alpha J_^T J_ (solve_al's alpha)
  Eigen::VectorXi branch_cols_;  // set_branch_columns
  DenseLU lu_branch_;  // branch_sign's LU of J's branch columns
  Vec terms_q_, terms_v_;  // (q, v) of the last eval_terms (M_, potential_energy_ valid there)
  /// Potential energy at terms_q_ [J] (gravity on the total mass, for record()).
  double potential_energy_ = 0.0;
  int tau_mode_ = 0;
  bp::object tau_obj_, np_asarray_;
  long n_evals_ = 0;
  // the reduced method and coordinate partitioning
  struct Align {
    int p, s;  // indices into fids_ (R_, p_)
    Vector3d u;
    int loop;
  };
  std::vector<int> red_ind_, red_dep_;  // the method's partition
  std::vector<int> ind0_, ind_, dep_;   // the stabilization's: at the start, current
  std::vector<std::string> coordinate_names_;
  std::string red_what_ = "J_D";
  bool partitions_ = false, rows_only_ = false;
  double dependent_tol_ = 1e-13, repartition_cond_ = 10.0, partition_singular_cond_ = 1e4;
  double pivot_tie_rtol_ = 1e-9;
  Mat Xwarm_;  // (J_D^-1 J_I) at warm_q_: the dependent solve's tangent predictor
  /// v_D at the stages of the current adaptive step, shape (nc, n_stages + 1).
  Mat stage_dependent_v_;
  Vec qD0_, qD_end_, qD_new_, vD_last_, guess_qD_;
  /// v_D at the start of the current adaptive step, shape (nc,).
  Vec start_dependent_v_;
  bool use_guess_ = false, use_out_guess_ = false;
  /// unpack: the independent coordinates' distance from warm_q_, shape (nv - nc,).
  Vec independent_dq_;
  Vec unpack_y_, unpack_warm_, unpack_q_, unpack_v_;
  bool predictor_valid_ = false, unpack_valid_ = false;
  double sign0_ = 0.0;  // sign of det(J_D) at the first step (0: not yet)
  Mat JD_;
  /// solve_reduced: a = S a_I + c with S (this, shape (nv, nv - nc)) and c
  /// (reduced_offset_, shape (nv,)); M S, shape (nv, nv - nc).
  Mat reduced_basis_, mass_reduced_basis_;
  Vec reduced_offset_;
  /// solve_reduced: tau - h - M c, shape (nv,), and the independent accelerations a_I,
  /// shape (nv - nc,).
  Vec reduced_force_, independent_a_;
  Vec phi_n_, phi_best_, step_c_, q_try_, q_best_, dv_n_, warm_q_;
  /// fun_partitioned: the full state (q, v) completed from the independent one.
  Vec fun_q_, fun_v_;
  DenseLU lu_jd_;
  Eigen::JacobiSVD<Mat> svd_jd_, svd_jd_uv_;
  std::vector<Align> align_;
  std::vector<std::string> align_names_;
  std::vector<double> rep_t_;
  std::vector<int> rep_ind_;
};

}  // namespace closedchain
