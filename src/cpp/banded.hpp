// closedchain._core: symmetric positive definite band matrices.
//
// Many loops in a chain (the N-four-bar) give a penalized mass matrix
// M + alpha J^T J and normal equations J J^T whose structural nonzeros lie in a
// narrow band (half bandwidth b, independent of the number of loops). A band
// Cholesky factorization costs O(n b^2) and its solves O(n b) instead of
// O(n^3) and O(n^2): the cost of a step grows linearly with the number of loops.
// The structure (which order, which bandwidth) is chosen on the Python side
// (closedchain/dynamics/augmented_lagrangian.py, PenalizedSolver and
// NormalSolver); here the factorization, solves and condition estimates.

#pragma once

#include <Eigen/Dense>

#include <algorithm>
#include <cmath>

namespace closedchain {

/// A symmetric n x n matrix of half bandwidth b, stored by lower diagonals:
/// A(k, j) = matrix entry (j + k, j), k = 0..b (entries beyond n unused), and its
/// Cholesky factor L in the same layout. Buffers are sized once (resize).
class BandCholesky {
 public:
  /// Storage for n x n matrices of half bandwidth b, zeroed.
  void resize(int n, int b) {
    n_ = n;
    b_ = b;
    A.setZero(b + 1, n);
    L_.setZero(b + 1, n);
    w1_.setZero(n);
    w2_.setZero(n);
    sign_.setZero(n);
    old_sign_.setZero(n);
  }

  /// The matrix size n.
  int n() const { return n_; }
  /// The half bandwidth b.
  int bandwidth() const { return b_; }

  /// Entry (i, j) of the matrix, |i - j| <= b (symmetric).
  double &at(int i, int j) { return i >= j ? A(i - j, j) : A(j - i, i); }

  /// Factorize A = L L^T (left-looking, O(n b^2)); false when a pivot is not positive.
  bool factor() {
    const int n = n_, b = b_;
    anorm_ = 0.0;  // 1-norm (= infinity norm) of A, for rcond
    for (int j = 0; j < n; ++j) {
      double s = 0.0;
      for (int k = 0; k <= b && j + k < n; ++k) s += std::abs(A(k, j));
      for (int k = 1; k <= b && j - k >= 0; ++k) s += std::abs(A(k, j - k));
      anorm_ = std::max(anorm_, s);
    }
    for (int j = 0; j < n; ++j) {
      const int k0 = std::max(0, j - b);
      double d = A(0, j);
      for (int k = k0; k < j; ++k) d -= L_(j - k, k) * L_(j - k, k);
      if (!(d > 0.0)) return false;
      const double ljj = std::sqrt(d);
      L_(0, j) = ljj;
      const int iend = std::min(n - 1, j + b);
      for (int i = j + 1; i <= iend; ++i) {
        double s = A(i - j, j);
        for (int k = std::max(0, i - b); k < j; ++k) s -= L_(i - k, k) * L_(j - k, k);
        L_(i - j, j) = s / ljj;
      }
    }
    return true;
  }

  /// Smallest relative pivot min_j L_jj^2 / A_jj (after a successful factor).
  double min_pivot_ratio() const {
    double r = 1.0;
    for (int j = 0; j < n_; ++j) r = std::min(r, L_(0, j) * L_(0, j) / A(0, j));
    return r;
  }

  /// x <- A^-1 x on the factor (O(n b)).
  template <typename V>
  void solve_in_place(V &x) const {
    const int n = n_, b = b_;
    for (int j = 0; j < n; ++j) {  // L y = x
      double s = x[j];
      for (int k = std::max(0, j - b); k < j; ++k) s -= L_(j - k, k) * x[k];
      x[j] = s / L_(0, j);
    }
    for (int j = n - 1; j >= 0; --j) {  // L^T z = y
      double s = x[j];
      const int iend = std::min(n - 1, j + b);
      for (int i = j + 1; i <= iend; ++i) s -= L_(i - j, j) * x[i];
      x[j] = s / L_(0, j);
    }
  }

  /// Reciprocal 1-norm condition number estimate of the factored A: Higham's
  /// estimator of ||A^-1||_1 (LAPACK's dlacon), the steps of Eigen's
  /// LLT::rcond (internal::rcond_invmatrix_L1_norm_estimate) on the band solves,
  /// so the banded and dense paths take the same decisions up to round-off.
  double rcond() {
    const int n = n_;
    if (n == 0) return 1.0;
    if (anorm_ == 0.0) return 0.0;
    w1_.setConstant(1.0 / n);
    solve_in_place(w1_);
    double lower = w1_.lpNorm<1>();
    if (n > 1) {
      double old_lower = lower;
      Eigen::Index jmax = -1, old_jmax = -1;
      for (int k = 0; k < 4; ++k) {
        for (int i = 0; i < n; ++i) sign_[i] = w1_[i] >= 0.0 ? 1.0 : -1.0;
        if (k > 0 && sign_ == old_sign_) break;
        w1_ = sign_;
        solve_in_place(w1_);  // A symmetric: A^-T = A^-1
        w1_.cwiseAbs().maxCoeff(&jmax);
        if (jmax == old_jmax) break;
        w1_.setZero();
        w1_[jmax] = 1.0;
        solve_in_place(w1_);
        lower = w1_.lpNorm<1>();
        if (lower <= old_lower) break;
        old_sign_ = sign_;
        old_jmax = jmax;
        old_lower = lower;
      }
      double alt = 1.0;
      for (int i = 0; i < n; ++i) {
        w2_[i] = alt * (1.0 + static_cast<double>(i) / static_cast<double>(n - 1));
        alt = -alt;
      }
      solve_in_place(w2_);
      lower = std::max(lower, 2.0 * w2_.lpNorm<1>() / (3.0 * n));
    }
    return lower > 0.0 ? (1.0 / lower) / anorm_ : 0.0;
  }

  /// The 1-norm of A at the last factor().
  double anorm() const { return anorm_; }

  Eigen::MatrixXd A;  ///< The matrix, lower band (assembled by the caller), (b + 1, n).

 private:
  int n_ = 0, b_ = 0;    ///< Size and half bandwidth.
  double anorm_ = 0.0;  ///< 1-norm of A at the last factor().
  Eigen::MatrixXd L_;   ///< The Cholesky factor, in A's layout.
  Eigen::VectorXd w1_, w2_, sign_, old_sign_;  ///< Workspace of the condition estimate.
};

}  // namespace closedchain
