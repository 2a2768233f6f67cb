// Dense linear algebra of the numpy fixed-lag engine's window (aqfg/fg/fastlag.py,
// LagWindow.step and LagWindow._marginalise): the Gauss-Newton step of the held quadratic
// and the Schur complement that marginalises a knot. The systems are small (P + 6 n, a few
// dozen variables), where a call into numpy/LAPACK costs more than the arithmetic; the
// numpy code in fastlag.py is the reference these are tested against.
#pragma once

#include <cmath>
#include <vector>

namespace aqfg {
namespace window {

// In-place Cholesky A = L L^T of the N x N row-major matrix A (its lower triangle is read
// and overwritten by L). False when A is not positive definite (or holds a NaN).
inline bool cholesky(double* A, int N) {
  for (int j = 0; j < N; ++j) {
    double* Aj = A + j * N;
    double d = Aj[j];
    for (int k = 0; k < j; ++k) d -= Aj[k] * Aj[k];
    if (!(d > 0.0)) return false;
    d = std::sqrt(d);
    Aj[j] = d;
    for (int i = j + 1; i < N; ++i) {
      double* Ai = A + i * N;
      double s = Ai[j];
      for (int k = 0; k < j; ++k) s -= Ai[k] * Aj[k];
      Ai[j] = s / d;
    }
  }
  return true;
}

// Solve L L^T X = B in place for B (N x m row-major), L from cholesky().
inline void chol_solve(const double* L, int N, double* B, int m) {
  for (int i = 0; i < N; ++i) {  // L Y = B
    double* Bi = B + i * m;
    for (int k = 0; k < i; ++k) {
      const double l = L[i * N + k];
      const double* Bk = B + k * m;
      for (int c = 0; c < m; ++c) Bi[c] -= l * Bk[c];
    }
    const double d = L[i * N + i];
    for (int c = 0; c < m; ++c) Bi[c] /= d;
  }
  for (int i = N - 1; i >= 0; --i) {  // L^T X = Y
    double* Bi = B + i * m;
    for (int k = i + 1; k < N; ++k) {
      const double l = L[k * N + i];
      const double* Bk = B + k * m;
      for (int c = 0; c < m; ++c) Bi[c] -= l * Bk[c];
    }
    const double d = L[i * N + i];
    for (int c = 0; c < m; ++c) Bi[c] /= d;
  }
}

// The window's Gauss-Newton step. With A = H + diag(hold) on the first P variables and
// g = H z + b + hold (z - th0) on them (hold may be null: no hold priors), solves
// A [s, X] = [g, E] (E: the first P columns of the identity): s (N) is the step to
// subtract from z, C (P x P) the parameters' block of A^-1 (their marginal covariance).
// False when A is not positive definite or a result is not finite.
inline bool gn_step(const double* H, const double* b, const double* z, const double* hold,
                    const double* th0, int N, int P, double* s, double* C) {
  std::vector<double> A(H, H + static_cast<std::size_t>(N) * N);
  const int m = P + 1;
  std::vector<double> B(static_cast<std::size_t>(N) * m, 0.0);
  for (int i = 0; i < N; ++i) {
    const double* Hi = H + i * N;
    double gi = 0.0;
    for (int k = 0; k < N; ++k) gi += Hi[k] * z[k];
    B[i * m] = gi + b[i];
  }
  if (hold != nullptr)
    for (int j = 0; j < P; ++j) {
      A[j * N + j] += hold[j];
      B[j * m] += hold[j] * (z[j] - th0[j]);
    }
  for (int j = 0; j < P; ++j) B[j * m + 1 + j] = 1.0;
  if (!cholesky(A.data(), N)) return false;
  chol_solve(A.data(), N, B.data(), m);
  for (int i = 0; i < N; ++i) {
    s[i] = B[i * m];
    if (!std::isfinite(s[i])) return false;
  }
  for (int i = 0; i < P; ++i)
    for (int j = 0; j < P; ++j) {
      C[i * P + j] = B[i * m + 1 + j];
      if (!std::isfinite(C[i * P + j])) return false;
    }
  return true;
}

// Schur complement eliminating the variables [a, a + na) of the quadratic (H, b), N x N:
// Hn = H_rr - H_ar^T H_aa^-1 H_ar and bn = b_r - H_ar^T H_aa^-1 b_a over the others r (in
// their order; (N - na)^2 and N - na). False when H_aa is not positive definite.
inline bool schur_drop(const double* H, const double* b, int N, int a, int na, double* Hn,
                       double* bn) {
  const int M = N - na;
  std::vector<double> L(static_cast<std::size_t>(na) * na);
  for (int i = 0; i < na; ++i)
    for (int j = 0; j < na; ++j) L[i * na + j] = H[(a + i) * N + a + j];
  if (!cholesky(L.data(), na)) return false;
  auto r_of = [a, na](int k) { return k < a ? k : k + na; };
  // X = H_aa^-1 [H_ar, b_a]
  const int w = M + 1;
  std::vector<double> X(static_cast<std::size_t>(na) * w);
  for (int i = 0; i < na; ++i) {
    const double* Hai = H + (a + i) * N;
    for (int k = 0; k < M; ++k) X[i * w + k] = Hai[r_of(k)];
    X[i * w + M] = b[a + i];
  }
  chol_solve(L.data(), na, X.data(), w);
  for (int p = 0; p < M; ++p) {
    const int rp = r_of(p);
    const double* Hp = H + rp * N;
    double* Hnp = Hn + p * M;
    for (int q = 0; q < M; ++q) Hnp[q] = Hp[r_of(q)];
    double bp = b[rp];
    for (int i = 0; i < na; ++i) {
      const double h = H[(a + i) * N + rp];  // (H_ar^T)[p, i]
      const double* Xi = X.data() + i * w;
      for (int q = 0; q < M; ++q) Hnp[q] -= h * Xi[q];
      bp -= h * Xi[M];
    }
    bn[p] = bp;
  }
  return true;
}

}  // namespace window
}  // namespace aqfg
