// closedchain._core: the errors thrown in C++ (translated into closedchain's Python
// exceptions by the module, expose-errors.cpp) and the number formats of their messages.

#pragma once

#include <cmath>
#include <cstdio>
#include <sstream>
#include <string>

#include "common.hpp"

namespace closedchain {


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

// A per-call result overflowed to inf or NaN (closedchain.exceptions.NonFiniteError).
struct NonFinite {
  std::string message;
};

// The kept rows stopped describing the loops at t (a dropped row opened, or the
// kept rows degenerate): the Python side re-selects them (closedchain.closure).
struct RowCheckRequired {
  std::string message;
  double t;
};

inline std::string fmt(const char *f, double x) {
  char buf[64];
  std::snprintf(buf, sizeof buf, f, x);
  return buf;
}

inline std::string vec_str(const Vec &q) {
  std::ostringstream s;
  s << "[";
  for (Eigen::Index i = 0; i < q.size(); ++i) s << (i ? " " : "") << fmt("%.6g", q[i]);
  s << "]";
  return s.str();
}

inline bp::object to_numpy(const Vec &x) { return bp::object(Vec(x)); }

}  // namespace closedchain
