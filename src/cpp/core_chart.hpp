// closedchain._core: the chart of q for the integrators when nq != nv (simulate/chart.py):
// the state holds x with q = integrate(q_c, x), dx/dt = D(x)^-1 v, D = dIntegrate/dx.
// (Functions over (CoreModel, CoreData): their declarations, then their definitions.)

#pragma once

#include <pinocchio/algorithm/joint-configuration.hpp>

#include "common.hpp"
#include "core_data.hpp"
#include "core_model.hpp"

namespace closedchain {

// -- declarations ------------------------------------------------------------

/// The chart of the adaptive loops when nq != nv (simulate/chart.py): the state
/// holds x with q = integrate(q_c, x), dx/dt = D(x)^-1 v, D = dIntegrate/dx.
void chart_start(const CoreModel &model, CoreData &data, const Vec &q0);

/// out = D(x)^-1 v for q = integrate(q_c, x): the identity but on the blocks of
/// the joints whose integrate is not x + v (free-flyer, spherical, planar).
void chart_rate(const CoreModel &model, CoreData &data, const Vec &q_c,
                const Eigen::Ref<const Vec> &x, const Eigen::Ref<const Vec> &v,
                Eigen::Ref<Vec> out);

/// The configuration of state y's position part (y itself without a chart).
RefV chart_q(const CoreModel &model, CoreData &data, const Eigen::Ref<const Vec> &x);

/// Re-centre the chart when a curved joint's block exceeds RECENTRE_NORM.
bool chart_recentre(const CoreModel &model, CoreData &data, Eigen::Ref<Vec> x);

// -- definitions -------------------------------------------------------------

inline void chart_start(const CoreModel &model, CoreData &data, const Vec &q0) {
  data.chart = model.nq != model.nv;
  if (!data.chart) return;
  data.chart_centre = q0;
  data.chart_config = q0;
}

inline void chart_rate(const CoreModel &model, CoreData &data, const Vec &q_c,
                       const Eigen::Ref<const Vec> &x, const Eigen::Ref<const Vec> &v,
                       Eigen::Ref<Vec> out) {
  out = v;
  if (model.curved_joints.empty()) return;
  pinocchio::dIntegrate(model.tree, q_c, x, data.chart_D, pinocchio::ARG1);
  for (const auto &b : model.curved_joints) {
    SmallMat Db = data.chart_D.block(b.first, b.first, b.second, b.second);
    out.segment(b.first, b.second) = Db.partialPivLu().solve(v.segment(b.first, b.second));
  }
}

inline RefV chart_q(const CoreModel &model, CoreData &data, const Eigen::Ref<const Vec> &x) {
  if (!data.chart) return x;
  pinocchio::integrate(model.tree, data.chart_centre, x, data.chart_config);
  return data.chart_config;
}

inline bool chart_recentre(const CoreModel &model, CoreData &data, Eigen::Ref<Vec> x) {
  bool far = false;
  for (const auto &b : model.curved_joints)
    far = far || x.segment(b.first, b.second).norm() > RECENTRE_NORM;
  if (!far) return false;
  pinocchio::integrate(model.tree, data.chart_centre, x, data.chart_config);
  data.chart_centre = data.chart_config;
  x.setZero();
  return true;
}

}  // namespace closedchain
