// closedchain._core: everything the bindings use (the facade Core and, through it, every
// concept header); expose-core.cpp, the one translation unit, includes this.

#pragma once

#include "core.hpp"
