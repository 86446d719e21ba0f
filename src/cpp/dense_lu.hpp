// LU with partial pivoting of a small square matrix on preallocated storage.
//
// LAPACK's dgetf2 (the first largest pivot, row swaps in piv), solves with the
// factors and their transpose, the sign of the determinant (numpy's slogdet
// sign) and the 1-norm reciprocal condition estimate of LAPACK's dgecon
// (Hager / Higham), also of a diagonally scaled S A^-1 S (the kkt method's equilibrated
// estimate on the raw factors). No heap allocation after construction below BLOCKED_MIN: used
// every evaluation by the kkt method (K), the reduced method and the partitioning
// stabilization (J_D), and for the branch series' sign of det(J_D).
#pragma once

#include <Eigen/Dense>

#include <algorithm>
#include <cmath>
#include <vector>

// Full unrolling of the fixed-size loops (factor_n<N> etc. for N <= FIXED_MAX; no
// effect on the generic N = 0 loops' results: the same operations in the same order).
#if defined(__GNUC__) && !defined(__clang__)
#define CLOSEDCHAIN_UNROLL _Pragma("GCC unroll 8")
#else
#define CLOSEDCHAIN_UNROLL
#endif

namespace closedchain {

/// P A = L U of a square matrix, in place, with its solves and condition estimates.
struct DenseLU {
  Eigen::MatrixXd A;           ///< The factors (column-major): L unit lower, U upper.
  std::vector<int> piv;        ///< Row k was swapped with row piv[k] at step k.
  Eigen::VectorXd ex, ey, ez;  ///< Workspace of the condition estimators.
  double anorm = 0.0;          ///< 1-norm of the factored matrix.
  bool regular = false;        ///< Whether every pivot is nonzero.

  /// Storage for n x n matrices (n = 0: none yet).
  explicit DenseLU(Eigen::Index n = 0) { resize(n); }

  /// Storage for n x n matrices, zeroed; the previous factors are lost.
  void resize(Eigen::Index n) {
    A = Eigen::MatrixXd::Zero(n, n);
    piv.assign(static_cast<std::size_t>(n), 0);
    ex = ey = ez = Eigen::VectorXd::Zero(n);
  }

  ///: Size from which the factorization uses Eigen's blocked LU instead of dgetf2's loop.
  static constexpr Eigen::Index BLOCKED_MIN = 96;

  /// Factor M (square, the size given at construction). Returns false on a zero pivot.
  template <class Derived>
  bool factor(const Eigen::MatrixBase<Derived> &M) {
    A = M;
    return factor_in_place();
  }

  /// Factor A as it stands (assembled in place by the caller). Written out for small
  /// matrices: Eigen's PartialPivLU and its solves spend more on dynamic-size
  /// bookkeeping (and heap copies of the permutation) than on arithmetic there. From
  /// BLOCKED_MIN (trees of hundreds of joints) Eigen's blocked LU with GEMM updates and
  /// the same row swaps in piv (its workspace may come from the heap, negligible against
  /// the O(n^3) work; the loop is 4x slower at n = 1000).
  /// Sizes up to FIXED_MAX run the same loops with the size a compile-time constant
  /// (unrolled by the compiler: the kkt method's K of a small linkage, J_D): the
  /// same operations in the same order, so the same results as the generic loops.
  static constexpr int FIXED_MAX = 8;

  /// Factor A in place (see FIXED_MAX). Returns false on a zero pivot.
  bool factor_in_place() {
    switch (A.rows()) {
      case 1: return factor_n<1>();
      case 2: return factor_n<2>();
      case 3: return factor_n<3>();
      case 4: return factor_n<4>();
      case 5: return factor_n<5>();
      case 6: return factor_n<6>();
      case 7: return factor_n<7>();
      case 8: return factor_n<8>();
      default: return factor_n<0>();
    }
  }

  /// x <- A^-1 x with the factors (regular), in place.
  template <class V>
  void solve(V &&x) const {
    switch (A.rows()) {
      case 1: return solve_n<1>(x);
      case 2: return solve_n<2>(x);
      case 3: return solve_n<3>(x);
      case 4: return solve_n<4>(x);
      case 5: return solve_n<5>(x);
      case 6: return solve_n<6>(x);
      case 7: return solve_n<7>(x);
      case 8: return solve_n<8>(x);
      default: return solve_n<0>(x);
    }
  }

  /// z <- A^-T z with the factors (regular), in place.
  template <class V>
  void solve_transposed(V &&z) const {
    switch (A.rows()) {
      case 1: return solve_transposed_n<1>(z);
      case 2: return solve_transposed_n<2>(z);
      case 3: return solve_transposed_n<3>(z);
      case 4: return solve_transposed_n<4>(z);
      case 5: return solve_transposed_n<5>(z);
      case 6: return solve_transposed_n<6>(z);
      case 7: return solve_transposed_n<7>(z);
      case 8: return solve_transposed_n<8>(z);
      default: return solve_transposed_n<0>(z);
    }
  }

  /// Upper bound of ||A^-1||_1 from the factors (regular): ||U^-1||_1 ||L^-1||_1 through
  /// the comparison matrices: |T^-1| <= M(T)^-1 elementwise for triangular T (Higham,
  /// Accuracy and Stability of Numerical Algorithms, 2002, Thm 8.12), so ||T^-1||_1 <=
  /// max(M(T)^-T e), one small triangular solve each; a relative margin of 1e-8 covers
  /// its own round-off. Cheaper than rcond().
  double inverse_norm_bound() {
    switch (A.rows()) {
      case 1: return inverse_norm_bound_n<1>();
      case 2: return inverse_norm_bound_n<2>();
      case 3: return inverse_norm_bound_n<3>();
      case 4: return inverse_norm_bound_n<4>();
      case 5: return inverse_norm_bound_n<5>();
      case 6: return inverse_norm_bound_n<6>();
      case 7: return inverse_norm_bound_n<7>();
      case 8: return inverse_norm_bound_n<8>();
      default: return inverse_norm_bound_n<0>();
    }
  }

 private:
  /// N > 0: the size as a compile-time constant (== A.rows()); N == 0: A.rows().
  template <int N>
  Eigen::Index size() const {
    return N > 0 ? static_cast<Eigen::Index>(N) : A.rows();
  }

  /// dgetf2 on A at size size<N>(): the first largest pivot of each column, row swaps in
  /// piv, anorm from A before it is overwritten. Returns regular.
  template <int N>
  bool factor_n() {
    const Eigen::Index n = size<N>();
    double *a = A.data();
    anorm = 0.0;
    CLOSEDCHAIN_UNROLL
    for (Eigen::Index j = 0; j < n; ++j) {
      double s = 0.0;
      CLOSEDCHAIN_UNROLL
      for (Eigen::Index i = 0; i < n; ++i) s += std::abs(a[i + j * n]);
      anorm = std::max(anorm, s);
    }
    if (N == 0 && n >= BLOCKED_MIN) {
      int swaps = 0;
      regular = Eigen::internal::partial_lu_impl<double, Eigen::ColMajor, int>::blocked_lu(
                    n, n, a, n, piv.data(), swaps) < 0;
      return regular;
    }
    regular = true;
    CLOSEDCHAIN_UNROLL
    for (Eigen::Index k = 0; k < n; ++k) {
      Eigen::Index p = k;
      double big = std::abs(a[k + k * n]);
      CLOSEDCHAIN_UNROLL
      for (Eigen::Index i = k + 1; i < n; ++i)
        if (std::abs(a[i + k * n]) > big) {
          big = std::abs(a[i + k * n]);
          p = i;
        }
      piv[k] = static_cast<int>(p);
      if (big == 0.0) {
        regular = false;
        continue;
      }
      if (p != k)
        CLOSEDCHAIN_UNROLL
        for (Eigen::Index j = 0; j < n; ++j) std::swap(a[k + j * n], a[p + j * n]);
      const double inv = 1.0 / a[k + k * n];
      CLOSEDCHAIN_UNROLL
      for (Eigen::Index i = k + 1; i < n; ++i) a[i + k * n] *= inv;
      CLOSEDCHAIN_UNROLL
      for (Eigen::Index j = k + 1; j < n; ++j) {
        const double akj = a[k + j * n];
        if (akj != 0.0)
          CLOSEDCHAIN_UNROLL
          for (Eigen::Index i = k + 1; i < n; ++i) a[i + j * n] -= a[i + k * n] * akj;
      }
    }
    return regular;
  }

  /// x <- A^-1 x: the row swaps, then L and U by columns.
  template <int N, class V>
  void solve_n(V &x) const {
    const Eigen::Index n = size<N>();
    const double *a = A.data();
    CLOSEDCHAIN_UNROLL
    for (Eigen::Index k = 0; k < n; ++k)
      if (piv[k] != k) std::swap(x[k], x[piv[k]]);
    CLOSEDCHAIN_UNROLL
    for (Eigen::Index j = 0; j < n; ++j) {
      const double xj = x[j];
      if (xj != 0.0)
        CLOSEDCHAIN_UNROLL
        for (Eigen::Index i = j + 1; i < n; ++i) x[i] -= a[i + j * n] * xj;
    }
    CLOSEDCHAIN_UNROLL
    for (Eigen::Index j = n - 1; j >= 0; --j) {
      x[j] /= a[j + j * n];
      const double xj = x[j];
      if (xj != 0.0)
        CLOSEDCHAIN_UNROLL
        for (Eigen::Index i = 0; i < j; ++i) x[i] -= a[i + j * n] * xj;
    }
  }

  /// z <- A^-T z: U^T and L^T by rows, then the row swaps in reverse.
  template <int N, class V>
  void solve_transposed_n(V &z) const {
    const Eigen::Index n = size<N>();
    const double *a = A.data();
    CLOSEDCHAIN_UNROLL
    for (Eigen::Index j = 0; j < n; ++j) {
      double s = z[j];
      CLOSEDCHAIN_UNROLL
      for (Eigen::Index i = 0; i < j; ++i) s -= a[i + j * n] * z[i];
      z[j] = s / a[j + j * n];
    }
    CLOSEDCHAIN_UNROLL
    for (Eigen::Index j = n - 1; j >= 0; --j) {
      double s = z[j];
      CLOSEDCHAIN_UNROLL
      for (Eigen::Index i = j + 1; i < n; ++i) s -= a[i + j * n] * z[i];
      z[j] = s;
    }
    CLOSEDCHAIN_UNROLL
    for (Eigen::Index k = n - 1; k >= 0; --k)
      if (piv[k] != k) std::swap(z[k], z[piv[k]]);
  }

  /// inverse_norm_bound at size size<N>().
  template <int N>
  double inverse_norm_bound_n() {
    const Eigen::Index n = size<N>();
    const double *a = A.data();
    double *ey_ = ey.data(), *ez_ = ez.data();
    double bu = 0.0, bl = 0.0;
    CLOSEDCHAIN_UNROLL
    for (Eigen::Index j = 0; j < n; ++j) {
      double s = 1.0;
      CLOSEDCHAIN_UNROLL
      for (Eigen::Index i = 0; i < j; ++i) s += std::abs(a[i + j * n]) * ey_[i];
      ey_[j] = s / std::abs(a[j + j * n]);
      bu = std::max(bu, ey_[j]);
    }
    CLOSEDCHAIN_UNROLL
    for (Eigen::Index j = n - 1; j >= 0; --j) {
      double s = 1.0;
      CLOSEDCHAIN_UNROLL
      for (Eigen::Index i = j + 1; i < n; ++i) s += std::abs(a[i + j * n]) * ez_[i];
      ez_[j] = s;
      bl = std::max(bl, s);
    }
    return bu * bl * (1.0 + 1e-8);
  }

 public:
  /// Sign of det(A) from the factors (+1 or -1); 0 when A is singular.
  double det_sign() const {
    if (!regular) return 0.0;
    double s = 1.0;
    for (Eigen::Index k = 0; k < A.rows(); ++k) {
      if (piv[k] != k) s = -s;
      if (A(k, k) < 0) s = -s;
    }
    return s;
  }

  /// Reciprocal 1-norm condition estimate (dgecon; 0 when singular).
  double rcond() {
    if (!regular || anorm == 0.0) return 0.0;
    if (A.rows() == 0) return 1.0;
    return reciprocal(anorm, inverse_norm_estimate(nullptr));
  }

  /// 1 / (bnorm est), or 0 where est is 0 or not finite (a singular matrix).
  static double reciprocal(double bnorm, double est) {
    if (!std::isfinite(est)) return 0.0;
    return est > 0 ? 1.0 / (est * bnorm) : 0.0;
  }

  /// Estimate of ||S A^-1 S||_1 for S = diag(s) (s == nullptr: S = I, dgecon's
  /// ||A^-1||_1) from the factors (regular, n > 0): Hager's method as refined by Higham
  /// (LAPACK's dlacn2: at most 5 sign iterations, then the alternating test vector), a
  /// lower bound of the norm, with solves by the factors wrapped by S on both sides
  /// (S A^-T S for the transpose). The kkt method's cond(D K D) = ||D K D||_1 ||D^-1
  /// K^-1 D^-1||_1 with s = 1 / d, on K's own factors. No heap allocation.
  double inverse_norm_estimate(const double *s) {
    const Eigen::Index n = A.rows();
    auto apply = [&](Eigen::VectorXd &x, bool transposed) {
      if (s)
        for (Eigen::Index i = 0; i < n; ++i) x[i] *= s[i];
      if (transposed)
        solve_transposed(x);
      else
        solve(x);
      if (s)
        for (Eigen::Index i = 0; i < n; ++i) x[i] *= s[i];
    };
    ex.setConstant(1.0 / static_cast<double>(n));
    double est = 0.0;
    Eigen::Index jlast = -1;
    for (int it = 0; it < 5; ++it) {
      ey = ex;
      apply(ey, false);
      const double e = ey.lpNorm<1>();
      if (it > 0 && e <= est) break;
      est = e;
      for (Eigen::Index i = 0; i < n; ++i) ez[i] = ey[i] >= 0 ? 1.0 : -1.0;
      apply(ez, true);
      Eigen::Index j;
      ez.cwiseAbs().maxCoeff(&j);
      if (it > 0 && j == jlast) break;
      jlast = j;
      ex.setZero();
      ex[j] = 1.0;
    }
    for (Eigen::Index i = 0; i < n; ++i)
      ex[i] = (i % 2 ? -1.0 : 1.0) *
              (1.0 + static_cast<double>(i) / std::max<Eigen::Index>(n - 1, 1));
    ey = ex;
    apply(ey, false);
    return std::max(est, 2.0 * ey.lpNorm<1>() / (3.0 * static_cast<double>(n)));
  }

  /// Upper bound of ||S A^-1 S||_1 for S = diag(s), s > 0, from the factors (regular):
  /// A = P^T L U, so |S A^-1 S| <= S M(U)^-1 M(L)^-1 P S elementwise (the comparison
  /// matrices, as inverse_norm_bound), whose 1-norm, its largest column sum, is
  /// max_j s_j (P^T z)_j for M(U)^T y = s, M(L)^T z = y (two triangular solves); a
  /// relative margin of 1e-8 covers its own round-off. Above the estimate (a lower bound
  /// of the same norm), so bound <= limit shows the estimate is too.
  double scaled_inverse_norm_bound(const double *s) {
    switch (A.rows()) {
      case 1: return scaled_inverse_norm_bound_n<1>(s);
      case 2: return scaled_inverse_norm_bound_n<2>(s);
      case 3: return scaled_inverse_norm_bound_n<3>(s);
      case 4: return scaled_inverse_norm_bound_n<4>(s);
      case 5: return scaled_inverse_norm_bound_n<5>(s);
      case 6: return scaled_inverse_norm_bound_n<6>(s);
      case 7: return scaled_inverse_norm_bound_n<7>(s);
      case 8: return scaled_inverse_norm_bound_n<8>(s);
      default: return scaled_inverse_norm_bound_n<0>(s);
    }
  }

 private:
  /// scaled_inverse_norm_bound at size size<N>().
  template <int N>
  double scaled_inverse_norm_bound_n(const double *s) {
    const Eigen::Index n = size<N>();
    const double *a = A.data();
    double *z = ez.data();
    CLOSEDCHAIN_UNROLL
    for (Eigen::Index j = 0; j < n; ++j) {
      double t = s[j];
      CLOSEDCHAIN_UNROLL
      for (Eigen::Index i = 0; i < j; ++i) t += std::abs(a[i + j * n]) * z[i];
      z[j] = t / std::abs(a[j + j * n]);
    }
    CLOSEDCHAIN_UNROLL
    for (Eigen::Index j = n - 1; j >= 0; --j) {
      double t = z[j];
      CLOSEDCHAIN_UNROLL
      for (Eigen::Index i = j + 1; i < n; ++i) t += std::abs(a[i + j * n]) * z[i];
      z[j] = t;
    }
    CLOSEDCHAIN_UNROLL
    for (Eigen::Index k = n - 1; k >= 0; --k)
      if (piv[k] != k) std::swap(z[k], z[piv[k]]);
    double bound = 0.0;
    CLOSEDCHAIN_UNROLL
    for (Eigen::Index j = 0; j < n; ++j) bound = std::max(bound, s[j] * z[j]);
    return bound * (1.0 + 1e-8);
  }
};

}  // namespace closedchain
