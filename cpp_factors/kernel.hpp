// Vehicle-model kernel: C++ mirror of aqfg/model/reference.py (the numpy reference), with
// the frames (heading) and USBL functions of aqfg/model/frames.py and measurements.py.
//
// Header-only so that a C++ estimator (e.g. an EKF loop) can #include it directly; the
// Python bindings live in bindings.cpp. Every formula here has its twin in the numpy
// reference and tests/test_kernel.py holds the two equal (values and Jacobians).
//
// Model (paper §II-D/E), per input step of length h, attitude R_raw and commands held:
//   R   = Rz(theta(tm)) R_raw,  theta: heading() below                           (Eq. 6)
//   s   = [s_x + ds_x tm, s_y + ds_y tm, 0],  v_r = R^T (v - s)                 (Eq. 3)
//   a_b = sum_i g_i d_i dir_i - kq .* sign(v_r) .* v_r^2 - kl .* v_r          (Eqs. 1, 2)
//   a   = R a_b + [a_n, a_e, 0]  (vertical zeroed for planar vehicles)     (Eqs. 9, 10)
//   x  += h v + h^2/2 a,  v += h a   (constant acceleration over the step)     (Eq. 8)
// with d_i the step mean of the first-order thrust-lag filter output (exact mean).
//
// Units: SI throughout (m, s, rad); positions/velocities NED ground frame; R body->ground,
// row-major 3x3 flattened to 9.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <vector>

#include "layout.hpp"  // ParamIndex (P_*), N_DYN, PARAM_NAMES: generated from aqfg/model/params.py

// Hot functions are forced inline so that a caller compiled for a wider instruction set
// (e.g. a target_clones wrapper, see bindings.cpp) gets them vectorised for that set.
#if defined(__GNUC__) || defined(__clang__)
#define AQFG_HOT_INLINE __attribute__((always_inline)) inline
#else
#define AQFG_HOT_INLINE inline
#endif

namespace aqfg {
namespace kernel {

// Below this time constant the lag filter is taken in its tau -> 0 limit (as filter_step).
inline constexpr double TAU_MIN = 1e-9;

// ------------------------------------------------------------------ frames, integration
// Heading offset theta (rad) at tm s since the mission start, for the parameters p
// (Eq. 6 with the heading drift): the twin of aqfg.model.frames.heading.
AQFG_HOT_INLINE double heading(const double* p, double tm) {
  return p[P_THETA_E] + p[P_HEADING_DRIFT_RATE] * tm;
}

// Corrected attitude R = Rz(theta) Rraw (3x3 row-major) given cos, sin of theta.
AQFG_HOT_INLINE void corrected_attitude(const double* Rraw, double cth, double sth, double* R) {
  for (int c = 0; c < 3; ++c) {
    R[c] = cth * Rraw[c] - sth * Rraw[3 + c];
    R[3 + c] = sth * Rraw[c] + cth * Rraw[3 + c];
    R[6 + c] = Rraw[6 + c];
  }
}

// One step of h s at constant acceleration over n components (Eqs. 8-9):
// pos += h vel + h^2/2 acc, vel += h acc (aqfg.model.reference.integrate_step). Carries
// the state and, column by column, its sensitivities.
AQFG_HOT_INLINE void integrate_step(double* __restrict__ pos, double* __restrict__ vel,
                                    const double* __restrict__ acc, double h, int n) {
  const double hh = 0.5 * h * h;
  for (int i = 0; i < n; ++i) {
    pos[i] += h * vel[i] + hh * acc[i];
    vel[i] += h * acc[i];
  }
}

// ------------------------------------------------------------------ USBL
// Position of a USBL fix, the inverse of the USBL measurement given the vehicle's depth
// (aqfg.model.measurements.usbl_inverse): the range scale and bearing bias are removed
// (r = range / scale, b = bearing - bias) and the depth below the station fixes the
// vertical leg, r_h = sqrt(max(r^2 - dz^2, 0)).
struct UsblFix {
  double pos[3];  // NED, m (the transponder's)
  double r;       // corrected slant range, m
  double rh;      // horizontal range, m
  double b;       // corrected bearing, rad
};

inline UsblFix usbl_inverse(double range, double bearing, double down, const double* station,
                            double scale, double bias) {
  UsblFix f;
  f.r = range / scale;
  f.b = bearing - bias;
  const double dz = down - station[2];
  f.rh = std::sqrt(std::max(f.r * f.r - dz * dz, 0.0));
  f.pos[0] = station[0] + f.rh * std::cos(f.b);
  f.pos[1] = station[1] + f.rh * std::sin(f.b);
  f.pos[2] = down;
  return f;
}

// Thruster layout: unit axes (n_thr x 3, row-major, body) and side (> 0: starboard).
struct Geometry {
  const double* dirs;
  const double* side;
  std::ptrdiff_t n_thr;
  bool planar;
};

// Input steps (views, no ownership), as reference.Steps. dem is n x n_thr row-major.
struct Steps {
  const double* h;
  const std::uint8_t* warm;
  const double* R;
  const double* dem;
  const double* tm;
  std::ptrdiff_t n;

  Steps slice(std::ptrdiff_t a, std::ptrdiff_t b, std::ptrdiff_t n_thr) const {
    return Steps{h + a, warm + a, R + 9 * a, dem + n_thr * a, tm + a, b - a};
  }
};

// ------------------------------------------------------------------ thrust-lag filter
// Coefficients of one filter step; they depend on (h, tau) only, so a run of equal step
// lengths computes the exponential once.
struct LagCoeffs {
  double h = std::numeric_limits<double>::quiet_NaN();
  double e = 0.0, phi = 1.0, dphi = 0.0, de = 0.0;

  AQFG_HOT_INLINE void update(double h_new, double tau) {
    if (h_new == h) return;
    h = h_new;
    e = std::exp(-h / tau);
    phi = h > 0 ? tau / h * (1.0 - e) : 1.0;
    dphi = h > 0 ? ((1.0 - e) / h - e / tau) : 0.0;
    de = e * h / (tau * tau);
  }
};

// One filter step for every thruster, as reference.filter_step: from state f (and its
// d/dtau df) under constant input c over h, the step mean d and its d/dtau dd; f and df
// are advanced in place.
AQFG_HOT_INLINE void filter_step(double* f, double* df, const double* c, double h, double tau,
                        LagCoeffs& k, double* d, double* dd, std::ptrdiff_t n) {
  if (tau < TAU_MIN) {
    if (h <= 0) {  // a zero-length step leaves the state and its d/dtau as they are
      for (std::ptrdiff_t i = 0; i < n; ++i) {
        d[i] = c[i];
        dd[i] = df[i];
      }
      return;
    }
    for (std::ptrdiff_t i = 0; i < n; ++i) {
      d[i] = c[i];
      dd[i] = h > 0 ? (f[i] - c[i]) / h : 0.0;
      f[i] = c[i];
      df[i] = 0.0;
    }
    return;
  }
  k.update(h, tau);
  for (std::ptrdiff_t i = 0; i < n; ++i) {
    const double fc = f[i] - c[i];
    d[i] = c[i] + fc * k.phi;
    dd[i] = df[i] * k.phi + fc * k.dphi;
    f[i] = c[i] + fc * k.e;
    df[i] = df[i] * k.e + fc * k.de;
  }
}

// ------------------------------------------------------------------ acceleration
// Ground acceleration a (3) for velocity v, raw attitude Rraw, mean demands d (n_thr) and
// their d/dtau dd, time since mission start tm, params p (N_DYN), with cos/sin of the
// corrected heading theta = heading(p, tm) given (cth, sth).
// With Jac: also A = da/dv (3x3 row-major) and Jp = da/dp, written as Jp[r * ldj + col].
template <bool Jac>
AQFG_HOT_INLINE void accel_core(const double* v, const double* Rraw, const double* d, const double* dd,
                       double tm, const double* p, const Geometry& g, double cth, double sth,
                       double* a, double* A, double* Jp, std::ptrdiff_t ldj) {
  double R[9];
  corrected_attitude(Rraw, cth, sth, R);
  const double w[3] = {v[0] - (p[P_S_X] + p[P_CURRENT_DRIFT_DS_X] * tm),
                       v[1] - (p[P_S_Y] + p[P_CURRENT_DRIFT_DS_Y] * tm), v[2]};
  double vr[3];
  for (int m = 0; m < 3; ++m) vr[m] = R[m] * w[0] + R[3 + m] * w[1] + R[6 + m] * w[2];

  // thrust (Eq. 1) with asymmetry and reverse-thrust ratios
  const double k = p[P_K], r_asym = p[P_THRUST_ASYMMETRY_RATIO], r_rev = p[P_REVERSE_THRUST_RATIO];
  double at[3] = {0, 0, 0}, bk[3] = {0, 0, 0}, ba[3] = {0, 0, 0}, br[3] = {0, 0, 0},
         bt[3] = {0, 0, 0};
  for (std::ptrdiff_t i = 0; i < g.n_thr; ++i) {
    const double* u = g.dirs + 3 * i;
    const bool stb = g.side[i] > 0, neg = d[i] < 0;
    const double ga = stb ? r_asym : 1.0, gr = neg ? r_rev : 1.0;
    const double gi = k * ga * gr;
    const double t = gi * d[i];
    for (int m = 0; m < 3; ++m) at[m] += t * u[m];
    if constexpr (Jac) {
      const double tk = ga * gr * d[i], tt = gi * dd[i];
      for (int m = 0; m < 3; ++m) {
        bk[m] += tk * u[m];
        bt[m] += tt * u[m];
      }
      if (stb) {
        const double ta = k * gr * d[i];
        for (int m = 0; m < 3; ++m) ba[m] += ta * u[m];
      }
      if (neg) {
        const double tr = k * ga * d[i];
        for (int m = 0; m < 3; ++m) br[m] += tr * u[m];
      }
    }
  }

  // inflow (ground_advance): each propeller loses c |u| va of its thrust, va the speed over
  // ground along its axis; |u| = (d^2 + 1e-4)^(1/4) (effects.abs_command)
  const double cga = p[P_GROUND_ADVANCE_C];
  double bga[3] = {0, 0, 0}, Mg[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
  if (Jac || cga != 0.0) {
    double vg[3];
    for (int m = 0; m < 3; ++m) vg[m] = R[m] * v[0] + R[3 + m] * v[1] + R[6 + m] * v[2];
    for (std::ptrdiff_t i = 0; i < g.n_thr; ++i) {
      const double* u = g.dirs + 3 * i;
      const double r = d[i] * d[i] + 1e-4, n = std::sqrt(std::sqrt(r));
      const double va = u[0] * vg[0] + u[1] * vg[1] + u[2] * vg[2];
      if constexpr (Jac)
        for (int m = 0; m < 3; ++m) bga[m] -= n * va * u[m];  // the column, also at c = 0
      if (cga == 0.0) continue;  // the effect off: its terms vanish
      const double loss = cga * n * va;
      for (int m = 0; m < 3; ++m) at[m] -= loss * u[m];
      if constexpr (Jac) {
        const double dn = 0.5 * d[i] * n / r, tt = cga * va * dn * dd[i];
        for (int m = 0; m < 3; ++m) {
          bt[m] -= tt * u[m];
          for (int l = 0; l < 3; ++l) Mg[3 * m + l] -= cga * n * u[m] * u[l];
        }
      }
    }
  }

  // drag (Eq. 2): quadratic + linear
  const double kq[3] = {p[P_K_X], p[P_K_YZ], p[P_K_YZ]};
  const double kl[3] = {p[P_LINEAR_DRAG_C_X], p[P_LINEAR_DRAG_C_YZ], p[P_LINEAR_DRAG_C_YZ]};
  double q2[3], ab[3];
  for (int m = 0; m < 3; ++m) {
    q2[m] = std::fabs(vr[m]) * vr[m];  // sign(v_r) v_r^2
    ab[m] = at[m] - kq[m] * q2[m] - kl[m] * vr[m];
  }
  double Rab[3];
  for (int r = 0; r < 3; ++r) Rab[r] = R[3 * r] * ab[0] + R[3 * r + 1] * ab[1] + R[3 * r + 2] * ab[2];
  a[0] = Rab[0] + p[P_WIND_DRAG_A_N];
  a[1] = Rab[1] + p[P_WIND_DRAG_A_E];
  a[2] = g.planar ? 0.0 : Rab[2];
  if constexpr (!Jac) return;

  // d a / d v = R D R^T, D = d a_drag / d v_r (diagonal)
  double D[3];
  for (int m = 0; m < 3; ++m) D[m] = -2.0 * kq[m] * std::fabs(vr[m]) - kl[m];
  double RD[9];
  for (int r = 0; r < 3; ++r)
    for (int m = 0; m < 3; ++m) RD[3 * r + m] = R[3 * r + m] * D[m];
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c)
      A[3 * r + c] = RD[3 * r] * R[3 * c] + RD[3 * r + 1] * R[3 * c + 1] + RD[3 * r + 2] * R[3 * c + 2];

  // heading: dR/dth = E_Z R, E_Z x = (-x1, x0, 0); d v_r/dth = R^T E_Z^T w, d v_g/dth = R^T E_Z^T v
  double qth[3], qg[3];
  for (int m = 0; m < 3; ++m) {
    qth[m] = R[m] * w[1] - R[3 + m] * w[0];
    qg[m] = R[m] * v[1] - R[3 + m] * v[0];
  }
  const double ez[3] = {-Rab[1], Rab[0], 0.0};
  // R Mg: d a / d v_g (the inflow), and its d a / d v = R Mg R^T (added after the current's columns)
  double RMg[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
  if (cga != 0.0)
    for (int r = 0; r < 3; ++r)
      for (int m = 0; m < 3; ++m)
        RMg[3 * r + m] = R[3 * r] * Mg[m] + R[3 * r + 1] * Mg[3 + m] + R[3 * r + 2] * Mg[6 + m];

  const int nrow = g.planar ? 2 : 3;
  for (int r = 0; r < nrow; ++r) {
    const double* Rr = R + 3 * r;
    double* J = Jp + r * ldj;
    double dth = ez[r] + RD[3 * r] * qth[0] + RD[3 * r + 1] * qth[1] + RD[3 * r + 2] * qth[2];
    if (cga != 0.0) dth += RMg[3 * r] * qg[0] + RMg[3 * r + 1] * qg[1] + RMg[3 * r + 2] * qg[2];
    J[P_THETA_E] = dth;
    J[P_HEADING_DRIFT_RATE] = dth * tm;
    J[P_S_X] = -A[3 * r];
    J[P_S_Y] = -A[3 * r + 1];
    J[P_CURRENT_DRIFT_DS_X] = -A[3 * r] * tm;
    J[P_CURRENT_DRIFT_DS_Y] = -A[3 * r + 1] * tm;
    J[P_K] = Rr[0] * bk[0] + Rr[1] * bk[1] + Rr[2] * bk[2];
    J[P_K_X] = -Rr[0] * q2[0];
    J[P_K_YZ] = -Rr[1] * q2[1] - Rr[2] * q2[2];
    J[P_LINEAR_DRAG_C_X] = -Rr[0] * vr[0];
    J[P_LINEAR_DRAG_C_YZ] = -Rr[1] * vr[1] - Rr[2] * vr[2];
    J[P_THRUST_ASYMMETRY_RATIO] = Rr[0] * ba[0] + Rr[1] * ba[1] + Rr[2] * ba[2];
    J[P_REVERSE_THRUST_RATIO] = Rr[0] * br[0] + Rr[1] * br[1] + Rr[2] * br[2];
    J[P_THRUST_LAG_TAU] = Rr[0] * bt[0] + Rr[1] * bt[1] + Rr[2] * bt[2];
    J[P_WIND_DRAG_A_N] = r == 0 ? 1.0 : 0.0;
    J[P_WIND_DRAG_A_E] = r == 1 ? 1.0 : 0.0;
    J[P_GROUND_ADVANCE_C] = Rr[0] * bga[0] + Rr[1] * bga[1] + Rr[2] * bga[2];
  }
  if (cga != 0.0)
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c)
        A[3 * r + c] += RMg[3 * r] * R[3 * c] + RMg[3 * r + 1] * R[3 * c + 1] + RMg[3 * r + 2] * R[3 * c + 2];
  if (g.planar) {
    for (int c = 0; c < 3; ++c) A[6 + c] = 0.0;
    for (int c = 0; c < N_DYN; ++c) Jp[2 * ldj + c] = 0.0;
  }
}

// reference.accel: a (3), A = da/dv (3x3 row-major), Jp = da/dp (3 x N_DYN row-major).
inline void accel(const double* v, const double* Rraw, const double* d, const double* dd,
                  double tm, const double* p, const Geometry& g, double* a, double* A,
                  double* Jp) {
  const double th = heading(p, tm);
  accel_core<true>(v, Rraw, d, dd, tm, p, g, std::cos(th), std::sin(th), a, A, Jp, N_DYN);
}

// ------------------------------------------------------------------ integration
namespace detail {
// Per-thruster scratch (f, df, d, dd): on the stack for usual vehicles, heap beyond.
class ThrusterScratch {
 public:
  explicit ThrusterScratch(std::ptrdiff_t n) {
    double* base = local_;
    if (n > kLocal) {
      heap_.resize(4 * static_cast<std::size_t>(n));
      base = heap_.data();
    }
    f = base;
    df = base + n;
    d = base + 2 * n;
    dd = base + 3 * n;
  }
  double *f, *df, *d, *dd;

 private:
  static constexpr std::ptrdiff_t kLocal = 16;
  double local_[4 * kLocal];
  std::vector<double> heap_;
};

// Cached cos/sin of the corrected heading (constant unless heading_drift.rate != 0).
struct Heading {
  double th = std::numeric_limits<double>::quiet_NaN(), c = 1.0, s = 0.0;
  AQFG_HOT_INLINE void update(double th_new) {
    if (th_new == th) return;
    th = th_new;
    c = std::cos(th);
    s = std::sin(th);
  }
};
}  // namespace detail

// Sensitivity columns carried through the steps: d v0 (3) then the N_DYN params, padded
// to a multiple of 4 doubles so the column loops vectorise.
inline constexpr int N_SENS = ((3 + N_DYN + 3) / 4) * 4;

// reference.propagate (no user effects): state x = [pos, vel] (NED) after the steps,
// Jx = dx1/dx0 (6x6 row-major), Jp = dx1/dp (6 x N_DYN row-major).
// Position does not feed back into the dynamics, so only the sensitivities w.r.t. v0 and
// p are integrated (d x1 / d pos0 = identity).
AQFG_HOT_INLINE void propagate(const double* x0, const double* p, const Steps& s, const Geometry& g,
                      double* x1, double* Jx, double* Jp) {
  double pos[3] = {x0[0], x0[1], x0[2]}, vel[3] = {x0[3], x0[4], x0[5]};
  alignas(32) double Sx[3][N_SENS] = {};
  alignas(32) double Sv[3][N_SENS] = {};
  alignas(32) double J[3][N_SENS] = {};  // da/d(v0, p): only the p columns are ever set
  alignas(32) double dA[3][N_SENS];
  for (int i = 0; i < 3; ++i) Sv[i][i] = 1.0;

  const std::ptrdiff_t nt = g.n_thr;
  const double tau = p[P_THRUST_LAG_TAU];
  detail::ThrusterScratch th(nt);
  if (s.n > 0)
    for (std::ptrdiff_t i = 0; i < nt; ++i) th.f[i] = s.dem[i], th.df[i] = 0.0;
  LagCoeffs lag;
  detail::Heading hd;
  double a[3], A[9];

  for (std::ptrdiff_t j = 0; j < s.n; ++j) {
    const double h = s.h[j];
    filter_step(th.f, th.df, s.dem + nt * j, h, tau, lag, th.d, th.dd, nt);
    if (s.warm[j] || !(h > 0.0)) continue;
    const double tm = s.tm[j];
    hd.update(heading(p, tm));
    accel_core<true>(vel, s.R + 9 * j, th.d, th.dd, tm, p, g, hd.c, hd.s, a, A, &J[0][3],
                     N_SENS);
    integrate_step(pos, vel, a, h, 3);
    if (g.planar) {
      // rows 2 of A and J vanish, so Sv's row 2 stays e_z: only rows 0, 1 evolve and
      // A's column 2 acts on the v0_z column alone.
      for (int i = 0; i < 2; ++i) {
        const double a0 = A[3 * i], a1 = A[3 * i + 1];
        for (int c = 0; c < N_SENS; ++c) dA[i][c] = a0 * Sv[0][c] + a1 * Sv[1][c] + J[i][c];
        dA[i][2] += A[3 * i + 2];
      }
      for (int i = 0; i < 2; ++i) integrate_step(Sx[i], Sv[i], dA[i], h, N_SENS);
      Sx[2][2] += h;
    } else {
      for (int i = 0; i < 3; ++i) {
        const double a0 = A[3 * i], a1 = A[3 * i + 1], a2 = A[3 * i + 2];
        for (int c = 0; c < N_SENS; ++c)
          dA[i][c] = a0 * Sv[0][c] + a1 * Sv[1][c] + a2 * Sv[2][c] + J[i][c];
      }
      for (int i = 0; i < 3; ++i) integrate_step(Sx[i], Sv[i], dA[i], h, N_SENS);
    }
  }

  for (int i = 0; i < 3; ++i) {
    x1[i] = pos[i];
    x1[3 + i] = vel[i];
  }
  for (int r = 0; r < 6; ++r)
    for (int c = 0; c < 6; ++c) Jx[6 * r + c] = (r == c) ? 1.0 : 0.0;
  for (int i = 0; i < 3; ++i)
    for (int c = 0; c < 3; ++c) {
      Jx[6 * i + 3 + c] = Sx[i][c];
      Jx[6 * (3 + i) + 3 + c] = Sv[i][c];
    }
  for (int i = 0; i < 3; ++i)
    for (int c = 0; c < N_DYN; ++c) {
      Jp[N_DYN * i + c] = Sx[i][3 + c];
      Jp[N_DYN * (3 + i) + c] = Sv[i][3 + c];
    }
}

// The state after every step (X: n x 6 row-major), no Jacobians. Warm-up steps (and steps
// of non-positive length) only advance the thrust-lag filter and repeat the state.
AQFG_HOT_INLINE void rollout(const double* x0, const double* p, const Steps& s, const Geometry& g,
                    double* X) {
  double pos[3] = {x0[0], x0[1], x0[2]}, vel[3] = {x0[3], x0[4], x0[5]};
  const std::ptrdiff_t nt = g.n_thr;
  const double tau = p[P_THRUST_LAG_TAU];
  detail::ThrusterScratch th(nt);
  if (s.n > 0)
    for (std::ptrdiff_t i = 0; i < nt; ++i) th.f[i] = s.dem[i], th.df[i] = 0.0;
  LagCoeffs lag;
  detail::Heading hd;
  double a[3];
  for (std::ptrdiff_t j = 0; j < s.n; ++j) {
    const double h = s.h[j];
    filter_step(th.f, th.df, s.dem + nt * j, h, tau, lag, th.d, th.dd, nt);
    if (!s.warm[j] && h > 0.0) {
      const double tm = s.tm[j];
      hd.update(heading(p, tm));
      accel_core<false>(vel, s.R + 9 * j, th.d, th.dd, tm, p, g, hd.c, hd.s, a, nullptr,
                        nullptr, 0);
      integrate_step(pos, vel, a, h, 3);
    }
    double* x = X + 6 * j;
    for (int i = 0; i < 3; ++i) {
      x[i] = pos[i];
      x[3 + i] = vel[i];
    }
  }
}

// One dynamics factor's whitened Gauss-Newton block, as aqfg.fg.fastlag.LagWindow.dyn_linear
// computes it in numpy (the reference it is tested against). Over z = [theta (P), x0 (6),
// x1 (6)] with theta_j = p[cols[j]] (0 <= cols[j] < N_DYN, P <= N_DYN):
//   M = [Jp[:, cols], Jx, -I],  J = W M,  c = W (f(x0, p) - M[:, :P+6] [theta; x0]),
//   H = J^T J ((P + 12) x (P + 12), row-major),  b = J^T c (P + 12),  x1 = f(x0, p).
// W: the factor's whitening (6 x 6 row-major, W^T W = Q^-1). The residual is the negated
// f(x0, p) - x1 (the normal equations are the same).
inline constexpr int MAX_LIN = N_DYN + 12;

AQFG_HOT_INLINE void linearise(const double* x0, const double* p, const double* theta,
                               const std::int64_t* cols, int P, const double* W, const Steps& s,
                               const Geometry& g, double* x1, double* H, double* b) {
  double Jx[36], Jp[6 * N_DYN];
  propagate(x0, p, s, g, x1, Jx, Jp);
  const int n = P + 12;
  double M[6][MAX_LIN], J[6][MAX_LIN], r[6], c[6];
  for (int i = 0; i < 6; ++i) {
    double lin = 0.0;
    for (int j = 0; j < P; ++j) {
      M[i][j] = Jp[N_DYN * i + cols[j]];
      lin += M[i][j] * theta[j];
    }
    for (int j = 0; j < 6; ++j) {
      M[i][P + j] = Jx[6 * i + j];
      lin += M[i][P + j] * x0[j];
      M[i][P + 6 + j] = (i == j) ? -1.0 : 0.0;
    }
    r[i] = x1[i] - lin;
  }
  for (int i = 0; i < 6; ++i) {
    double ci = 0.0;
    for (int j = 0; j < n; ++j) J[i][j] = 0.0;
    for (int k = 0; k < 6; ++k) {
      const double w = W[6 * i + k];
      if (w == 0.0) continue;
      ci += w * r[k];
      for (int j = 0; j < n; ++j) J[i][j] += w * M[k][j];
    }
    c[i] = ci;
  }
  for (int a = 0; a < n; ++a) {
    double ba = 0.0;
    for (int i = 0; i < 6; ++i) ba += J[i][a] * c[i];
    b[a] = ba;
    for (int e = a; e < n; ++e) {
      double h = 0.0;
      for (int i = 0; i < 6; ++i) h += J[i][a] * J[i][e];
      H[n * a + e] = h;
      H[n * e + a] = h;
    }
  }
}

// reference.propagate_many: K segments; segment k uses steps offsets[k]:offsets[k+1]
// (offsets must be non-decreasing within [0, s.n]). Outputs X1 (K x 6), JX (K x 36),
// JP (K x 6 N_DYN), row-major.
inline void propagate_many(const double* X0, const double* p, const Steps& s,
                           const std::int64_t* offsets, std::ptrdiff_t K, const Geometry& g,
                           double* X1, double* JX, double* JP) {
  for (std::ptrdiff_t k = 0; k < K; ++k)
    propagate(X0 + 6 * k, p, s.slice(offsets[k], offsets[k + 1], g.n_thr), g, X1 + 6 * k,
              JX + 36 * k, JP + 6 * N_DYN * k);
}

}  // namespace kernel
}  // namespace aqfg
