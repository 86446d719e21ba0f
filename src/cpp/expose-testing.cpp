// closedchain._core_testing: helpers that only the tests call, in a module of their own
// built only with -DCLOSEDCHAIN_TESTING=ON (scripts/setup_venv.sh test, the test install).
// tests/test_compiled.py compares tree_terms.hpp's passes with pinocchio.crba,
// nonLinearEffects, computeJointJacobians and forwardKinematics; tests/test_pindata.py
// compares lean_data with pinocchio.Data field by field; tests/test_dynamics.py runs
// al_iteration.hpp's iteration with P factored at another penalty (a divergence).

#include <boost/python.hpp>
#include <eigenpy/eigenpy.hpp>

#include "al_iteration.hpp"
#include "common.hpp"
#include "errors.hpp"
#include "lean_data.hpp"
#include "tree_terms.hpp"

namespace closedchain {

namespace {

/// oMi, J (world columns), ov, oa of `data` after a pass of tree_terms.hpp.
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

/// M, h, oMi, J (world columns), ov, oa (bias accelerations) by tree_terms(q, v);
/// at_kinematics: by joint_kinematics(q) then tree_terms_at_kinematics(q, v).
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

/// oMi and J by joint_kinematics(q) alone.
bp::dict kinematics_py(bp::object model_obj, const Vec &q) {
  const Model &model = bp::extract<const Model &>(model_obj)();
  if (q.size() != model.nq) throw BadArgument{"_joint_kinematics: q must have shape (nq,)"};
  Data data = lean_data(model);
  joint_kinematics(TreePlan(model), model, data, q);
  return results(model, data);
}

/// Which joints (by index, the universe 0 included) take the revolute path.
bp::list revolute_joints_py(bp::object model_obj) {
  const Model &model = bp::extract<const Model &>(model_obj)();
  const TreePlan plan(model);
  bp::list out;
  for (int i = 0; i < model.njoints; ++i) out.append(i > 0 && plan.revolute((std::size_t)i));
  return out;
}

/// True when lean_data(model), with the four tensors of a full Data copied in,
/// equals pinocchio::Data(model) field by field (Pinocchio's operator==).
bool lean_data_matches_full(const Model &model) {
  Data full(model);
  Data lean = lean_data(model);
  if (lean.d2tau_dqdq.size() != 0) return false;
  lean.d2tau_dqdq = full.d2tau_dqdq;
  lean.d2tau_dvdv = full.d2tau_dvdv;
  lean.d2tau_dqdv = full.d2tau_dqdv;
  lean.d2tau_dadq = full.d2tau_dadq;
  return lean == full;
}

/// al_iterate's products on dense M, J and the Cholesky factor of P.
struct DenseTestOps {
  const Mat &M, &J;
  const Eigen::LLT<Mat> &P;
  void add_j(const Vec &x, Vec &y) const { y += J * x; }
  void sub_m(const Vec &x, Vec &y) const { y -= M * x; }
  void sub_jt(const Vec &y, Vec &x) const { x -= J.transpose() * y; }
  void sub_scaled_jt(double s, const Vec &y, Vec &x) const { x -= s * (J.transpose() * y); }
  void solve(Vec &x) const { x = P.solve(x); }
};

/// al_iterate from x = 0 with P = M + alpha_factor J^T J factored and the iteration's
/// penalty alpha: (x, lam, iterates); its SingularError as SingularConfigurationError.
bp::tuple al_iterate_py(const Mat &M, const Mat &J, const Vec &rhs, const Vec &g,
                        double alpha_factor, double alpha, double tol, int max_iter) {
  Eigen::LLT<Mat> P(M + alpha_factor * J.transpose() * J);
  DenseTestOps ops{M, J, P};
  Vec x = Vec::Zero(M.rows()), delta = x, lam = Vec::Zero(J.rows()), rc = lam;
  int it = 0;
  try {
    it = al_iterate(ops, alpha, rhs, g, max_iter, tol, x, lam, delta, rc);
  } catch (const SingularError &e) {
    bp::object cls = bp::import("closedchain.exceptions").attr("SingularConfigurationError");
    PyErr_SetObject(cls.ptr(), cls(e.message).ptr());
    bp::throw_error_already_set();
  }
  return bp::make_tuple(x, lam, it);
}

}  // namespace

}  // namespace closedchain

BOOST_PYTHON_MODULE(_core_testing) {
  using namespace closedchain;
  // The production module registers the converters and the error translators.
  bp::import("closedchain._core");
  bp::def("_tree_terms", &tree_terms_py,
          (bp::arg("model"), bp::arg("q"), bp::arg("v"), bp::arg("at_kinematics") = false),
          "Test helper: dict of M, h, oMi, J, ov, oa from tree_terms.hpp's pass.");
  bp::def("_joint_kinematics", &kinematics_py, bp::args("model", "q"),
          "Test helper: dict of oMi, J (and zero ov, oa) from tree_terms.hpp's kinematics pass.");
  bp::def("_revolute_joints", &revolute_joints_py, bp::args("model"),
          "Test helper: per joint, whether tree_terms.hpp's revolute path computes it.");
  bp::def("_lean_data_matches_full", &lean_data_matches_full, bp::args("model"),
          "Test helper: lean_data(model) equals pinocchio.Data(model) apart from those tensors.");
  bp::def("_al_iterate", &al_iterate_py,
          bp::args("M", "J", "rhs", "g", "alpha_factor", "alpha", "tol", "max_iter"),
          "Test helper: (x, lam, iterates) of al_iteration.hpp with P factored at alpha_factor.");
}
