// closedchain._core: the types every header of the core uses (Pinocchio's model and
// data, Eigen vectors and matrices, boost.python).

#pragma once

#include <pinocchio/multibody/data.hpp>
#include <pinocchio/multibody/model.hpp>

#include <Eigen/Dense>
#include <boost/python.hpp>

namespace bp = boost::python;

namespace closedchain {

using Model = pinocchio::Model;  ///< Pinocchio's kinematic tree and inertias.
using Data = pinocchio::Data;    ///< Pinocchio's work buffers for one Model.
using Vec = Eigen::VectorXd;     ///< A dynamic column vector.
using Mat = Eigen::MatrixXd;     ///< A dynamic column-major matrix.
using Mat6x = Eigen::Matrix<double, 6, Eigen::Dynamic>;  ///< Rows of a spatial Jacobian.
using Eigen::Vector3d;
using RefV = Eigen::Ref<const Vec>;  ///< A read-only vector argument that binds without a copy.
/// At most 6 x 6 (one loop's rows), stored inline: no heap allocation.
using SmallMat = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, 0, 6, 6>;

}  // namespace closedchain
