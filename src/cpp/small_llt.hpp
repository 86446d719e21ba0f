// closedchain._core: Cholesky factorization of the small symmetric positive
// definite matrices of one evaluation (M + alpha J^T J, J J^T), used by the core's methods.
//
// Eigen's LLT on dynamic-size matrices spends more on blocking and expression
// bookkeeping than on arithmetic at the sizes of a linkage (nv, nc ~ 2 to 20):
// written out, a factorization and a solve cost about a third and two thirds of
// Eigen's, and inverse_norm_bound() below a tenth of Eigen's rcond(). This is the textbook
// right-looking column Cholesky (Golub & Van Loan, Matrix Computations, 4th
// ed., Alg. 4.2.2) on the lower triangle, column-major, with the same
// acceptance test as Eigen's LLT (every pivot > 0); from BLOCKED_MIN on,
// Eigen's blocked LLT (its GEMM updates win there).

#pragma once

#include <Eigen/Dense>

#include <algorithm>
#include <cmath>

namespace closedchain {

/// A = L L^T of a symmetric positive definite matrix on preallocated storage (see above).
class SmallLLT {
 public:
  ///: Size from which Eigen's blocked LLT is used.
  static constexpr Eigen::Index BLOCKED_MIN = 64;

  /// Storage for n x n matrices (n = 0: none yet).
  explicit SmallLLT(Eigen::Index n = 0) { resize(n); }

  /// Storage for n x n matrices; the previous factor is lost.
  void resize(Eigen::Index n) {
    L_.setZero(n, n);
    y_.setZero(n);
    z_.setZero(n);
    eigen_ = Eigen::LLT<Eigen::MatrixXd>(n >= BLOCKED_MIN ? n : 0);
  }

  /// Factor A = L L^T from A's lower triangle (A: n x n, the size given to resize).
  /// Returns false when a pivot is not positive (A not numerically positive definite).
  bool compute(const Eigen::MatrixXd &A) {
    const Eigen::Index n = L_.rows();
    if (n >= BLOCKED_MIN) {
      eigen_.compute(A);
      ok_ = eigen_.info() == Eigen::Success;
      if (ok_) L_.triangularView<Eigen::Lower>() = eigen_.matrixL();
      return ok_;
    }
    L_.triangularView<Eigen::Lower>() = A.triangularView<Eigen::Lower>();
    double *a = L_.data();
    ok_ = true;
    for (Eigen::Index k = 0; k < n; ++k) {
      const double d = a[k + k * n];
      if (!(d > 0.0)) {
        ok_ = false;
        return false;
      }
      const double s = std::sqrt(d);
      a[k + k * n] = s;
      const double inv = 1.0 / s;
      for (Eigen::Index i = k + 1; i < n; ++i) a[i + k * n] *= inv;
      for (Eigen::Index j = k + 1; j < n; ++j) {
        const double ljk = a[j + k * n];
        if (ljk != 0.0)
          for (Eigen::Index i = j; i < n; ++i) a[i + j * n] -= a[i + k * n] * ljk;
      }
    }
    return true;
  }

  /// Whether the last compute succeeded.
  bool ok() const { return ok_; }

  /// Smallest relative pivot min_k L_kk^2 / A_kk of the factor of A (after a successful
  /// compute(A)): how much of A's diagonal the elimination cancelled.
  double min_pivot_ratio(const Eigen::MatrixXd &A) const {
    double r = 1.0;
    for (Eigen::Index k = 0; k < L_.rows(); ++k)
      r = std::min(r, L_(k, k) * L_(k, k) / A(k, k));
    return r;
  }

  /// x <- A^-1 x (after a successful compute).
  template <typename Derived>
  void solveInPlace(Eigen::MatrixBase<Derived> &x) const {
    const Eigen::Index n = L_.rows();
    const double *a = L_.data();
    for (Eigen::Index j = 0; j < n; ++j) {  // L y = x
      const double yj = x[j] / a[j + j * n];
      x[j] = yj;
      if (yj != 0.0)
        for (Eigen::Index i = j + 1; i < n; ++i) x[i] -= a[i + j * n] * yj;
    }
    for (Eigen::Index j = n - 1; j >= 0; --j) {  // L^T x = y
      double s = x[j];
      for (Eigen::Index i = j + 1; i < n; ++i) s -= a[i + j * n] * x[i];
      x[j] = s / a[j + j * n];
    }
  }

  /// Upper bound of ||A^-1||_1 = ||L^-T L^-1||_1 <= ||L^-1||_inf ||L^-1||_1, each
  /// bounded through the comparison matrix of L: |L^-1| <= M(L)^-1 elementwise
  /// (Higham, Accuracy and Stability of Numerical Algorithms, 2002, Thm 8.12), so
  /// ||L^-1||_inf <= max(M(L)^-1 e) and ||L^-1||_1 <= max(M(L)^-T e). `margin`
  /// (relative) covers the bound's own round-off.
  double inverse_norm_bound(double margin) {
    const Eigen::Index n = L_.rows();
    const double *a = L_.data();
    double b_inf = 0.0, b_one = 0.0;
    for (Eigen::Index i = 0; i < n; ++i) {  // M(L) y = e, forward
      double s = 1.0;
      for (Eigen::Index k = 0; k < i; ++k) s += std::abs(a[i + k * n]) * y_[k];
      y_[i] = s / a[i + i * n];
      b_inf = std::max(b_inf, y_[i]);
    }
    for (Eigen::Index j = n - 1; j >= 0; --j) {  // M(L)^T z = e, backward
      double s = 1.0;
      for (Eigen::Index i = j + 1; i < n; ++i) s += std::abs(a[i + j * n]) * z_[i];
      z_[j] = s / a[j + j * n];
      b_one = std::max(b_one, z_[j]);
    }
    return b_inf * b_one * (1.0 + margin);
  }

 private:
  Eigen::MatrixXd L_;                  ///< The factor L (lower triangle), below BLOCKED_MIN.
  Eigen::VectorXd y_, z_;              ///< Workspace of the condition estimate.
  Eigen::LLT<Eigen::MatrixXd> eigen_;  ///< Eigen's factorization, from BLOCKED_MIN.
  bool ok_ = false;                    ///< Whether the last compute succeeded.
};

/// For a size N known at compile time (Core's fixed-size augmented-Lagrangian path,
/// nv <= 6): A = L D L^T (L unit lower triangular), without square roots, with the
/// reciprocals of D kept so that a solve multiplies instead of dividing; the loops
/// unroll. The square roots and the 2N divisions per solve of the factorization above
/// would be the longest dependency chains of the 4-bar's evaluation. Accepts A when
/// every pivot d_k > 0 (as LLT does); the results differ from SmallLLT's by round-off.
template <int N>
class FixedLDLT {
 public:
  using Mat = Eigen::Matrix<double, N, N>;  ///< The fixed-size matrix type.

  /// Factor A from its lower triangle; false when a pivot is not positive.
  bool compute(const Mat &A) {
    L_ = A;  // L below the diagonal, D on it (overwritten column by column)
    min_pivot_ratio_ = 1.0;
    for (int k = 0; k < N; ++k) {
      const double d = L_(k, k);
      if (!(d > 0.0)) return false;
      min_pivot_ratio_ = std::min(min_pivot_ratio_, d / A(k, k));
      inv_[k] = 1.0 / d;
      for (int j = k + 1; j < N; ++j) {
        const double ljk = L_(j, k) * inv_[k];
        for (int i = j; i < N; ++i) L_(i, j) -= L_(i, k) * ljk;
      }
      for (int i = k + 1; i < N; ++i) L_(i, k) *= inv_[k];
    }
    return true;
  }

  /// Smallest relative pivot min_k D_k / A_kk of the last successful compute.
  double min_pivot_ratio() const { return min_pivot_ratio_; }

  /// x <- A^-1 x (after a successful compute).
  template <typename Derived>
  void solveInPlace(Eigen::MatrixBase<Derived> &x) const {
    for (int j = 0; j < N; ++j)  // L y = x
      for (int i = j + 1; i < N; ++i) x[i] -= L_(i, j) * x[j];
    for (int j = 0; j < N; ++j) x[j] *= inv_[j];  // D z = y
    for (int j = N - 1; j >= 0; --j)  // L^T x = z
      for (int i = j + 1; i < N; ++i) x[j] -= L_(i, j) * x[i];
  }

 private:
  Mat L_;                          ///< L below the diagonal, D on it.
  Eigen::Matrix<double, N, 1> inv_;  ///< The reciprocals 1 / D_k.
  double min_pivot_ratio_ = 1.0;   ///< min_k D_k / A_kk of the last successful compute.
};

/// ||A||_1 of a symmetric matrix A, shape (n, n), from its lower triangle.
inline double lower_norm1(const Eigen::MatrixXd &A) {
  double anorm = 0.0;
  for (Eigen::Index j = 0; j < A.cols(); ++j) {
    double c = 0.0;
    for (Eigen::Index i = 0; i < A.rows(); ++i) c += std::abs(i >= j ? A(i, j) : A(j, i));
    anorm = std::max(anorm, c);
  }
  return anorm;
}

}  // namespace closedchain
