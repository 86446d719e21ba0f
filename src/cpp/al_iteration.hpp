// closedchain._core: the augmented-Lagrangian iteration (Bayo & Ledesma 1996), written
// once for solve_al (core_methods.hpp: its dense and band paths), the mass-orthogonal
// velocity step of the stage projection (project, core_projection.hpp) and the ALI3-P
// projections (ali3p.hpp).
//
// With P = M + alpha J^T J factored, from lam_0 = 0:
//   x_1 = P^-1 (rhs - alpha J^T g),   lam_1 = alpha (J x_1 + g),
//   x_{k+1} = x_k + P^-1 (rhs - M x_k - J^T (lam_k + alpha (J x_k + g))),
//   lam_{k+1} = lam_k + alpha (J x_{k+1} + g),
// until max |x_{k+1} - x_k| <= tol (1 + max |x_{k+1}|), or the change stops shrinking
// (max |x_{k+1} - x_k| >= max |x_k - x_{k-1}|: the round-off floor of an ill-conditioned
// M, as in iterative refinement), or max_iter iterates; a correction more than
// AL_DIVERGENCE_GROWTH times the previous one while above AL_DIVERGENCE_RTOL (1 + max |x|)
// is a divergence (P's solve wrong by more than its size): SingularError, with the message of
// augmented_lagrangian.diverged_message (check_al_divergence, also the rule of the tree
// path's dual form, tree_rows.hpp's tree_al_iterate):
// min (x - x*)^T M (x - x*) s.t. J x + g = 0 for rhs = M x* (a projection), or the
// accelerations for rhs = tau - h, g = gamma (the dynamics).
//
// The products are the Ops policy's, so that each caller keeps its own arithmetic to
// the bit (the N-four-bar's trajectories through flat positions are round-off
// sensitive): Core's dense path coefficient-based (lazyProduct) or, for nv <= 6 in
// the dynamics, on fixed-size matrices, its band path over the structural hulls,
// ALI3-P's dense path Eigen's matrix-vector kernels. Ops:
//   add_j(x, y)             y += J x
//   sub_m(x, y)             y -= M x
//   sub_jt(y, x)            x -= J^T y
//   sub_scaled_jt(s, y, x)  x -= s J^T y
//   solve(x)                x <- P^-1 x

#pragma once

#include <Eigen/Dense>

#include <limits>

#include "constants.hpp"
#include "errors.hpp"

namespace closedchain {

/// The divergence rule of the iteration above: SingularError (the message of
/// augmented_lagrangian.diverged_message) when `change`, max |x_{k+1} - x_k| at iterate
/// `iterate`, is more than AL_DIVERGENCE_GROWTH times `last_change` (the previous one) while
/// above AL_DIVERGENCE_RTOL (1 + x_max), x_max = max |x_{k+1}|; alpha: the penalty.
inline void check_al_divergence(double last_change, double change, double x_max, int iterate,
                                double alpha) {
  if (change > AL_DIVERGENCE_GROWTH * last_change && change > AL_DIVERGENCE_RTOL * (1.0 + x_max))
    throw SingularError{
        "the augmented-Lagrangian iteration diverged: its correction grew from " +
            fmt("%.3e", last_change) + " to " + fmt("%.3e", change) + " at iterate " +
            std::to_string(iterate) + " (alpha = " + fmt("%.3e", alpha) + "); " +
            AL_DIVERGED_HINT,
        std::numeric_limits<double>::infinity(), std::numeric_limits<double>::quiet_NaN(), Vec()};
}

/// The iteration above into (x, lam); delta (nv) and rc (nc) are scratch. J x + g at an
/// iterate is computed once (for lam and for the next correction's r_c). Returns the
/// number of iterates.
/// XV, CV: the nv- and nc-vectors (Eigen::VectorXd, or fixed-size for Core's small
/// dense path).
/// from_x: x holds a start x_0 on entry, and x_1 (the same iterate) is computed as its
/// correction, x_1 = x_0 + P^-1 (rhs - M x_0 - alpha J^T (J x_0 + g)): P's round-off
/// (about rho eps) is then relative to the correction, not to x_1 (the stage
/// projection's velocity step from the velocity it projects: two iterates instead of
/// four on the N-four-bar; solve_augmented_lagrangian's a0).
template <class Ops, class XV, class CV>
int al_iterate(Ops &ops, double alpha, const XV &rhs, const CV &g, int max_iter, double tol,
               XV &x, CV &lam, XV &delta, CV &rc, bool from_x = false) {
  if (from_x) {
    rc = g;
    ops.add_j(x, rc);  // J x_0 + g
    delta = rhs;
    ops.sub_m(x, delta);
    ops.sub_scaled_jt(alpha, rc, delta);
    ops.solve(delta);
    x += delta;
  } else {
    x = rhs;
    ops.sub_scaled_jt(alpha, g, x);
    ops.solve(x);
  }
  rc = g;
  ops.add_j(x, rc);  // r_c = J x + g, kept for the next iterate (the same bits)
  lam = rc * alpha;
  int it = 1;
  double last_change = std::numeric_limits<double>::infinity();
  for (; it < max_iter; ++it) {
    rc *= alpha;
    rc += lam;
    delta = rhs;
    ops.sub_m(x, delta);
    ops.sub_jt(rc, delta);
    ops.solve(delta);
    x += delta;
    rc = g;
    ops.add_j(x, rc);
    lam += alpha * rc;
    const double change = delta.cwiseAbs().maxCoeff();
    const double x_max = x.cwiseAbs().maxCoeff();
    check_al_divergence(last_change, change, x_max, it + 1, alpha);
    if (change <= tol * (1.0 + x_max) || change >= last_change) break;
    last_change = change;
  }
  return it;
}

}  // namespace closedchain
