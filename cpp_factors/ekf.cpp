// EKF window evaluation (see ekf.hpp) and its Python binding ekf_window.
#include "ekf.hpp"

#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/tuple.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <initializer_list>
#include <limits>
#include <string>
#include <tuple>
#include <vector>

namespace aqfg {
namespace ekf {

namespace kn = aqfg::kernel;

namespace {

constexpr double NaN = std::numeric_limits<double>::quiet_NaN();

// P (9x9) <- M (Phi P6 Phi^T + Q) M^T + diag(0, 0, sigma_ab^2): ekf_window.predict_covariance.
void predict_cov(double* P, const double Sx[9], const double Sv[9], double T, const double Jab[9],
                 const Config& cfg, bool planar) {
  // Phi = [[I, Sx], [0, Sv]] in 3x3 blocks: P6 = Phi P[:6, :6] Phi^T
  double Pxx[9], Pxv[9], Pvv[9];
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) {
      Pxx[3 * r + c] = P[9 * r + c];
      Pxv[3 * r + c] = P[9 * r + 3 + c];
      Pvv[3 * r + c] = P[9 * (3 + r) + 3 + c];
    }
  auto mul = [](const double* A, const double* B, double* C, bool bt) {  // C = A B (or A B^T)
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) {
        double acc = 0.0;
        for (int k = 0; k < 3; ++k) acc += A[3 * r + k] * (bt ? B[3 * c + k] : B[3 * k + c]);
        C[3 * r + c] = acc;
      }
  };
  double W[9], U[9], P6[36];
  mul(Sx, Pvv, W, false);  // Sx Pvv
  for (int i = 0; i < 9; ++i) U[i] = Pxv[i] + W[i];  // Pxv + Sx Pvv
  double Nxx[9], Nxv[9], Nvv[9], T1[9], T2[9];
  mul(U, Sx, T1, true);     // (Pxv + Sx Pvv) Sx^T
  mul(Sx, Pxv, T2, true);   // Sx Pvx  (Pvx = Pxv^T)
  for (int i = 0; i < 9; ++i) Nxx[i] = Pxx[i] + T2[i] + T1[i];
  mul(U, Sv, Nxv, true);    // (Pxv + Sx Pvv) Sv^T
  mul(Sv, Pvv, T1, false);
  mul(T1, Sv, Nvv, true);
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) {
      P6[6 * r + c] = Nxx[3 * r + c];
      P6[6 * r + 3 + c] = Nxv[3 * r + c];
      P6[6 * (3 + c) + r] = Nxv[3 * r + c];
      P6[6 * (3 + r) + 3 + c] = Nvv[3 * r + c];
    }
  const double q[3] = {cfg.q_h, cfg.q_h, planar ? 0.0 : cfg.q_v};
  for (int i = 0; i < 3; ++i) {
    P6[6 * i + i] += q[i] * T * T * T / 3.0;
    P6[6 * i + 3 + i] += q[i] * T * T / 2.0;
    P6[6 * (3 + i) + i] += q[i] * T * T / 2.0;
    P6[6 * (3 + i) + 3 + i] += q[i] * T;
  }
  // M = [I6; 0 Jab]
  double Bv[18];  // Jab * P6[3:6, :] (3 x 6)
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 6; ++c) {
      double acc = 0.0;
      for (int k = 0; k < 3; ++k) acc += Jab[3 * r + k] * P6[6 * (3 + k) + c];
      Bv[6 * r + c] = cfg.full_cov ? acc : 0.0;
    }
  for (int r = 0; r < 6; ++r)
    for (int c = 0; c < 6; ++c) P[9 * r + c] = P6[6 * r + c];
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 6; ++c) {
      P[9 * (6 + r) + c] = Bv[6 * r + c];
      P[9 * c + 6 + r] = Bv[6 * r + c];
    }
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) {
      double acc = 0.0;
      for (int k = 0; k < 3; ++k) acc += Bv[6 * r + 3 + k] * Jab[3 * c + k];
      P[9 * (6 + r) + 6 + c] = acc + (r == c ? cfg.sigma_ab * cfg.sigma_ab : 0.0);
    }
}

// Kalman update of the directly measured components idx (d <= 3): ekf_window._update.
// Returns true if accepted; fills e (9), nu, nu_w, s (d each).
bool update(double* x, double* P, const int* idx, int d, const double* z, const double* hx,
            const double* Rm, double gate, double* e, double* nu, double* nu_w, double* s) {
  double S[9], L[9] = {};
  for (int i = 0; i < d; ++i)
    for (int j = 0; j < d; ++j) S[d * i + j] = P[9 * idx[i] + idx[j]] + Rm[d * i + j];
  for (int i = 0; i < d; ++i) nu[i] = z[i] - hx[i];
  // Cholesky S = L L^T
  for (int i = 0; i < d; ++i)
    for (int j = 0; j <= i; ++j) {
      double acc = S[d * i + j];
      for (int k = 0; k < j; ++k) acc -= L[d * i + k] * L[d * j + k];
      L[d * i + j] = (i == j) ? std::sqrt(acc) : acc / L[d * j + j];
    }
  double m2 = 0.0;
  for (int i = 0; i < d; ++i) {
    double acc = nu[i];
    for (int k = 0; k < i; ++k) acc -= L[d * i + k] * nu_w[k];
    nu_w[i] = acc / L[d * i + i];
    m2 += nu_w[i] * nu_w[i];
    s[i] = std::sqrt(S[d * i + i]);
  }
  // K = P[:, idx] S^-1 (9 x d): solve S k_r = P[idx, r] for each row r of K
  double K[27];
  for (int r = 0; r < 9; ++r) {
    double y[3];
    for (int i = 0; i < d; ++i) {
      double acc = P[9 * idx[i] + r];
      for (int k = 0; k < i; ++k) acc -= L[d * i + k] * y[k];
      y[i] = acc / L[d * i + i];
    }
    for (int i = d - 1; i >= 0; --i) {
      double acc = y[i];
      for (int k = i + 1; k < d; ++k) acc -= L[d * k + i] * K[3 * r + k];
      K[3 * r + i] = acc / L[d * i + i];
    }
  }
  for (int r = 0; r < 9; ++r) {
    double acc = 0.0;
    for (int i = 0; i < d; ++i) acc += K[3 * r + i] * nu[i];
    e[r] = acc;
  }
  if (std::isfinite(gate) && m2 > gate) {  // rejected: error at the gate boundary, no update
    const double sc = std::sqrt(gate / m2);
    for (int r = 0; r < 9; ++r) e[r] *= sc;
    return false;
  }
  for (int r = 0; r < 9; ++r) x[r] += e[r];
  // Joseph form: P = (I - K H) P (I - K H)^T + K Rm K^T. Only the block of the states
  // correlated with the measured ones changes (K's other rows are exactly zero), so it is
  // computed on that block alone: e.g. 3x3 for an IMU update under the kinematic covariance.
  int act[9], na = 0;
  for (int r = 0; r < 9; ++r) {
    bool on = false;
    for (int i = 0; i < d; ++i) on = on || P[9 * r + idx[i]] != 0.0 || r == idx[i];
    if (on) act[na++] = r;
  }
  int pos_of[9];
  for (int a = 0; a < na; ++a) pos_of[act[a]] = a;
  double A[81], Pa[81], AP[81];
  for (int a = 0; a < na; ++a)
    for (int b = 0; b < na; ++b) {
      A[9 * a + b] = (a == b) ? 1.0 : 0.0;
      Pa[9 * a + b] = P[9 * act[a] + act[b]];
    }
  for (int a = 0; a < na; ++a)
    for (int i = 0; i < d; ++i) A[9 * a + pos_of[idx[i]]] -= K[3 * act[a] + i];
  for (int a = 0; a < na; ++a)
    for (int b = 0; b < na; ++b) {
      double acc = 0.0;
      for (int k = 0; k < na; ++k) acc += A[9 * a + k] * Pa[9 * k + b];
      AP[9 * a + b] = acc;
    }
  double KR[27];
  for (int a = 0; a < na; ++a)
    for (int j = 0; j < d; ++j) {
      double acc = 0.0;
      for (int i = 0; i < d; ++i) acc += K[3 * act[a] + i] * Rm[d * i + j];
      KR[3 * a + j] = acc;
    }
  for (int a = 0; a < na; ++a)
    for (int b = 0; b < na; ++b) {
      double acc = 0.0;
      for (int k = 0; k < na; ++k) acc += AP[9 * a + k] * A[9 * b + k];
      double kk = 0.0;
      for (int j = 0; j < d; ++j) kk += KR[3 * a + j] * K[3 * act[b] + j];
      P[9 * act[a] + act[b]] = acc + kk;
    }
  return true;
}

// Antenna / transponder position: pos + Rz(th) Rraw l (aqfg.model.measurements.sensor_position).
void sensor_position(const double* pos, const double* Rraw, double tm, const double* p,
                     const double* pm, double* out) {
  const double th = kn::heading(p, tm);
  double R[9];
  kn::corrected_attitude(Rraw, std::cos(th), std::sin(th), R);
  for (int r = 0; r < 3; ++r)
    out[r] = pos[r] + R[3 * r] * pm[M_LEVER_ARM_X] + R[3 * r + 1] * pm[M_LEVER_ARM_Y] +
             R[3 * r + 2] * pm[M_LEVER_ARM_Z];
}

// USBL (range, bearing, down) -> horizontal position (kernel::usbl_inverse) and its
// covariance (aqfg.ekf.window.usbl_to_position): the covariance axes and tangential spread at
// the predicted position pr (north, east).
void usbl_to_position(const double* z, const double* st, const double* pm, double sr0, double sb,
                      const double* pr, double* pos, double* Rm) {
  const kn::UsblFix f = kn::usbl_inverse(z[0], z[1], z[2], st, pm[M_USBL_RANGE_SCALE_SCALE],
                                         pm[M_USBL_BEARING_BIAS_BIAS]);
  const double r = f.r, rh = f.rh;
  double c = std::cos(f.b), s = std::sin(f.b);
  pos[0] = f.pos[0];
  pos[1] = f.pos[1];
  const double sr = sr0 * std::min(r / std::max(rh, 1e-6), 10.0);
  const double dn = pr[0] - st[0], de = pr[1] - st[1];
  const double rt = std::sqrt(dn * dn + de * de);
  if (rt > 1e-6) c = dn / rt, s = de / rt;
  const double stg = std::max(rt, 1e-3) * sb;
  const double vr = sr * sr, vt = stg * stg;
  // Rot diag(vr, vt) Rot^T, Rot = [[c, -s], [s, c]]
  Rm[0] = c * c * vr + s * s * vt;
  Rm[1] = c * s * vr - s * c * vt;
  Rm[2] = Rm[1];
  Rm[3] = s * s * vr + c * c * vt;
}

}  // namespace

int window(const double* x0, const double* P0, std::int64_t k0, std::int64_t k1,
            const double* p, const double* pm, const Config& cfg, const Timeline& tl,
            const kn::Geometry& g, std::int64_t w0, std::int64_t lo, std::int64_t hi,
            const Output& out, int rejects) {
  const kn::Steps& st = tl.steps;
  const std::ptrdiff_t nt = g.n_thr;
  const double tau = p[kn::P_THRUST_LAG_TAU];
  std::vector<double> scratch(4 * static_cast<std::size_t>(std::max<std::ptrdiff_t>(nt, 1)));
  double *f = scratch.data(), *df = f + nt, *d = f + 2 * nt, *dd = f + 3 * nt;
  kn::LagCoeffs lag;
  const std::int64_t s0 = tl.offsets[k0];
  if (st.n > 0) {
    const std::int64_t j0 = std::min<std::int64_t>(w0, st.n - 1);
    for (std::ptrdiff_t i = 0; i < nt; ++i) f[i] = st.dem[nt * j0 + i], df[i] = 0.0;
  }
  for (std::int64_t j = w0; j < s0; ++j)
    kn::filter_step(f, df, st.dem + nt * j, st.h[j], tau, lag, d, dd, nt);

  double x[9], P[81];
  std::memcpy(x, x0, sizeof x);
  std::memcpy(P, P0, sizeof P);
  double Sx[9] = {}, Sv[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1}, T = 0.0, Jab[9] = {};
  double a[3], A[9], Jp[3 * kn::N_DYN], Rc[9];
  kn::detail::Heading hd;
  const std::int64_t n = hi - lo;
  for (std::int64_t r = 0; r < n; ++r) {
    for (int c = 0; c < 9; ++c) out.e[9 * r + c] = 0.0;
    for (int c = 0; c < 3; ++c) out.nu[3 * r + c] = out.nu_w[3 * r + c] = out.s[3 * r + c] = NaN;
    out.status[r] = NOOP;
  }
  if (out.X) std::memcpy(out.X, x, sizeof x);
  std::int64_t m = lo;
  for (std::int64_t k = k0; k < k1; ++k) {
    double* pos = x;
    double* vel = x + 3;
    for (std::int64_t j = tl.offsets[k]; j < tl.offsets[k + 1]; ++j) {
      const double h = st.h[j];
      kn::filter_step(f, df, st.dem + nt * j, h, tau, lag, d, dd, nt);
      if (!(h > 0.0)) continue;
      const double tm = st.tm[j];
      const double* Rraw = st.R + 9 * j;
      hd.update(kn::heading(p, tm));
      kn::accel_core<true>(vel, Rraw, d, dd, tm, p, g, hd.c, hd.s, a, A, Jp, kn::N_DYN);
      kn::corrected_attitude(Rraw, hd.c, hd.s, Rc);
      for (int r = 0; r < 3; ++r) {  // a_b = Rc^T a, Jab = Rc^T A (Eq. 10)
        x[6 + r] = Rc[r] * a[0] + Rc[3 + r] * a[1] + Rc[6 + r] * a[2];
        for (int c = 0; c < 3; ++c)
          Jab[3 * r + c] = Rc[r] * A[c] + Rc[3 + r] * A[3 + c] + Rc[6 + r] * A[6 + c];
      }
      double ASv[9] = {};
      if (cfg.full_cov)
        for (int r = 0; r < 3; ++r)
          for (int c = 0; c < 3; ++c)
            ASv[3 * r + c] = A[3 * r] * Sv[c] + A[3 * r + 1] * Sv[3 + c] + A[3 * r + 2] * Sv[6 + c];
      kn::integrate_step(Sx, Sv, ASv, h, 9);
      kn::integrate_step(pos, vel, a, h, 3);
    }
    T += tl.knots[k + 1] - tl.knots[k];
    std::int64_t b = m;
    bool any = false;
    while (b < hi && tl.node_knot[b] == k + 1) {
      any = any || tl.node_kind[b] != MOTOR;
      ++b;
    }
    if (any) {
      predict_cov(P, Sx, Sv, T, Jab, cfg, g.planar);
      for (int i = 0; i < 9; ++i) Sx[i] = 0.0, Sv[i] = (i % 4 == 0) ? 1.0 : 0.0;
      T = 0.0;
    }
    for (std::int64_t i = m; i < b; ++i) {
      const std::int64_t r = i - lo;
      const double* z = tl.node_z + 4 * i;
      const std::int32_t kind = tl.node_kind[i];
      double* e = out.e + 9 * r;
      double* nu = out.nu + 3 * r;
      double* nuw = out.nu_w + 3 * r;
      double* sd = out.s + 3 * r;
      int ok = -1;
      if (kind == GNSS || kind == USBL) {
        const int idx[2] = {0, 1};
        double zp[3], zz[2], Rm[4];
        sensor_position(x, tl.node_R + 9 * i, tl.node_tm[i], p, pm, zp);
        double gate = cfg.gate_gnss;
        if (kind == GNSS) {
          zz[0] = z[0];
          zz[1] = z[1];
          Rm[0] = Rm[3] = z[2] * z[2];
          Rm[1] = Rm[2] = 0.0;
        } else {
          usbl_to_position(z, tl.station, pm, cfg.sigma_range, cfg.sigma_bearing, zp, zz, Rm);
          gate = rejects < cfg.max_rejects ? cfg.gate_usbl : std::numeric_limits<double>::infinity();
        }
        ok = update(x, P, idx, 2, zz, zp, Rm, gate, e, nu, nuw, sd);
        if (kind == USBL) rejects = ok ? 0 : rejects + 1;
      } else if (kind == DEPTH) {
        const int idx[1] = {2};
        const double Rm[1] = {z[1] * z[1]};
        const double hx[1] = {x[2]};
        ok = update(x, P, idx, 1, z, hx, Rm, std::numeric_limits<double>::infinity(), e, nu,
                    nuw, sd);
      } else if (kind == IMU_ACC) {
        const int idx[3] = {6, 7, 8};
        const double v = z[3] * z[3];
        const double Rm[9] = {v, 0, 0, 0, v, 0, 0, 0, v};
        const double hx[3] = {x[6], x[7], x[8]};
        ok = update(x, P, idx, 3, z, hx, Rm, std::numeric_limits<double>::infinity(), e, nu,
                    nuw, sd);
      }
      if (ok >= 0) out.status[r] = ok ? ACCEPTED : REJECTED;
      if (out.Pn) std::memcpy(out.Pn + 81 * r, P, sizeof P);
    }
    m = b;
    if (out.X) std::memcpy(out.X + 9 * (k + 1 - k0), x, sizeof x);
  }
  if (T > 0) predict_cov(P, Sx, Sv, T, Jab, cfg, g.planar);
  std::memcpy(out.x, x, sizeof x);
  std::memcpy(out.P, P, sizeof P);
  return rejects;
}

// ------------------------------------------------------------------ Python binding
namespace nb = nanobind;

namespace {

using InF64 = nb::ndarray<const double, nb::c_contig, nb::device::cpu>;
using InI64 = nb::ndarray<const std::int64_t, nb::c_contig, nb::device::cpu>;
using InI32 = nb::ndarray<const std::int32_t, nb::c_contig, nb::device::cpu>;
using OutF64 = nb::ndarray<nb::numpy, double>;
using OutI8 = nb::ndarray<nb::numpy, std::int8_t>;

constexpr std::int64_t ANY = -1;

template <class Arr>
void need(const char* name, const Arr& a, std::initializer_list<std::int64_t> want,
          const std::string& meaning) {
  bool ok = a.ndim() == want.size();
  std::size_t i = 0;
  for (auto w : want) {
    if (!ok) break;
    ok = (w == ANY) || static_cast<std::int64_t>(a.shape(i)) == w;
    ++i;
  }
  if (!ok) {
    std::string got = "(";
    for (std::size_t j = 0; j < a.ndim(); ++j) got += (j ? ", " : "") + std::to_string(a.shape(j));
    throw nb::value_error((std::string("ekf_window: argument '") + name + "' must have shape " +
                           meaning + ", got " + got + ")")
                              .c_str());
  }
}

template <class T>
nb::ndarray<nb::numpy, T> new_out(std::initializer_list<std::size_t> shape, T*& data) {
  std::size_t n = 1;
  for (auto s : shape) n *= s;
  data = new T[n > 0 ? n : 1];
  nb::capsule owner(data, [](void* q) noexcept { delete[] static_cast<T*>(q); });
  return nb::ndarray<nb::numpy, T>(data, shape.size(), shape.begin(), owner);
}

using WindowResult =
    std::tuple<OutF64, OutF64, OutF64, OutF64, OutI8, OutF64, OutF64, OutF64, OutF64, int>;

WindowResult py_ekf_window(const InF64& x0, const InF64& P0, std::int64_t k0, std::int64_t k1,
                           const InF64& p, const InF64& pm, const Config& cfg, const InF64& h,
                           const InF64& R, const InF64& dem, const InF64& tm,
                           const InI64& offsets, const InF64& knots, std::int64_t w0,
                           const InI64& node_knot, const InI32& node_kind, const InF64& node_z,
                           const InF64& node_R, const InF64& node_tm, const InF64& station,
                           const InF64& dirs, const InF64& side, bool planar, std::int64_t lo,
                           std::int64_t hi, bool record, int rejects) {
  need("x0", x0, {9}, "(9,)");
  need("P0", P0, {9, 9}, "(9, 9)");
  need("p", p, {kn::N_DYN}, "(N_DYN,) = (" + std::to_string(kn::N_DYN) + ",)");
  need("pm", pm, {N_MEAS}, "(N_MEAS,) = (" + std::to_string(N_MEAS) + ",): the measurement parameters");
  need("h", h, {ANY}, "(n,)");
  const std::int64_t ns = static_cast<std::int64_t>(h.shape(0));
  need("dem", dem, {ns, ANY}, "(n, N_thrusters) with n = len(h)");
  const std::int64_t nt = static_cast<std::int64_t>(dem.shape(1));
  need("R", R, {ns, 9}, "(n, 9)");
  need("tm", tm, {ns}, "(n,)");
  need("knots", knots, {ANY}, "(K,)");
  const std::int64_t K = static_cast<std::int64_t>(knots.shape(0));
  need("offsets", offsets, {K}, "(K,) with K = len(knots)");
  need("node_knot", node_knot, {ANY}, "(M,)");
  const std::int64_t M = static_cast<std::int64_t>(node_knot.shape(0));
  need("node_kind", node_kind, {M}, "(M,)");
  need("node_z", node_z, {M, 4}, "(M, 4)");
  need("node_R", node_R, {M, 9}, "(M, 9)");
  need("node_tm", node_tm, {M}, "(M,)");
  need("station", station, {3}, "(3,)");
  need("dirs", dirs, {nt, 3}, "(N_thrusters, 3)");
  need("side", side, {nt}, "(N_thrusters,)");
  if (!(0 <= k0 && k0 <= k1 && k1 < K))
    throw nb::value_error(("ekf_window: need 0 <= k0 <= k1 < K, got k0=" + std::to_string(k0) +
                           ", k1=" + std::to_string(k1) + ", K=" + std::to_string(K))
                              .c_str());
  if (!(0 <= lo && lo <= hi && hi <= M))
    throw nb::value_error("ekf_window: need 0 <= lo <= hi <= M (node range)");
  if (!(0 <= w0 && w0 <= offsets.data()[k0]))
    throw nb::value_error("ekf_window: need 0 <= w0 <= offsets[k0] (warm-up start)");
  if (offsets.data()[K - 1] > ns)
    throw nb::value_error("ekf_window: offsets exceed the number of steps");

  const std::size_t n = static_cast<std::size_t>(hi - lo);
  const std::size_t nk = record ? static_cast<std::size_t>(k1 - k0 + 1) : 0;
  const std::size_t nP = record ? n : 0;
  Output o{};
  OutF64 ae = new_out<double>({n, 9}, o.e), anu = new_out<double>({n, 3}, o.nu),
         anw = new_out<double>({n, 3}, o.nu_w), as = new_out<double>({n, 3}, o.s);
  OutI8 ast = new_out<std::int8_t>({n}, o.status);
  OutF64 ax = new_out<double>({9}, o.x), aP = new_out<double>({9, 9}, o.P);
  double *X, *Pn;
  OutF64 aX = new_out<double>({nk, 9}, X), aPn = new_out<double>({nP, 9, 9}, Pn);
  o.X = record ? X : nullptr;
  o.Pn = record ? Pn : nullptr;
  std::vector<std::uint8_t> warm(1, 0);
  Timeline tl{kn::Steps{h.data(), warm.data(), R.data(), dem.data(), tm.data(), ns},
              offsets.data(),
              K,
              knots.data(),
              node_knot.data(),
              node_kind.data(),
              node_z.data(),
              node_R.data(),
              node_tm.data(),
              station.data()};
  kn::Geometry g{dirs.data(), side.data(), nt, planar};
  {
    nb::gil_scoped_release release;
    rejects = window(x0.data(), P0.data(), k0, k1, p.data(), pm.data(), cfg, tl, g, w0, lo, hi, o,
                     rejects);
  }
  return {ae, anu, anw, as, ast, ax, aP, aX, aPn, rejects};
}

}  // namespace

void register_ekf(nb::module_& m) {
  nb::class_<Config>(m, "EkfSettings",
                     "The EKF settings a window pass reads (aqfg.ekf.history.EkfConfig; "
                     "full_cov: covariance with the model's Jacobian, cov_model 'full').")
      .def(
          "__init__",
          [](Config* c, double q_h, double q_v, double sigma_ab, double sigma_range,
             double sigma_bearing, double gate_usbl, double gate_gnss, int max_rejects,
             bool full_cov) {
            new (c) Config{q_h,       q_v,       sigma_ab,    sigma_range, sigma_bearing,
                           gate_usbl, gate_gnss, max_rejects, full_cov};
          },
          nb::kw_only(), nb::arg("q_h"), nb::arg("q_v"), nb::arg("sigma_ab"),
          nb::arg("sigma_range"), nb::arg("sigma_bearing"), nb::arg("gate_usbl"),
          nb::arg("gate_gnss"), nb::arg("max_rejects"), nb::arg("full_cov"))
      .def_rw("q_h", &Config::q_h)
      .def_rw("q_v", &Config::q_v)
      .def_rw("sigma_ab", &Config::sigma_ab)
      .def_rw("sigma_range", &Config::sigma_range)
      .def_rw("sigma_bearing", &Config::sigma_bearing)
      .def_rw("gate_usbl", &Config::gate_usbl)
      .def_rw("gate_gnss", &Config::gate_gnss)
      .def_rw("max_rejects", &Config::max_rejects)
      .def_rw("full_cov", &Config::full_cov);
  m.def("ekf_window", &py_ekf_window, nb::arg("x0"), nb::arg("P0"), nb::arg("k0"), nb::arg("k1"),
        nb::arg("p"), nb::arg("pm"), nb::arg("cfg"), nb::arg("h"), nb::arg("R"), nb::arg("dem"),
        nb::arg("tm"), nb::arg("offsets"), nb::arg("knots"), nb::arg("w0"),
        nb::arg("node_knot"), nb::arg("node_kind"), nb::arg("node_z"), nb::arg("node_R"),
        nb::arg("node_tm"), nb::arg("station"), nb::arg("dirs"), nb::arg("side"),
        nb::arg("planar"), nb::arg("lo"), nb::arg("hi"), nb::arg("record"), nb::arg("rejects"),
        "One EKF pass of the update-error method from knot k0 to k1 (see aqfg.ekf.window). "
        "Returns (e (n, 9), nu (n, 3), nu_w (n, 3), s (n, 3), status (n,) int8, x (9,), "
        "P (9, 9), X (k1-k0+1 or 0, 9), Pn (n or 0, 9, 9), consecutive USBL rejections at k1).");
}

}  // namespace ekf
}  // namespace aqfg
