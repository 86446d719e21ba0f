// closedchain._core: a Pinocchio Data without the nv^3 tensors (lean_data.cpp).
#pragma once

#include <pinocchio/multibody/fwd.hpp>

namespace closedchain {

/// pinocchio::Data(model) minus d2tau_dqdq/dvdv/dqdv/dadq (left empty).
pinocchio::Data lean_data(const pinocchio::Model& model);

}  // namespace closedchain
