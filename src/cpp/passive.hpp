// closedchain._core: the passive joint forces of a mechanism, a term of the dynamics
// (closedchain/passive.py is the numpy reference):
//   tau_passive(q, v) = -K (q - q_ref) - D v,
// K the joint springs (one coordinate each: revolute or prismatic joints), D the viscous
// damping per velocity coordinate. They enter the bias forces, h <- h - tau_passive, so
// that every method, integrator and the inverse dynamics solve M a + h = tau + J^T lam
// with them (eval_terms, core_rows.hpp). Armature needs nothing here: it is Pinocchio's
// model.armature, on M's diagonal in tree_terms and in the tree path's recursion.

#pragma once

#include <Eigen/Dense>

#include <vector>

#include "common.hpp"
#include "errors.hpp"

namespace closedchain {

/// Joint springs and viscous damping (set_passive); none by default.
struct PassiveForces {
  /// The springs' configuration and velocity indices.
  std::vector<int> spring_q, spring_v;
  /// Their stiffness [N m/rad or N/m] and reference [rad or m].
  Vec stiffness, reference;
  /// Damping per velocity coordinate [N m s/rad or N s/m], shape (nv,), or empty: none.
  Vec damping;

  /// Set them, checked against the model's sizes (BadArgument).
  void set(int nq, int nv, const Eigen::VectorXi &idx_q, const Eigen::VectorXi &idx_v,
           const Vec &k, const Vec &ref, const Vec &d) {
    const Eigen::Index n = idx_q.size();
    if (idx_v.size() != n || k.size() != n || ref.size() != n)
      throw BadArgument{"set_passive: spring arrays of different lengths"};
    if (d.size() != 0 && d.size() != nv)
      throw BadArgument{"set_passive: damping must have shape (nv,) or (0,)"};
    for (Eigen::Index s = 0; s < n; ++s)
      if (idx_q[s] < 0 || idx_q[s] >= nq || idx_v[s] < 0 || idx_v[s] >= nv)
        throw BadArgument{"set_passive: spring index out of range"};
    if (!k.allFinite() || !ref.allFinite() || !d.allFinite() || (k.array() < 0.0).any() ||
        (d.array() < 0.0).any())
      throw BadArgument{"set_passive: stiffness and damping must be finite and >= 0"};
    spring_q.assign(idx_q.data(), idx_q.data() + n);
    spring_v.assign(idx_v.data(), idx_v.data() + n);
    stiffness = k;
    reference = ref;
    damping = d.size() && (d.array() != 0.0).any() ? d : Vec();
  }

  /// h += K (q - q_ref) + D v: the bias forces minus tau_passive(q, v).
  template <class Q, class V>
  void subtract_from_bias(const Q &q, const V &v, Vec &h) const {
    for (std::size_t s = 0; s < spring_q.size(); ++s)
      h[spring_v[s]] += stiffness[s] * (q[spring_q[s]] - reference[s]);
    if (damping.size()) h += damping.cwiseProduct(v);
  }
};

}  // namespace closedchain
