// EKF window evaluation of the update-error method: C++ mirror of aqfg/ekf/window.py
// (window_ref, the readable numpy version). tests/test_ekf.py holds the two equal.
//
// One pass of the paper's EKF (Eqs. 5-11, 13) from a state (x0, P0) at knot k0 to knot k1:
// prediction with the shared model kernel (kernel.hpp: accel_core, filter_step; the same
// x += h v + h^2/2 a, v += h a integration as kernel::propagate), covariance carried with
// the step Jacobians and propagated at knots that hold an update, and the update nodes
// (motor: no-op with zero error; GNSS; USBL converted to a position with range-dependent
// covariance and a chi^2 gate; depth; IMU acceleration). Returns per node the update error
// e = K (z - h(x)) (Eq. 11), the innovation, its whitened form and std, and the status.
//
// State x = [pos (3) NED m, vel (3) NED m/s, a_b (3) body m/s^2]; P 9x9 row-major.
#pragma once

#include <cstdint>

#include "kernel.hpp"

namespace nanobind {
class module_;
}

namespace aqfg {
namespace ekf {

// Node kinds (NodeKind), statuses (Status) and the measurement parameters pm (MeasParam,
// N_MEAS) are generated into layout.hpp from the Python definitions.

// The settings a window pass reads: the fields of aqfg.ekf.history.EkfConfig of the same
// names (units there); bound to Python as aqfg._kernel.EkfSettings.
struct Config {
  double q_h, q_v;        // acceleration noise PSD, horizontal / vertical, m^2/s^3
  double sigma_ab;        // model error of a_b, m/s^2
  double sigma_range;     // USBL slant range, m
  double sigma_bearing;   // USBL bearing, rad
  double gate_usbl, gate_gnss;  // chi^2(2) gates on the innovations
  int max_rejects;        // after this many consecutive USBL rejections the next fix is taken
  bool full_cov;          // covariance with the model's Jacobian (else kinematic, cov_model)
};

// The history of one mission (views, no ownership): see aqfg/ekf/history.py.
struct Timeline {
  kernel::Steps steps;          // contiguous in time; warm flags unused (all zero)
  const std::int64_t* offsets;  // (K,) first step of each knot's segment
  std::int64_t n_knots;
  const double* knots;          // (K,) s
  const std::int64_t* node_knot;
  const std::int32_t* node_kind;
  const double* node_z;         // (M, 4)
  const double* node_R;         // (M, 9)
  const double* node_tm;        // (M,)
  const double* station;        // (3,)
};

// Outputs (caller-allocated). n = hi - lo nodes; X and Pn only when record.
struct Output {
  double* e;            // n x 9
  double* nu;           // n x 3 (NaN-padded)
  double* nu_w;         // n x 3
  double* s;            // n x 3
  std::int8_t* status;  // n
  double* x;            // 9
  double* P;            // 81
  double* X;            // (k1 - k0 + 1) x 9, or null
  double* Pn;           // n x 81, or null
};

// The pass. p: the N_DYN dynamics parameters; pm: the N_MEAS measurement parameters;
// w0: first thrust-lag warm-up step (<= offsets[k0]); nodes lo..hi-1 are those with knot
// in (k0, k1]; rejects: consecutive USBL rejections before k0. Returns those at k1.
// A rejected (gated) node leaves the state alone; its update error is K nu scaled to the
// gate boundary (Mahalanobis distance sqrt(gate)).
int window(const double* x0, const double* P0, std::int64_t k0, std::int64_t k1,
           const double* p, const double* pm, const Config& cfg, const Timeline& tl,
           const kernel::Geometry& g, std::int64_t w0, std::int64_t lo, std::int64_t hi,
           const Output& out, int rejects);

// Adds ekf_window to the Python module aqfg._kernel (called from bindings.cpp).
void register_ekf(nanobind::module_& m);

}  // namespace ekf
}  // namespace aqfg
