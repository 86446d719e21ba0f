// closedchain._core: the typed settings (settings.hpp) as Python classes. Each class
// lists the fields it binds in its attribute `fields`: closedchain.compiled copies
// them by name from the Python settings dataclasses (SolverSettings,
// SimulationSettings, SimulationSettings.ali3p_*), so a field the core reads is a
// field of the dataclass or the copy fails.

#include <boost/python.hpp>
#include <eigenpy/eigenpy.hpp>

#include <string>

#include "errors.hpp"
#include "expose.hpp"
#include "settings.hpp"

namespace closedchain {

namespace {

/// A bound settings class that records the names of the fields it binds.
template <class T>
class SettingsClass {
 public:
  SettingsClass(const char *name, const char *doc) : cls_(name, doc, bp::init<>()) {}

  /// Bind the member `member` as the read-write attribute `name` (read by value: an
  /// array field is returned as a new numpy array).
  template <class M>
  SettingsClass &field(const char *name, M T::*member, const char *doc) {
    cls_.add_property(name, bp::make_getter(member, bp::return_value_policy<bp::return_by_value>()),
                      bp::make_setter(member), doc);
    names_.append(name);
    return *this;
  }

  /// Bind the property `name` (getter, setter) as a field.
  template <class Get, class Set>
  SettingsClass &property(const char *name, Get get, Set set, const char *doc) {
    cls_.add_property(name, get, set, doc);
    names_.append(name);
    return *this;
  }

  /// Set the class attribute `fields`: the names bound, in order.
  void done() { cls_.attr("fields") = bp::tuple(names_); }

 private:
  bp::class_<T> cls_;
  bp::list names_;
};

/// SolverSettings.baumgarte as in Python: None, or the gains (alpha, beta) [1/s].
bp::object get_baumgarte(const SolverSettings &s) {
  return s.baumgarte ? bp::object(bp::make_tuple(s.baumgarte_alpha, s.baumgarte_beta))
                     : bp::object();
}

void set_baumgarte(SolverSettings &s, bp::object gains) {
  s.baumgarte = !gains.is_none();
  if (!s.baumgarte) return;
  if (bp::len(gains) != 2)
    throw BadArgument{"SolverSettings.baumgarte: None or the gains (alpha, beta) [1/s]"};
  s.baumgarte_alpha = bp::extract<double>(gains[0]);
  s.baumgarte_beta = bp::extract<double>(gains[1]);
}

}  // namespace

void expose_settings() {
  SettingsClass<RunOptions>("RunOptions", "The method and the options of Core.configure.")
      .field("method", &RunOptions::method,
             "Forward-dynamics method: kkt, schur, nullspace, augmented-lagrangian or reduced.")
      .field("stage_projects", &RunOptions::stage_projects,
             "Project every stage state of a fixed-step loop (stage-projection).")
      .field("singular_robust", &RunOptions::singular_robust,
             "Pass singular positions: no stop on cond(J).")
      .field("partitions", &RunOptions::partitions,
             "Stabilization partitioning (dependent coordinates solved at every evaluation).")
      .field("independent", &RunOptions::independent,
             "The partition a partitioning run starts from (int32 velocity indices); empty: "
             "the last one given.")
      .done();
  SettingsClass<SolverSettings>(
      "SolverSettings", "closedchain.dynamics.SolverSettings: the fields the core reads.")
      .field("cond_max", &SolverSettings::cond_max,
             "Largest condition number of a matrix a method factorizes.")
      .property("baumgarte", &get_baumgarte, &set_baumgarte,
                "Baumgarte gains (alpha, beta) [1/s], or None.")
      .field("al_penalty", &SolverSettings::al_penalty,
             "Relative penalty rho of the augmented Lagrangian (dimensionless).")
      .field("al_tol", &SolverSettings::al_tol,
             "Its stop: max |a_{k+1} - a_k| <= al_tol (1 + max |a_{k+1}|).")
      .field("al_max_iter", &SolverSettings::al_max_iter, "Its iteration cap.")
      .done();
  using S = SimulationSettings;
  SettingsClass<S>("SimulationSettings",
                   "closedchain.simulate.SimulationSettings: the fields the compiled loops read.")
      .field("projection_tol", &S::projection_tol,
             "Target max |phi| of the position projection [m or -].")
      .field("projection_iters", &S::projection_iters,
             "Gauss-Newton iterations of the position projection.")
      .field("project_velocities", &S::project_velocities,
             "Project v onto J v = 0 after each step.")
      .field("singular_cond", &S::singular_cond, "Stop when cond_2(J) at a step exceeds this.")
      .field("drift_limit", &S::drift_limit,
             "Stop when max |phi| over every declared row exceeds this [m or -].")
      .field("singular_zone", &S::singular_zone,
             "ALI3-P keeps its step ends this many steps from a singular position.")
      .field("stage_singular_zone", &S::stage_singular_zone,
             "rk4 with stage projection keeps its evaluation points this many steps away.")
      .field("dropped_row_tol", &S::dropped_row_tol,
             "A dropped row open by more than this [m or -] calls for re-selection.")
      .field("dropped_row_ratio", &S::dropped_row_ratio,
             "... and by this times the kept rows' residual.")
      .field("dependent_tol", &S::dependent_tol,
             "Max |phi| of the dependent-coordinate solve [m or -].")
      .field("repartition_cond", &S::repartition_cond,
             "Re-partition when cond(J_D) exceeds this.")
      .field("partition_singular_cond", &S::partition_singular_cond,
             "Stop when the best-conditioned J_D exceeds this condition number.")
      .done();
  SettingsClass<Ali3pSettings>("Ali3pSettings",
                               "SimulationSettings.ali3p_*: the settings of one ALI3-P run.")
      .field("tol", &Ali3pSettings::tol,
             "Newton stops when the largest correction is below this [rad or m].")
      .field("phi_tol", &Ali3pSettings::phi_tol, "... and max |phi| is below this [m or -].")
      .field("max_iter", &Ali3pSettings::max_iter, "Newton iterations per step at most.")
      .field("penalty", &Ali3pSettings::penalty,
             "Relative penalty rho, h^2 alpha / 4 = rho tr(M) / tr(J^T J).")
      .done();
}

}  // namespace closedchain
