// closedchain._core: lean_data (lean_data.cpp), the pinocchio.Data that closedchain.pindata
// builds for large models.

#include <boost/python.hpp>

#include <pinocchio/multibody/data.hpp>
#include <pinocchio/multibody/model.hpp>

#include "expose.hpp"
#include "lean_data.hpp"

namespace closedchain {

void expose_pindata() {
  boost::python::def(
      "lean_data", &lean_data, boost::python::args("model"),
      "A pinocchio.Data of model without the four nv^3 second-order derivative tensors "
      "(every other field as pinocchio.Data(model)).");
}

}  // namespace closedchain
