// closedchain._core: the types every header of the core uses (Pinocchio's model and
// data, Eigen vectors and matrices, boost.python).

#pragma once

#include <pinocchio/multibody/data.hpp>
#include <pinocchio/multibody/model.hpp>

#include <Eigen/Dense>
#include <boost/python.hpp>

namespace bp = boost::python;

namespace closedchain {

using Model = pinocchio::Model;
using Data = pinocchio::Data;
using Vec = Eigen::VectorXd;
using Mat = Eigen::MatrixXd;
using Mat6x = Eigen::Matrix<double, 6, Eigen::Dynamic>;
using Eigen::Vector3d;
using RefV = Eigen::Ref<const Vec>;
using SmallMat = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, 0, 6, 6>;  // no heap

}  // namespace closedchain
