// closedchain._core: the argument checks of the per-call entry points (expose-core.cpp's
// *_checked functions): shape, finiteness and normalization of q, v and tau, with the
// messages of closedchain.mechanism.Mechanism.check_q / check_v, so that a public call
// on the compiled core checks its arguments in one pass instead of in numpy.

#pragma once

#include <Python.h>

#include <pinocchio/algorithm/joint-configuration.hpp>

#include <cmath>
#include <string>

#include "common.hpp"
#include "constants.hpp"
#include "errors.hpp"

namespace closedchain {

/// numpy, imported once.
inline bp::object numpy_module() {
  static bp::object np = bp::import("numpy");
  return np;
}

/// A read-only 1-D float64 view of a Python argument: the object itself when it exposes
/// such a buffer (a float64 numpy array, also strided), else numpy.asarray(obj,
/// dtype=float) (lists, other dtypes; copied when its stride is negative). The
/// constructor checks the shape (n,) and finiteness and throws BadArgument with the
/// messages of Mechanism.check_v: "<name> has shape (k,), expected (n,)", "<name>
/// contains non-finite values: <array>".
class VectorArg {
 public:
  /// The argument's values in place: a strided view of the Python buffer.
  using Map = Eigen::Map<const Vec, 0, Eigen::InnerStride<>>;

  /// Check obj as argument `name` of length n; throws BadArgument (see the class).
  VectorArg(bp::object obj, const std::string &name, Eigen::Index n) : obj_(obj) {
    if (!take_view()) {
      obj_ = numpy_module().attr("asarray")(obj, "float64");
      const bp::object shape = obj_.attr("shape");
      if (bp::len(shape) != 1 || bp::extract<long>(shape[0])() != n) shape_error(name, shape, n);
      if (!take_view()) {  // a negative stride
        obj_ = obj_.attr("copy")();
        if (!take_view()) throw BadArgument{name + ": not a 1-D array of floats"};
      }
    }
    if (buffer_.view.shape[0] != n) shape_error(name, obj_.attr("shape"), n);
    if (!map().allFinite()) {
      const bp::object arr = numpy_module().attr("asarray")(obj_, "float64");
      throw BadArgument{name + " contains non-finite values: " +
                        std::string(bp::extract<std::string>(bp::str(arr)))};
    }
  }
  /// Not copyable: it holds a Python buffer.
  VectorArg(const VectorArg &) = delete;
  VectorArg &operator=(const VectorArg &) = delete;

  /// The values, shape (n,).
  Map map() const {
    const Py_buffer &view = buffer_.view;
    return Map(static_cast<const double *>(view.buf), view.shape[0],
               Eigen::InnerStride<>(view.strides[0] / static_cast<Py_ssize_t>(sizeof(double))));
  }

 private:
  /// Take obj_'s buffer when it is 1-D float64 with a positive stride; else false.
  bool take_view() {
    Py_buffer &view = buffer_.view;
    if (PyObject_GetBuffer(obj_.ptr(), &view, PyBUF_RECORDS_RO) != 0) {
      PyErr_Clear();
      return false;
    }
    const std::string format = view.format ? view.format : "B";
    const bool ok = view.ndim == 1 && view.itemsize == sizeof(double) &&
                    (format == "d" || format == "<d" || format == "=d") &&
                    view.strides[0] > 0 && view.strides[0] % sizeof(double) == 0;
    if (!ok) {
      PyBuffer_Release(&view);
      return false;
    }
    buffer_.held = true;
    return true;
  }

  /// Throw BadArgument: "<name> has shape <shape>, expected (n,)".
  [[noreturn]] static void shape_error(const std::string &name, const bp::object &shape,
                                       Eigen::Index n) {
    throw BadArgument{name + " has shape " + std::string(bp::extract<std::string>(bp::str(shape))) +
                      ", expected (" + std::to_string(n) + ",)"};
  }

  /// The buffer taken from obj_, released on destruction (also when the constructor
  /// throws: a member, it is destroyed then).
  struct Buffer {
    Py_buffer view{};   ///< The exporter's buffer description.
    bool held = false;  ///< Whether view holds a buffer to release.
    Buffer() = default;
    /// Not copyable: a buffer is released once.
    Buffer(const Buffer &) = delete;
    Buffer &operator=(const Buffer &) = delete;
    ~Buffer() {
      if (held) PyBuffer_Release(&view);
    }
  };

  bp::object obj_;  ///< The object whose buffer is viewed (the argument or its float64 copy).
  Buffer buffer_;   ///< Its buffer, while held.
};

/// Throw BadArgument, with Mechanism.check_q's message, when a joint whose configuration is
/// on a sphere (a continuous joint's (cos, sin), a quaternion) is off it by more than
/// NORMALIZATION_TOL: Pinocchio would use a scaled rotation, silently.
inline void check_normalized(const Model &model, const Eigen::Ref<const Vec> &q,
                             const std::string &name) {
  if (model.nq == model.nv || pinocchio::isNormalized(model, q, NORMALIZATION_TOL)) return;
  for (std::size_t j = 1; j < model.joints.size(); ++j) {
    const auto &jm = model.joints[j];
    if (jm.nq() == jm.nv()) continue;
    const Vec seg = q.segment(jm.idx_q(), jm.nq());
    const double norm = (jm.nq() > 4 ? Vec(seg.tail(4)) : seg).norm();
    if (std::abs(norm - 1.0) > NORMALIZATION_TOL) {
      const bp::object msg =
          bp::str("{}: the configuration of joint {!r} (q[{}:{}] = {}) has norm {:.12g}, "
                  "expected 1 (use pinocchio.normalize)")
              .attr("format")(name, model.names[j], jm.idx_q(), jm.idx_q() + jm.nq(),
                              to_numpy(seg), norm);
      throw BadArgument{bp::extract<std::string>(msg)};
    }
  }
}

/// A checked configuration: VectorArg of shape (nq,) and check_normalized.
class ConfigurationArg : public VectorArg {
 public:
  ConfigurationArg(bp::object obj, const Model &model, const std::string &name = "q")
      : VectorArg(obj, name, model.nq) {
    if (model.nq != model.nv) check_normalized(model, map(), name);
  }
};

}  // namespace closedchain
