"""Would a symbolic definition of ``accel`` (sympy codegen) replace the hand-kept C++ mirror?

Defines the model's ground acceleration once in sympy (base model and the seven built-in
dynamics effects, as ``aqfg.model.reference.accel``), differentiates it w.r.t. the velocity
and the N_DYN parameters, prints C with common-subexpression elimination, compiles it with
the kernel's flags next to the hand-written ``kernel::accel_core<true>`` and compares the
two on the same random inputs: equal values (max |diff|) and time per call (median of
batches, C++ timer, no Python).

The generated code is specialised to one thruster layout (2 thrusters, port and
starboard, 3-D), which favours it: the hand kernel reads any layout at run time.
Run: ``python experiments/codegen_accel.py [--calls N]`` (needs sympy and g++).
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import sympy as sp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from aqfg.model.params import N_DYN, NAMES  # noqa: E402


def symbolic_accel(n_thr: int = 2, side=(-1.0, 1.0)):
    """a (3,), d a/d v (3x3), d a/d p (3 x N_DYN) as sympy expressions, and the symbols."""
    v = sp.Matrix(sp.symbols("v0:3", real=True))
    Rr = sp.Matrix(3, 3, sp.symbols("Rr0:9", real=True))
    d = sp.Matrix(sp.symbols(f"d0:{n_thr}", real=True))
    dd = sp.Matrix(sp.symbols(f"dd0:{n_thr}", real=True))
    dirs = sp.Matrix(n_thr, 3, sp.symbols(f"u0:{3 * n_thr}", real=True))
    p = sp.Matrix(sp.symbols(f"p0:{N_DYN}", real=True))
    tm, th, cth, sth = sp.symbols("tm th cth sth", real=True)
    P = dict(zip(NAMES[:N_DYN], p))
    Rz = sp.Matrix([[sp.cos(th), -sp.sin(th), 0], [sp.sin(th), sp.cos(th), 0], [0, 0, 1]])
    R = Rz * Rr
    s = sp.Matrix([P["s_x"] + P["current_drift.ds_x"] * tm, P["s_y"] + P["current_drift.ds_y"] * tm, 0])
    vr = R.T * (v - s)
    a_thr = sp.zeros(3, 1)
    for i in range(n_thr):
        g = P["k"] * (P["thrust_asymmetry.ratio"] if side[i] > 0 else 1)
        g = g * sp.Piecewise((P["reverse_thrust.ratio"], d[i] < 0), (1, True))
        a_thr += g * d[i] * dirs[i, :].T
    kq = [P["k_x"], P["k_yz"], P["k_yz"]]
    kl = [P["linear_drag.c_x"], P["linear_drag.c_yz"], P["linear_drag.c_yz"]]
    a_b = sp.Matrix([a_thr[m] - kq[m] * sp.Abs(vr[m]) * vr[m] - kl[m] * vr[m] for m in range(3)])
    a = R * a_b + sp.Matrix([P["wind_drag.a_n"], P["wind_drag.a_e"], 0])
    A = a.jacobian(v)
    Jp = a.jacobian(p)
    dth = a.diff(th)
    i_th, i_hdr, i_tau = (NAMES.index(n) for n in ("theta_e", "heading_drift.rate", "thrust_lag.tau"))
    Jp[:, i_th] = dth
    Jp[:, i_hdr] = dth * tm
    Jp[:, i_tau] = a.jacobian(d) * dd
    sub = {sp.cos(th): cth, sp.sin(th): sth}
    outs = [e.subs(sub) for e in list(a) + list(A) + list(Jp)]
    ins = dict(v=v, Rr=Rr, d=d, dd=dd, dirs=dirs, p=p, tm=tm, cth=cth, sth=sth)
    return outs, ins


def c_source(outs, ins) -> str:
    """C++ of the generated function (``accel_gen``), same arguments as accel_core."""
    repl, red = sp.cse(outs, optimizations="basic")
    lines = ["inline void accel_gen(const double* v, const double* Rraw, const double* d,",
             "                      const double* dd, double tm, const double* p,",
             "                      const double* dirs, double cth, double sth, double* a,",
             "                      double* A, double* Jp) {"]
    def arr(name, syms, cname):
        return [f"  const double {s} = {cname}[{i}];" for i, s in enumerate(syms)]
    lines += arr("v", ins["v"], "v") + arr("Rr", ins["Rr"], "Rraw") + arr("d", ins["d"], "d")
    lines += arr("dd", ins["dd"], "dd") + arr("u", ins["dirs"], "dirs") + arr("p", ins["p"], "p")
    for sym, e in repl:
        lines.append(f"  const double {sym} = {sp.cxxcode(e, standard='c++17')};")
    n_a = 3
    for i, e in enumerate(red):
        if i < n_a:
            lines.append(f"  a[{i}] = {sp.cxxcode(e, standard='c++17')};")
        elif i < n_a + 9:
            lines.append(f"  A[{i - n_a}] = {sp.cxxcode(e, standard='c++17')};")
        else:
            lines.append(f"  Jp[{i - n_a - 9}] = {sp.cxxcode(e, standard='c++17')};")
    lines.append("}")
    return "\n".join(lines)


HARNESS = r"""
#include <chrono>
#include <cmath>
#include <cstdio>
#include <random>
#include <algorithm>
#include <vector>
#include "kernel.hpp"
namespace kn = aqfg::kernel;
using std::abs;
GENERATED

int main(int argc, char** argv) {
  const int calls = argc > 1 ? std::atoi(argv[1]) : 200000;
  std::mt19937_64 rng(1);
  std::uniform_real_distribution<double> U(-1.0, 1.0);
  const int n = 64;  // distinct inputs, cycled
  std::vector<double> V(3 * n), R(9 * n), D(2 * n), DD(2 * n), P(kn::N_DYN * n), T(n);
  for (auto* x : {&V, &R, &D, &DD, &T}) for (auto& y : *x) y = U(rng);
  for (int k = 0; k < n; ++k) {
    double q[4] = {U(rng), U(rng), U(rng), U(rng)}, s = 0;
    for (double w : q) s += w * w;
    s = std::sqrt(s); for (double& w : q) w /= s;
    const double w = q[0], x = q[1], y = q[2], z = q[3];
    double* r = &R[9 * k];
    r[0] = 1 - 2 * (y * y + z * z); r[1] = 2 * (x * y - w * z); r[2] = 2 * (x * z + w * y);
    r[3] = 2 * (x * y + w * z); r[4] = 1 - 2 * (x * x + z * z); r[5] = 2 * (y * z - w * x);
    r[6] = 2 * (x * z - w * y); r[7] = 2 * (y * z + w * x); r[8] = 1 - 2 * (x * x + y * y);
    for (int i = 0; i < kn::N_DYN; ++i) P[kn::N_DYN * k + i] = 0.5 + 0.5 * std::abs(U(rng));
    T[k] = 100.0 * std::abs(T[k]);
  }
  const double dirs[6] = {1, 0.1, 0, 0.9, -0.1, 0.2}, side[2] = {-1, 1};
  kn::Geometry g{dirs, side, 2, false};
  double a1[3], A1[9], J1[3 * kn::N_DYN], a2[3], A2[9], J2[3 * kn::N_DYN];
  double maxdiff = 0, scale = 0;
  for (int k = 0; k < n; ++k) {
    const double* p = &P[kn::N_DYN * k];
    const double th = kn::heading(p, T[k]), c = std::cos(th), s = std::sin(th);
    kn::accel_core<true>(&V[3 * k], &R[9 * k], &D[2 * k], &DD[2 * k], T[k], p, g, c, s,
                         a1, A1, J1, kn::N_DYN);
    accel_gen(&V[3 * k], &R[9 * k], &D[2 * k], &DD[2 * k], T[k], p, dirs, c, s, a2, A2, J2);
    auto upd = [&](const double* x, const double* y, int m) {
      for (int i = 0; i < m; ++i) {
        maxdiff = std::max(maxdiff, std::abs(x[i] - y[i]));
        scale = std::max(scale, std::abs(x[i]));
      }
    };
    upd(a1, a2, 3);
    upd(A1, A2, 9);
    upd(J1, J2, 3 * kn::N_DYN);
  }
  std::printf("max_abs_diff %.3e scale %.3e\n", maxdiff, scale);
  volatile double sink = 0;
  auto run = [&](bool gen) {
    std::vector<double> ts;
    for (int rep = 0; rep < 15; ++rep) {
      auto t0 = std::chrono::steady_clock::now();
      for (int i = 0; i < calls; ++i) {
        const int k = i % n;
        const double* p = &P[kn::N_DYN * k];
        const double c = 0.8, s = 0.6;
        if (gen)
          accel_gen(&V[3 * k], &R[9 * k], &D[2 * k], &DD[2 * k], T[k], p, dirs, c, s, a2, A2,
                    J2);
        else
          kn::accel_core<true>(&V[3 * k], &R[9 * k], &D[2 * k], &DD[2 * k], T[k], p, g, c, s,
                               a2, A2, J2, kn::N_DYN);
        sink = sink + a2[0] + J2[5];
      }
      auto t1 = std::chrono::steady_clock::now();
      ts.push_back(std::chrono::duration<double>(t1 - t0).count() / calls * 1e9);
    }
    std::sort(ts.begin(), ts.end());
    return std::make_pair(ts[ts.size() / 10], ts[ts.size() / 2]);
  };
  auto h = run(false), q = run(true);
  std::printf("hand_ns p10 %.1f median %.1f\n", h.first, h.second);
  std::printf("gen_ns p10 %.1f median %.1f\n", q.first, q.second);
  return 0;
}
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=200000, help="calls per timed batch")
    ap.add_argument("--flags", default="-O3 -fno-math-errno -march=x86-64-v3",
                    help="compiler flags (the kernel's, with its AVX2 clone)")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    outs, ins = symbolic_accel()
    src = c_source(outs, ins)
    t_sym = time.perf_counter() - t0
    n_lines = src.count("\n") + 1
    with tempfile.TemporaryDirectory() as tmp:
        cpp = Path(tmp) / "bench.cpp"
        cpp.write_text(HARNESS.replace("GENERATED", src))
        exe = Path(tmp) / "bench"
        subprocess.run(["g++", "-std=c++17", *a.flags.split(), "-I", str(ROOT / "cpp_factors"),
                        str(cpp), "-o", str(exe)], check=True)
        out = subprocess.run([str(exe), str(a.calls)], check=True, capture_output=True,
                             text=True).stdout
    print(f"sympy: {t_sym:.1f} s to derive and print; generated accel + Jacobians: "
          f"{n_lines} lines of C++ (2 thrusters, 3-D)")
    print(out.strip())
    return 0


if __name__ == "__main__":
    sys.exit(main())
