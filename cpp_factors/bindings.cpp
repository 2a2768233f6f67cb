// Python bindings (nanobind) of the vehicle-model kernel in kernel.hpp: module aqfg._kernel.
// Signatures follow what aqfg/model/vehicle.py calls; shapes are checked here and a bad one raises
// ValueError naming the argument.
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/string.h>
#include <nanobind/stl/tuple.h>

#include <chrono>
#include <cmath>
#include <cstdint>
#include <initializer_list>
#include <string>
#include <tuple>

#include "ekf.hpp"
#include "kernel.hpp"
#include "window.hpp"

namespace nb = nanobind;
namespace kn = aqfg::kernel;

namespace {

using InF64 = nb::ndarray<const double, nb::c_contig, nb::device::cpu>;
using InU8 = nb::ndarray<const std::uint8_t, nb::c_contig, nb::device::cpu>;
using InI64 = nb::ndarray<const std::int64_t, nb::c_contig, nb::device::cpu>;
using OutF64 = nb::ndarray<nb::numpy, double>;
using InOutF64 = nb::ndarray<double, nb::c_contig, nb::device::cpu>;

constexpr std::int64_t ANY = -1;
const std::string P_SHAPE = "(N_DYN,) = (" + std::to_string(kn::N_DYN) + ",)";

// The integration loops compiled twice on x86-64 Linux: for AVX2+FMA (x86-64-v3) and for
// the baseline; the loader picks the one the CPU supports (GNU ifunc, so glibc and GCC >= 11
// only; elsewhere the baseline alone). The kernel's hot functions are always_inline, so each
// clone holds its own vectorised copy.
#if defined(__x86_64__) && defined(__linux__) && defined(__GLIBC__) && !defined(__clang__) && \
    defined(__GNUC__) && __GNUC__ >= 11
#define AQFG_CLONES __attribute__((target_clones("arch=x86-64-v3", "default")))
#else
#define AQFG_CLONES
#endif

AQFG_CLONES void run_propagate(const double* x0, const double* p, const kn::Steps& s,
                               const kn::Geometry& g, double* x1, double* Jx, double* Jp) {
  kn::propagate(x0, p, s, g, x1, Jx, Jp);
}

AQFG_CLONES void run_propagate_many(const double* X0, const double* p, const kn::Steps& s,
                                    const std::int64_t* off, std::ptrdiff_t K,
                                    const kn::Geometry& g, double* X1, double* JX, double* JP) {
  for (std::ptrdiff_t k = 0; k < K; ++k)
    kn::propagate(X0 + 6 * k, p, s.slice(off[k], off[k + 1], g.n_thr), g, X1 + 6 * k,
                  JX + 36 * k, JP + 6 * kn::N_DYN * k);
}

AQFG_CLONES void run_linearise(const double* x0, const double* p, const double* theta,
                              const std::int64_t* cols, int P, const double* W,
                              const kn::Steps& s, const kn::Geometry& g, double* x1, double* H,
                              double* b) {
  kn::linearise(x0, p, theta, cols, P, W, s, g, x1, H, b);
}

AQFG_CLONES void run_rollout(const double* x0, const double* p, const kn::Steps& s,
                             const kn::Geometry& g, double* X) {
  kn::rollout(x0, p, s, g, X);
}

template <class Arr>
std::string shape_str(const Arr& a) {
  std::string s = "(";
  for (std::size_t i = 0; i < a.ndim(); ++i) {
    if (i) s += ", ";
    s += std::to_string(a.shape(i));
  }
  return s + (a.ndim() == 1 ? ",)" : ")");
}

// Raise ValueError unless `a` has the shape `want` (ANY = any length on that axis).
template <class Arr>
void check_shape(const char* fn, const char* name, const Arr& a,
                 std::initializer_list<std::int64_t> want, const std::string& meaning) {
  bool ok = a.ndim() == want.size();
  std::size_t i = 0;
  for (auto w : want) {
    if (!ok) break;
    ok = (w == ANY) || (static_cast<std::int64_t>(a.shape(i)) == w);
    ++i;
  }
  if (!ok)
    throw nb::value_error((std::string(fn) + ": argument '" + name + "' must have shape " +
                           meaning + ", got " + shape_str(a))
                              .c_str());
}

// `planar`: a Python bool or a numpy bool (e.g. from an array comparison).
bool as_bool(const char* fn, const char* name, nb::handle h) {
  if (h.is(nb::handle(Py_True))) return true;
  if (h.is(nb::handle(Py_False))) return false;
  nb::handle tp = h.type();
  if (nb::hasattr(tp, "__module__") && nb::cast<std::string>(tp.attr("__module__")) == "numpy" &&
      nb::cast<std::string>(tp.attr("__name__")).rfind("bool", 0) == 0)
    return PyObject_IsTrue(h.ptr()) == 1;
  throw nb::type_error((std::string(fn) + ": argument '" + name + "' must be a bool, got " +
                        nb::cast<std::string>(nb::str(tp.attr("__name__"))))
                           .c_str());
}

OutF64 new_array(std::initializer_list<std::size_t> shape, double*& data) {
  std::size_t n = 1;
  for (auto s : shape) n *= s;
  data = new double[n > 0 ? n : 1];
  nb::capsule owner(data, [](void* p) noexcept { delete[] static_cast<double*>(p); });
  return OutF64(data, shape.size(), shape.begin(), owner);
}

// The geometry and step arguments shared by propagate / propagate_many / rollout.
struct Inputs {
  kn::Steps steps;
  kn::Geometry geom;
};

Inputs check_inputs(const char* fn, const InF64& p, const InF64& h, const InU8& warm,
                    const InF64& R, const InF64& dem, const InF64& tm, const InF64& dirs,
                    const InF64& side, bool planar) {
  check_shape(fn, "p", p, {kn::N_DYN}, P_SHAPE);
  check_shape(fn, "h", h, {ANY}, "(n,)");
  const std::int64_t n = static_cast<std::int64_t>(h.shape(0));
  check_shape(fn, "dem", dem, {n, ANY}, "(n, N_thrusters) with n = len(h)");
  const std::int64_t nt = static_cast<std::int64_t>(dem.shape(1));
  check_shape(fn, "warm", warm, {n}, "(n,) with n = len(h)");
  check_shape(fn, "R", R, {n, 9}, "(n, 9) with n = len(h)");
  check_shape(fn, "tm", tm, {n}, "(n,) with n = len(h)");
  check_shape(fn, "dirs", dirs, {nt, 3}, "(N_thrusters, 3) with N_thrusters = dem.shape[1]");
  check_shape(fn, "side", side, {nt}, "(N_thrusters,) with N_thrusters = dem.shape[1]");
  return Inputs{kn::Steps{h.data(), warm.data(), R.data(), dem.data(), tm.data(), n},
                kn::Geometry{dirs.data(), side.data(), nt, planar}};
}

std::tuple<OutF64, OutF64, OutF64> py_propagate(const InF64& x0, const InF64& p, const InF64& h,
                                                const InU8& warm, const InF64& R,
                                                const InF64& dem, const InF64& tm,
                                                const InF64& dirs, const InF64& side,
                                                nb::handle planar_obj) {
  const char* fn = "propagate";
  const bool planar = as_bool(fn, "planar", planar_obj);
  check_shape(fn, "x0", x0, {6}, "(6,)");
  Inputs in = check_inputs(fn, p, h, warm, R, dem, tm, dirs, side, planar);
  double *x1, *Jx, *Jp;
  OutF64 ax1 = new_array({6}, x1), aJx = new_array({6, 6}, Jx),
         aJp = new_array({6, kn::N_DYN}, Jp);
  run_propagate(x0.data(), p.data(), in.steps, in.geom, x1, Jx, Jp);
  return {ax1, aJx, aJp};
}

std::tuple<OutF64, OutF64, OutF64> py_propagate_many(const InF64& X0, const InF64& p,
                                                     const InF64& h, const InU8& warm,
                                                     const InF64& R, const InF64& dem,
                                                     const InF64& tm, const InI64& offsets,
                                                     const InF64& dirs, const InF64& side,
                                                     nb::handle planar_obj) {
  const char* fn = "propagate_many";
  const bool planar = as_bool(fn, "planar", planar_obj);
  check_shape(fn, "X0", X0, {ANY, 6}, "(K, 6)");
  const std::int64_t K = static_cast<std::int64_t>(X0.shape(0));
  check_shape(fn, "offsets", offsets, {K + 1}, "(K + 1,) with K = X0.shape[0]");
  Inputs in = check_inputs(fn, p, h, warm, R, dem, tm, dirs, side, planar);
  const std::int64_t* off = offsets.data();
  for (std::int64_t k = 0; k <= K; ++k) {
    if (off[k] < 0 || off[k] > in.steps.n || (k > 0 && off[k] < off[k - 1]))
      throw nb::value_error(("propagate_many: argument 'offsets' must be non-decreasing "
                             "within [0, len(h)] = [0, " +
                             std::to_string(in.steps.n) + "]; offsets[" + std::to_string(k) +
                             "] = " + std::to_string(off[k]))
                                .c_str());
  }
  double *X1, *JX, *JP;
  const std::size_t Ks = static_cast<std::size_t>(K);
  OutF64 a1 = new_array({Ks, 6}, X1), a2 = new_array({Ks, 6, 6}, JX),
         a3 = new_array({Ks, 6, kn::N_DYN}, JP);
  {
    nb::gil_scoped_release release;
    run_propagate_many(X0.data(), p.data(), in.steps, off, K, in.geom, X1, JX, JP);
  }
  return {a1, a2, a3};
}

// A quadratic's H (N, N) and b (N,): returns N.
template <class Arr>
std::int64_t check_quadratic(const char* fn, const Arr& H, const Arr& b) {
  check_shape(fn, "H", H, {ANY, ANY}, "(N, N)");
  const std::int64_t N = static_cast<std::int64_t>(H.shape(0));
  check_shape(fn, "H", H, {N, N}, "(N, N)");
  check_shape(fn, "b", b, {N}, "(N,) with N = len(H)");
  return N;
}

// theta's kernel columns: P <= N_DYN indices into the N_DYN parameters.
void check_cols(const char* fn, const InI64& cols, std::int64_t P);

// The arguments linearise and linearise_into share: x0 (6,), theta (P,), cols (P,), W (6, 6).
// Returns P.
std::int64_t check_block_args(const char* fn, const InF64& x0, const InF64& theta,
                              const InI64& cols, const InF64& W) {
  check_shape(fn, "x0", x0, {6}, "(6,)");
  check_shape(fn, "theta", theta, {ANY}, "(P,)");
  const std::int64_t P = static_cast<std::int64_t>(theta.shape(0));
  check_cols(fn, cols, P);
  check_shape(fn, "W", W, {6, 6}, "(6, 6)");
  return P;
}

void check_cols(const char* fn, const InI64& cols, std::int64_t P) {
  if (P > kn::N_DYN)
    throw nb::value_error((std::string(fn) + ": argument 'theta' must have at most N_DYN = " +
                           std::to_string(kn::N_DYN) + " entries, got " + std::to_string(P))
                              .c_str());
  check_shape(fn, "cols", cols, {P}, "(P,) with P = len(theta)");
  for (std::int64_t j = 0; j < P; ++j)
    if (cols.data()[j] < 0 || cols.data()[j] >= kn::N_DYN)
      throw nb::value_error((std::string(fn) + ": argument 'cols' must index the N_DYN = " +
                             std::to_string(kn::N_DYN) + " parameters; cols[" +
                             std::to_string(j) + "] = " + std::to_string(cols.data()[j]))
                                .c_str());
}

std::tuple<OutF64, OutF64, OutF64> py_linearise(const InF64& x0, const InF64& p,
                                                 const InF64& theta, const InI64& cols,
                                                 const InF64& W, const InF64& h,
                                                 const InU8& warm, const InF64& R,
                                                 const InF64& dem, const InF64& tm,
                                                 const InF64& dirs, const InF64& side,
                                                 nb::handle planar_obj) {
  const char* fn = "linearise";
  const bool planar = as_bool(fn, "planar", planar_obj);
  const std::int64_t P = check_block_args(fn, x0, theta, cols, W);
  Inputs in = check_inputs(fn, p, h, warm, R, dem, tm, dirs, side, planar);
  const std::size_t n = static_cast<std::size_t>(P + 12);
  double *x1, *H, *b;
  OutF64 ax1 = new_array({6}, x1), aH = new_array({n, n}, H), ab = new_array({n}, b);
  run_linearise(x0.data(), p.data(), theta.data(), cols.data(), static_cast<int>(P), W.data(),
                in.steps, in.geom, x1, H, b);
  return {ax1, aH, ab};
}

// linearise, and the block swapped into the window's held quadratic in place: with
// r = [0..P) + [o, o+12) (P = len(theta)), H[r, r] += Hn - Hblk, b[r] += bn - bblk, then
// Hblk, bblk = Hn, bn (the factor's block, kept for its next relinearisation). Nothing is
// written when f(x0, p) is not finite. Returns f(x0, p).
OutF64 py_linearise_into(const InF64& x0, const InF64& p, const InF64& theta, const InI64& cols,
                         const InF64& W, std::int64_t o, InOutF64 H, InOutF64 b, InOutF64 Hblk,
                         InOutF64 bblk, const InF64& h, const InU8& warm, const InF64& R,
                         const InF64& dem, const InF64& tm, const InF64& dirs,
                         const InF64& side, nb::handle planar_obj) {
  const char* fn = "linearise_into";
  const bool planar = as_bool(fn, "planar", planar_obj);
  const std::int64_t P = check_block_args(fn, x0, theta, cols, W);
  const std::int64_t N = check_quadratic(fn, H, b);
  const std::int64_t n = P + 12;
  check_shape(fn, "Hblk", Hblk, {n, n}, "(P+12, P+12) with P = len(theta)");
  check_shape(fn, "bblk", bblk, {n}, "(P+12,) with P = len(theta)");
  if (o < P || o + 12 > N)
    throw nb::value_error(("linearise_into: argument 'o' must be in [P, N - 12] = [" +
                           std::to_string(P) + ", " + std::to_string(N - 12) + "], got " +
                           std::to_string(o))
                              .c_str());
  Inputs in = check_inputs(fn, p, h, warm, R, dem, tm, dirs, side, planar);
  double* x1;
  OutF64 ax1 = new_array({6}, x1);
  double Hn[kn::MAX_LIN * kn::MAX_LIN], bn[kn::MAX_LIN];
  run_linearise(x0.data(), p.data(), theta.data(), cols.data(), static_cast<int>(P), W.data(),
                in.steps, in.geom, x1, Hn, bn);
  for (int i = 0; i < 6; ++i)
    if (!std::isfinite(x1[i])) return ax1;
  std::int64_t r[kn::MAX_LIN];
  for (std::int64_t j = 0; j < P; ++j) r[j] = j;
  for (std::int64_t j = 0; j < 12; ++j) r[P + j] = o + j;
  double *Hd = H.data(), *bd = b.data(), *Hb = Hblk.data(), *bb = bblk.data();
  for (std::int64_t a = 0; a < n; ++a) {
    double* Hrow = Hd + r[a] * N;
    for (std::int64_t c = 0; c < n; ++c) {
      const std::int64_t k = a * n + c;
      Hrow[r[c]] += Hn[k] - Hb[k];
      Hb[k] = Hn[k];
    }
    bd[r[a]] += bn[a] - bb[a];
    bb[a] = bn[a];
  }
  return ax1;
}

// window.hpp gn_step: (ok, s (N,), C (P, P)); hold of length 0 means no hold priors.
std::tuple<bool, OutF64, OutF64> py_window_step(const InF64& H, const InF64& b, const InF64& z,
                                                const InF64& hold, const InF64& th0,
                                                std::int64_t P) {
  const char* fn = "window_step";
  const std::int64_t N = check_quadratic(fn, H, b);
  check_shape(fn, "z", z, {N}, "(N,) with N = len(H)");
  if (P < 0 || P > N)
    throw nb::value_error(("window_step: argument 'P' must be in [0, N] = [0, " +
                           std::to_string(N) + "], got " + std::to_string(P))
                              .c_str());
  const bool held = hold.shape(0) > 0;
  if (held) check_shape(fn, "hold", hold, {P}, "(P,) or (0,)");
  check_shape(fn, "th0", th0, {P}, "(P,)");
  double *s, *C;
  const std::size_t Ns = static_cast<std::size_t>(N), Ps = static_cast<std::size_t>(P);
  OutF64 as = new_array({Ns}, s), aC = new_array({Ps, Ps}, C);
  const bool ok = aqfg::window::gn_step(H.data(), b.data(), z.data(),
                                        held ? hold.data() : nullptr, th0.data(),
                                        static_cast<int>(N), static_cast<int>(P), s, C);
  return {ok, as, aC};
}

// window.hpp schur_drop: (ok, Hn, bn).
std::tuple<bool, OutF64, OutF64> py_schur_drop(const InF64& H, const InF64& b, std::int64_t a,
                                               std::int64_t na) {
  const char* fn = "schur_drop";
  const std::int64_t N = check_quadratic(fn, H, b);
  if (na < 1 || a < 0 || a + na > N)
    throw nb::value_error(("schur_drop: arguments 'a', 'na' must give 0 <= a, 1 <= na, a + na "
                           "<= N = " + std::to_string(N) + "; got a = " + std::to_string(a) +
                           ", na = " + std::to_string(na))
                              .c_str());
  const std::size_t M = static_cast<std::size_t>(N - na);
  double *Hn, *bn;
  OutF64 aH = new_array({M, M}, Hn), ab = new_array({M}, bn);
  const bool ok = aqfg::window::schur_drop(H.data(), b.data(), static_cast<int>(N),
                                           static_cast<int>(a), static_cast<int>(na), Hn, bn);
  return {ok, aH, ab};
}

OutF64 py_rollout(const InF64& x0, const InF64& p, const InF64& h, const InU8& warm,
                  const InF64& R, const InF64& dem, const InF64& tm, const InF64& dirs,
                  const InF64& side, nb::handle planar_obj) {
  const char* fn = "rollout";
  const bool planar = as_bool(fn, "planar", planar_obj);
  check_shape(fn, "x0", x0, {6}, "(6,)");
  Inputs in = check_inputs(fn, p, h, warm, R, dem, tm, dirs, side, planar);
  double* X;
  OutF64 out = new_array({static_cast<std::size_t>(in.steps.n), 6}, X);
  {
    nb::gil_scoped_release release;
    run_rollout(x0.data(), p.data(), in.steps, in.geom, X);
  }
  return out;
}

std::tuple<OutF64, OutF64, OutF64> py_accel(const InF64& v, const InF64& R_raw, const InF64& d,
                                            const InF64& dd_tau, double tm, const InF64& p,
                                            const InF64& dirs, const InF64& side,
                                            nb::handle planar_obj) {
  const char* fn = "accel";
  const bool planar = as_bool(fn, "planar", planar_obj);
  check_shape(fn, "v", v, {3}, "(3,)");
  if (R_raw.ndim() == 2)
    check_shape(fn, "R_raw", R_raw, {3, 3}, "(9,) or (3, 3)");
  else
    check_shape(fn, "R_raw", R_raw, {9}, "(9,) or (3, 3)");
  check_shape(fn, "p", p, {kn::N_DYN}, P_SHAPE);
  check_shape(fn, "d", d, {ANY}, "(N_thrusters,)");
  const std::int64_t nt = static_cast<std::int64_t>(d.shape(0));
  check_shape(fn, "dd_tau", dd_tau, {nt}, "(N_thrusters,) with N_thrusters = len(d)");
  check_shape(fn, "dirs", dirs, {nt, 3}, "(N_thrusters, 3) with N_thrusters = len(d)");
  check_shape(fn, "side", side, {nt}, "(N_thrusters,) with N_thrusters = len(d)");
  kn::Geometry g{dirs.data(), side.data(), nt, planar};
  double *a, *A, *Jp;
  OutF64 aa = new_array({3}, a), aA = new_array({3, 3}, A), aJ = new_array({3, kn::N_DYN}, Jp);
  kn::accel(v.data(), R_raw.data(), d.data(), dd_tau.data(), tm, p.data(), g, a, A, Jp);
  return {aa, aA, aJ};
}

// Seconds per propagate call, timed in C++ over `repeats` calls (no Python overhead).
double py_bench_propagate(const InF64& x0, const InF64& p, const InF64& h, const InU8& warm,
                          const InF64& R, const InF64& dem, const InF64& tm, const InF64& dirs,
                          const InF64& side, nb::handle planar_obj, int repeats) {
  const char* fn = "bench_propagate";
  const bool planar = as_bool(fn, "planar", planar_obj);
  check_shape(fn, "x0", x0, {6}, "(6,)");
  Inputs in = check_inputs(fn, p, h, warm, R, dem, tm, dirs, side, planar);
  if (repeats < 1) throw nb::value_error("bench_propagate: argument 'repeats' must be >= 1");
  double x1[6], Jx[36], Jp[6 * kn::N_DYN];
  volatile double sink = 0.0;
  nb::gil_scoped_release release;
  const auto t0 = std::chrono::steady_clock::now();
  for (int r = 0; r < repeats; ++r) {
    run_propagate(x0.data(), p.data(), in.steps, in.geom, x1, Jx, Jp);
    sink = sink + x1[0] + Jp[0];
  }
  const auto t1 = std::chrono::steady_clock::now();
  (void)sink;
  return std::chrono::duration<double>(t1 - t0).count() / repeats;
}

}  // namespace

NB_MODULE(_kernel, m) {
  m.doc() =
      "C++ vehicle-model kernel (mirror of aqfg.model.reference): integration of the inputs over a "
      "segment with analytic Jacobians w.r.t. the start state and the N_DYN dynamics "
      "parameters.";
  m.attr("N_DYN") = static_cast<int>(kn::N_DYN);
  nb::dict idx;
  for (int i = 0; i < kn::N_DYN; ++i) idx[kn::PARAM_NAMES[i]] = i;
  m.attr("PARAM_INDEX") = idx;
  nb::dict midx;
  for (int i = 0; i < aqfg::ekf::N_MEAS; ++i) midx[aqfg::ekf::MEAS_NAMES[i]] = i;
  m.attr("MEAS_INDEX") = midx;

  m.def("propagate", &py_propagate, nb::arg("x0"), nb::arg("p"), nb::arg("h"), nb::arg("warm"),
        nb::arg("R"), nb::arg("dem"), nb::arg("tm"), nb::arg("dirs"), nb::arg("side"),
        nb::arg("planar"),
        "State [pos, vel] (NED, m, m/s) after the steps; returns (x1 (6,), Jx (6, 6) = dx1/dx0, "
        "Jp (6, N_DYN) = dx1/dp). As aqfg.model.reference.propagate without user effects.");
  m.def("propagate_many", &py_propagate_many, nb::arg("X0"), nb::arg("p"), nb::arg("h"),
        nb::arg("warm"), nb::arg("R"), nb::arg("dem"), nb::arg("tm"), nb::arg("offsets"),
        nb::arg("dirs"), nb::arg("side"), nb::arg("planar"),
        "propagate for K segments (segment k: steps offsets[k]:offsets[k+1]); returns "
        "(X1 (K, 6), JX (K, 6, 6), JP (K, 6, N_DYN)).");
  m.def("linearise", &py_linearise, nb::arg("x0"), nb::arg("p"), nb::arg("theta"),
        nb::arg("cols"), nb::arg("W"), nb::arg("h"), nb::arg("warm"), nb::arg("R"),
        nb::arg("dem"), nb::arg("tm"), nb::arg("dirs"), nb::arg("side"), nb::arg("planar"),
        "One dynamics factor's whitened Gauss-Newton block over z = [theta, x0, x1] "
        "(theta_j = p[cols[j]]): returns (x1 (6,) = f(x0, p), H (P+12, P+12) = J^T J, "
        "b (P+12,) = J^T c) with J = W [Jp[:, cols], Jx, -I] and c = W (x1 - [Jp[:, cols], "
        "Jx] [theta; x0]); as aqfg.fg.fastlag.LagWindow.dyn_linear.");
  m.def("linearise_into", &py_linearise_into, nb::arg("x0"), nb::arg("p"), nb::arg("theta"),
        nb::arg("cols"), nb::arg("W"), nb::arg("o"), nb::arg("H").noconvert(),
        nb::arg("b").noconvert(), nb::arg("Hblk").noconvert(), nb::arg("bblk").noconvert(),
        nb::arg("h"), nb::arg("warm"), nb::arg("R"), nb::arg("dem"), nb::arg("tm"),
        nb::arg("dirs"), nb::arg("side"), nb::arg("planar"),
        "linearise, with the block swapped into the quadratic (H, b) in place: rows/columns "
        "[0, P) and [o, o+12) get (Hn - Hblk, bn - bblk), then Hblk, bblk = Hn, bn; nothing "
        "written when the prediction is not finite. Returns the prediction f(x0, p) (6,).");
  m.def("window_step", &py_window_step, nb::arg("H"), nb::arg("b"), nb::arg("z"),
        nb::arg("hold"), nb::arg("th0"), nb::arg("P"),
        "The fixed-lag window's Gauss-Newton step (aqfg.fg.fastlag.LagWindow.step): with "
        "A = H + diag(hold) and g = H z + b + hold (z - th0) on the first P variables "
        "(hold of length 0: none), returns (ok, s (N,), C (P, P)) with A s = g and C the "
        "first P rows and columns of A^-1; ok False when A is not positive definite or a "
        "result is not finite.");
  m.def("schur_drop", &py_schur_drop, nb::arg("H"), nb::arg("b"), nb::arg("a"), nb::arg("na"),
        "Schur complement eliminating variables [a, a + na) of the quadratic (H, b): returns "
        "(ok, Hn, bn) over the others, in order; ok False when H_aa is not positive "
        "definite.");
  m.def("rollout", &py_rollout, nb::arg("x0"), nb::arg("p"), nb::arg("h"), nb::arg("warm"),
        nb::arg("R"), nb::arg("dem"), nb::arg("tm"), nb::arg("dirs"), nb::arg("side"),
        nb::arg("planar"),
        "State after every step (n, 6), no Jacobians; warm-up steps repeat the state.");
  m.def("accel", &py_accel, nb::arg("v"), nb::arg("R_raw"), nb::arg("d"), nb::arg("dd_tau"),
        nb::arg("tm"), nb::arg("p"), nb::arg("dirs"), nb::arg("side"), nb::arg("planar"),
        "Ground acceleration (3,) and its Jacobians w.r.t. v (3, 3) and p (3, N_DYN); as "
        "aqfg.model.reference.accel.");
  m.def("bench_propagate", &py_bench_propagate, nb::arg("x0"), nb::arg("p"), nb::arg("h"),
        nb::arg("warm"), nb::arg("R"), nb::arg("dem"), nb::arg("tm"), nb::arg("dirs"),
        nb::arg("side"), nb::arg("planar"), nb::arg("repeats"),
        "Seconds per propagate call, timed in C++ over `repeats` calls.");
  aqfg::ekf::register_ekf(m);  // update-error EKF window (ekf.cpp)
}
