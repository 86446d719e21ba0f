// closedchain._core: the compiled right-hand side and integration loops.
//
// One translation unit (a unit including Pinocchio's algorithms compiles in
// minutes). The Python side (closedchain.compiled) builds one Core per
// mechanism from the Pinocchio model and the constraint layer's row table; the
// model is used by reference, the Core owns its Data and every buffer.
//
// Every constraint row is one of three smooth scalar functions of the cut
// frames c1 (predecessor, R_p, p_p) and c2 (successor, R_s, p_s):
//   kind 0  translation along a world axis n:   phi = n . (p_p - p_s)
//   kind 1  translation along n fixed in c1:    phi = (R_p n) . (p_p - p_s)
//   kind 2  rotation, u in c1 and w in c2:      phi = (R_p u) . (R_s w)
// with exact J (derivative along pinocchio::integrate) and gamma = Jdot v, the
// formulas of closedchain/constraints.py.

#include <pinocchio/algorithm/energy.hpp>
#include <pinocchio/algorithm/jacobian.hpp>
#include <pinocchio/algorithm/joint-configuration.hpp>
#include <pinocchio/algorithm/kinematics.hpp>
#include <pinocchio/multibody/data.hpp>
#include <pinocchio/multibody/model.hpp>

#include <Eigen/Dense>
#include <boost/python.hpp>
#include <eigenpy/eigenpy.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <limits>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include "lean_data.hpp"
#include "rk_coefficients.hpp"
#include "small_llt.hpp"
#include "tree_terms.hpp"

namespace bp = boost::python;

namespace closedchain {

using Model = pinocchio::Model;
using Data = pinocchio::Data;
using Vec = Eigen::VectorXd;
using Mat = Eigen::MatrixXd;
using Mat6x = Eigen::Matrix<double, 6, Eigen::Dynamic>;
using Eigen::Vector3d;
using RefV = Eigen::Ref<const Vec>;

// ---------------------------------------------------------------------------
// Errors: thrown in C++, translated into closedchain's Python exceptions.

struct SingularError {
  std::string message;
  double cond;
  double t;  // NaN outside a simulation
  Vec q;
};

struct SimulationFailure {
  std::string message;
  double t;
};

struct BadArgument {
  std::string message;
};

// The kept rows stopped describing the loops at t (a dropped row opened, or the
// kept rows degenerate): the Python side re-selects them (closedchain.closure).
struct RowCheckRequired {
  std::string message;
  double t;
};

static std::string fmt(const char *f, double x) {
  char buf[64];
  std::snprintf(buf, sizeof buf, f, x);
  return buf;
}

static std::string vec_str(const Vec &q) {
  std::ostringstream s;
  s << "[";
  for (Eigen::Index i = 0; i < q.size(); ++i) s << (i ? " " : "") << fmt("%.6g", q[i]);
  s << "]";
  return s.str();
}

static bp::object to_numpy(const Vec &x) { return bp::object(Vec(x)); }

static void translate_singular(const SingularError &e) {
  bp::object exc = bp::import("closedchain.exceptions").attr("SingularConfigurationError");
  bp::dict kw;
  kw["q"] = to_numpy(e.q);
  kw["condition_number"] = e.cond;
  kw["t"] = std::isnan(e.t) ? bp::object() : bp::object(e.t);
  bp::object inst = exc(*bp::make_tuple(e.message), **kw);
  PyErr_SetObject(exc.ptr(), inst.ptr());
}

static void translate_simulation(const SimulationFailure &e) {
  bp::object exc = bp::import("closedchain.simulate.settings").attr("SimulationError");
  bp::object inst = exc(e.message, e.t);
  PyErr_SetObject(exc.ptr(), inst.ptr());
}

static void translate_row_check(const RowCheckRequired &e) {
  bp::object exc = bp::import("closedchain.compiled").attr("RowCheckRequired");
  bp::object inst = exc(e.message, e.t);
  PyErr_SetObject(exc.ptr(), inst.ptr());
}

static void translate_bad(const BadArgument &e) {
  bp::object exc = bp::import("closedchain.exceptions").attr("ClosedChainError");
  bp::object inst = exc(e.message);
  PyErr_SetObject(exc.ptr(), inst.ptr());
}

// ---------------------------------------------------------------------------

//: Relative regularization of the normal equations that polish the augmented-
//: Lagrangian multipliers (NORMAL_EQ_REG of dynamics/augmented_lagrangian.py).
constexpr double AL_NORMAL_EQ_REG = 1e-14;

//: min_norm solves through J J^T while its reciprocal condition number is above
//: this (cond(J) below ~1e4), else through the SVD of J.
constexpr double MIN_NORM_RCOND = 1e-8;

//: Relative margin of lu_inverse_norm_bound over its own round-off.
constexpr double INVERSE_BOUND_MARGIN = 1e-8;

enum Method { KKT = 0, SCHUR = 1, NULLSPACE = 2, AUGMENTED_LAGRANGIAN = 3 };
enum Integrator { EULER = 0, SEMI_IMPLICIT = 1, RK4 = 2, RK45 = 3, DOP853 = 4 };

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
       const Mat &vec2)
      : model_obj_(model_obj),
        model_(bp::extract<Model &>(model_obj)()),
        data_(lean_data(model_)),  // no nv^3 tensors: see lean_data.cpp
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
    K_ = Mat::Zero(nv_ + nc_, nv_ + nc_);
    rhs_ = Vec::Zero(nv_ + nc_);
    x_ = Vec::Zero(nv_ + nc_);
    est_x_ = Vec::Zero(nv_ + nc_);
    est_y_ = Vec::Zero(nv_ + nc_);
    est_z_ = Vec::Zero(nv_ + nc_);
    z_ = Vec::Zero(std::max(nv_ - nc_, 0));
    llt_m_ = Eigen::LLT<Mat>(nv_);
    llt_c_ = Eigen::LLT<Mat>(nc_);
    Y_ = Mat::Zero(nv_, nc_ + 1);
    D_ = Mat::Zero(nc_, nc_);
    svd_ = Eigen::JacobiSVD<Mat>(nc_, nv_, Eigen::ComputeFullU | Eigen::ComputeFullV);
    llt_r_ = Eigen::LLT<Mat>(nv_ - nc_ > 0 ? nv_ - nc_ : 0);
    Mr_ = Mat::Zero(std::max(nv_ - nc_, 0), std::max(nv_ - nc_, 0));
    JJt_ = Mat::Zero(nc_, nc_);
    eig_ = Eigen::SelfAdjointEigenSolver<Mat>(nc_);
    dq_ = Vec::Zero(nv_);
    tmp_c_ = Vec::Zero(nc_);
    tmp_v_ = Vec::Zero(nv_);
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
    piv_.assign(nv_ + nc_, 0);
  }

  int nc() const { return nc_; }
  long n_evals() const { return n_evals_; }
  void reset_evals() { n_evals_ = 0; }

  // Settings: method, cond_max, Baumgarte gains, simulation settings.
  void configure(bp::dict s) {
    std::string m = bp::extract<std::string>(s.get("method", "kkt"));
    if (m == "kkt")
      method_ = KKT;
    else if (m == "schur")
      method_ = SCHUR;
    else if (m == "nullspace")
      method_ = NULLSPACE;
    else if (m == "augmented-lagrangian")
      method_ = AUGMENTED_LAGRANGIAN;
    else
      throw BadArgument{"compiled core: unknown method '" + m +
                        "'; compiled: kkt, schur, nullspace, augmented-lagrangian"};
    method_name_ = m;
    cond_max_ = bp::extract<double>(s.get("cond_max", 1e12));
    bp::object bg = s.get("baumgarte", bp::object());
    baumgarte_ = !bg.is_none();
    if (baumgarte_) {
      alpha_ = bp::extract<double>(bg[0]);
      beta_ = bp::extract<double>(bg[1]);
    }
    projection_tol_ = bp::extract<double>(s.get("projection_tol", 1e-13));
    projection_iters_ = bp::extract<int>(s.get("projection_iters", 10));
    project_velocities_ = bp::extract<bool>(s.get("project_velocities", true));
    singular_cond_ = bp::extract<double>(s.get("singular_cond", 1e3));
    drift_limit_ = bp::extract<double>(s.get("drift_limit", 1e-2));
    al_penalty_ = bp::extract<double>(s.get("al_penalty", 1e11));
    al_tol_ = bp::extract<double>(s.get("al_tol", 1e-13));
    al_max_iter_ = bp::extract<int>(s.get("al_max_iter", 30));
    stage_projects_ = bp::extract<bool>(s.get("stage_projects", false));
    singular_robust_ = bp::extract<bool>(s.get("singular_robust", false));
    dropped_tol_ = bp::extract<double>(s.get("dropped_row_tol", 1e-9));
    dropped_ratio_ = bp::extract<double>(s.get("dropped_row_ratio", 100.0));
  }

  // Every declared row (the kept ones and those dropped as redundant), checked at
  // every step: kinds/frames/vectors as for the kept rows, kept[i] = 1 for a row
  // the methods use, labels "loop.kind" for messages.
  void set_declared(const Eigen::VectorXi &kinds, const Eigen::VectorXi &fid_p,
                    const Eigen::VectorXi &fid_s, const Mat &vec1, const Mat &vec2,
                    const Eigen::VectorXi &kept, bp::list labels) {
    const int nd = static_cast<int>(kinds.size());
    if (fid_p.size() != nd || fid_s.size() != nd || vec1.rows() != nd || vec2.rows() != nd ||
        kept.size() != nd || bp::len(labels) != nd || (nd && (vec1.cols() != 3 || vec2.cols() != 3)))
      throw BadArgument{"Core.set_declared: row tables of inconsistent shapes"};
    drows_.clear();
    dlabels_.clear();
    for (int r = 0; r < nd; ++r) {
      drows_.push_back(make_row(r, kinds, fid_p, fid_s, vec1, vec2));
      dlabels_.push_back(bp::extract<std::string>(labels[r]));
    }
    dkept_ = kept;
    dphi_ = Vec::Zero(nd);
    frame_buffers();
    J_at_valid_ = false;
  }

  // tau: None, a constant (nv,) array or a callable tau(t, q, v).
  void set_tau(bp::object tau) {
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

  // -- constraint rows ------------------------------------------------------

  // phi only: placements from forwardKinematics(q).
  void eval_phi(const RefV &q) {
    J_at_valid_ = false;
    pinocchio::forwardKinematics(model_, data_, q);
    placements();
    rows(true, false, false);
  }

  // phi and J: computeJointJacobians(q) (placements and world joint Jacobians).
  // Each step asks several times at one q (projection, regularity check, declared
  // rows, output): the last evaluation is reused while q is the same.
  void eval_phi_J(const RefV &q) {
    if (J_at_valid_ && q == J_at_) return;
    pinocchio::computeJointJacobians(model_, data_, q);
    placements();
    rows(true, true, false);
    J_at_ = q;
    J_at_valid_ = true;
  }

  // M, h, phi, J, gamma at (q, v): one pass over the tree (tree_terms.hpp: M, h,
  // the joints' placements, world Jacobian columns, velocities and bias
  // accelerations), then the cut frames' placements, velocities and classical
  // accelerations, then the rows. `mark(stage)` is called after each stage
  // (0 tree, 1 frames, 2 rows): a no-op, or py_profile's clock.
  template <class Mark>
  void eval_terms(const RefV &q, const RefV &v, Mark &&mark) {
    J_at_valid_ = false;
    tree_terms(model_, data_, q, v, M_, h_);
    mark(0);
    placements();
    frame_motion();
    mark(1);
    rows(true, true, true);
    if (baumgarte_ && nc_) {
      tmp_c_.noalias() = J_ * v;
      gamma_ += (2.0 * alpha_) * tmp_c_ + (beta_ * beta_) * phi_;
    }
    // phi_, J_ and the placements are those eval_phi_J(q) would compute; M_ and the
    // potential energy (total mass and centre of mass in data_.oYcrb[0]) serve record().
    J_at_ = q;
    J_at_valid_ = true;
    terms_q_ = q;
    terms_v_ = v;
    pe_ = -data_.oYcrb[0].mass() * model_.gravity.linear().dot(data_.oYcrb[0].lever());
    mark(2);
  }

  void eval_terms(const RefV &q, const RefV &v) {
    eval_terms(q, v, [](int) {});
  }

  // -- forward dynamics -------------------------------------------------------

  // Accelerations a_ and multipliers lam_ at (q, v) with generalized force tau.
  void solve(const RefV &q, const RefV &v, const Vec &tau, double t) {
    eval_terms(q, v);
    ++n_evals_;
    dispatch(q, tau, t);
  }

  void dispatch(const RefV &q, const Vec &tau, double t) {
    switch (method_) {
      case KKT: solve_kkt(q, tau, t); break;
      case SCHUR: solve_schur(q, tau, t); break;
      case NULLSPACE: solve_nullspace(q, tau, t); break;
      case AUGMENTED_LAGRANGIAN: solve_al(q, tau, t); break;
    }
  }

  // Augmented Lagrangian at the acceleration level (closedchain/dynamics/
  // augmented_lagrangian.py, Bayo & Ledesma 1996): P = M + alpha J^T J with
  // alpha = rho tr(M) / tr(J^T J); from lam_0 = 0,
  //   a_1 = P^-1 (tau - h - alpha J^T gamma),  lam_1 = alpha (J a_1 + gamma),
  //   a_{k+1} = a_k + P^-1 (tau - h - M a_k - J^T (lam_k + alpha (J a_k + gamma))),
  //   lam_{k+1} = lam_k + alpha (J a_{k+1} + gamma),
  // until max |a_{k+1} - a_k| <= al_tol (1 + max |a_{k+1}|); then lam is polished by
  // the regularized normal equations J J^T dlam = J (tau - h - M a - J^T lam).
  void solve_al(const RefV &q, const Vec &tau, double t) {
    if (nc_ == 0) {
      llt_m_.compute(M_);
      if (llt_m_.info() != Eigen::Success)
        singular(q, "the mass matrix M", std::numeric_limits<double>::infinity(),
                 "it is not positive definite (a massless subtree)", t);
      a_ = tau - h_;
      llt_m_.solveInPlace(a_);
      return;
    }
    const double jj = J_.squaredNorm();
    const double alpha = al_penalty_ * M_.trace() / std::max(jj, std::numeric_limits<double>::min());
    // Small dynamic sizes: coefficient-based products (lazyProduct) and SmallLLT,
    // no BLAS-style kernels; only P's lower triangle is factored.
    P_.triangularView<Eigen::Lower>() = J_.transpose().lazyProduct(J_);
    P_.triangularView<Eigen::Lower>() = alpha * P_ + M_;
    if (!llt_p_.compute(P_))
      singular(q, "the penalized mass matrix M + alpha J^T J",
               std::numeric_limits<double>::infinity(),
               "it is not positive definite, so M itself is singular (a massless subtree)", t);
    rhs_v_ = tau - h_;
    a_ = rhs_v_;
    a_.noalias() -= alpha * J_.transpose().lazyProduct(gamma_);
    llt_p_.solveInPlace(a_);
    lam_ = gamma_;
    lam_.noalias() += J_.lazyProduct(a_);
    lam_ *= alpha;
    for (int it = 1; it < al_max_iter_; ++it) {
      tmp_c_ = gamma_;
      tmp_c_.noalias() += J_.lazyProduct(a_);  // r_c
      tmp_c_ *= alpha;
      tmp_c_ += lam_;
      dq_ = rhs_v_;
      dq_.noalias() -= M_.lazyProduct(a_);
      dq_.noalias() -= J_.transpose().lazyProduct(tmp_c_);
      llt_p_.solveInPlace(dq_);  // delta
      a_ += dq_;
      tmp_c_ = gamma_;
      tmp_c_.noalias() += J_.lazyProduct(a_);
      lam_ += alpha * tmp_c_;
      if (dq_.cwiseAbs().maxCoeff() <= al_tol_ * (1.0 + a_.cwiseAbs().maxCoeff())) break;
    }
    tmp_v_ = rhs_v_;
    tmp_v_.noalias() -= M_.lazyProduct(a_);
    tmp_v_.noalias() -= J_.transpose().lazyProduct(lam_);  // r_d
    JJt_.triangularView<Eigen::Lower>() = J_.lazyProduct(J_.transpose());
    JJt_.diagonal().array() +=
        AL_NORMAL_EQ_REG * std::max(JJt_.trace(), 1.0) / static_cast<double>(nc_);
    llt_jj_.compute(JJt_);
    tmp_c_.noalias() = J_.lazyProduct(tmp_v_);
    llt_jj_.solveInPlace(tmp_c_);
    lam_ += tmp_c_;
  }

  [[noreturn]] void singular(const RefV &q, const std::string &what, double cond,
                             const std::string &hint, double t) {
    std::string msg = name_ + ": " + what + " is singular at q = " + vec_str(q) +
                      " (condition number " + fmt("%.3e", cond) + " > cond_max " +
                      fmt("%.1e", cond_max_) + "); " + hint;
    if (!std::isnan(t)) msg = "at t = " + fmt("%.9g", t) + " s: " + msg;
    throw SingularError{msg, cond, t, Vec(q)};
  }

  void check_rcond(const RefV &q, const std::string &what, double rcond, double t) {
    double cond = (rcond > 0 && std::isfinite(rcond)) ? 1.0 / rcond
                                                       : std::numeric_limits<double>::infinity();
    if (!(cond <= cond_max_))
      singular(q, what, cond,
               "the constraint Jacobian has lost rank or the configuration is a singularity", t);
  }

  void solve_kkt(const RefV &q, const Vec &tau, double t) {
    // K = [[M, J^T], [J, 0]] column by column, with its 1-norm (written out: the
    // block assignments cost more than the copy at these sizes).
    const Eigen::Index nv = nv_, nc = nc_, n = nv + nc;
    double *k = K_.data();
    double anorm = 0.0;
    for (Eigen::Index j = 0; j < nv; ++j) {
      double *col = k + j * n, s = 0.0;
      for (Eigen::Index i = 0; i < nv; ++i) s += std::abs(col[i] = M_(i, j));
      for (Eigen::Index r = 0; r < nc; ++r) s += std::abs(col[nv + r] = J_(r, j));
      anorm = std::max(anorm, s);
    }
    for (Eigen::Index r = 0; r < nc; ++r) {
      double *col = k + (nv + r) * n, s = 0.0;
      for (Eigen::Index i = 0; i < nv; ++i) s += std::abs(col[i] = J_(r, i));
      for (Eigen::Index i = nv; i < n; ++i) col[i] = 0.0;
      anorm = std::max(anorm, s);
    }
    for (Eigen::Index i = 0; i < nv; ++i) rhs_[i] = tau[i] - h_[i];
    for (Eigen::Index r = 0; r < nc; ++r) rhs_[nv + r] = -gamma_[r];
    // An exactly singular K leaves a zero pivot: rcond 0 (as LAPACK's info > 0).
    // Away from singular configurations a cheap upper bound of cond_1(K) already
    // shows that the dgecon-style estimate (a lower bound of it) cannot exceed
    // cond_max; only otherwise is the estimate computed.
    if (!lu_factor()) {
      check_rcond(q, "the KKT matrix [[M, J^T], [J, 0]]", 0.0, t);
    } else if (!(anorm * lu_inverse_norm_bound() <= cond_max_)) {
      check_rcond(q, "the KKT matrix [[M, J^T], [J, 0]]", rcond_lu(anorm), t);
    }
    lu_solve(rhs_, x_);
    a_ = x_.head(nv_);
    lam_ = x_.tail(nc_);
  }

  //: Size of K from which lu_factor uses Eigen's blocked LU instead of dgetf2's loop.
  static constexpr Eigen::Index LU_BLOCKED_MIN = 96;

  // LU with partial pivoting of K_ in place (LAPACK's dgetf2: the first largest pivot,
  // row swaps in piv_), x = K^-1 b and z = K^-T y on the factors. Written out for the
  // small KKT matrices: Eigen's blocked PartialPivLU and its solves spend more on
  // dynamic-size bookkeeping (and heap copies of the permutation) than on arithmetic.
  // Returns false when a pivot is exactly zero (K singular).
  bool lu_factor() {
    const Eigen::Index n = K_.rows();
    double *A = K_.data();  // column-major, leading dimension n
    if (n >= LU_BLOCKED_MIN) {
      // Large trees (hundreds of joints): Eigen's blocked LU (GEMM updates; its
      // workspace may come from the heap, which is negligible against the O(n^3)
      // work), the same row swaps in piv_; the loop below is 4x slower at n = 1000.
      int swaps = 0;
      return Eigen::internal::partial_lu_impl<double, Eigen::ColMajor, int>::blocked_lu(
                 n, n, A, n, piv_.data(), swaps) < 0;
    }
    bool regular = true;
    for (Eigen::Index k = 0; k < n; ++k) {
      Eigen::Index p = k;
      double big = std::abs(A[k + k * n]);
      for (Eigen::Index i = k + 1; i < n; ++i)
        if (std::abs(A[i + k * n]) > big) {
          big = std::abs(A[i + k * n]);
          p = i;
        }
      piv_[k] = static_cast<int>(p);
      if (big == 0.0) {
        regular = false;
        continue;
      }
      if (p != k)
        for (Eigen::Index j = 0; j < n; ++j) std::swap(A[k + j * n], A[p + j * n]);
      const double inv = 1.0 / A[k + k * n];
      for (Eigen::Index i = k + 1; i < n; ++i) A[i + k * n] *= inv;
      for (Eigen::Index j = k + 1; j < n; ++j) {
        const double akj = A[k + j * n];
        if (akj != 0.0)
          for (Eigen::Index i = k + 1; i < n; ++i) A[i + j * n] -= A[i + k * n] * akj;
      }
    }
    return regular;
  }

  void lu_solve(const Vec &b, Vec &x) {
    const Eigen::Index n = K_.rows();
    const double *A = K_.data();
    if (&x != &b) x = b;
    for (Eigen::Index k = 0; k < n; ++k)
      if (piv_[k] != k) std::swap(x[k], x[piv_[k]]);
    for (Eigen::Index j = 0; j < n; ++j) {  // L (unit lower)
      const double xj = x[j];
      if (xj != 0.0)
        for (Eigen::Index i = j + 1; i < n; ++i) x[i] -= A[i + j * n] * xj;
    }
    for (Eigen::Index j = n - 1; j >= 0; --j) {  // U
      x[j] /= A[j + j * n];
      const double xj = x[j];
      if (xj != 0.0)
        for (Eigen::Index i = 0; i < j; ++i) x[i] -= A[i + j * n] * xj;
    }
  }

  void lu_solve_transposed(const Vec &y, Vec &z) {
    const Eigen::Index n = K_.rows();
    const double *A = K_.data();
    z = y;
    for (Eigen::Index j = 0; j < n; ++j) {  // U^T w = y
      double s = z[j];
      for (Eigen::Index i = 0; i < j; ++i) s -= A[i + j * n] * z[i];
      z[j] = s / A[j + j * n];
    }
    for (Eigen::Index j = n - 1; j >= 0; --j) {  // L^T u = w
      double s = z[j];
      for (Eigen::Index i = j + 1; i < n; ++i) s -= A[i + j * n] * z[i];
      z[j] = s;
    }
    for (Eigen::Index k = n - 1; k >= 0; --k)  // z = P^T u
      if (piv_[k] != k) std::swap(z[k], z[piv_[k]]);
  }

  // Upper bound of ||K^-1||_1 from the factors (regular): ||U^-1||_1 ||L^-1||_1, each
  // bounded through the comparison matrix, |T^-1| <= M(T)^-1 elementwise for
  // triangular T (Higham, Accuracy and Stability of Numerical Algorithms, 2002,
  // Thm 8.12), so ||T^-1||_1 <= max(M(T)^-T e): one small triangular solve each.
  // A relative margin covers its own round-off.
  double lu_inverse_norm_bound() {
    const Eigen::Index n = K_.rows();
    const double *A = K_.data();
    double bu = 0.0, bl = 0.0;
    for (Eigen::Index j = 0; j < n; ++j) {  // M(U)^T y = e, forward
      double s = 1.0;
      for (Eigen::Index i = 0; i < j; ++i) s += std::abs(A[i + j * n]) * est_y_[i];
      est_y_[j] = s / std::abs(A[j + j * n]);
      bu = std::max(bu, est_y_[j]);
    }
    for (Eigen::Index j = n - 1; j >= 0; --j) {  // M(L)^T y = e, backward (unit diagonal)
      double s = 1.0;
      for (Eigen::Index i = j + 1; i < n; ++i) s += std::abs(A[i + j * n]) * est_z_[i];
      est_z_[j] = s;
      bl = std::max(bl, s);
    }
    return bu * bl * (1.0 + INVERSE_BOUND_MARGIN);
  }

  // Reciprocal 1-norm condition estimate of the factored K (Hager / Higham, the
  // estimator of LAPACK's dgecon), on preallocated vectors.
  double rcond_lu(double anorm) {
    const Eigen::Index n = x_.size();
    if (anorm == 0.0) return 0.0;
    est_x_.setConstant(1.0 / static_cast<double>(n));
    double est = 0.0;
    Eigen::Index jlast = -1;
    for (int it = 0; it < 5; ++it) {
      lu_solve(est_x_, est_y_);  // y = K^-1 x
      const double e = est_y_.lpNorm<1>();
      if (it > 0 && e <= est) break;
      est = e;
      for (Eigen::Index i = 0; i < n; ++i) est_y_[i] = est_y_[i] >= 0 ? 1.0 : -1.0;
      lu_solve_transposed(est_y_, est_z_);  // z = K^-T sign(y)
      Eigen::Index j;
      est_z_.cwiseAbs().maxCoeff(&j);
      if (it > 0 && j == jlast) break;
      jlast = j;
      est_x_.setZero();
      est_x_[j] = 1.0;
    }
    // Higham's alternating-sign vector guards against underestimation.
    for (Eigen::Index i = 0; i < n; ++i)
      est_x_[i] = (i % 2 ? -1.0 : 1.0) * (1.0 + static_cast<double>(i) / std::max<Eigen::Index>(n - 1, 1));
    lu_solve(est_x_, est_y_);
    est = std::max(est, 2.0 * est_y_.lpNorm<1>() / (3.0 * static_cast<double>(n)));
    return est > 0 ? 1.0 / (est * anorm) : 0.0;
  }

  void solve_schur(const RefV &q, const Vec &tau, double t) {
    llt_m_.compute(M_);
    check_rcond(q, "the mass matrix M", llt_m_.info() == Eigen::Success ? llt_m_.rcond() : 0.0, t);
    Y_.leftCols(nc_) = J_.transpose();
    Y_.col(nc_) = tau - h_;
    llt_m_.solveInPlace(Y_);
    if (nc_ == 0) {
      a_ = Y_.col(0);
      return;
    }
    D_.noalias() = J_ * Y_.leftCols(nc_);
    tmp_c_.noalias() = J_ * Y_.col(nc_);
    tmp_c_ += gamma_;
    llt_c_.compute(D_);
    check_rcond(q, "the Delassus matrix J M^-1 J^T",
                llt_c_.info() == Eigen::Success ? llt_c_.rcond() : 0.0, t);
    lam_ = tmp_c_;
    llt_c_.solveInPlace(lam_);
    a_ = Y_.col(nc_);
    a_.noalias() -= Y_.leftCols(nc_) * lam_;
  }

  void solve_nullspace(const RefV &q, const Vec &tau, double t) {
    const int nr = nv_ - nc_;
    if (nc_ == 0) {
      llt_m_.compute(M_);
      a_ = llt_m_.solve(tau - h_);
      return;
    }
    svd_.compute(J_, Eigen::ComputeFullU | Eigen::ComputeFullV);
    const Vec &s = svd_.singularValues();
    double cond = s[nc_ - 1] > 0 ? s[0] / s[nc_ - 1] : std::numeric_limits<double>::infinity();
    if (!(cond <= cond_max_))
      singular(q, "the constraint Jacobian J", cond,
               "it has lost rank: a singular configuration", t);
    const Mat &U = svd_.matrixU();
    const Mat &V = svd_.matrixV();
    // a_p = -V_r S^-1 U^T gamma
    tmp_c_.noalias() = U.transpose() * gamma_;
    tmp_c_.array() /= s.head(nc_).array();
    a_.noalias() = -(V.leftCols(nc_) * tmp_c_);
    if (nr > 0) {
      auto N = V.rightCols(nr);
      Mr_.noalias() = N.transpose() * M_ * N;
      llt_r_.compute(Mr_);
      check_rcond(q, "the reduced mass matrix N^T M N",
                  llt_r_.info() == Eigen::Success ? llt_r_.rcond() : 0.0, t);
      tmp_v_ = tau - h_;
      tmp_v_.noalias() -= M_ * a_;
      z_.noalias() = N.transpose() * tmp_v_;
      llt_r_.solveInPlace(z_);
      a_.noalias() += N * z_;
    }
    tmp_v_ = tau - h_;
    tmp_v_.noalias() -= M_ * a_;
    tmp_c_.noalias() = V.leftCols(nc_).transpose() * tmp_v_;
    tmp_c_.array() /= s.head(nc_).array();
    lam_.noalias() = U * tmp_c_;
  }

  // The generalized force at (t, q, v) into tau_.
  const Vec &tau_at(double t, const RefV &q, const RefV &v) {
    if (tau_mode_ == 0) return zero_v_;
    if (tau_mode_ == 1) return tau_const_;
    bp::object r = np_asarray_(tau_obj_(t, to_numpy(q), to_numpy(v)), "float64");
    bp::extract<Vec> ex(r);
    bool ok = bp::len(r.attr("shape")) == 1 && ex.check();
    if (ok) {
      tau_ = ex();
      ok = tau_.size() == nv_ && tau_.allFinite();
    }
    if (!ok) {
      std::string rep = bp::extract<std::string>(bp::str(r));
      throw SimulationFailure{"tau(t, q, v) returned " + rep + " at t = " + fmt("%.6g", t) +
                                  " s; expected finite shape (" + std::to_string(nv_) + ",)",
                              t};
    }
    return tau_;
  }

  // The right-hand side of a simulation: a_ (and lam_) at (t, q, v).
  void accel(double t, const RefV &q, const RefV &v) {
    const Vec &tau = tau_at(t, q, v);
    solve(q, v, tau, t);
    if (!a_.allFinite())
      throw SimulationFailure{"non-finite acceleration at t = " + fmt("%.9g", t) +
                                  " s, q = " + vec_str(q),
                              t};
  }

  // -- Python entry points of one evaluation ---------------------------------

  bp::tuple py_rows(const Vec &q, const Vec &v) {
    check_sizes(q, v);
    eval_terms(q, v);
    return bp::make_tuple(Vec(phi_), Mat(J_), Vec(gamma_));
  }

  bp::tuple py_forward(const Vec &q, const Vec &v, const Vec &tau) {
    check_sizes(q, v);
    if (tau.size() != nv_) throw BadArgument{"tau must have shape (nv,)"};
    solve(q, v, tau, std::numeric_limits<double>::quiet_NaN());
    return bp::make_tuple(Vec(a_), Vec(lam_));
  }

  // a at (q, v) for n_eval repetitions inside C++ (the per-evaluation cost in the loop).
  Vec py_repeat(const Vec &q, const Vec &v, const Vec &tau, int n) {
    check_sizes(q, v);
    for (int i = 0; i < n; ++i) solve(q, v, tau, std::numeric_limits<double>::quiet_NaN());
    return a_;
  }

  // Mean wall time [ns] of each stage of one evaluation over n repetitions
  // (profiling): the sequence of solve(), with a clock between its stages.
  bp::dict py_profile(const Vec &q, const Vec &v, const Vec &tau, int n) {
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

  // -- stabilization and checks ----------------------------------------------

  // cond_2(J) from the eigenvalues of J J^T.
  double cond_J() {
    if (nc_ == 0) return 1.0;
    JJt_.noalias() = J_ * J_.transpose();
    eig_.compute(JJt_, Eigen::EigenvaluesOnly);
    const Vec &ev = eig_.eigenvalues();
    if (!(ev[0] > 0)) return std::numeric_limits<double>::infinity();
    return std::sqrt(ev[nc_ - 1] / ev[0]);
  }

  // The step's checks at q (Problem.check_regular and LoopClosure.check_rows of the
  // numpy backend), plus the drift limit over every declared row at every step:
  // - every declared row (dropped ones too) within drift_limit, else SimulationFailure
  //   naming the row;
  // - a dropped row open by more than max(dropped_row_tol, dropped_row_ratio x the kept
  //   rows' residual), or kept rows degenerate (cond(J) > singular_cond while there are
  //   dropped rows): RowCheckRequired (the Python side re-selects the rows);
  // - unless singular_robust, cond(J) > singular_cond: SingularError.
  void check_regular(const RefV &q, double t) {
    if (nc_ == 0 && drows_.empty()) return;
    eval_phi_J(q);  // placements at q for the declared rows too
    const int nd = static_cast<int>(drows_.size());
    double res = 0.0, kept_res = 0.0, drop_res = 0.0;
    int worst = -1, worst_drop = -1;
    if (nd) {
      declared_phi();
      for (int r = 0; r < nd; ++r) {
        const double x = std::abs(dphi_[r]);
        if (!(x <= res)) {  // NaN is the worst
          res = x;
          worst = r;
        }
        if (dkept_[r]) {
          kept_res = std::max(kept_res, x);
        } else if (!(x <= drop_res)) {
          drop_res = x;
          worst_drop = r;
        }
      }
    } else {
      res = nc_ ? phi_.cwiseAbs().maxCoeff() : 0.0;
    }
    if (!std::isfinite(res) || res > drift_limit_)
      throw SimulationFailure{
          name_ + ": the state left the constraint manifold at t = " + fmt("%.9g", t) +
              " s (max |phi| = " + fmt("%.3e", res) + " > drift_limit " +
              fmt("%.1e", drift_limit_) + (worst >= 0 ? ", row " + dlabels_[worst] : "") +
              "); use a stabilization or a smaller step",
          t};
    const bool has_dropped = nd > nc_;
    if (has_dropped && drop_res > std::max(dropped_tol_, dropped_ratio_ * kept_res))
      throw RowCheckRequired{"dropped row " + dlabels_[worst_drop] + " open by " +
                                 fmt("%.3e", drop_res) + " (kept rows " + fmt("%.3e", kept_res) +
                                 ") at t = " + fmt("%.9g", t) + " s",
                             t};
    if (singular_robust_ || nc_ == 0) return;
    double cond = cond_J();
    if (!(cond <= singular_cond_)) {
      if (has_dropped && declared_cond() <= singular_cond_)
        throw RowCheckRequired{"kept rows degenerate (condition number " + fmt("%.3e", cond) +
                                   ") at t = " + fmt("%.9g", t) + " s",
                               t};
      std::string msg =
          name_ + ": at t = " + fmt("%.9g", t) +
          " s the constraint Jacobian is close to losing rank at q = " + vec_str(q) +
          " (condition number " + fmt("%.3e", cond) + " > singular_cond " +
          fmt("%.1e", singular_cond_) +
          "): a singular configuration, where the motion is not determined by the equations "
          "and method '" + method_name_ + "' loses accuracy without any error estimate "
          "noticing; to pass singular positions use method='augmented-lagrangian' with "
          "stabilization='stage-projection' (and a fixed-step integrator)";
      throw SingularError{msg, cond, t, Vec(q)};
    }
  }

  // Condition number of the nc largest singular values of the declared rows' J at the
  // last eval_phi_J (LoopClosure.check_rows): above singular_cond the mechanism itself
  // is singular there, no re-selection of rows helps.
  double declared_cond() {
    const int nd = static_cast<int>(drows_.size());
    Mat Jd(nd, nv_);  // only where the kept rows degenerate: not the hot path
    for (int r = 0; r < nd; ++r) row_jacobian(drows_[r], Jd.row(r));
    Eigen::JacobiSVD<Mat> svd(Jd);
    const Vec &sv = svd.singularValues();
    if (nc_ == 0 || sv.size() < nc_ || !(sv[nc_ - 1] > 0))
      return std::numeric_limits<double>::infinity();
    return sv[0] / sv[nc_ - 1];
  }

  // phi of every declared row from the placements of the last kinematics pass.
  void declared_phi() {
    for (std::size_t r = 0; r < drows_.size(); ++r) {
      const Row &row = drows_[r];
      if (row.kind != 2) {
        const Vector3d d = p_[row.p] - p_[row.s];
        dphi_[r] = row.kind == 0 ? row.n.dot(d) : (R_[row.p] * row.n).dot(d);
      } else {
        dphi_[r] = (R_[row.p] * row.n).dot(R_[row.s] * row.w);
      }
    }
  }

  // Minimum-norm solution x of J x = b (J full row rank): J^T (J J^T)^-1 b.
  // Where J J^T is ill-conditioned (J nearly rank-deficient, e.g. passing a singular
  // position with stage projection) it is numpy.linalg.lstsq's minimum-norm solution
  // from the SVD, singular values below eps max(nc, nv) s_max treated as zero.
  // The test "the estimate rcond of J J^T exceeds MIN_NORM_RCOND" is decided by an
  // upper bound of cond_1 from the Cholesky factor where it can (rcond >= 1 / that
  // bound), so Eigen's estimator runs only near singular positions.
  void min_norm(const Vec &b, Vec &x) {
    JJt_.triangularView<Eigen::Lower>() = J_.lazyProduct(J_.transpose());
    bool regular = false;
    if (llt_jj_.compute(JJt_)) {
      double anorm = 0.0;  // ||J J^T||_1 from its lower triangle
      for (Eigen::Index j = 0; j < nc_; ++j) {
        double c = 0.0;
        for (Eigen::Index i = 0; i < nc_; ++i) c += std::abs(i >= j ? JJt_(i, j) : JJt_(j, i));
        anorm = std::max(anorm, c);
      }
      if (anorm * llt_jj_.inverse_norm_bound(INVERSE_BOUND_MARGIN) < 1.0 / MIN_NORM_RCOND) {
        regular = true;
      } else {
        JJt_.triangularView<Eigen::StrictlyUpper>() = JJt_.transpose();
        llt_c_.compute(JJt_);
        regular = llt_c_.info() == Eigen::Success && llt_c_.rcond() > MIN_NORM_RCOND;
      }
    }
    if (regular) {
      tmp_c_ = b;
      llt_jj_.solveInPlace(tmp_c_);
      x.noalias() = J_.transpose().lazyProduct(tmp_c_);
      return;
    }
    svd_.compute(J_, Eigen::ComputeFullU | Eigen::ComputeFullV);
    const Vec &sv = svd_.singularValues();
    const double cut = std::numeric_limits<double>::epsilon() * std::max(nc_, nv_) *
                       (sv.size() ? sv[0] : 0.0);
    x.setZero();
    for (Eigen::Index i = 0; i < sv.size(); ++i)
      if (sv[i] > cut)
        x += (svd_.matrixU().col(i).dot(b) / sv[i]) * svd_.matrixV().col(i);
  }

  // Gauss-Newton (minimum-norm) projection of q onto phi = 0, then v onto J v = 0.
  void project(Vec &q, Vec &v) {
    if (nc_ == 0) return;
    for (int it = 0; it < projection_iters_; ++it) {
      eval_phi_J(q);
      if (phi_.cwiseAbs().maxCoeff() <= projection_tol_) break;
      tmp_c_ = -phi_;
      min_norm(tmp_c_, dq_);
      q_prev_ = q;
      pinocchio::integrate(model_, q_prev_, dq_, q);
    }
    if (project_velocities_) {
      eval_phi_J(q);
      vel_c_.noalias() = J_ * v;
      min_norm(vel_c_, dq_);
      v -= dq_;
    }
  }

  // -- recording ---------------------------------------------------------------

  struct Samples {
    std::vector<double> t, res, vres, e, ke, branch;
    std::vector<double> q, v, a, lam;
  };

  // The columns D of J whose sign of det(J[:, D]) is recorded with every sample (the
  // assembly branch, Recorder._add_branch); empty: none recorded.
  void set_branch_columns(const Eigen::VectorXi &cols) {
    if (cols.size() != 0 && cols.size() != nc_)
      throw BadArgument{"Core.set_branch_columns: need nc = " + std::to_string(nc_) + " columns"};
    for (Eigen::Index i = 0; i < cols.size(); ++i)
      if (cols[i] < 0 || cols[i] >= nv_) throw BadArgument{"Core.set_branch_columns: column out of range"};
    branch_cols_ = cols;
    JD_ = Mat::Zero(cols.size(), cols.size());
  }

  // Sign of det(J_[:, branch_cols_]) (J_ at the sample's q): the parity of the row
  // swaps of an LU with partial pivoting times the signs of its pivots, 0 for an
  // exactly zero pivot (numpy.linalg.slogdet's sign).
  double branch_sign() {
    const Eigen::Index n = branch_cols_.size();
    for (Eigen::Index j = 0; j < n; ++j) JD_.col(j) = J_.col(branch_cols_[j]);
    double sign = 1.0;
    double *A = JD_.data();
    for (Eigen::Index k = 0; k < n; ++k) {
      Eigen::Index p = k;
      double big = std::abs(A[k + k * n]);
      for (Eigen::Index i = k + 1; i < n; ++i)
        if (std::abs(A[i + k * n]) > big) {
          big = std::abs(A[i + k * n]);
          p = i;
        }
      if (big == 0.0) return 0.0;
      if (p != k) {
        sign = -sign;
        for (Eigen::Index j = k; j < n; ++j) std::swap(A[k + j * n], A[p + j * n]);
      }
      if (A[k + k * n] < 0) sign = -sign;
      for (Eigen::Index i = k + 1; i < n; ++i) {
        const double l = A[i + k * n] / A[k + k * n];
        for (Eigen::Index j = k + 1; j < n; ++j) A[i + j * n] -= l * A[k + j * n];
      }
    }
    return sign;
  }

  void record(Samples &out, double t, const Vec &q, const Vec &v) {
    // a_ and lam_ are those at (t, q, v)
    // res: max |phi| over every declared row (a loop is never reported closed while
    // a dropped row is open); vres: max |J v| over the kept rows.
    double res = 0.0, vres = 0.0;
    int worst = -1;
    if (nc_ || !drows_.empty()) {
      eval_phi_J(q);
      if (!drows_.empty()) {
        declared_phi();
        for (Eigen::Index r = 0; r < dphi_.size(); ++r)
          if (!(std::abs(dphi_[r]) <= res)) {
            res = std::abs(dphi_[r]);
            worst = static_cast<int>(r);
          }
      } else {
        res = phi_.cwiseAbs().maxCoeff();
      }
      if (nc_) {
        vel_c_.noalias() = J_ * v;
        vres = vel_c_.cwiseAbs().maxCoeff();
      }
    }
    if (!std::isfinite(res) || res > drift_limit_)
      throw SimulationFailure{
          name_ + ": the state left the constraint manifold at t = " + fmt("%.9g", t) +
              " s (max |phi| = " + fmt("%.3e", res) + " > drift_limit " +
              fmt("%.1e", drift_limit_) + (worst >= 0 ? ", row " + dlabels_[worst] : "") +
              "); use a stabilization or a smaller step",
          t};
    // Energies: from the last eval_terms when it was at (q, v) (the loops record
    // right after accel there), else from Pinocchio's own passes.
    double ke, pe;
    if (q == terms_q_ && v == terms_v_) {
      ke = 0.5 * v.dot(M_.lazyProduct(v));
      pe = pe_;
    } else {
      ke = pinocchio::computeKineticEnergy(model_, data_, q, v);
      pe = pinocchio::computePotentialEnergy(model_, data_, q);
    }
    out.t.push_back(t);
    out.res.push_back(res);
    out.vres.push_back(vres);
    out.e.push_back(ke + pe);
    out.ke.push_back(ke);
    out.q.insert(out.q.end(), q.data(), q.data() + nq_);
    out.v.insert(out.v.end(), v.data(), v.data() + nv_);
    out.a.insert(out.a.end(), a_.data(), a_.data() + nv_);
    out.lam.insert(out.lam.end(), lam_.data(), lam_.data() + nc_);
    if (branch_cols_.size() && nc_) out.branch.push_back(branch_sign());  // J_ at q (eval_phi_J)
  }

  static bp::object block(const std::vector<double> &x, long rows, long cols) {
    Mat m(rows, cols);
    for (long i = 0; i < rows; ++i)
      for (long j = 0; j < cols; ++j) m(i, j) = x[i * cols + j];
    return bp::object(m);
  }

  bp::dict samples_dict(const Samples &s, long steps) {
    long n = static_cast<long>(s.t.size());
    bp::dict d;
    d["t"] = block(s.t, n, 1);
    d["q"] = block(s.q, n, nq_);
    d["v"] = block(s.v, n, nv_);
    d["a"] = block(s.a, n, nv_);
    d["lam"] = block(s.lam, n, nc_);
    d["res"] = block(s.res, n, 1);
    d["vres"] = block(s.vres, n, 1);
    d["e"] = block(s.e, n, 1);
    d["ke"] = block(s.ke, n, 1);
    if (branch_cols_.size() && nc_) d["branch"] = block(s.branch, n, 1);
    d["steps"] = steps;
    d["evaluations"] = n_evals_;
    return d;
  }

  void poll(long k, double t, const bp::object &progress) {
    if (!progress.is_none()) progress(t);
    if ((k & 63) == 0 && PyErr_CheckSignals() != 0) bp::throw_error_already_set();
  }

  void check_finite(const Vec &q, const Vec &v, double t) {
    if (!(q.allFinite() && v.allFinite()))
      throw SimulationFailure{name_ + ": non-finite state at t = " + fmt("%.9g", t) + " s", t};
  }

  // -- fixed-step integration ----------------------------------------------------

  // Integrate with a fixed step dt for n_steps, recording at the steps in `out`.
  bp::dict run_fixed(int integrator, const Vec &q0, const Vec &v0, double dt, long n_steps,
                     const Eigen::VectorXi &out_steps, bool projects, bp::object progress) {
    check_sizes(q0, v0);
    if (integrator < EULER || integrator > RK4) throw BadArgument{"run_fixed: unknown integrator"};
    n_evals_ = 0;
    Samples S;
    std::vector<char> out(n_steps + 1, 0);
    for (Eigen::Index i = 0; i < out_steps.size(); ++i)
      if (out_steps[i] >= 0 && out_steps[i] <= n_steps) out[out_steps[i]] = 1;
    Vec q = q0, v = v0, qn(nq_), vn(nv_), qs(nq_), vs(nv_);
    Vec k1v(nv_), k1a(nv_), k2v(nv_), k2a(nv_), k3v(nv_), k3a(nv_), k4v(nv_), k4a(nv_), dv(nv_);
    double t = 0.0;
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
        if (stage_projects_) project(qs, vs);
        accel(t + dt / 2, qs, vs);
        k2v = vs;
        k2a = a_;
        dv = (dt / 2) * k2v;
        pinocchio::integrate(model_, q, dv, qs);
        vs = v + (dt / 2) * k2a;
        if (stage_projects_) project(qs, vs);
        accel(t + dt / 2, qs, vs);
        k3v = vs;
        k3a = a_;
        dv = dt * k3v;
        pinocchio::integrate(model_, q, dv, qs);
        vs = v + dt * k3a;
        if (stage_projects_) project(qs, vs);
        accel(t + dt, qs, vs);
        k4v = vs;
        k4a = a_;
        dv = (dt / 6) * (k1v + 2 * k2v + 2 * k3v + k4v);
        pinocchio::integrate(model_, q, dv, qn);
        vn = v + (dt / 6) * (k1a + 2 * k2a + 2 * k3a + k4a);
      }
      t = k * dt;
      check_finite(qn, vn, t);
      if (projects) project(qn, vn);
      check_regular(qn, t);
      q = qn;
      v = vn;
      accel(t, q, v);
      if (out[k]) record(S, t, q, v);
      poll(k, t, progress);
    }
    return samples_dict(S, n_steps);
  }

  // -- adaptive explicit Runge-Kutta (scipy's RK45 / DOP853, same error control) --

  double rms(const Vec &x) const { return x.norm() / std::sqrt(static_cast<double>(x.size())); }

  void fun(double t, const Vec &y, Eigen::Ref<Vec> f) {
    accel(t, y.head(nv_), y.tail(nv_));
    f.head(nv_) = y.tail(nv_);
    f.tail(nv_) = a_;
  }

  bp::dict run_adaptive(int integrator, const Vec &q0, const Vec &v0, double t_final,
                        double rtol, double atol, bp::object t_eval_obj, bool projects,
                        bp::object progress) {
    check_sizes(q0, v0);
    if (nq_ != nv_) throw BadArgument{"adaptive integration needs nq == nv"};
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
    n_evals_ = 0;
    Samples S;
    const int n = 2 * nv_;
    std::vector<double> pending;
    const bool dense = !t_eval_obj.is_none();
    if (dense) {
      Vec te = bp::extract<Vec>(t_eval_obj);
      pending.assign(te.data(), te.data() + te.size());
    }
    std::size_t ip = 0;
    Vec y(n), y_new(n), f(n), f_new(n), scale(n), dy(n), ye(n), tmp(n), e5(n), e3(n);
    y.head(nv_) = q0;
    y.tail(nv_) = v0;
    Mat K(n, dop ? dop853::N_STAGES_EXTENDED : n_stages + 1);
    Mat F(n, dop853::INTERPOLATOR_POWER);
    auto output = [&](double t, const Vec &yy) {
      accel(t, yy.head(nv_), yy.tail(nv_));
      record(S, t, yy.head(nv_), yy.tail(nv_));
    };
    double t = 0.0;
    if (!dense || (ip < pending.size() && pending[ip] <= 0.0)) {
      output(0.0, y);
      if (dense) ++ip;
    }
    fun(t, y, f);
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
      fun(t + h0, y1, f1);
      double d2 = rms((f1 - f).cwiseQuotient(scale)) / h0;
      double h1 = (d1 <= 1e-15 && d2 <= 1e-15) ? std::max(1e-6, h0 * 1e-3)
                                                : std::pow(0.01 / std::max(d1, d2),
                                                           1.0 / (error_order + 1));
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
          throw SimulationFailure{name_ + ": integrator " + iname + " failed at t = " +
                                      fmt("%.9g", t) +
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
        for (int s = 1; s < n_stages; ++s) {
          dy.setZero();
          for (int j = 0; j < s; ++j) {
            double c = dop ? dop853::A[s][j] : rk45::A[s][j];
            if (c != 0.0) dy += c * K.col(j);
          }
          ye = y + h * dy;
          fun(t + (dop ? dop853::C[s] : rk45::C[s]) * h, ye, K.col(s));
        }
        dy.setZero();
        for (int j = 0; j < n_stages; ++j) {
          double b = dop ? dop853::B[j] : rk45::B[j];
          if (b != 0.0) dy += b * K.col(j);
        }
        y_new = y + h * dy;
        fun(t + h, y_new, f_new);
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
      // dense output at the t_eval within the step, from the unprojected step
      if (dense && ip < pending.size() && pending[ip] <= t_new) {
        if (dop) {
          for (int s = n_stages + 1, e = 0; e < 3; ++s, ++e) {
            dy.setZero();
            for (int j = 0; j < s; ++j)
              if (dop853::A_EXTRA[e][j] != 0.0) dy += dop853::A_EXTRA[e][j] * K.col(j);
            ye = y + h * dy;
            fun(t_old + dop853::C_EXTRA[e] * h, ye, K.col(s));
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
        } else {
          for (int i = 0; i < 4; ++i) {  // Q = K^T P
            tmp.setZero();
            for (int j = 0; j <= n_stages; ++j)
              if (rk45::P[j][i] != 0.0) tmp += rk45::P[j][i] * K.col(j);
            F.col(i) = tmp;
          }
        }
        while (ip < pending.size() && pending[ip] <= t_new * (1 + 1e-15)) {
          double x = (pending[ip] - t_old) / h;
          if (dop) {
            ye.setZero();
            for (int i = dop853::INTERPOLATOR_POWER - 1, r = 0; i >= 0; --i, ++r) {
              ye += F.col(i);
              ye *= (r % 2 == 0) ? x : 1 - x;
            }
            ye += y;
          } else {
            double p = x;
            ye = y;
            for (int i = 0; i < 4; ++i, p *= x) ye += (h * p) * F.col(i);
          }
          output(pending[ip], ye);
          ++ip;
        }
      }
      t = t_new;
      y = y_new;
      f = f_new;
      check_finite(y.head(nv_), y.tail(nv_), t);
      if (projects) {
        Vec q = y.head(nv_), v = y.tail(nv_);
        project(q, v);
        y.head(nv_) = q;
        y.tail(nv_) = v;
        fun(t, y, f);
      }
      check_regular(y.head(nv_), t);
      if (!dense) output(t, y);
      poll(steps, t, progress);
    }
    return samples_dict(S, steps);
  }

 private:
  // Row r of a row table (kind, frames, vectors as the layer's RowTable), checked.
  Row make_row(int r, const Eigen::VectorXi &kinds, const Eigen::VectorXi &fid_p,
               const Eigen::VectorXi &fid_s, const Mat &vec1, const Mat &vec2) {
    if (kinds[r] < 0 || kinds[r] > 2) throw BadArgument{"Core: row kind must be 0, 1 or 2"};
    for (int f : {fid_p[r], fid_s[r]})
      if (f < 0 || f >= static_cast<int>(model_.nframes))
        throw BadArgument{"Core: frame id out of range"};
    Row row;
    row.kind = kinds[r];
    row.p = frame_index(fid_p[r]);
    row.s = frame_index(fid_s[r]);
    row.n = vec1.row(r).transpose();
    row.w = vec2.row(r).transpose();
    return row;
  }

  int frame_index(int fid) {
    for (std::size_t k = 0; k < fids_.size(); ++k)
      if (fids_[k] == static_cast<pinocchio::FrameIndex>(fid)) return static_cast<int>(k);
    fids_.push_back(static_cast<pinocchio::FrameIndex>(fid));
    return static_cast<int>(fids_.size() - 1);
  }

  void check_sizes(const Vec &q, const Vec &v) const {
    if (q.size() != nq_ || v.size() != nv_)
      throw BadArgument{"q must have shape (" + std::to_string(nq_) + ",) and v shape (" +
                        std::to_string(nv_) + ",)"};
  }

  // Per cut frame: the parent joint and the columns of its support, sized buffers.
  void frame_buffers() {
    const std::size_t nf = fids_.size();
    R_.resize(nf);
    p_.resize(nf);
    vf_.resize(nf, Eigen::Matrix<double, 6, 1>::Zero());
    af_.resize(nf, Eigen::Matrix<double, 6, 1>::Zero());
    fjoint_.resize(nf);
    fcols_.resize(nf);
    for (std::size_t k = 0; k < nf; ++k) {
      const pinocchio::JointIndex j = model_.frames[fids_[k]].parentJoint;
      fjoint_[k] = j;
      fcols_[k].clear();
      for (pinocchio::JointIndex s : model_.supports[j]) {
        if (s == 0) continue;
        for (int c = 0; c < model_.nvs[s]; ++c) fcols_[k].push_back(model_.idx_vs[s] + c);
      }
    }
  }

  // World placement (R_, p_) of every cut frame from data_.oMi.
  void placements() {
    for (std::size_t k = 0; k < fids_.size(); ++k) {
      const pinocchio::SE3 oMf = data_.oMi[fjoint_[k]] * model_.frames[fids_[k]].placement;
      R_[k] = oMf.rotation();
      p_[k] = oMf.translation();
    }
  }

  // Velocity vf_ and classical acceleration af_ (at a = 0) of every cut frame's
  // origin p, world axes (LOCAL_WORLD_ALIGNED), from its joint's world spatial
  // velocity (v_o, w) = data_.ov and bias acceleration (a_o, al) = data_.oa:
  //   v_p = v_o + w x p,   a_p = a_o + al x p + w x v_p   (linear; angular w, al).
  void frame_motion() {
    for (std::size_t k = 0; k < fids_.size(); ++k) {
      const pinocchio::Motion &ov = data_.ov[fjoint_[k]], &oa = data_.oa[fjoint_[k]];
      const Vector3d w = ov.angular(), al = oa.angular();
      const Vector3d vp = ov.linear() + w.cross(p_[k]);
      vf_[k].head<3>() = vp;
      vf_[k].tail<3>() = w;
      af_[k].head<3>() = oa.linear() + al.cross(p_[k]) + w.cross(vp);
      af_[k].tail<3>() = al;
    }
  }

  // Row J of `row` from the world Jacobian columns data_.J (of the last kinematics
  // pass) and the frame placements. A frame's LOCAL_WORLD_ALIGNED Jacobian at p
  // has, on its joint's support, linear columns J_lin + J_ang x p and angular
  // columns J_ang, so a row c . (linear) + e . (angular) of it is the 6-vector
  // (c, p x c + e) applied to the world columns: the row is that of the
  // predecessor frame minus that of the successor.
  //   kinds 0, 1: U^T (Jlin_p - Jlin_s) + [kind 1] (U x d)^T Jang_p,
  //   kind 2:     (W x U)^T (Jang_s - Jang_p).
  template <typename RowXpr>
  void row_jacobian(const Row &row, RowXpr &&out) {
    Eigen::Matrix<double, 6, 1> wp, ws;
    const int P = row.p, S = row.s;
    if (row.kind != 2) {
      const Vector3d U = row.kind == 0 ? row.n : Vector3d(R_[P] * row.n);
      wp.head<3>() = U;
      ws.head<3>() = U;
      wp.tail<3>() = p_[P].cross(U);
      if (row.kind == 1) wp.tail<3>() += U.cross(p_[P] - p_[S]);
      ws.tail<3>() = p_[S].cross(U);
    } else {
      const Vector3d WxU = (R_[S] * row.w).cross(R_[P] * row.n);
      wp.head<3>().setZero();
      ws.head<3>().setZero();
      wp.tail<3>() = -WxU;
      ws.tail<3>() = -WxU;
    }
    out.setZero();
    const Data::Matrix6x &Jw = data_.J;
    for (Eigen::Index c : fcols_[P]) out(c) += wp.dot(Jw.col(c));
    for (Eigen::Index c : fcols_[S]) out(c) -= ws.dot(Jw.col(c));
  }

  // Fill phi_, J_, gamma_ from the per-frame quantities.
  void rows(bool want_phi, bool want_J, bool want_gamma) {
    for (int r = 0; r < nc_; ++r) {
      const Row &row = rows_[r];
      const int P = row.p, S = row.s;
      if (want_J) row_jacobian(row, J_.row(r));
      if (row.kind != 2) {
        const Vector3d d = p_[P] - p_[S];
        const Vector3d U = row.kind == 0 ? row.n : Vector3d(R_[P] * row.n);
        if (want_phi) phi_[r] = U.dot(d);
        if (want_gamma) {
          const Vector3d dd = af_[P].head<3>() - af_[S].head<3>();
          double g = U.dot(dd);
          if (row.kind == 1) {
            const Vector3d wp = vf_[P].tail<3>(), alp = af_[P].tail<3>();
            const Vector3d Ud = wp.cross(U);
            const Vector3d Udd = alp.cross(U) + wp.cross(Ud);
            const Vector3d ddot = vf_[P].head<3>() - vf_[S].head<3>();
            g += Udd.dot(d) + 2.0 * Ud.dot(ddot);
          }
          gamma_[r] = g;
        }
      } else {
        const Vector3d U = R_[P] * row.n, W = R_[S] * row.w;
        const double UW = U.dot(W);
        if (want_phi) phi_[r] = UW;
        if (want_gamma) {
          const Vector3d WxU = W.cross(U);
          const Vector3d wp = vf_[P].tail<3>(), ws = vf_[S].tail<3>();
          const double pu = wp.dot(U), pw = wp.dot(W), su = ws.dot(U), sw = ws.dot(W);
          gamma_[r] = WxU.dot(af_[S].tail<3>() - af_[P].tail<3>()) + pu * pw + su * sw -
                      2.0 * pw * su - (wp - ws).squaredNorm() * UW;
        }
      }
    }
  }

  bp::object model_obj_;  // keeps the Python model alive
  const Model &model_;
  Data data_;
  std::string name_;
  int nq_ = 0, nv_ = 0, nc_ = 0;
  std::vector<Row> rows_;
  std::vector<pinocchio::FrameIndex> fids_;
  std::vector<pinocchio::JointIndex> fjoint_;  // parent joint of each of fids_
  std::vector<std::vector<Eigen::Index>> fcols_;  // its support's columns
  std::vector<Eigen::Matrix3d> R_;
  std::vector<Vector3d> p_;
  std::vector<Eigen::Matrix<double, 6, 1>> vf_, af_;
  Mat M_, J_, K_, Y_, D_, Mr_, JJt_;
  Vec est_x_, est_y_, est_z_, z_;
  Vec h_, phi_, gamma_, a_, lam_, tau_, tau_const_, zero_v_, rhs_, x_, dq_, tmp_c_, tmp_v_;
  Eigen::LLT<Mat> llt_m_, llt_c_, llt_r_;
  SmallLLT llt_p_, llt_jj_;  // M + alpha J^T J; J J^T (+ regularization)
  Mat P_;
  Vec rhs_v_, q_prev_, vel_c_, rhs_work_;
  std::vector<int> piv_;  // row swaps of lu_factor
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
  double dropped_tol_ = 1e-9, dropped_ratio_ = 100.0;
  std::vector<Row> drows_;  // every declared row
  std::vector<std::string> dlabels_;
  Eigen::VectorXi dkept_;
  Vec dphi_;
  Vec J_at_;  // the q of the last eval_phi_J (J_, phi_ and the placements valid there)
  bool J_at_valid_ = false;
  Eigen::VectorXi branch_cols_;  // set_branch_columns
  Mat JD_;
  Vec terms_q_, terms_v_;  // (q, v) of the last eval_terms (M_, pe_ valid there)
  double pe_ = 0.0;
  int tau_mode_ = 0;
  bp::object tau_obj_, np_asarray_;
  long n_evals_ = 0;
};

}  // namespace closedchain

BOOST_PYTHON_MODULE(_core) {
  using namespace closedchain;
  bp::import("pinocchio");
  eigenpy::enableEigenPy();
  eigenpy::enableEigenPySpecific<Eigen::VectorXi>();
  bp::register_exception_translator<SingularError>(&translate_singular);
  bp::register_exception_translator<SimulationFailure>(&translate_simulation);
  bp::register_exception_translator<BadArgument>(&translate_bad);
  register_lean_data();
  bp::register_exception_translator<RowCheckRequired>(&translate_row_check);
  bp::scope().attr("EULER") = static_cast<int>(EULER);
  bp::scope().attr("SEMI_IMPLICIT") = static_cast<int>(SEMI_IMPLICIT);
  bp::scope().attr("RK4") = static_cast<int>(RK4);
  bp::scope().attr("RK45") = static_cast<int>(RK45);
  bp::scope().attr("DOP853") = static_cast<int>(DOP853);
  bp::class_<Core, boost::noncopyable>(
      "Core",
      "Compiled constraint rows, forward dynamics and integration loops of one mechanism.",
      bp::init<bp::object, std::string, Eigen::VectorXi, Eigen::VectorXi, Eigen::VectorXi,
               Eigen::MatrixXd, Eigen::MatrixXd>(
          bp::args("self", "model", "name", "kinds", "fid_p", "fid_s", "vec1", "vec2")))
      .def("configure", &Core::configure, bp::args("self", "settings"))
      .def("set_tau", &Core::set_tau, bp::args("self", "tau"))
      .def("set_declared", &Core::set_declared,
           bp::args("self", "kinds", "fid_p", "fid_s", "vec1", "vec2", "kept", "labels"),
           "Every declared row (kept[i] = 1 for the rows the methods use), checked each step.")
      .def("rows", &Core::py_rows, bp::args("self", "q", "v"),
           "(phi, J, gamma) at (q, v); gamma includes the Baumgarte terms when configured.")
      .def("forward", &Core::py_forward, bp::args("self", "q", "v", "tau"), "(a, lam) at (q, v).")
      .def("repeat", &Core::py_repeat, bp::args("self", "q", "v", "tau", "n"),
           "a at (q, v) after n evaluations inside C++ (timing).")
      .def("profile", &Core::py_profile, bp::args("self", "q", "v", "tau", "n"),
           "Mean time [ns] of each stage of one evaluation (profiling).")
      .def("set_branch_columns", &Core::set_branch_columns, bp::args("self", "cols"),
           "Record the sign of det(J[:, cols]) with every sample ('branch'); cols: (nc,) or empty.")
      .def("run_fixed", &Core::run_fixed,
           bp::args("self", "integrator", "q0", "v0", "dt", "n_steps", "out_steps", "projects",
                    "progress"))
      .def("run_adaptive", &Core::run_adaptive,
           bp::args("self", "integrator", "q0", "v0", "t_final", "rtol", "atol", "t_eval",
                    "projects", "progress"))
      .add_property("nc", &Core::nc)
      .add_property("n_evals", &Core::n_evals);
}
