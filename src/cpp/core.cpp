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

#include "dense_lu.hpp"
#include "banded.hpp"
#include "lean_data.hpp"
#include "rk_coefficients.hpp"
#include "small_llt.hpp"
#include "tree_terms.hpp"
#include "stage_terms.hpp"
#include "al_iteration.hpp"

namespace bp = boost::python;

namespace closedchain {

using Model = pinocchio::Model;
using Data = pinocchio::Data;
using Vec = Eigen::VectorXd;
using Mat = Eigen::MatrixXd;
using Mat6x = Eigen::Matrix<double, 6, Eigen::Dynamic>;
using Eigen::Vector3d;
using RefV = Eigen::Ref<const Vec>;
using SmallMat = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, 0, 6, 6>;  // no heap

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

//: rk4 with stage projection near singular positions: the constants of
//: closedchain/simulate/fixed.py (RANK_INDICATOR_CAP, RETAKE_GRID, CROSSING_FIT_RTOL,
//: RANK_INDICATOR_ITERS).
constexpr double RANK_INDICATOR_CAP = 1e-2;
constexpr int RETAKE_GRID = 40;
constexpr double CROSSING_FIT_RTOL = 0.5;
constexpr int RANK_INDICATOR_ITERS = 4;

//: Relative margin of the Cholesky inverse-norm bound (min_norm) over its own round-off.
constexpr double INVERSE_BOUND_MARGIN = 1e-8;

//: How to pass singular positions (simulate.problem.passing_hint with the registries
//: of this build), appended to the partitioning stabilization's singular errors.
static const char *const PASSING_HINT =
    "to pass singular positions use method='augmented-lagrangian' with "
    "stabilization='stage-projection' (and a fixed-step integrator)";

enum Method { KKT = 0, SCHUR = 1, NULLSPACE = 2, AUGMENTED_LAGRANGIAN = 3, REDUCED = 4 };
enum Integrator { EULER = 0, SEMI_IMPLICIT = 1, RK4 = 2, RK45 = 3, DOP853 = 4 };

}  // namespace closedchain

#include "ali3p.hpp"  // after the errors and fmt it uses

namespace closedchain {

struct Row {
  int kind;  // 0 world translation, 1 translation along n in c1, 2 rotation
  int p, s;  // indices into the Core's frame list
  Vector3d n;  // n (kinds 0, 1) or u (kind 2)
  Vector3d w;  // w (kind 2)
};

class Core {
  template <class> friend class Ali3pLoop;  // the ALI3-P loop (ali3p.hpp)

 public:
  Core(bp::object model_obj, const std::string &name, const Eigen::VectorXi &kinds,
       const Eigen::VectorXi &fid_p, const Eigen::VectorXi &fid_s, const Mat &vec1,
       const Mat &vec2)
      : model_obj_(model_obj),
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
    x_ = Vec::Zero(nv_ + nc_);
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

  // Structural nonzeros, from the kinematic tree: row r of J is nonzero only on the
  // columns of the joints supporting its two frames (jcols_ from jcol_start_[r],
  // sorted; hull [jlo_[r], jhi_[r]]), row i of M on those of the joints that support
  // or are supported by i's joint (hull [mlo_[i], mhi_[i]]). The rules of
  // closedchain/dynamics/augmented_lagrangian.py (structure, row_structure).
  void sparsity() {
    const Model &model = model_;
    auto support_cols = [&](pinocchio::JointIndex j, std::vector<int> &cols) {
      for (pinocchio::JointIndex s : model.supports[j]) {
        if (s == 0) continue;
        for (int c = 0; c < model.joints[s].nv(); ++c) cols.push_back(model.joints[s].idx_v() + c);
      }
    };
    jcol_start_.assign(1, 0);
    jcols_.clear();
    jlo_.assign(nc_, 0);
    jhi_.assign(nc_, nv_ ? nv_ - 1 : 0);
    for (int r = 0; r < nc_; ++r) {
      std::vector<int> cols;
      support_cols(model.frames[fids_[rows_[r].p]].parentJoint, cols);
      support_cols(model.frames[fids_[rows_[r].s]].parentJoint, cols);
      std::sort(cols.begin(), cols.end());
      cols.erase(std::unique(cols.begin(), cols.end()), cols.end());
      jcols_.insert(jcols_.end(), cols.begin(), cols.end());
      jcol_start_.push_back(static_cast<int>(jcols_.size()));
      if (!cols.empty()) {
        jlo_[r] = cols.front();
        jhi_[r] = cols.back();
      } else {  // a row on two frames of the base: J row zero
        jlo_[r] = 0;
        jhi_[r] = -1;
      }
    }
    mlo_.assign(nv_, 0);
    mhi_.assign(nv_, 0);
    for (pinocchio::JointIndex j = 1; j < static_cast<pinocchio::JointIndex>(model.njoints); ++j) {
      int lo = model.joints[j].idx_v(), hi = lo + model.joints[j].nv() - 1;
      for (pinocchio::JointIndex s : model.supports[j])
        if (s != 0) lo = std::min(lo, model.joints[s].idx_v());
      for (pinocchio::JointIndex s : model.subtrees[j])
        hi = std::max(hi, model.joints[s].idx_v() + model.joints[s].nv() - 1);
      for (int c = 0; c < model.joints[j].nv(); ++c) {
        mlo_[model.joints[j].idx_v() + c] = lo;
        mhi_[model.joints[j].idx_v() + c] = hi;
      }
    }
  }

  // Choose the band paths (closedchain.compiled.make_core, from PenalizedSolver and
  // NormalSolver): banded_p factorizes M + alpha J^T J in the order perm (perm[k] =
  // the column at position k) as a band, banded_n the normal equations J J^T in the
  // natural row order. Returns the half bandwidths (b_p, b_n) of the structure in
  // those orders (the Python side's bandwidths, checked by the tests).
  bp::tuple set_band(const Eigen::VectorXi &perm, bool banded_p, bool banded_n) {
    if (perm.size() != nv_) throw BadArgument{"Core.set_band: perm must have shape (nv,)"};
    perm_.assign(perm.data(), perm.data() + nv_);
    pinv_.assign(nv_, -1);
    for (int k = 0; k < nv_; ++k) {
      if (perm_[k] < 0 || perm_[k] >= nv_ || pinv_[perm_[k]] >= 0)
        throw BadArgument{"Core.set_band: perm must be a permutation of range(nv)"};
      pinv_[perm_[k]] = k;
    }
    perm_identity_ = true;
    for (int k = 0; k < nv_; ++k) perm_identity_ = perm_identity_ && perm_[k] == k;
    int b_p = 0;  // M's pattern and J^T J's, in the order perm
    for (int i = 0; i < nv_; ++i)
      for (int c = mlo_[i]; c <= mhi_[i]; ++c)
        if (M_structural(i, c)) b_p = std::max(b_p, std::abs(pinv_[i] - pinv_[c]));
    for (int r = 0; r < nc_; ++r)
      for (int x = jcol_start_[r]; x < jcol_start_[r + 1]; ++x)
        for (int y = jcol_start_[r]; y < jcol_start_[r + 1]; ++y)
          b_p = std::max(b_p, std::abs(pinv_[jcols_[x]] - pinv_[jcols_[y]]));
    int b_n = 0;  // rows sharing a column
    for (int r = 0; r < nc_; ++r)
      for (int s2 = 0; s2 < r; ++s2)
        if (r - s2 > b_n && rows_share_column(r, s2)) b_n = r - s2;
    b_p_ = b_p;
    b_n_ = b_n;
    band_p_ = banded_p && nc_ > 0;
    band_n_ = banded_n && nc_ > 0;
    if (band_p_) {
      bp_.resize(nv_, b_p);
      pw_ = Vec::Zero(nv_);
    }
    if (band_n_) bn_.resize(nc_, b_n);
    invalidate_kinematics();
    return bp::make_tuple(b_p, b_n);
  }

  // M(i, c) structurally nonzero: one of the two joints supports the other.
  bool M_structural(int i, int c) const {
    const pinocchio::JointIndex ji = col_joint(i), jc = col_joint(c);
    const auto &si = model_.supports[ji], &sc = model_.supports[jc];
    return std::find(si.begin(), si.end(), jc) != si.end() ||
           std::find(sc.begin(), sc.end(), ji) != sc.end();
  }

  pinocchio::JointIndex col_joint(int c) const {
    for (pinocchio::JointIndex j = 1; j < static_cast<pinocchio::JointIndex>(model_.njoints); ++j)
      if (c >= model_.joints[j].idx_v() && c < model_.joints[j].idx_v() + model_.joints[j].nv())
        return j;
    return 0;
  }

  bool rows_share_column(int r, int s2) const {
    for (int x = jcol_start_[r]; x < jcol_start_[r + 1]; ++x)
      for (int y = jcol_start_[s2]; y < jcol_start_[s2 + 1]; ++y)
        if (jcols_[x] == jcols_[y]) return true;
    return false;
  }

  bp::tuple band_info() const { return bp::make_tuple(band_p_, band_n_, b_p_, b_n_); }

  // -- products on the structure (the band paths) ------------------------------

  // y = J x over each row's column hull.
  void j_mul(const Vec &x, Vec &y) const {
    for (int r = 0; r < nc_; ++r) {
      const int lo = jlo_[r], len = jhi_[r] - jlo_[r] + 1;
      y[r] = len > 0 ? J_.row(r).segment(lo, len).dot(x.segment(lo, len)) : 0.0;
    }
  }

  // x = J^T y (x overwritten).
  void jt_mul(const Vec &y, Vec &x) const {
    x.setZero();
    for (int r = 0; r < nc_; ++r) {
      const int lo = jlo_[r], len = jhi_[r] - jlo_[r] + 1;
      if (len > 0) x.segment(lo, len) += y[r] * J_.row(r).segment(lo, len).transpose();
    }
  }

  // y -= M x over each row's hull.
  void m_mul_sub(const Vec &x, Vec &y) const {
    for (int i = 0; i < nv_; ++i) {
      const int lo = mlo_[i], len = mhi_[i] - mlo_[i] + 1;
      y[i] -= M_.row(i).segment(lo, len).dot(x.segment(lo, len));
    }
  }

  // sum of J_ij^2
  double j_squared_norm() const {
    double s = 0.0;
    for (int r = 0; r < nc_; ++r) {
      const int lo = jlo_[r], len = jhi_[r] - jlo_[r] + 1;
      if (len > 0) s += J_.row(r).segment(lo, len).squaredNorm();
    }
    return s;
  }

  // Factorize P = M + alpha J^T J as a band in the order perm_.
  bool factor_penalized_band(double alpha) {
    const int b = bp_.bandwidth();
    Mat &A = bp_.A;
    for (int j = 0; j < nv_; ++j)
      for (int k = 0; k <= b; ++k) A(k, j) = j + k < nv_ ? M_(perm_[j + k], perm_[j]) : 0.0;
    for (int r = 0; r < nc_; ++r)
      for (int x = jcol_start_[r]; x < jcol_start_[r + 1]; ++x) {
        const int cx = jcols_[x], px = pinv_[cx];
        const double ax = alpha * J_(r, cx);
        for (int y = jcol_start_[r]; y < jcol_start_[r + 1]; ++y) {
          const int cy = jcols_[y], py = pinv_[cy];
          if (px >= py) A(px - py, py) += ax * J_(r, cy);
        }
      }
    return bp_.factor();
  }

  // x <- P^-1 x on the band factor.
  void solve_penalized_band(Vec &x) {
    if (perm_identity_) {
      bp_.solve_in_place(x);
      return;
    }
    for (int k = 0; k < nv_; ++k) pw_[k] = x[perm_[k]];
    bp_.solve_in_place(pw_);
    for (int k = 0; k < nv_; ++k) x[perm_[k]] = pw_[k];
  }

  // Assemble J J^T + eps I as a band (natural row order), eps = rel_reg max(tr(J J^T), 1)
  // / nc (0: none), and factorize it.
  bool factor_normal_band(double rel_reg) {
    assemble_normal_band(rel_reg);
    return bn_.factor();
  }

  void assemble_normal_band(double rel_reg) {
    const int b = bn_.bandwidth();
    Mat &A = bn_.A;
    for (int j = 0; j < nc_; ++j)
      for (int k = 0; k <= b; ++k) {
        const int i = j + k;
        double v = 0.0;
        if (i < nc_) {
          const int lo = std::max(jlo_[i], jlo_[j]), hi = std::min(jhi_[i], jhi_[j]);
          if (hi >= lo)
            v = J_.row(i).segment(lo, hi - lo + 1).dot(J_.row(j).segment(lo, hi - lo + 1));
        }
        A(k, j) = v;
      }
    if (rel_reg != 0.0)
      A.row(0).array() += rel_reg * std::max(A.row(0).sum(), 1.0) / static_cast<double>(nc_);
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
    else if (m == "reduced")
      method_ = REDUCED;
    else
      throw BadArgument{"compiled core: unknown method '" + m +
                        "'; compiled: kkt, schur, nullspace, augmented-lagrangian, reduced"};
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
    singular_zone_ = bp::extract<double>(s.get("singular_zone", 0.0));
    stage_zone_ = bp::extract<double>(s.get("stage_singular_zone", 0.0));
    singular_robust_ = bp::extract<bool>(s.get("singular_robust", false));
    dropped_tol_ = bp::extract<double>(s.get("dropped_row_tol", 1e-9));
    dropped_ratio_ = bp::extract<double>(s.get("dropped_row_ratio", 100.0));
    configure_partitioning(s);
    invalidate_kinematics();  // the kept factor of M + alpha J^T J has the old al_penalty
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
    invalidate_kinematics();
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

  // data_'s kinematics, J_ and M_ no longer known to be at J_at_; the factor of
  // M + alpha J^T J dropped.
  void invalidate_kinematics() {
    J_at_valid_ = false;
    m_at_J_ = false;
    p_fact_ = false;
  }

  // phi only: placements from the kinematics pass (tree_terms.hpp's joint_kinematics,
  // the same placements as eval_phi_J and eval_terms).
  void eval_phi(const RefV &q) {
    invalidate_kinematics();
    joint_kinematics(plan_, model_, data_, q);
    placements();
    rows(true, false, false);
  }

  // phi and J: joint_kinematics(q) (placements and world joint Jacobians, as
  // pinocchio::computeJointJacobians; revolute joints by tree_terms.hpp's own path).
  // Each step asks several times at one q (projection, regularity check, declared
  // rows, output): the last evaluation is reused while q is the same.
  void eval_phi_J(const RefV &q) {
    if (J_at_valid_ && q == J_at_) return;
    invalidate_kinematics();
    joint_kinematics(plan_, model_, data_, q);
    placements();
    rows(true, true, false);
    J_at_ = q;
    J_at_valid_ = true;
  }

  // eval_phi_J at a trial point of the dependent solve, which moves only the
  // dependent coordinates dep_: when the kinematics in data_ (J_at_) agree with q on
  // every independent coordinate, the joints whose supports hold no dependent
  // coordinate keep their placements and Jacobian columns (the same values a full
  // pass computes: same inputs, same arithmetic) and only the others are recomputed.
  void eval_phi_J_trial(const Vec &q) {
    bool same = J_at_valid_ && nq_ == nv_;  // coordinates are velocity indices
    for (std::size_t k = 0; same && k < ind_.size(); ++k) same = J_at_[ind_[k]] == q[ind_[k]];
    if (!same || q == J_at_) return eval_phi_J(q);
    if (moved_for_ != dep_) {  // the joints moved by dep_ (allocates: once per partition)
      moved_for_ = dep_;
      moved_.assign(static_cast<std::size_t>(model_.njoints), 0);
      std::vector<char> is_dep(static_cast<std::size_t>(nv_), 0);
      for (int d : dep_) is_dep[static_cast<std::size_t>(d)] = 1;
      for (std::size_t j = 1; j < static_cast<std::size_t>(model_.njoints); ++j) {
        char m = moved_[model_.parents[j]];
        for (int c = 0; c < model_.nvs[j]; ++c) m |= is_dep[model_.idx_vs[j] + c];
        moved_[j] = m;
      }
    }
    invalidate_kinematics();
    joint_kinematics(plan_, model_, data_, q, &moved_);
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
  //
  // When the last kinematics pass was at q (eval_phi_J(q): the dependent solve of
  // the partitioning stabilization ends there), data_ already holds the joints'
  // placements and Jacobian columns and phi_, J_ and the frame placements are
  // those of q: only the velocity-dependent part of the tree pass and gamma are
  // computed (tree_terms_at_kinematics; the same arithmetic, the same results); when
  // M_ is at q too (m_at_J_: the stage projection's velocity step computed it, or an
  // evaluation at q with another v), only h (bias_at_kinematics, stage_terms.hpp),
  // and M_ and the factor of M + alpha J^T J (p_fact_) stay.
  template <class Mark>
  void eval_terms(const RefV &q, const RefV &v, Mark &&mark) {
    if (J_at_valid_ && q == J_at_) {
      if (m_at_J_) {
        bias_at_kinematics(plan_, model_, data_, q, v, h_);
      } else {
        tree_terms_at_kinematics(plan_, model_, data_, q, v, M_, h_);
        m_at_J_ = true;
        p_fact_ = false;
      }
      mark(0);
      frame_motion();
      mark(1);
      rows(false, false, true);
    } else {
      invalidate_kinematics();
      tree_terms(plan_, model_, data_, q, v, M_, h_);
      mark(0);
      placements();
      frame_motion();
      mark(1);
      rows(true, true, true);
    }
    if (baumgarte_ && nc_) {
      tmp_c_.noalias() = J_ * v;
      gamma_ += (2.0 * alpha_) * tmp_c_ + (beta_ * beta_) * phi_;
    }
    // phi_, J_ and the placements are those eval_phi_J(q) would compute; M_ and the
    // potential energy (total mass and centre of mass in data_.oYcrb[0]) serve record().
    J_at_ = q;
    J_at_valid_ = true;
    m_at_J_ = true;
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
      case REDUCED: solve_reduced(q, tau, t); break;
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
    rhs_v_ = tau - h_;
    if (!band_p_ && solve_al_small<1, 1>(q, t)) return;
    al_solve(q, t, rhs_v_, gamma_, a_);
    if (band_p_) {  // the multiplier polish on the band normal equations
      tmp_v_ = rhs_v_;
      m_mul_sub(a_, tmp_v_);
      jt_mul(lam_, dq_);
      tmp_v_ -= dq_;  // r_d
      j_mul(tmp_v_, tmp_c_);
      if (band_n_ && factor_normal_band(AL_NORMAL_EQ_REG)) {
        bn_.solve_in_place(tmp_c_);
      } else {  // dense normal equations (no narrow row band, or the band factor failed)
        JJt_.noalias() = J_ * J_.transpose();
        JJt_.diagonal().array() +=
            AL_NORMAL_EQ_REG * std::max(JJt_.trace(), 1.0) / static_cast<double>(nc_);
        llt_c_.compute(JJt_);
        llt_c_.solveInPlace(tmp_c_);
      }
      lam_ += tmp_c_;
      return;
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

  // solve_al for nv <= AL_FIXED_MAX (the 4-bar: nv 3, nc 2) on fixed-size matrices:
  // the same iteration (al_iterate), penalty, acceptance test of P's Cholesky and
  // multiplier polish, with Eigen's unrolled fixed-size products and small_llt.hpp's
  // FixedLDLT in place of the dynamic-size ones (in the C++ loop, 4-bar: about 4,300
  // instructions of the dynamic path's 10,000 per evaluation are the solve). The results differ from the
  // dynamic path by round-off. P is factored here each time (a few dozen operations);
  // the factor kept for the stage projection (p_fact_, llt_p_) is left as it is.
  // Returns false when (nv, nc) is not among the sizes compiled.
  static constexpr int AL_FIXED_MAX = 6;

  template <int NV, int NC>
  bool solve_al_small(const RefV &q, double t) {
    if constexpr (NV > AL_FIXED_MAX) {
      return false;
    } else {
      if (nv_ != NV || nc_ != NC) {
        if constexpr (NC < NV)
          return solve_al_small<NV, NC + 1>(q, t);
        else
          return solve_al_small<NV + 1, 1>(q, t);
      }
      using MatN = Eigen::Matrix<double, NV, NV>;
      using MatC = Eigen::Matrix<double, NC, NC>;
      using MatJ = Eigen::Matrix<double, NC, NV>;
      using VecN = Eigen::Matrix<double, NV, 1>;
      using VecC = Eigen::Matrix<double, NC, 1>;
      struct Ops {
        const Eigen::Map<const MatN> &M;
        const Eigen::Map<const MatJ> &J;
        const FixedLDLT<NV> &llt;
        void add_j(const VecN &x, VecC &y) { y.noalias() += J * x; }
        void sub_m(const VecN &x, VecN &y) { y.noalias() -= M * x; }
        void sub_jt(const VecC &y, VecN &x) { x.noalias() -= J.transpose() * y; }
        void sub_scaled_jt(double s, const VecC &y, VecN &x) {
          x.noalias() -= s * (J.transpose() * y);
        }
        void solve(VecN &x) { llt.solveInPlace(x); }
      };
      const Eigen::Map<const MatN> M(M_.data());
      const Eigen::Map<const MatJ> J(J_.data());
      const double alpha =
          al_penalty_ * M.trace() / std::max(J.squaredNorm(), std::numeric_limits<double>::min());
      FixedLDLT<NV> llt;
      if (!llt.compute(M + alpha * (J.transpose() * J)))
        singular(q, "the penalized mass matrix M + alpha J^T J",
                 std::numeric_limits<double>::infinity(),
                 "it is not positive definite, so M itself is singular (a massless subtree)", t);
      Ops ops{M, J, llt};
      const VecN rhs = rhs_v_;
      const VecC g = gamma_;
      VecN x, delta;
      VecC lam, rc;
      al_iterate(ops, alpha, rhs, g, al_max_iter_, al_tol_, x, lam, delta, rc);
      // the multiplier polish: J J^T dlam = J (rhs - M a - J^T lam), regularized
      const VecN rd = rhs - M * x - J.transpose() * lam;
      MatC JJt = J * J.transpose();
      JJt.diagonal().array() += AL_NORMAL_EQ_REG * std::max(JJt.trace(), 1.0) / double(NC);
      FixedLDLT<NC> llt_c;
      if (!llt_c.compute(JJt)) return false;  // the dynamic path decides
      VecC dlam = J * rd;
      llt_c.solveInPlace(dlam);
      lam += dlam;
      a_ = x;
      lam_ = lam;
      return true;
    }
  }

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

  // P = M + alpha J^T J at the last evaluation with alpha = al_penalty tr(M) / tr(J^T J),
  // factored (dense SmallLLT of P's lower triangle, or the band Cholesky) unless
  // the factor of these M_ and J_ is kept (p_fact_); returns alpha.
  double al_factor(const RefV &q, double t) {
    const double jj = band_p_ ? j_squared_norm() : J_.squaredNorm();
    const double alpha = al_penalty_ * M_.trace() / std::max(jj, std::numeric_limits<double>::min());
    if (p_fact_) return alpha;
    bool ok;
    if (band_p_) {
      ok = factor_penalized_band(alpha);
    } else {
      P_.triangularView<Eigen::Lower>() = J_.transpose().lazyProduct(J_);
      P_.triangularView<Eigen::Lower>() = alpha * P_ + M_;
      ok = llt_p_.compute(P_);
    }
    if (!ok)
      singular(q, "the penalized mass matrix M + alpha J^T J",
               std::numeric_limits<double>::infinity(),
               "it is not positive definite, so M itself is singular (a massless subtree)", t);
    p_fact_ = true;
    return alpha;
  }

  // The augmented-Lagrangian iteration (al_iterate) at the last evaluation: x and
  // lam_ with M x + J^T lam = rhs, J x + g = 0 (to al_tol), no multiplier polish;
  // from_x: start from x as given (al_iterate).
  void al_solve(const RefV &q, double t, const Vec &rhs, const Vec &g, Vec &x,
                bool from_x = false) {
    const double alpha = al_factor(q, t);
    if (band_p_) {
      BandAlOps ops{*this};
      al_iterate(ops, alpha, rhs, g, al_max_iter_, al_tol_, x, lam_, dq_, tmp_c_, from_x);
    } else {
      DenseAlOps ops{*this};
      al_iterate(ops, alpha, rhs, g, al_max_iter_, al_tol_, x, lam_, dq_, tmp_c_, from_x);
    }
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
    // K = [[M, J^T], [J, 0]] column by column (written out: the block assignments cost
    // more than the copy at these sizes), factored in place by DenseLU (dense_lu.hpp).
    const Eigen::Index nv = nv_, nc = nc_, n = nv + nc;
    double *k = kkt_.A.data();
    for (Eigen::Index j = 0; j < nv; ++j) {
      double *col = k + j * n;
      for (Eigen::Index i = 0; i < nv; ++i) col[i] = M_(i, j);
      for (Eigen::Index r = 0; r < nc; ++r) col[nv + r] = J_(r, j);
    }
    for (Eigen::Index r = 0; r < nc; ++r) {
      double *col = k + (nv + r) * n;
      for (Eigen::Index i = 0; i < nv; ++i) col[i] = J_(r, i);
      for (Eigen::Index i = nv; i < n; ++i) col[i] = 0.0;
    }
    for (Eigen::Index i = 0; i < nv; ++i) x_[i] = tau[i] - h_[i];
    for (Eigen::Index r = 0; r < nc; ++r) x_[nv + r] = -gamma_[r];
    // An exactly singular K leaves a zero pivot: rcond 0 (as LAPACK's info > 0).
    // Away from singular configurations a cheap upper bound of cond_1(K) already
    // shows that the dgecon-style estimate (a lower bound of it) cannot exceed
    // cond_max; only otherwise is the estimate computed.
    if (!kkt_.factor_in_place()) {
      check_rcond(q, "the KKT matrix [[M, J^T], [J, 0]]", 0.0, t);
    } else if (!(kkt_.anorm * kkt_.inverse_norm_bound() <= cond_max_)) {
      check_rcond(q, "the KKT matrix [[M, J^T], [J, 0]]", kkt_.rcond(), t);
    }
    kkt_.solve(x_);
    a_ = x_.head(nv_);
    lam_ = x_.tail(nc_);
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
    invalidate_kinematics();  // one whole evaluation per call
    solve(q, v, tau, std::numeric_limits<double>::quiet_NaN());
    return bp::make_tuple(Vec(a_), Vec(lam_));
  }

  // a at (q, v) for n_eval repetitions inside C++ (the per-evaluation cost in the loop).
  Vec py_repeat(const Vec &q, const Vec &v, const Vec &tau, int n) {
    check_sizes(q, v);
    for (int i = 0; i < n; ++i) {
      invalidate_kinematics();  // a whole evaluation each time (not the kinematics' reuse)
      solve(q, v, tau, std::numeric_limits<double>::quiet_NaN());
    }
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

  // True when cond_2(J) < limit is certain, in O(nc b^2) on the band of A = J J^T
  // (band_n_): lambda_max(A) <= ||A||_1, and A - (||A||_1 / limit^2) I is positive
  // definite (its Cholesky factor exists) iff lambda_min(A) > ||A||_1 / limit^2
  // (Sylvester's law of inertia), which gives cond_2(J)^2 = lambda_max / lambda_min
  // < limit^2. False means "not certain": cond_J() decides (only within a factor
  // sqrt(||A||_1 / lambda_max) <= sqrt(nc) of the limit, i.e. near singular positions).
  bool cond_J_below(double limit) {
    const int b = bn_.bandwidth();
    assemble_normal_band(0.0);
    Mat &A = bn_.A;
    double anorm = 0.0;
    for (int j = 0; j < nc_; ++j) {
      double s = 0.0;
      for (int k = 0; k <= b && j + k < nc_; ++k) s += std::abs(A(k, j));
      for (int k = 1; k <= b && j - k >= 0; ++k) s += std::abs(A(k, j - k));
      anorm = std::max(anorm, s);
    }
    if (!(anorm > 0.0) || !std::isfinite(anorm)) return false;
    A.row(0).array() -= anorm / (limit * limit);
    return bn_.factor();
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
    if (singular_robust_ || rows_only_ || nc_ == 0) return;
    if (band_n_ && cond_J_below(singular_cond_)) return;
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
    if (band_n_) {
      // The same test and solve on the band of J J^T. Where it is ill-conditioned the
      // SVD below, as the dense path: the numpy backend's regularized normal equations
      // (J J^T + eps I) there were measured less accurate through the N-four-bar's
      // flat positions (N = 10, 20 s: B0 error 2.2e-6 m against 3.1e-8 m) and barely
      // cheaper (N = 40: 5 %).
      if (factor_normal_band(0.0) && bn_.rcond() > MIN_NORM_RCOND) {
        tmp_c_ = b;
        bn_.solve_in_place(tmp_c_);
        jt_mul(tmp_c_, x);
        return;
      }
    } else {
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
    }
    min_norm_svd(b, x);
  }

  // numpy.linalg.lstsq's minimum-norm solution of J x = b (dense SVD of J: only where
  // J J^T is ill-conditioned, i.e. within a step or two of a singular position).
  void min_norm_svd(const Vec &b, Vec &x) {
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
  // With mass_orth (the stage projection; problem.project's mass_orthogonal) v is
  // projected in the metric of M: the augmented-Lagrangian iteration (al_solve) at q
  // with right-hand side M v and g = 0. Only where the run passes singular positions
  // (singular_robust_), as problem.project. M_ (mass_at_kinematics: no velocity pass)
  // and the factor of M + alpha J^T J are then those of q and stay for the evaluation
  // at q that follows (eval_terms: the bias forces only; solve_al: no second
  // factorization); lam_ is overwritten.
  void project(Vec &q, Vec &v, bool mass_orth = false) {
    mass_orth = mass_orth && singular_robust_;
    if (nc_ == 0) return;
    for (int it = 0; it < projection_iters_; ++it) {
      eval_phi_J(q);
      if (phi_.cwiseAbs().maxCoeff() <= projection_tol_) break;
      tmp_c_ = -phi_;
      min_norm(tmp_c_, dq_);
      q_prev_ = q;
      pinocchio::integrate(model_, q_prev_, dq_, q);
    }
    if (project_velocities_ && mass_orth) {
      eval_phi_J(q);
      if (!m_at_J_) {
        mass_at_kinematics(plan_, model_, data_, M_);
        m_at_J_ = true;
        p_fact_ = false;
        terms_q_.setConstant(std::numeric_limits<double>::quiet_NaN());  // M_, not pe_
      }
      mv_.noalias() = M_ * v;
      // From v itself (problem.project's a0): its correction is small here.
      al_solve(q, std::numeric_limits<double>::quiet_NaN(), mv_, zero_c_, v, true);
    } else if (project_velocities_) {
      eval_phi_J(q);
      if (band_n_)
        j_mul(v, vel_c_);
      else
        vel_c_.noalias() = J_ * v;
      min_norm(vel_c_, dq_);
      v -= dq_;
    }
  }

  // -- the reduced method and coordinate partitioning ---------------------------
  //
  // Same math as closedchain/dynamics/reduced.py (the method) and simulate/problem.py,
  // fixed.py, adaptive.py (the stabilization). Two partitions are kept: the method's,
  // mech.independent_idx_v for the whole run (as the numpy method), and the
  // stabilization's, which re-partitioning changes.

  void init_partitioning() {
    const int m = std::max(nv_ - nc_, 0);
    JD_ = Mat::Zero(nc_, nc_);
    lu_jd_.resize(nc_);
    Sred_ = Mat::Zero(nv_, m);
    MS_ = Mat::Zero(nv_, m);
    cred_ = Vec::Zero(nv_);
    fred_ = Vec::Zero(nv_);
    aI_ = Vec::Zero(m);
    svd_jd_ = Eigen::JacobiSVD<Mat>(nc_, nc_);
    svd_jd_uv_ = Eigen::JacobiSVD<Mat>(nc_, nc_, Eigen::ComputeFullU | Eigen::ComputeFullV);
    phi_n_ = Vec::Zero(nc_);
    phi_best_ = Vec::Zero(nc_);
    step_c_ = Vec::Zero(nc_);
    q_try_ = Vec::Zero(nq_);
    q_best_ = Vec::Zero(nq_);
    dv_n_ = Vec::Zero(nv_);
    warm_q_ = Vec::Zero(nq_);
    fq_ = Vec::Zero(nq_);
    fv_ = Vec::Zero(nv_);
    Xwarm_ = Mat::Zero(nc_, m);
    qD0_ = KD0_ = qD_end_ = qD_new_ = vD_last_ = guess_qD_ = Vec::Zero(nc_);
    dqI_ = Vec::Zero(m);
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

  // ind: the independent velocity indices; dep: the others, both sorted.
  void set_indices(std::vector<int> ind, std::vector<int> &ind_out, std::vector<int> &dep_out) {
    std::sort(ind.begin(), ind.end());
    ind_out = ind;
    dep_out.clear();
    for (int i = 0; i < nv_; ++i)
      if (!std::binary_search(ind.begin(), ind.end(), i)) dep_out.push_back(i);
  }

  std::vector<int> checked_indices(const Eigen::VectorXi &ind, const std::string &what) {
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

  // The reduced method's partition (mech.independent_idx_v) and the names of the
  // velocity coordinates (for the J_D messages).
  void set_partition(const Eigen::VectorXi &ind, bp::list names) {
    if (bp::len(names) != nv_) throw BadArgument{"Core.set_partition: one name per coordinate"};
    set_indices(checked_indices(ind, "independent_idx_v"), red_ind_, red_dep_);
    coordinate_names_.clear();
    for (int i = 0; i < nv_; ++i) coordinate_names_.push_back(bp::extract<std::string>(names[i]));
    red_what_ = "J_D (constraint-Jacobian columns of the dependent coordinates " +
                join_names(red_dep_) + ")";
    Sred_.setZero();
    for (std::size_t k = 0; k < red_ind_.size(); ++k) Sred_(red_ind_[k], k) = 1.0;
    ind0_ = ind_ = red_ind_;
    dep_ = red_dep_;
  }

  // The loops' alignment checks (ConstraintLayer.alignment_vectors): phi = 0 is a
  // spurious closure when (R_p u).(R_s u) <= 0 for a vector u of loop loop[i].
  void set_alignment(const Eigen::VectorXi &fid_p, const Eigen::VectorXi &fid_s, const Mat &u,
                     const Eigen::VectorXi &loop, bp::list loop_names) {
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

  void configure_partitioning(const bp::dict &s) {
    dependent_tol_ = bp::extract<double>(s.get("dependent_tol", 1e-13));
    repartition_cond_ = bp::extract<double>(s.get("repartition_cond", 10.0));
    partition_singular_cond_ = bp::extract<double>(s.get("partition_singular_cond", 1e4));
    partitions_ = bp::extract<bool>(s.get("partitions", false));
    rows_only_ = false;  // set by begin_partitioning for the run
    pivot_tie_rtol_ = bp::extract<double>(s.get("pivot_tie_rtol", 1e-9));
    bp::object ind = s.get("independent", bp::object());
    if (!ind.is_none()) {
      Eigen::VectorXi v = bp::extract<Eigen::VectorXi>(ind);
      ind0_ = checked_indices(v, "independent");
    }
  }

  std::string join_names(const std::vector<int> &idx) const {
    std::string s;
    for (std::size_t k = 0; k < idx.size(); ++k) {
      if (k) s += ", ";
      s += idx[k] < static_cast<int>(coordinate_names_.size()) ? coordinate_names_[idx[k]]
                                                                 : std::to_string(idx[k]);
    }
    return s;
  }

  // J_D: the columns dep of J_ into JD_.
  void gather_JD(const std::vector<int> &dep) {
    for (int c = 0; c < nc_; ++c) JD_.col(c) = J_.col(dep[c]);
  }

  // Reduced coordinates (dynamics/reduced.py): a = S a_I + c with S = [I; -J_D^-1 J_I],
  // c = [0; -J_D^-1 gamma]; (S^T M S) a_I = S^T (tau - h - M c); lam = J_D^-T (tau - h - M a)_D.
  void solve_reduced(const RefV &q, const Vec &tau, double t) {
    const int m = nv_ - nc_;
    fred_ = tau - h_;
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
        for (int i = 0; i < nc_; ++i) Sred_(red_dep_[i], k) = -tmp_c_[i];
      }
      tmp_c_ = gamma_;
      lu_jd_.solve(tmp_c_);
      for (int i = 0; i < nc_; ++i) cred_[red_dep_[i]] = -tmp_c_[i];
      fred_.noalias() -= M_ * cred_;
    }
    if (m) {
      MS_.noalias() = M_ * Sred_;
      Mr_.noalias() = Sred_.transpose() * MS_;
      llt_r_.compute(Mr_);
      check_rcond(q, "the reduced mass matrix S^T M S",
                  llt_r_.info() == Eigen::Success ? llt_r_.rcond() : 0.0, t);
      aI_.noalias() = Sred_.transpose() * fred_;
      llt_r_.solveInPlace(aI_);
      a_.noalias() = Sred_ * aI_;
      a_ += cred_;
      if (!nc_) return;
      fred_.noalias() -= MS_ * aI_;
    } else {
      a_ = cred_;
    }
    for (int i = 0; i < nc_; ++i) tmp_c_[i] = fred_[red_dep_[i]];
    lu_jd_.solve_transposed(tmp_c_);
    lam_ = tmp_c_;
  }

  // Gauss-Newton on phi(q) = 0 moving the dependent coordinates dep_ only, to
  // dependent_tol (closure.solve_closure with AssemblySettings(tol=dependent_tol,
  // max_iter=20): the full step, then, unless it contracts the sum of squares by
  // 1/4, the step without J_D's directions below 1e-2 of its largest singular
  // value; each with up to 12 halvings; the lower one is taken). nq == nv, so the
  // held coordinates stay exact under pinocchio::integrate. Every trial point is
  // evaluated with its J (one kinematics pass, computeJointJacobians): the accepted
  // one's J serves the next iteration and v_D from the memo of eval_phi_J.
  void newton_dependent(Vec &q, double t) {
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

  // Problem.complete: q_D from phi = 0 (q_I held, q the guess), v_D = -J_D^-1 J_I v_I.
  void complete(Vec &q, Vec &v, double t) {
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

  // cond_2(J_D(q)) of the stabilization's partition (np.linalg.cond).
  double cond_JD(const Vec &q) {
    if (nc_ == 0) return 1.0;
    eval_phi_J(q);
    gather_JD(dep_);
    svd_jd_.compute(JD_);
    const Vec &sv = svd_jd_.singularValues();
    return sv[nc_ - 1] > 0 ? sv[0] / sv[nc_ - 1] : std::numeric_limits<double>::infinity();
  }

  // The pivot columns of Householder QR of J_, each the lowest-index column whose
  // remaining norm is within pivot_tie_rtol of the largest (closure._tie_pivots), sorted.
  // Only when re-partitioning is considered: allocates.
  std::vector<int> tie_pivots() const {
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

  // Problem.repartition: the dependent set of column-pivoted QR of J (Wehage-Haug, ties
  // to the lowest index); true when it changed. SingularError when its J_D is above
  // partition_singular_cond.
  bool repartition(const Vec &q, double t) {
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

  // The start of a run: the stabilization's partition from configure ("independent").
  void begin_partitioning(bool fixed_step) {
    rep_t_.clear();
    rep_ind_.clear();
    sign0_ = 0.0;
    rows_only_ = partitions_ && fixed_step;  // fixed.py checks the rows only
    predictor_valid_ = unpack_valid_ = false;
    if (!partitions_) return;
    if (nq_ != nv_) throw BadArgument{"stabilization partitioning needs nq == nv"};
    set_indices(ind0_, ind_, dep_);
  }

  // After a fixed step (fixed.py): complete (q, v), re-partition when cond(J_D) is large.
  void partition_step(Vec &q, Vec &v, double t) {
    complete(q, v, t);
    if (cond_JD(q) > repartition_cond_) repartition(q, t);
  }

  void pack(const Vec &q, const Vec &v, Vec &y) const {
    const int m = static_cast<int>(ind_.size());
    for (int k = 0; k < m; ++k) {
      y[k] = q[ind_[k]];
      y[m + k] = v[ind_[k]];
    }
  }

  // (q, v) of the partitioned state y = (q_I, v_I), the dependent solve warm-started
  // from the last evaluation's q (adaptive.py's unpack).
  //
  // Two savings over the numpy loop, same solution to dependent_tol: the guess of q_D
  // follows the tangent, q_D = warm_D - (J_D^-1 J_I)(warm) (q_I - warm_I) (the numpy
  // loop starts from warm_D: one Newton iteration more per evaluation; a dense
  // output of run_adaptive passes q_D from the step's own interpolant instead,
  // use_out_guess_: one iteration where the tangent took two to four), and the
  // state of the last call is reused when y and the warm start are the same (each
  // step unpacks its end state three times: checks, output, re-partitioning).
  // Returns false when the result came from that memo (J_ and lu_jd_ are then not
  // necessarily those of q).
  bool unpack(const Vec &y, double t, Vec &q, Vec &v) {
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
      for (int k = 0; k < m; ++k) dqI_[k] = y[k] - warm_q_[ind_[k]];
      tmp_c_.noalias() = Xwarm_ * dqI_;
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

  void fun_partitioned(double t, const Vec &y, Eigen::Ref<Vec> f) {
    const int m = static_cast<int>(ind_.size());
    if (use_guess_) {  // the stage's guess of q_D (stage_guess)
      use_guess_ = false;
      fq_ = warm_q_;
      fv_.setZero();
      for (int k = 0; k < m; ++k) {
        fq_[ind_[k]] = y[k];
        fv_[ind_[k]] = y[m + k];
      }
      for (int i = 0; i < nc_; ++i) fq_[dep_[i]] = guess_qD_[i];
      complete(fq_, fv_, t);
    } else if (!unpack(y, t, fq_, fv_) && nc_) {
      eval_phi_J(fq_);
      gather_JD(dep_);
      lu_jd_.factor(JD_);
    }
    for (int i = 0; i < nc_; ++i) {
      vD_last_[i] = fv_[dep_[i]];
      qD_new_[i] = fq_[dep_[i]];
    }
    // the tangent at the new warm start: lu_jd_ holds J_D(fq_) from complete, J_ is J(fq_)
    if (nc_) {
      for (int k = 0; k < m; ++k) {
        tmp_c_ = J_.col(ind_[k]);
        lu_jd_.solve(tmp_c_);
        Xwarm_.col(k) = tmp_c_;
      }
      predictor_valid_ = true;
    }
    accel(t, fq_, fv_);
    warm_q_ = fq_;
    for (int k = 0; k < m; ++k) {
      f[k] = fv_[ind_[k]];
      f[m + k] = a_[ind_[k]];
    }
  }

  // After an adaptive step (adaptive.py): stop when det(J_D) changed sign since the
  // first step (or the last re-partition); re-partition when cond(J_D) is large and
  // t < t_final, then y is the new partition's state. Returns true on re-partition.
  bool adaptive_partition_check(double t, double t_final, Vec &y, Vec &q, Vec &v) {
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

  // The guess of q_D at a Runge-Kutta stage with coefficients a[0..s-1]: the dependent
  // coordinates integrated with the stage's own weights, q_D0 + h sum_j a_j v_D,j
  // (v_D,j of the earlier stages): accurate to the step's truncation error, so the
  // dependent solve needs one Newton iteration (the numpy loop starts from the last
  // evaluation's q_D, and from the tangent predictor of unpack here elsewhere).
  void stage_guess(const double *a, int s, double h) {
    guess_qD_ = qD0_;
    for (int j = 0; j < s; ++j)
      if (a[j] != 0.0) guess_qD_.noalias() += (h * a[j]) * KD_.col(j);
    use_guess_ = nc_ > 0;
  }

  // The step start (t, y) is the last evaluation's: its q_D and v_D.
  void step_start_from_last() {
    qD0_ = qD_new_;
    KD0_ = vD_last_;
  }

  bp::list repartitions_list() const {
    bp::list out;
    const std::size_t m = ind_.size();
    for (std::size_t i = 0; i < rep_t_.size(); ++i) {
      bp::list ind;
      for (std::size_t k = 0; k < m; ++k) ind.append(rep_ind_[i * m + k]);
      out.append(bp::make_tuple(rep_t_[i], ind));
    }
    return out;
  }

  bp::tuple py_partition() const {
    bp::list ind, dep;
    for (int i : ind_) ind.append(i);
    for (int i : dep_) dep.append(i);
    return bp::make_tuple(ind, dep);
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
    lu_branch_.resize(cols.size());
  }

  // Sign of det(J_[:, branch_cols_]) (J_ at the sample's q): the parity of the row
  // swaps of an LU with partial pivoting times the signs of its pivots, 0 for an
  // exactly zero pivot (numpy.linalg.slogdet's sign).
  double branch_sign() {
    for (Eigen::Index j = 0; j < branch_cols_.size(); ++j)
      lu_branch_.A.col(j) = J_.col(branch_cols_[j]);
    lu_branch_.factor_in_place();
    return lu_branch_.det_sign();
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
      invalidate_kinematics();  // Pinocchio's passes moved data_'s placements to q
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
    d["repartitions"] = repartitions_list();
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

  // -- rk4 with stage projection near singular positions -----------------------
  // (simulate/fixed.py, _run_rk4_stage_projected: the same rule, step for step)

  // sqrt(mu / mean eigenvalue of J J^T) at q, capped: mu the Rayleigh quotient after
  // RANK_INDICATOR_ITERS inverse iterations from the ones vector (fixed.rank_indicator).
  // With a narrow row band (set_band's banded_n) J J^T is factorized as a band and
  // x^T J J^T x = |J^T x|^2: O(nc) instead of the dense product and Cholesky, O(nc^3)
  // (the same quantity to round-off; also the ALI3-P loop's indicator).
  double rank_indicator(const Vec &q) {
    if (nc_ == 0) return RANK_INDICATOR_CAP;
    eval_phi_J(q);
    if (band_n_) {
      assemble_normal_band(0.0);
      const double ref = bn_.A.row(0).sum() / nc_;
      if (!(ref > 0.0)) return 0.0;
      if (!bn_.factor()) return 0.0;
      al_wc_.setConstant(1.0 / std::sqrt(static_cast<double>(nc_)));
      for (int i = 0; i < RANK_INDICATOR_ITERS; ++i) {
        bn_.solve_in_place(al_wc_);
        al_wc_ /= al_wc_.norm();
      }
      jt_mul(al_wc_, al_wv_);
      const double mu = al_wv_.squaredNorm();
      return std::min(std::sqrt(std::max(mu, 0.0) / ref), RANK_INDICATOR_CAP);
    }
    JJt_.noalias() = J_.lazyProduct(J_.transpose());  // small (no row band): coefficient-based
    const double ref = JJt_.trace() / nc_;
    if (!(ref > 0.0)) return 0.0;
    llt_c_.compute(JJt_);
    if (llt_c_.info() != Eigen::Success) return 0.0;
    tmp_c_.setConstant(1.0 / std::sqrt(static_cast<double>(nc_)));
    for (int i = 0; i < RANK_INDICATOR_ITERS; ++i) {
      llt_c_.solveInPlace(tmp_c_);
      tmp_c_ /= tmp_c_.norm();
    }
    vel_c_.noalias() = JJt_ * tmp_c_;
    const double mu = tmp_c_.dot(vel_c_);
    return std::min(std::sqrt(std::max(mu, 0.0) / ref), RANK_INDICATOR_CAP);
  }

  // The crossing time in steps from the start that the indicator at the start, midpoint
  // and end points to, inf when none is ahead (fixed.crossing_estimate): rho = s |t - tau|
  // fitted by least squares for tau in [0, 0.5), [0.5, 1) and [1, inf), the signs of
  // t - tau at the samples known in each; the fit in its interval with the smallest
  // residual is taken.
  static double crossing_estimate(double r0, double r1, double r2) {
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

  // Distance [steps] of a crossing at tau from the evaluation points of a retake of one
  // (double: two) grid steps split at h1 (h1 = span: one substep) (fixed._plan_points).
  static double plan_distance(double tau, bool twice, double h1) {
    const double end = twice ? 2.0 : 1.0;
    if (h1 >= end) return std::min(std::abs(end / 2 - tau), std::abs(end - tau));
    const double pts[4] = {h1 / 2, h1, (h1 + end) / 2, end};
    double d = std::numeric_limits<double>::infinity();
    for (double p : pts) d = std::min(d, std::abs(p - tau));
    return d;
  }

  // false when the plain step keeps its points at least `zone` steps from a crossing at
  // tau; else true with the retake (twice, h1) whose points are farthest from it, ties
  // to the single step (fixed.retake_plan).
  static bool retake_plan(double tau, double zone, bool &twice, double &h1) {
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

  // One rk4 step of length h from (q, v) with accelerations a0 at t, every stage and
  // the end projected; (qn, vn) the end, qm the projected stage-2 (midpoint) state.
  void rk4_projected(double t, const Vec &q, const Vec &v, const Vec &a0, double h, Vec &qn,
                     Vec &vn, Vec &qm) {
    dv_ = (h / 2) * v;
    pinocchio::integrate(model_, q, dv_, qm);
    vs_ = v + (h / 2) * a0;
    project(qm, vs_, true);
    // the retake rule's midpoint indicator, while J is at qm (no kinematics pass later)
    if (stage_zone_ > 0) rho_m_ = rank_indicator(qm);
    accel(t + h / 2, qm, vs_);
    chart_rate(q, dv_, vs_, k2v_);  // the stages' rates in the chart about q (run_fixed)
    k2a_ = a_;
    dv_ = (h / 2) * k2v_;
    pinocchio::integrate(model_, q, dv_, qs_);
    vs_ = v + (h / 2) * k2a_;
    project(qs_, vs_, true);
    accel(t + h / 2, qs_, vs_);
    chart_rate(q, dv_, vs_, k3v_);
    k3a_ = a_;
    dv_ = h * k3v_;
    pinocchio::integrate(model_, q, dv_, qs_);
    vs_ = v + h * k3a_;
    project(qs_, vs_, true);
    accel(t + h, qs_, vs_);
    chart_rate(q, dv_, vs_, k4v_);
    dv_ = (h / 6) * (v + 2 * k2v_ + 2 * k3v_ + k4v_);
    pinocchio::integrate(model_, q, dv_, qn);
    vn = v + (h / 6) * (a0 + 2 * k2a_ + 2 * k3a_ + a_);
    check_finite(qn, vn, t + h);
    project(qn, vn, true);
  }

  // The state at t = t0 + s h of the substep (q0, v0, a0) -> (q1, v1, a1) of length h
  // by cubic Hermite interpolation, q projected onto phi = 0, recorded (v is not
  // projected: near the crossing that is the ill-conditioned step avoided).
  void record_interpolated(Samples &S, double t, double s, double h, const Vec &q0,
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

  bp::dict run_rk4_stage_projected(const Vec &q0, const Vec &v0, double dt, long n_steps,
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
          retake_plan(crossing_estimate(rho_start, rho_m_, rho_new), stage_zone_,
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

  // -- fixed-step integration ----------------------------------------------------

  // Integrate with a fixed step dt for n_steps, recording at the steps in `out`.
  bp::dict run_fixed(int integrator, const Vec &q0, const Vec &v0, double dt, long n_steps,
                     const Eigen::VectorXi &out_steps, bool projects, bp::object progress) {
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

  // The ALI3-P integrator (ali3p.hpp) at the fixed step dt for n_steps, recording at
  // the steps in out_steps; settings = (ali3p_tol, ali3p_phi_tol, ali3p_max_iter,
  // ali3p_penalty).
  bp::dict run_ali3p(const Vec &q0, const Vec &v0, double dt, long n_steps,
                     const Eigen::VectorXi &out_steps, bp::tuple settings, bp::object progress) {
    check_sizes(q0, v0);
    invalidate_kinematics();  // nothing kept from before the run (M_, the factor of P)
    if (bp::len(settings) != 4)
      throw BadArgument{"run_ali3p: settings = (ali3p_tol, ali3p_phi_tol, ali3p_max_iter, "
                        "ali3p_penalty)"};
    Ali3pSettings s;
    s.tol = bp::extract<double>(settings[0]);
    s.phi_tol = bp::extract<double>(settings[1]);
    s.max_iter = bp::extract<int>(settings[2]);
    s.penalty = bp::extract<double>(settings[3]);
    if (!(dt > 0.0) || n_steps < 0 || s.max_iter < 1)
      throw BadArgument{"run_ali3p: dt > 0, n_steps >= 0 and ali3p_max_iter >= 1 required"};
    std::vector<char> out(n_steps + 1, 0);
    for (Eigen::Index i = 0; i < out_steps.size(); ++i)
      if (out_steps[i] >= 0 && out_steps[i] <= n_steps) out[out_steps[i]] = 1;
    return Ali3pLoop<Core>(*this, s).run(q0, v0, dt, n_steps, out, progress);
  }

  // -- adaptive explicit Runge-Kutta (scipy's RK45 / DOP853, same error control) --

  double rms(const Vec &x) const { return x.norm() / std::sqrt(static_cast<double>(x.size())); }

  // The chart of the adaptive loops when nq != nv (simulate/chart.py): the state
  // holds x with q = integrate(q_c, x), dx/dt = D(x)^-1 v, D = dIntegrate/dx.
  void chart_start(const Vec &q0) {
    chart_ = nq_ != nv_;
    if (!chart_) return;
    q_c_ = q0;
    q_x_ = q0;
  }

  // out = D(x)^-1 v for q = integrate(q_c, x): the identity but on the blocks of
  // the joints whose integrate is not x + v (free-flyer, spherical, planar).
  void chart_rate(const Vec &q_c, const Eigen::Ref<const Vec> &x, const Eigen::Ref<const Vec> &v,
                  Eigen::Ref<Vec> out) {
    out = v;
    if (curved_.empty()) return;
    pinocchio::dIntegrate(model_, q_c, x, D_chart_, pinocchio::ARG1);
    for (const auto &b : curved_) {
      SmallMat Db = D_chart_.block(b.first, b.first, b.second, b.second);
      out.segment(b.first, b.second) = Db.partialPivLu().solve(v.segment(b.first, b.second));
    }
  }

  // The configuration of state y's position part (y itself without a chart).
  RefV chart_q(const Eigen::Ref<const Vec> &x) {
    if (!chart_) return x;
    pinocchio::integrate(model_, q_c_, x, q_x_);
    return q_x_;
  }

  // Re-centre the chart when a curved joint's block exceeds 1 (chart.RECENTRE_NORM).
  bool chart_recentre(Eigen::Ref<Vec> x) {
    bool far = false;
    for (const auto &b : curved_) far = far || x.segment(b.first, b.second).norm() > 1.0;
    if (!far) return false;
    pinocchio::integrate(model_, q_c_, x, q_x_);
    q_c_ = q_x_;
    x.setZero();
    return true;
  }

  void fun(double t, const Vec &y, Eigen::Ref<Vec> f) {
    if (partitions_) {
      fun_partitioned(t, y, f);
      return;
    }
    accel(t, chart_q(y.head(nv_)), y.tail(nv_));
    if (chart_)
      chart_rate(q_c_, y.head(nv_), y.tail(nv_), f.head(nv_));
    else
      f.head(nv_) = y.tail(nv_);
    f.tail(nv_) = a_;
  }

  bp::dict run_adaptive(int integrator, const Vec &q0, const Vec &v0, double t_final,
                        double rtol, double atol, bp::object t_eval_obj, bool projects,
                        bp::object progress) {
    check_sizes(q0, v0);
    invalidate_kinematics();  // nothing kept from before the run (M_, the factor of P)
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
    begin_partitioning(false);
    // Partitioning integrates (q_I, v_I) only; (q_D, v_D) follow at every evaluation.
    const int ns = partitions_ ? nv_ - nc_ : nv_;
    const int n = 2 * ns;
    Vec qc(nv_), vc(nv_);
    std::vector<double> pending;
    const bool dense = !t_eval_obj.is_none();
    if (dense) {
      Vec te = bp::extract<Vec>(t_eval_obj);
      pending.assign(te.data(), te.data() + te.size());
    }
    std::size_t ip = 0;
    Vec y(n), y_new(n), f(n), f_new(n), scale(n), dy(n), ye(n), tmp(n), e5(n), e3(n);
    Vec q_out(nq_), v_out(nv_), x_out(nv_);
    chart_start(q0);  // partitioning needs nq == nv (refused in Python): no chart then
    if (partitions_) {
      qc = q0;
      vc = v0;
      complete(qc, vc, 0.0);
      warm_q_ = q0;  // the dependent solves start from the last evaluation's q
      pack(qc, vc, y);
    } else {
      y.head(nv_) = chart_ ? Vec::Zero(nv_) : q0;
      y.tail(nv_) = v0;
    }
    Mat K(n, dop ? dop853::N_STAGES_EXTENDED : n_stages + 1);
    KD_ = Mat::Zero(nc_, K.cols());
    Mat F(n, dop853::INTERPOLATOR_POWER);
    // partitioning: the same dense output of q_D from its rates v_D at the stages (KD_),
    // the guess of the output's dependent solve (as stage_guess for the stages)
    Mat FD(nc_, partitions_ ? dop853::INTERPOLATOR_POWER : 0);
    auto output = [&](double t, const Vec &yy) {
      if (partitions_) {
        unpack(yy, t, qc, vc);
        accel(t, qc, vc);
        record(S, t, qc, vc);
        return;
      }
      q_out = chart_q(yy.head(nv_));
      v_out = yy.tail(nv_);
      accel(t, q_out, v_out);
      record(S, t, q_out, v_out);
    };
    double t = 0.0;
    if (!dense || (ip < pending.size() && pending[ip] <= 0.0)) {
      output(0.0, y);
      if (dense) ++ip;
    }
    fun(t, y, f);
    if (partitions_) step_start_from_last();
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
        if (partitions_) KD_.col(0) = KD0_;
        for (int s = 1; s < n_stages; ++s) {
          dy.setZero();
          for (int j = 0; j < s; ++j) {
            double c = dop ? dop853::A[s][j] : rk45::A[s][j];
            if (c != 0.0) dy += c * K.col(j);
          }
          ye = y + h * dy;
          if (partitions_) stage_guess(dop ? dop853::A[s] : rk45::A[s], s, h);
          fun(t + (dop ? dop853::C[s] : rk45::C[s]) * h, ye, K.col(s));
          if (partitions_) KD_.col(s) = vD_last_;
        }
        dy.setZero();
        for (int j = 0; j < n_stages; ++j) {
          double b = dop ? dop853::B[j] : rk45::B[j];
          if (b != 0.0) dy += b * K.col(j);
        }
        y_new = y + h * dy;
        if (partitions_) stage_guess(dop ? dop853::B : rk45::B, n_stages, h);
        fun(t + h, y_new, f_new);
        if (partitions_) KD_.col(n_stages) = vD_last_;
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
      if (partitions_) {  // the dependent state at y_new and its rate: the next step's start
        qD_end_ = qD_new_;  // (qD0_ stays the step start's for the dense-output stages)
        KD0_ = KD_.col(n_stages);
      }
      // dense output at the t_eval within the step, from the unprojected step
      if (dense && ip < pending.size() && pending[ip] <= t_new) {
        if (dop) {
          for (int s = n_stages + 1, e = 0; e < 3; ++s, ++e) {
            dy.setZero();
            for (int j = 0; j < s; ++j)
              if (dop853::A_EXTRA[e][j] != 0.0) dy += dop853::A_EXTRA[e][j] * K.col(j);
            ye = y + h * dy;
            if (partitions_) stage_guess(dop853::A_EXTRA[e], s, h);
            fun(t_old + dop853::C_EXTRA[e] * h, ye, K.col(s));
            if (partitions_) KD_.col(s) = vD_last_;
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
          if (partitions_ && nc_) {
            FD.col(0) = qD_end_ - qD0_;
            FD.col(1) = h * KD_.col(0) - FD.col(0);
            FD.col(2) = 2 * FD.col(0) - h * (KD_.col(n_stages) + KD_.col(0));
            for (int i = 0; i < 4; ++i) {
              FD.col(3 + i).setZero();
              for (int j = 0; j < dop853::N_STAGES_EXTENDED; ++j)
                if (dop853::D[i][j] != 0.0) FD.col(3 + i) += (h * dop853::D[i][j]) * KD_.col(j);
            }
          }
        } else {
          for (int i = 0; i < 4; ++i) {  // Q = K^T P
            tmp.setZero();
            for (int j = 0; j <= n_stages; ++j)
              if (rk45::P[j][i] != 0.0) tmp += rk45::P[j][i] * K.col(j);
            F.col(i) = tmp;
            if (partitions_ && nc_) {
              FD.col(i).setZero();
              for (int j = 0; j <= n_stages; ++j)
                if (rk45::P[j][i] != 0.0) FD.col(i) += rk45::P[j][i] * KD_.col(j);
            }
          }
        }
        while (ip < pending.size() && pending[ip] <= t_new * (1 + 1e-15)) {
          double x = (pending[ip] - t_old) / h;
          const bool guess = partitions_ && nc_;
          if (dop) {
            ye.setZero();
            if (guess) guess_qD_.setZero();
            for (int i = dop853::INTERPOLATOR_POWER - 1, r = 0; i >= 0; --i, ++r) {
              ye += F.col(i);
              ye *= (r % 2 == 0) ? x : 1 - x;
              if (guess) {
                guess_qD_ += FD.col(i);
                guess_qD_ *= (r % 2 == 0) ? x : 1 - x;
              }
            }
            ye += y;
            if (guess) guess_qD_ += qD0_;
          } else {
            double p = x;
            ye = y;
            if (guess) guess_qD_ = qD0_;
            for (int i = 0; i < 4; ++i, p *= x) {
              ye += (h * p) * F.col(i);
              if (guess) guess_qD_ += (h * p) * FD.col(i);
            }
          }
          use_out_guess_ = guess;
          output(pending[ip], ye);
          ++ip;
        }
      }
      t = t_new;
      y = y_new;
      f = f_new;
      if (partitions_) {
        qD0_ = qD_end_;
        check_finite(y.head(ns), y.tail(ns), t);
      } else {
        q_out = chart_q(y.head(nv_));
        v_out = y.tail(nv_);
        check_finite(q_out, v_out, t);
      }
      if (projects) {
        project(q_out, v_out);
        if (chart_)
          pinocchio::difference(model_, q_c_, q_out, x_out);
        y.head(nv_) = chart_ ? x_out : q_out;
        y.tail(nv_) = v_out;
        fun(t, y, f);
      }
      if (partitions_) {
        unpack(y, t, qc, vc);
        check_regular(qc, t);
      } else {
        if (chart_ && t < t_final && chart_recentre(y.head(nv_))) fun(t, y, f);
        check_regular(q_out, t);
      }
      if (!dense) output(t, y);
      poll(steps, t, progress);
      // det(J_D) sign and re-partitioning; a new partition restarts the integrator
      // from (t, y) with the step size it proposed (as the numpy loop restarts scipy's).
      if (partitions_ && adaptive_partition_check(t, t_final, y, qc, vc)) {
        fun(t, y, f);
        step_start_from_last();
      }
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
  Mat M_, J_, Y_, D_, Mr_, JJt_;
  Vec z_;
  DenseLU kkt_;  // K of the kkt method
  Vec h_, phi_, gamma_, a_, lam_, tau_, tau_const_, zero_v_, x_, dq_, tmp_c_, tmp_v_;
  Eigen::LLT<Mat> llt_m_, llt_c_, llt_r_;
  SmallLLT llt_p_, llt_jj_;  // M + alpha J^T J; J J^T (+ regularization)
  Mat P_;
  Vec rhs_v_, q_prev_, vel_c_, rhs_work_;
  Vec dv_, vs_, qs_, k2v_, k2a_, k3v_, k3a_, k4v_;  // rk4_projected's stages
  Vec a2_;  // run_rk4_stage_projected: accelerations at a two-step retake's end
  Vec mv_;  // project(mass_orth): M v
  Vec zero_c_;  // project(mass_orth): g = 0
  Vec al_wc_, al_wv_;  // BandAlOps' products
  double rho_m_ = 0.0;  // rk4_projected: rank indicator at the projected midpoint
  // Structure (sparsity) and the band paths (set_band).
  std::vector<int> jcol_start_, jcols_, jlo_, jhi_, mlo_, mhi_;
  std::vector<int> perm_, pinv_;
  bool perm_identity_ = true, band_p_ = false, band_n_ = false;
  int b_p_ = 0, b_n_ = 0;
  BandCholesky bp_, bn_;  // M + alpha J^T J (order perm_), J J^T
  Vec pw_;
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
  bool p_fact_ = false;  // llt_p_ / bp_ hold P = M_ + alpha J_^T J_ (solve_al's alpha)
  Eigen::VectorXi branch_cols_;  // set_branch_columns
  DenseLU lu_branch_;  // branch_sign's LU of J's branch columns
  Vec terms_q_, terms_v_;  // (q, v) of the last eval_terms (M_, pe_ valid there)
  double pe_ = 0.0;
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
  Mat KD_;     // v_D at the stages of the current adaptive step
  Vec qD0_, KD0_, qD_end_, qD_new_, vD_last_, guess_qD_;
  bool use_guess_ = false, use_out_guess_ = false;
  Vec dqI_, unpack_y_, unpack_warm_, unpack_q_, unpack_v_;
  bool predictor_valid_ = false, unpack_valid_ = false;
  double sign0_ = 0.0;  // sign of det(J_D) at the first step (0: not yet)
  Mat JD_, Sred_, MS_;
  Vec cred_, fred_, aI_, phi_n_, phi_best_, step_c_, q_try_, q_best_, dv_n_, warm_q_, fq_, fv_;
  DenseLU lu_jd_;
  Eigen::JacobiSVD<Mat> svd_jd_, svd_jd_uv_;
  std::vector<Align> align_;
  std::vector<std::string> align_names_;
  std::vector<double> rep_t_;
  std::vector<int> rep_ind_;
};

// Test helpers of tree_terms.hpp (tests/test_compiled.py compares them with
// pinocchio.crba, nonLinearEffects, computeJointJacobians and forwardKinematics).
namespace tree_test {

bp::dict results(const Model &model, const Data &data) {
  bp::dict d;
  bp::list oMi;
  Mat ov(6, model.njoints), oa(6, model.njoints);
  for (int i = 0; i < model.njoints; ++i) {
    oMi.append(Mat(data.oMi[(std::size_t)i].toHomogeneousMatrix()));
    ov.col(i) = data.ov[(std::size_t)i].toVector();
    oa.col(i) = data.oa[(std::size_t)i].toVector();
  }
  d["oMi"] = oMi;
  d["J"] = Mat(data.J);
  d["ov"] = ov;
  d["oa"] = oa;
  return d;
}

// M, h, oMi, J (world columns), ov, oa (bias accelerations) by tree_terms(q, v);
// at_kinematics: by joint_kinematics(q) then tree_terms_at_kinematics(q, v).
bp::dict tree_terms_py(bp::object model_obj, const Vec &q, const Vec &v, bool at_kinematics) {
  const Model &model = bp::extract<const Model &>(model_obj)();
  if (q.size() != model.nq || v.size() != model.nv)
    throw BadArgument{"_tree_terms: q must have shape (nq,) and v shape (nv,)"};
  Data data = lean_data(model);
  const TreePlan plan(model);
  Mat M = Mat::Zero(model.nv, model.nv);
  Vec h = Vec::Zero(model.nv);
  if (at_kinematics) {
    joint_kinematics(plan, model, data, q);
    tree_terms_at_kinematics(plan, model, data, q, v, M, h);
  } else {
    tree_terms(plan, model, data, q, v, M, h);
  }
  bp::dict d = results(model, data);
  d["M"] = M;
  d["h"] = h;
  return d;
}

// oMi and J by joint_kinematics(q) alone.
bp::dict kinematics_py(bp::object model_obj, const Vec &q) {
  const Model &model = bp::extract<const Model &>(model_obj)();
  if (q.size() != model.nq) throw BadArgument{"_joint_kinematics: q must have shape (nq,)"};
  Data data = lean_data(model);
  joint_kinematics(TreePlan(model), model, data, q);
  return results(model, data);
}

// Which joints (by index, the universe 0 included) take the revolute path.
bp::list revolute_joints_py(bp::object model_obj) {
  const Model &model = bp::extract<const Model &>(model_obj)();
  const TreePlan plan(model);
  bp::list out;
  for (int i = 0; i < model.njoints; ++i) out.append(i > 0 && plan.revolute((std::size_t)i));
  return out;
}

}  // namespace tree_test

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
  bp::def("_tree_terms", &tree_test::tree_terms_py,
          (bp::arg("model"), bp::arg("q"), bp::arg("v"), bp::arg("at_kinematics") = false),
          "Test helper: dict of M, h, oMi, J, ov, oa from tree_terms.hpp's pass.");
  bp::def("_joint_kinematics", &tree_test::kinematics_py, bp::args("model", "q"),
          "Test helper: dict of oMi, J (and zero ov, oa) from tree_terms.hpp's kinematics pass.");
  bp::def("_revolute_joints", &tree_test::revolute_joints_py, bp::args("model"),
          "Test helper: per joint, whether tree_terms.hpp's revolute path computes it.");
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
      .def("set_band", &Core::set_band, bp::args("self", "perm", "banded_p", "banded_n"),
           "Use band Cholesky factorizations: of M + alpha J^T J in the order perm "
           "(banded_p) and of J J^T (banded_n); returns their half bandwidths.")
      .def("band_info", &Core::band_info, bp::args("self"),
           "(banded_p, banded_n, b_p, b_n) as set by set_band.")
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
      .def("run_ali3p", &Core::run_ali3p,
           bp::args("self", "q0", "v0", "dt", "n_steps", "out_steps", "settings", "progress"),
           "ALI3-P (index-3 augmented Lagrangian, trapezoidal rule, mass-orthogonal "
           "projections); settings = (tol, phi_tol, max_iter, penalty).")
      .def("run_adaptive", &Core::run_adaptive,
           bp::args("self", "integrator", "q0", "v0", "t_final", "rtol", "atol", "t_eval",
                    "projects", "progress"))
      .def("set_partition", &Core::set_partition, bp::args("self", "independent", "names"),
           "The reduced method's partition (independent velocity indices) and coordinate names.")
      .def("set_alignment", &Core::set_alignment,
           bp::args("self", "fid_p", "fid_s", "u", "loop", "loop_names"),
           "The loops' alignment checks of the dependent solve (spurious closures).")
      .add_property("partition", &Core::py_partition,
                    "(independent, dependent) velocity indices of the stabilization's partition.")
      .add_property("nc", &Core::nc)
      .add_property("n_evals", &Core::n_evals);
}
