// closedchain._core: the compiled constraint rows, dynamics methods and integration
// loops (see docs/design/compiled-core.md). The bindings are split by concept
// (expose.hpp); the test-only helpers are in a second module, closedchain._core_testing
// (expose-testing.cpp), built only with -DCLOSEDCHAIN_TESTING=ON.

#include <boost/python.hpp>
#include <eigenpy/eigenpy.hpp>

#include "expose.hpp"

BOOST_PYTHON_MODULE(_core) {
  boost::python::import("pinocchio");  // its converters (Model, Data) first
  eigenpy::enableEigenPy();
  eigenpy::enableEigenPySpecific<Eigen::VectorXi>();
  closedchain::expose_errors();
  closedchain::expose_settings();
  closedchain::expose_pindata();
  closedchain::expose_core();
}
