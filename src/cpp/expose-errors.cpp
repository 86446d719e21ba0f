// closedchain._core: the C++ errors (errors.hpp) raised in Python as the exceptions
// that closedchain.exceptions declares (the one module that declares them).

#include <boost/python.hpp>

#include <cmath>

#include "errors.hpp"
#include "expose.hpp"

namespace closedchain {

namespace {

/// The exception class `name` of closedchain.exceptions.
bp::object exception_class(const char *name) {
  return bp::import("closedchain.exceptions").attr(name);
}

/// Raise the Python exception `inst` of class `cls`.
void set_error(const bp::object &cls, const bp::object &inst) {
  PyErr_SetObject(cls.ptr(), inst.ptr());
}

/// SingularError -> SingularConfigurationError with q, condition_number and t.
void translate_singular(const SingularError &e) {
  bp::object cls = exception_class("SingularConfigurationError");
  bp::dict kw;
  kw["q"] = to_numpy(e.q);
  kw["condition_number"] = e.cond;
  kw["t"] = std::isnan(e.t) ? bp::object() : bp::object(e.t);
  set_error(cls, cls(*bp::make_tuple(e.message), **kw));
}

/// SimulationFailure -> SimulationError(message, t).
void translate_simulation(const SimulationFailure &e) {
  bp::object cls = exception_class("SimulationError");
  set_error(cls, cls(e.message, e.t));
}

/// RowCheckRequired -> closedchain's RowCheckRequired(message, t).
void translate_row_check(const RowCheckRequired &e) {
  bp::object cls = exception_class("RowCheckRequired");
  set_error(cls, cls(e.message, e.t));
}

/// BadArgument -> ClosedChainError(message).
void translate_bad(const BadArgument &e) {
  bp::object cls = exception_class("ClosedChainError");
  set_error(cls, cls(e.message));
}

/// NonFinite -> NonFiniteError(message).
void translate_non_finite(const NonFinite &e) {
  bp::object cls = exception_class("NonFiniteError");
  set_error(cls, cls(e.message));
}

}  // namespace

void expose_errors() {
  bp::register_exception_translator<SingularError>(&translate_singular);
  bp::register_exception_translator<SimulationFailure>(&translate_simulation);
  bp::register_exception_translator<RowCheckRequired>(&translate_row_check);
  bp::register_exception_translator<BadArgument>(&translate_bad);
  bp::register_exception_translator<NonFinite>(&translate_non_finite);
}

}  // namespace closedchain
