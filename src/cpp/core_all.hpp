// closedchain._core: class Core with every member function (one translation unit,
// expose-core.cpp, includes this: Pinocchio's algorithms are instantiated once).

#pragma once

#include "core.hpp"

#include "core_interface.hpp"
#include "core_rows.hpp"
#include "core_structure.hpp"
#include "core_methods.hpp"
#include "core_projection.hpp"
#include "core_partitioning.hpp"
#include "core_recording.hpp"
#include "core_fixed.hpp"
#include "core_adaptive.hpp"
