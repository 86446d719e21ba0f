// closedchain._core: CoreModel, what is fixed once a mechanism is built and configured: the
// Pinocchio model, the constraint rows and their cut frames, the sparsity and band structure,
// the settings (method, tolerances, stabilization) and the partitions chosen in Python.
//
// Pinocchio's pattern: the functions of every concept header take (const CoreModel &, CoreData
// &); only the set-up functions (the constructor, set_band, set_declared, set_partition,
// set_alignment, set_branch_columns, set_tau, set_passive and Core::configure) change a CoreModel.
//
// Every constraint row is one of three smooth scalar functions, with the row codes of
// closedchain/constraints.py (generated into constants.hpp): of the cut frames c1
// (predecessor, R_p, p_p) and c2 (successor, R_s, p_s),
//   ROW_TRANSLATION  translation along n fixed in c1:  phi = (R_p n) . (p_p - p_s)
//   ROW_ROTATION     rotation, u in c1 and w in c2:    phi = (R_p u) . (R_s w)
// or of the coordinates of the parent joints i of c1 and j of c2 (1-dof, nq = nv = 1),
//   ROW_COUPLING     a joint coupling:                 phi = q_j - m q_i - c
// with exact J (derivative along pinocchio::integrate) and gamma = Jdot v (0 for a
// coupling), the formulas of closedchain/constraints.py (core_rows.hpp).

#pragma once

#include <pinocchio/multibody/model.hpp>

#include <Eigen/Dense>
#include <boost/python.hpp>

#include <algorithm>
#include <string>
#include <utility>
#include <vector>

#include "common.hpp"
#include "constants.hpp"
#include "errors.hpp"
#include "passive.hpp"
#include "tree_terms.hpp"

namespace closedchain {

/// One constraint row on two cut frames (see the header comment for its three kinds).
struct Row {
  /// ROW_TRANSLATION, ROW_ROTATION or ROW_COUPLING.
  int kind;
  /// The predecessor and successor frames: indices into CoreModel::frame_ids.
  int p, s;
  /// n (translation), u (rotation), or (m, c, 0) of a coupling (the layer's RowTable).
  Vector3d n;
  /// w (rotation).
  Vector3d w;
  /// A coupling: the q and v indices of joint i (c1's parent joint) and j (c2's).
  int qi = 0, vi = 0, qj = 0, vj = 0;
};

/// One alignment check of a loop (ConstraintLayer.alignment_vectors): phi = 0 is a spurious
/// closure when (R_p u) . (R_s u) <= 0.
struct LoopAlignment {
  /// The two frames: indices into CoreModel::frame_ids (their placements in CoreData).
  int p, s;
  /// u, in both frames.
  Vector3d u;
  /// The loop's index into CoreModel::loop_names.
  int loop;
};

/// The velocity indices in 0..nv-1 not in `ind`, and `ind` itself, both sorted.
inline void split_indices(int nv, std::vector<int> ind, std::vector<int> &ind_out,
                          std::vector<int> &dep_out) {
  std::sort(ind.begin(), ind.end());
  ind_out = ind;
  dep_out.clear();
  for (int i = 0; i < nv; ++i)
    if (!std::binary_search(ind.begin(), ind.end(), i)) dep_out.push_back(i);
}

/// What is fixed once the mechanism is built: the Pinocchio model (by reference), the rows,
/// the cut frames, the structure, the settings and the partitions.
struct CoreModel {
  /// Build from the Pinocchio model (held by reference: model_obj keeps it alive) and the
  /// constraint layer's row table (kinds, frame ids and vectors as its RowTable).
  CoreModel(bp::object model_obj, const std::string &name, const Eigen::VectorXi &kinds,
            const Eigen::VectorXi &fid_p, const Eigen::VectorXi &fid_s, const Mat &vec1,
            const Mat &vec2);

  /// The index of frame `fid` in frame_ids, appended when new.
  int frame_index(int fid);

  /// Row r of a row table (kind, frames, vectors as the layer's RowTable), checked.
  Row make_row(int r, const Eigen::VectorXi &kinds, const Eigen::VectorXi &fid_p,
               const Eigen::VectorXi &fid_s, const Mat &vec1, const Mat &vec2);

  /// Per cut frame: its parent joint and the columns of that joint's support.
  void frame_supports();

  /// Structural nonzeros, from the kinematic tree: row r of J is nonzero only on the
  /// columns of the joints supporting its two frames (jcols from jcol_start[r], sorted;
  /// hull [jlo[r], jhi[r]]), row i of M on those of the joints that support or are
  /// supported by i's joint (hull [mlo[i], mhi[i]]). The rules of
  /// closedchain/dynamics/augmented_lagrangian.py (structure, row_structure).
  void sparsity();

  // -- the mechanism -----------------------------------------------------------------------

  /// The Python pinocchio.Model that `tree` refers to (kept alive).
  bp::object tree_object;
  /// The Pinocchio model of the kinematic tree.
  const Model &tree;
  /// Which joints take tree_terms.hpp's revolute path.
  TreePlan tree_plan;
  /// Only revolute and prismatic joints: pinocchio::integrate is q + dq.
  bool vector_space = false;
  /// The mechanism's name, the first word of every error message.
  std::string name;
  /// Configuration size, velocity size and number of kept constraint rows.
  int nq = 0, nv = 0, nc = 0;
  /// The kept rows (those the methods use).
  std::vector<Row> rows;
  /// The Pinocchio frame ids of the cut frames (rows and alignment checks).
  std::vector<pinocchio::FrameIndex> frame_ids;
  /// The parent joint of each of frame_ids.
  std::vector<pinocchio::JointIndex> frame_joint;
  /// The velocity columns of each frame's support.
  std::vector<std::vector<Eigen::Index>> frame_columns;
  /// Joints with nv > 1 and nq != nv (free-flyer, spherical, planar): (idx_v, nv) of each.
  std::vector<std::pair<int, int>> curved_joints;
  /// Every declared row (kept and dropped), checked at every step (set_declared).
  std::vector<Row> declared_rows;
  /// The declared rows' labels "loop.kind", for messages.
  std::vector<std::string> declared_labels;
  /// declared_kept[i] = 1 for a declared row among the kept rows.
  Eigen::VectorXi declared_kept;
  /// The columns D of J whose sign of det(J[:, D]) is recorded (empty: none).
  Eigen::VectorXi branch_columns;

  // -- structure (sparsity) and the band paths (set_band) ----------------------------------

  /// Row r of J: structural columns jcols[jcol_start[r] .. jcol_start[r + 1]), their hull
  /// [jlo[r], jhi[r]]; row i of M: hull [mlo[i], mhi[i]].
  std::vector<int> jcol_start, jcols, jlo, jhi, mlo, mhi;
  /// The band order of M + alpha J^T J (perm[k] = the column at position k) and its inverse.
  std::vector<int> perm, perm_inverse;
  /// perm is the identity.
  bool perm_identity = true;
  /// M + alpha J^T J is factored as a band (in the order perm); J J^T is.
  bool banded_penalized = false, banded_normal = false;
  /// Half bandwidths of M + alpha J^T J in the order perm and of J J^T.
  int penalized_bandwidth = 0, normal_bandwidth = 0;

  // -- the tree path (core_tree.hpp) -------------------------------------------------------

  /// Every method but schur may solve by the articulated-body recursion, M never
  /// formed: chosen at construction for nv > TREE_SOLVE_MIN_NV and nc <= nv /
  /// TREE_SOLVE_NV_PER_ROW (constants.hpp), changed by set_tree_path.
  bool tree_path = false;

  /// The configured method's solve takes the tree path: tree_path, a method that has one
  /// (all but schur) and no band path (set_band).
  bool tree_solves() const { return tree_path && !banded_penalized && method != SCHUR; }

  // -- settings (Core::configure) ----------------------------------------------------------

  /// The dynamics method and its name.
  Method method = KKT;
  std::string method_name = "kkt";
  /// Largest condition number a method accepts.
  double cond_max = 1e12;
  /// Baumgarte stabilization on, with gains alpha [1/s] and beta [1/s].
  bool baumgarte = false;
  double baumgarte_alpha = 0.0, baumgarte_beta = 0.0;
  /// Projection: tolerance on max |phi| [m or 1], iterations, velocities projected too.
  double projection_tol = 1e-13;
  int projection_iters = 10;
  bool project_velocities = true;
  /// Largest cond(J) of a regular configuration.
  double singular_cond = 1e3;
  /// Largest max |phi| over the declared rows before a run stops [m or 1].
  double drift_limit = 1e-2;
  /// Augmented Lagrangian: penalty, tolerance, iteration limit.
  double al_penalty = 1e11, al_tol = 1e-13;
  int al_max_iter = 30;
  /// The stage projection is on; the run passes singular positions.
  bool stage_projects = false, singular_robust = false;
  /// SimulationSettings.singular_zone and stage_singular_zone [steps].
  double singular_zone = 0.0, stage_zone = 0.0;
  /// A dropped row is open beyond max(dropped_tol, dropped_ratio x the kept rows' residual).
  double dropped_tol = 1e-9, dropped_ratio = 100.0;

  // -- the generalized force (set_tau) -----------------------------------------------------

  /// 0 none, 1 constant (tau_constant), 2 callable (tau_function).
  int tau_mode = 0;
  /// The constant tau, shape (nv,) [N, N m].
  Vec tau_constant;
  /// The callable tau(t, q, v) and numpy.asarray.
  bp::object tau_function, np_asarray;

  /// Joint springs and damping, a term of h (set_passive; passive.hpp).
  PassiveForces passive;

  // -- the reduced method and coordinate partitioning --------------------------------------

  /// The reduced method's partition (mech.independent_idx_v), for the whole run.
  std::vector<int> method_independent, method_dependent;
  /// The stabilization's partition at the start of a run ("independent" of configure).
  std::vector<int> start_independent;
  /// The velocity coordinates' names, and the label of the method's J_D in messages.
  std::vector<std::string> coordinate_names;
  std::string method_jd_label = "J_D";
  /// The stabilization is coordinate partitioning.
  bool partitions = false;
  /// Dependent solve tolerance [m or 1]; cond(J_D) limits of re-partitioning and of stopping.
  double dependent_tol = 1e-13, repartition_cond = 10.0, partition_singular_cond = 1e4;
  /// Relative tie of the column-pivoted QR's pivots (closure._tie_pivots).
  double pivot_tie_rtol = 1e-9;
  /// The loops' alignment checks of the dependent solve, and the loops' names.
  std::vector<LoopAlignment> alignments;
  std::vector<std::string> loop_names;
};

inline CoreModel::CoreModel(bp::object model_obj, const std::string &mechanism_name,
                            const Eigen::VectorXi &kinds, const Eigen::VectorXi &fid_p,
                            const Eigen::VectorXi &fid_s, const Mat &vec1, const Mat &vec2)
    : tree_object(model_obj),
      tree(bp::extract<Model &>(model_obj)()),
      tree_plan(tree),
      name(mechanism_name) {
  nq = tree.nq;
  nv = tree.nv;
  nc = static_cast<int>(kinds.size());
  if (fid_p.size() != nc || fid_s.size() != nc || vec1.rows() != nc || vec2.rows() != nc ||
      (nc && (vec1.cols() != 3 || vec2.cols() != 3)))
    throw BadArgument{"Core: row tables of inconsistent shapes"};
  for (int r = 0; r < nc; ++r) rows.push_back(make_row(r, kinds, fid_p, fid_s, vec1, vec2));
  if (!tree.mimicking_joints.empty())
    throw BadArgument{
        "compiled core: models with mimic joints are not supported "
        "(use backend='numpy')"};
  frame_supports();
  tau_constant = Vec::Zero(nv);
  for (std::size_t j = 1; j < tree.joints.size(); ++j) {
    const auto &jm = tree.joints[j];
    if (jm.nv() > 1 && jm.nq() != jm.nv()) {
      if (jm.nv() > 6) throw BadArgument{"Core: a curved joint with more than 6 velocities"};
      curved_joints.emplace_back(jm.idx_v(), jm.nv());
    }
  }
  vector_space = true;
  for (std::size_t j = 1; j < tree.joints.size(); ++j) {
    const std::string jn = tree.joints[j].shortname();
    if (!(tree_plan.revolute(j) || jn == "JointModelPX" || jn == "JointModelPY" ||
          jn == "JointModelPZ" || jn == "JointModelPrismaticUnaligned"))
      vector_space = false;
  }
  const int m = std::max(nv - nc, 0);
  std::vector<int> ind(m);
  for (int i = 0; i < m; ++i) ind[i] = nc + i;  // until set_partition
  split_indices(nv, ind, method_independent, method_dependent);
  start_independent = method_independent;
  sparsity();
  tree_path = nv > TREE_SOLVE_MIN_NV && nc * TREE_SOLVE_NV_PER_ROW <= nv;
}

inline int CoreModel::frame_index(int fid) {
  for (std::size_t k = 0; k < frame_ids.size(); ++k)
    if (frame_ids[k] == static_cast<pinocchio::FrameIndex>(fid)) return static_cast<int>(k);
  frame_ids.push_back(static_cast<pinocchio::FrameIndex>(fid));
  return static_cast<int>(frame_ids.size() - 1);
}

inline Row CoreModel::make_row(int r, const Eigen::VectorXi &kinds, const Eigen::VectorXi &fid_p,
                               const Eigen::VectorXi &fid_s, const Mat &vec1, const Mat &vec2) {
  if (kinds[r] != ROW_TRANSLATION && kinds[r] != ROW_ROTATION && kinds[r] != ROW_COUPLING)
    throw BadArgument{"Core: row kind must be ROW_TRANSLATION, ROW_ROTATION or ROW_COUPLING"};
  for (int f : {fid_p[r], fid_s[r]})
    if (f < 0 || f >= static_cast<int>(tree.nframes))
      throw BadArgument{"Core: frame id out of range"};
  Row row;
  row.kind = kinds[r];
  row.p = frame_index(fid_p[r]);
  row.s = frame_index(fid_s[r]);
  row.n = vec1.row(r).transpose();
  row.w = vec2.row(r).transpose();
  if (row.kind == ROW_COUPLING) {
    const pinocchio::JointIndex ji = tree.frames[fid_p[r]].parentJoint,
                                jj = tree.frames[fid_s[r]].parentJoint;
    for (pinocchio::JointIndex j : {ji, jj})
      if (j == 0 || tree.nqs[j] != 1 || tree.nvs[j] != 1)
        throw BadArgument{"Core: a coupling row ties two joints with one coordinate each"};
    row.qi = tree.idx_qs[ji];
    row.vi = tree.idx_vs[ji];
    row.qj = tree.idx_qs[jj];
    row.vj = tree.idx_vs[jj];
  }
  return row;
}

inline void CoreModel::frame_supports() {
  const std::size_t nf = frame_ids.size();
  frame_joint.resize(nf);
  frame_columns.resize(nf);
  for (std::size_t k = 0; k < nf; ++k) {
    const pinocchio::JointIndex j = tree.frames[frame_ids[k]].parentJoint;
    frame_joint[k] = j;
    frame_columns[k].clear();
    for (pinocchio::JointIndex s : tree.supports[j]) {
      if (s == 0) continue;
      for (int c = 0; c < tree.nvs[s]; ++c) frame_columns[k].push_back(tree.idx_vs[s] + c);
    }
  }
}

inline void CoreModel::sparsity() {
  auto support_cols = [&](pinocchio::JointIndex j, std::vector<int> &cols) {
    for (pinocchio::JointIndex s : tree.supports[j]) {
      if (s == 0) continue;
      for (int c = 0; c < tree.joints[s].nv(); ++c) cols.push_back(tree.joints[s].idx_v() + c);
    }
  };
  jcol_start.assign(1, 0);
  jcols.clear();
  jlo.assign(nc, 0);
  jhi.assign(nc, nv ? nv - 1 : 0);
  for (int r = 0; r < nc; ++r) {
    std::vector<int> cols;
    support_cols(tree.frames[frame_ids[rows[r].p]].parentJoint, cols);
    support_cols(tree.frames[frame_ids[rows[r].s]].parentJoint, cols);
    std::sort(cols.begin(), cols.end());
    cols.erase(std::unique(cols.begin(), cols.end()), cols.end());
    jcols.insert(jcols.end(), cols.begin(), cols.end());
    jcol_start.push_back(static_cast<int>(jcols.size()));
    if (!cols.empty()) {
      jlo[r] = cols.front();
      jhi[r] = cols.back();
    } else {  // a row on two frames of the base: J row zero
      jlo[r] = 0;
      jhi[r] = -1;
    }
  }
  mlo.assign(nv, 0);
  mhi.assign(nv, 0);
  for (pinocchio::JointIndex j = 1; j < static_cast<pinocchio::JointIndex>(tree.njoints); ++j) {
    int lo = tree.joints[j].idx_v(), hi = lo + tree.joints[j].nv() - 1;
    for (pinocchio::JointIndex s : tree.supports[j])
      if (s != 0) lo = std::min(lo, tree.joints[s].idx_v());
    for (pinocchio::JointIndex s : tree.subtrees[j])
      hi = std::max(hi, tree.joints[s].idx_v() + tree.joints[s].nv() - 1);
    for (int c = 0; c < tree.joints[j].nv(); ++c) {
      mlo[tree.joints[j].idx_v() + c] = lo;
      mhi[tree.joints[j].idx_v() + c] = hi;
    }
  }
}

}  // namespace closedchain
