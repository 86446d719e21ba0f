// closedchain._core: the errors thrown in C++ (translated into closedchain's Python
// exceptions by the module, expose-errors.cpp) and the number formats of their messages.

#pragma once

#include <cmath>
#include <cstdio>
#include <sstream>
#include <string>

#include "common.hpp"

namespace closedchain {

/// A singular configuration (closedchain.exceptions.SingularConfigurationError).
struct SingularError {
  std::string message;  ///< One line naming the matrix, its condition and the remedy.
  double cond;          ///< The condition estimate that failed the limit.
  double t;             ///< Time of the failure in s; NaN outside a simulation.
  Vec q;                ///< Configuration at the failure.
};

/// A simulation that cannot go on (closedchain.exceptions.SimulationError).
struct SimulationFailure {
  std::string message;  ///< One line: what failed and the remedy.
  double t;             ///< Time of the failure in s.
};

/// An argument that fails its check (closedchain.exceptions.ClosedChainError).
struct BadArgument {
  std::string message;  ///< One line naming the argument and what it takes.
};

/// A per-call result overflowed to inf or NaN (closedchain.exceptions.NonFiniteError).
struct NonFinite {
  std::string message;  ///< One line naming the result and the input sizes.
};

/// The kept rows stopped describing the loops at t (a dropped row opened, or the
/// kept rows degenerate): the Python side re-selects them (closedchain.closure).
struct RowCheckRequired {
  std::string message;  ///< Which row check failed.
  double t;             ///< Time of the check in s.
};

/// x formatted by the printf format f (one number).
inline std::string fmt(const char *f, double x) {
  char buf[64];
  std::snprintf(buf, sizeof buf, f, x);
  return buf;
}

/// q as "[a b c]", each entry to 6 significant digits, for error messages.
inline std::string vec_str(const Vec &q) {
  std::ostringstream s;
  s << "[";
  for (Eigen::Index i = 0; i < q.size(); ++i) s << (i ? " " : "") << fmt("%.6g", q[i]);
  s << "]";
  return s.str();
}

/// A copy of x as a numpy array.
inline bp::object to_numpy(const Vec &x) { return bp::object(Vec(x)); }

}  // namespace closedchain
