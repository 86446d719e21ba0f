// closedchain._core: the binding functions of the module, one per concept, each
// defined in its own expose-<concept>.cpp and called by module.cpp (Pinocchio's
// bindings/python layout). Only expose-core.cpp instantiates Pinocchio's algorithms
// (through core_all.hpp); the others include light headers.

#pragma once

namespace closedchain {

/// Translators of the C++ errors (errors.hpp) into closedchain.exceptions (expose-errors.cpp).
void expose_errors();

/// The typed settings classes of Core.configure and Core.run_ali3p (expose-settings.cpp).
void expose_settings();

/// lean_data: a pinocchio.Data without the nv^3 tensors (expose-pindata.cpp).
void expose_pindata();

/// class Core and the integrator codes (expose-core.cpp).
void expose_core();

}  // namespace closedchain
