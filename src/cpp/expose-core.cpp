// closedchain._core: class Core, the compiled constraint rows, forward dynamics and
// integration loops of one mechanism, and the integrator codes.
//
// The one translation unit that instantiates Pinocchio's algorithms (core_all.hpp:
// a unit including them compiles in minutes). The Python side (closedchain.compiled)
// builds one Core per mechanism from the Pinocchio model and the constraint layer's
// row table; the model is used by reference, the Core owns its Data and every buffer.

#include <boost/python.hpp>
#include <eigenpy/eigenpy.hpp>

#include <string>

#include "core_all.hpp"
#include "expose.hpp"
#include "percall.hpp"

namespace closedchain {

void expose_core() {
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
      .def("configure", &Core::configure, bp::args("self", "run", "solver", "simulation"),
           "Set the method and options (RunOptions), SolverSettings and SimulationSettings.")
      .def("set_tau", &Core::set_tau, bp::args("self", "tau"))
      .def("set_passive", &Core::set_passive,
           bp::args("self", "idx_q", "idx_v", "stiffness", "reference", "damping"),
           "Joint springs and damping: h - tau_passive, tau_passive = -K (q - q_ref) - D v.")
      .def("set_declared", &Core::set_declared,
           bp::args("self", "kinds", "fid_p", "fid_s", "vec1", "vec2", "kept", "labels"),
           "Every declared row (kept[i] = 1 for the rows the methods use), checked each step.")
      .def("set_band", &Core::set_band, bp::args("self", "perm", "banded_p", "banded_n"),
           "Use band Cholesky factorizations: of M + alpha J^T J in the order perm "
           "(banded_p) and of J J^T (banded_n); returns their half bandwidths.")
      .def("tree_solves", &Core::tree_solves, bp::args("self"),
           "True when the configured method takes the tree path (core_tree.hpp).")
      .def("set_tree_path", &Core::set_tree_path, bp::args("self", "on"),
           "Allow the tree path (chosen at construction by size) or not (the dense path).")
      .def("band_info", &Core::band_info, bp::args("self"),
           "(banded_p, banded_n, b_p, b_n) as set by set_band.")
      .def("rows", &Core::py_rows, bp::args("self", "q", "v"),
           "(phi, J, gamma) at (q, v); gamma includes the Baumgarte terms when configured.")
      .def("forward", &Core::py_forward, bp::args("self", "q", "v", "tau"), "(a, lam) at (q, v).")
      .def("forward_checked", &forward_checked, bp::args("self", "q", "v", "tau"),
           "(a, lam, J, gamma) at (q, v) with tau (None: zeros), the arguments checked: "
           "closedchain.forward_dynamics.")
      .def("phi_checked", &phi_checked, bp::args("self", "q"), "phi(q), q checked.")
      .def("jacobian_checked", &jacobian_checked, bp::args("self", "q"), "J(q), q checked.")
      .def("gamma_checked", &gamma_checked, bp::args("self", "q", "v"),
           "gamma(q, v), the arguments checked.")
      .def("project_checked", &project_checked, bp::args("self", "q", "v", "free", "rcond"),
           "(v projected onto J v = 0 moving the free entries, max |J v|, its row, "
           "sigma_max(J)): closedchain.project_velocity.")
      .def("assemble_checked", &assemble_checked,
           bp::args("self", "q_guess", "free", "tol", "max_iter", "max_halvings",
                    "fallback_rcond", "contraction"),
           "q closed by Gauss-Newton moving the free velocity indices and aligned, or None "
           "(not converged, or a spurious closure): closedchain.assemble.")
      .def("inverse_checked", &inverse_checked,
           bp::args("self", "q", "v", "a_P", "indices", "n_A", "tau_passive", "cond_max",
                    "weak_rcond"),
           "(status, cond, a, tau, lam, J, gamma, dynamics residual, constraint residual): "
           "closedchain.inverse_dynamics.")
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
           "projections) with settings (Ali3pSettings).")
      .def("run_adaptive", &Core::run_adaptive,
           bp::args("self", "integrator", "q0", "v0", "t_final", "rtol", "atol", "t_eval",
                    "projects", "progress"))
      .def("run_rk43", &Core::run_rk43,
           bp::args("self", "q0", "v0", "t_final", "rtol", "atol", "h0", "t_eval", "record_all",
                    "progress"),
           "rk4 with stage projection and an embedded error estimate (simulate/rk43.py).")
      .def("run_dop853_rk43", &Core::run_dop853_rk43,
           bp::args("self", "q0", "v0", "t_final", "rtol", "atol", "h0", "t_eval", "progress"),
           "DOP853 far from singular positions, rk43 near them (simulate/dop853_rk43.py); "
           "every step end recorded and the times t_eval, their samples in 'outputs'.")
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

}  // namespace closedchain
