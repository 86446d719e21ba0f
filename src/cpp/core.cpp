// closedchain._core: the compiled right-hand side and integration loops.
//
// One translation unit (a unit including Pinocchio's algorithms compiles in
// minutes). The Python side (closedchain.compiled) builds one Core per
// mechanism from the Pinocchio model and the constraint layer's row table; the
// model is used by reference, the Core owns its Data and every buffer.
//

#include <boost/python.hpp>
#include <eigenpy/eigenpy.hpp>

#include <cmath>
#include <string>

#include "core_all.hpp"
#include "lean_data.hpp"
#include "tree_terms.hpp"

namespace closedchain {

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
      .def("run_rk43", &Core::run_rk43,
           bp::args("self", "q0", "v0", "t_final", "rtol", "atol", "h0", "t_eval", "record_all",
                    "progress"),
           "rk4 with stage projection and an embedded error estimate (simulate/rk43.py).")
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
