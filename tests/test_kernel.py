"""The C++ kernel ``aqfg._kernel`` against the numpy reference ``aqfg.model.reference``.

Random states, parameters (every effect away from its null value) and inputs; planar and
not, 2 and 5 thrusters, with and without thrust lag, with warm-up steps. Values and
Jacobians must agree to 1e-9 (relative 1e-6 at worst), and the Jacobians of both must agree
with central finite differences.
"""
from __future__ import annotations

import numpy as np
import pytest

from aqfg import _kernel as K
from aqfg.model import reference as ref
from aqfg.model.vehicle import quat_to_rot
from aqfg.model.params import DYNAMICS_EFFECTS, INDEX, N_DYN, NAMES, PARAMS, vector

I_TAU = INDEX["thrust_lag.tau"]


# ---------------------------------------------------------------- random problems
# ranges of the random dynamics parameters; a parameter not listed here (a new effect) is
# drawn between half and one and a half times its typical distance from its null value
RANGES = {
    "theta_e": (-1.0, 1.0), "s_x": (-0.4, 0.4), "s_y": (-0.4, 0.4),
    "k": (3.0, 10.0), "k_x": (0.5, 3.0), "k_yz": (0.1, 1.0),
    "thrust_asymmetry.ratio": (0.6, 1.6), "reverse_thrust.ratio": (0.4, 1.5),
    "linear_drag.c_x": (0.05, 0.5), "linear_drag.c_yz": (0.05, 0.5),
    "heading_drift.rate": (-0.02, 0.02),
    "current_drift.ds_x": (-0.005, 0.005), "current_drift.ds_y": (-0.005, 0.005),
    "wind_drag.a_n": (-0.3, 0.3), "wind_drag.a_e": (-0.3, 0.3),
    "ground_advance.c": (0.02, 0.2),
}
# parameters of effects the C++ kernel evaluates (the others stay at their null value)
IN_CPP = {n for e in DYNAMICS_EFFECTS if e.in_cpp for n in e.params} | set(NAMES[:6])
# their columns of J_p (an effect evaluated in Python only has a zero column in C++)
CPP_COLS = np.array([i for i, n in enumerate(NAMES[:N_DYN]) if n in IN_CPP])


def random_params(rng: np.random.Generator, tau: float) -> np.ndarray:
    """Dynamics parameters with every effect evaluated in C++ away from its null value."""
    values = {}
    for s in PARAMS[:N_DYN]:
        if s.name == "thrust_lag.tau":
            values[s.name] = tau
        elif s.name not in IN_CPP:
            continue
        elif s.name in RANGES:
            values[s.name] = rng.uniform(*RANGES[s.name])
        else:
            step = (s.typical if s.typical not in (None, s.null) else s.null + s.scale) - s.null
            values[s.name] = s.null + step * rng.uniform(0.5, 1.5)
    p = vector(values)[:N_DYN]
    for s, v in zip(PARAMS[:N_DYN], p):
        if s.name in IN_CPP and (s.name != "thrust_lag.tau" or tau > 0):
            assert v != s.null, s.name
    return p


def random_geometry(rng: np.random.Generator, n_thr: int, planar: bool) -> ref.Geometry:
    dirs = rng.normal(size=(n_thr, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    side = np.where(np.arange(n_thr) % 2 == 0, -1.0, 1.0)  # port and starboard both present
    if n_thr > 2:
        side[-1] = 0.0                                      # and one on the centre line
    return ref.Geometry(dirs=dirs, side=side, planar=planar)


def random_steps(rng: np.random.Generator, n_thr: int, n: int = 40, n_warm: int = 8,
                 t_start: float = 30.0) -> ref.Steps:
    """Steps of uneven length (one of zero length), commands of both signs, warm-up first."""
    h = rng.uniform(0.005, 0.03, size=n)
    warm = np.zeros(n, bool)
    warm[:n_warm] = True
    R = quat_to_rot(rng.normal(size=(n, 4))).reshape(n, 9)
    dem = rng.normal(scale=0.8, size=(n, n_thr))
    if n >= n_warm + 25:
        h[n_warm + 5] = 0.0
        h[n_warm + 10:n_warm + 20] = 0.02                # a run of equal steps
        dem[n_warm + 20:n_warm + 25] = dem[n_warm + 20]  # held commands
    tm = t_start + np.cumsum(h) - h
    return ref.Steps(h=h, warm=warm, R=R, dem=dem, tm=tm)


def random_x0(rng: np.random.Generator) -> np.ndarray:
    return np.concatenate([rng.normal(scale=20.0, size=3), rng.normal(scale=1.0, size=3)])


def cpp_propagate(x0, p, s: ref.Steps, g: ref.Geometry):
    return K.propagate(x0, p, s.h, s.warm.astype(np.uint8), s.R, s.dem, s.tm, g.dirs, g.side,
                       g.planar)


CASES = [(planar, n_thr, tau) for planar in (True, False) for n_thr in (2, 5)
         for tau in (0.0, 0.35)]
CASE_IDS = [f"{'planar' if c[0] else '3d'}-{c[1]}thr-tau{c[2]}" for c in CASES]


def make_case(planar: bool, n_thr: int, tau: float, seed: int):
    rng = np.random.default_rng(seed)
    return (random_x0(rng), random_params(rng, tau), random_steps(rng, n_thr),
            random_geometry(rng, n_thr, planar))


def assert_close(a, b, what: str):
    """Equal to 1e-9 times the array's magnitude (at least 1)."""
    a, b = np.asarray(a), np.asarray(b)
    tol = 1e-9 * max(1.0, float(np.abs(b).max(initial=0.0)))
    err = float(np.abs(a - b).max(initial=0.0))
    assert err <= tol, f"{what}: max |diff| {err:.3e} > {tol:.1e}"


# ---------------------------------------------------------------- layout
def test_parameter_layout_matches_params_table():
    assert K.N_DYN == N_DYN
    assert K.PARAM_INDEX == {name: i for i, name in enumerate(NAMES[:N_DYN])}


# ---------------------------------------------------------------- C++ == reference
@pytest.mark.parametrize("planar", [True, False])
@pytest.mark.parametrize("n_thr", [2, 5])
def test_accel_matches_reference(planar, n_thr):
    rng = np.random.default_rng(10 + n_thr + 100 * planar)
    g = random_geometry(rng, n_thr, planar)
    for _ in range(20):
        p = random_params(rng, rng.uniform(0.0, 1.0))
        v = rng.normal(size=3)
        R = quat_to_rot(rng.normal(size=(1, 4)))[0]
        d, dd = rng.normal(size=n_thr), rng.normal(size=n_thr)
        tm = rng.uniform(0.0, 500.0)
        a_r, A_r, J_r = ref.accel(v, R, d, dd, tm, p, g)
        for R_arg in (R.reshape(9), R):
            a_c, A_c, J_c = K.accel(v, R_arg, d, dd, tm, p, g.dirs, g.side, planar)
            assert_close(a_c, a_r, "a")
            assert_close(A_c, A_r, "A")
            assert_close(J_c[:, CPP_COLS], J_r[:, CPP_COLS], "Jp")
        if planar:
            assert a_c[2] == 0.0 and not A_c[2].any() and not J_c[2].any()


@pytest.mark.parametrize("planar,n_thr,tau", CASES, ids=CASE_IDS)
def test_propagate_matches_reference(planar, n_thr, tau):
    x0, p, s, g = make_case(planar, n_thr, tau, seed=1 + n_thr + 10 * planar)
    r = ref.propagate(x0, p, s, g)
    c = cpp_propagate(x0, p, s, g)
    for name, a, b in zip(("x1", "Jx", "Jp"), c, r):
        assert a.shape == b.shape, name
        assert_close(a[..., CPP_COLS] if name == "Jp" else a,
                     b[..., CPP_COLS] if name == "Jp" else b, name)
    # the state really moved and every parameter column is alive
    assert np.abs(c[0] - x0).max() > 0.1
    alive = (np.abs(c[2]).max(axis=0) > 0) | ~np.isin(NAMES[:N_DYN], list(IN_CPP))
    assert alive.all(), [NAMES[i] for i in np.flatnonzero(~alive)]


def test_propagate_no_steps_is_identity():
    x0, p, s, g = make_case(False, 2, 0.3, seed=3)
    e = s.slice(0, 0)
    x1, Jx, Jp = cpp_propagate(x0, p, e, g)
    np.testing.assert_array_equal(x1, x0)
    np.testing.assert_array_equal(Jx, np.eye(6))
    np.testing.assert_array_equal(Jp, np.zeros((6, N_DYN)))


# ---------------------------------------------------------------- vs finite differences
def fd_jacobians(f, x0, p, s, g, tau_one_sided: bool):
    """Central differences of x1 = f(x0, p) w.r.t. x0 and p (one-sided 2nd order for tau=0)."""
    Jx = np.zeros((6, 6))
    for i in range(6):
        e = np.zeros(6); e[i] = 1e-5 * max(1.0, abs(x0[i]))
        Jx[:, i] = (f(x0 + e, p, s, g)[0] - f(x0 - e, p, s, g)[0]) / (2 * e[i])
    Jp = np.zeros((6, N_DYN))
    for i in range(N_DYN):
        e = np.zeros(N_DYN); e[i] = 1e-5 * PARAMS[i].scale
        if i == I_TAU and tau_one_sided:
            # one-sided: a 10x smaller step (|u| of a demand near zero curves sharply,
            # abs_command, and the one-sided formula's error is of the step squared)
            e[i] *= 0.1
            f0, f1, f2 = (f(x0, p + k * e, s, g)[0] for k in (0, 1, 2))
            Jp[:, i] = (-3 * f0 + 4 * f1 - f2) / (2 * e[i])
        else:
            Jp[:, i] = (f(x0, p + e, s, g)[0] - f(x0, p - e, s, g)[0]) / (2 * e[i])
    return Jx, Jp


def assert_jac_close(J, J_fd, what):
    scale = np.maximum(np.abs(J_fd).max(axis=0), 1e-3)   # per column
    rel = np.abs(J - J_fd) / scale
    worst = np.unravel_index(np.argmax(rel), rel.shape)
    assert rel.max() <= 1e-6, f"{what}: relative error {rel.max():.2e} at {worst}"


@pytest.mark.parametrize("planar,n_thr,tau", CASES, ids=CASE_IDS)
def test_jacobians_match_finite_differences(planar, n_thr, tau):
    x0, p, s, g = make_case(planar, n_thr, tau, seed=50 + n_thr + 10 * planar)
    for name, f in (("C++", cpp_propagate), ("numpy", ref.propagate)):
        _, Jx, Jp = f(x0, p, s, g)
        Jx_fd, Jp_fd = fd_jacobians(f, x0, p, s, g, tau_one_sided=tau == 0.0)
        assert_jac_close(Jx, Jx_fd, f"{name} Jx")
        assert_jac_close(Jp, Jp_fd, f"{name} Jp")


# ---------------------------------------------------------------- many segments, rollout
def segments(rng, n_thr, planar, K_seg=4):
    """K segments, each with its own warm-up steps, concatenated as build_steps does."""
    parts = [random_steps(rng, n_thr, n=int(rng.integers(31, 45)), n_warm=6,
                          t_start=10.0 * k) for k in range(K_seg)]
    parts.insert(2, random_steps(rng, n_thr, n=0, n_warm=0))   # an empty segment
    cat = lambda a: np.concatenate(a)
    s = ref.Steps(cat([q.h for q in parts]), cat([q.warm for q in parts]),
                  cat([q.R for q in parts]).reshape(-1, 9),
                  cat([q.dem for q in parts]).reshape(-1, n_thr), cat([q.tm for q in parts]))
    offsets = np.concatenate([[0], np.cumsum([len(q.h) for q in parts])]).astype(np.int64)
    X0 = np.stack([random_x0(rng) for _ in parts])
    return X0, s, offsets


@pytest.mark.parametrize("planar", [True, False])
def test_propagate_many_equals_repeated_propagate(planar):
    rng = np.random.default_rng(7 + planar)
    g = random_geometry(rng, 3, planar)
    p = random_params(rng, 0.25)
    X0, s, off = segments(rng, 3, planar)
    X1, JX, JP = K.propagate_many(X0, p, s.h, s.warm.astype(np.uint8), s.R, s.dem, s.tm, off,
                                  g.dirs, g.side, planar)
    assert X1.shape == (len(X0), 6) and JX.shape == (len(X0), 6, 6)
    assert JP.shape == (len(X0), 6, N_DYN)
    for k in range(len(X0)):
        x1, Jx, Jp = cpp_propagate(X0[k], p, s.slice(off[k], off[k + 1]), g)
        # same code, but the compiler may contract differently: equal to rounding
        for a, b in ((X1[k], x1), (JX[k], Jx), (JP[k], Jp)):
            np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-13 * np.abs(b).max())
    R1, RX, RP = ref.propagate_many(X0, p, s, off, g)
    assert_close(X1, R1, "X1")
    assert_close(JX, RX, "JX")
    assert_close(JP[..., CPP_COLS], RP[..., CPP_COLS], "JP")


@pytest.mark.parametrize("planar,tau", [(True, 0.0), (False, 0.4)])
def test_rollout_rows_are_propagated_states(planar, tau):
    x0, p, s, g = make_case(planar, 2, tau, seed=21)
    X = K.rollout(x0, p, s.h, s.warm.astype(np.uint8), s.R, s.dem, s.tm, g.dirs, g.side,
                  planar)
    assert X.shape == (len(s.h), 6)
    n_warm = int(s.warm.sum())
    np.testing.assert_array_equal(X[:n_warm], np.tile(x0, (n_warm, 1)))  # warm-up: state held
    # equal to rounding: the two may contract multiply-adds differently (target_clones)
    assert_close(X[-1], cpp_propagate(x0, p, s, g)[0], "last row")
    for j in (n_warm, n_warm + 5, n_warm + 17):                        # 5: zero-length step
        assert_close(X[j], ref.propagate(x0, p, s.slice(0, j + 1), g)[0], f"row {j}")
    np.testing.assert_array_equal(X[n_warm + 5], X[n_warm + 4])


# ---------------------------------------------------------------- bad input
def _good_args():
    x0, p, s, g = make_case(False, 2, 0.2, seed=5)
    return dict(x0=x0, p=p, h=s.h, warm=s.warm.astype(np.uint8), R=s.R, dem=s.dem, tm=s.tm,
                dirs=g.dirs, side=g.side, planar=False)


BAD = {
    "x0": lambda a: a["x0"][:5],
    "p": lambda a: np.concatenate([a["p"], [0.0]]),
    "h": lambda a: a["h"].reshape(-1, 1),
    "warm": lambda a: a["warm"][:-1],
    "R": lambda a: a["R"][:, :8],
    "dem": lambda a: a["dem"][:-1],
    "tm": lambda a: a["tm"][1:],
    "dirs": lambda a: a["dirs"][:, :2],
    "side": lambda a: a["side"][:1],
}


@pytest.mark.parametrize("arg", list(BAD))
def test_bad_shape_raises_value_error_naming_argument(arg):
    args = _good_args()
    args[arg] = BAD[arg](args)
    with pytest.raises(ValueError, match=f"'{arg}'"):
        K.propagate(**args)
    if arg != "x0":
        with pytest.raises(ValueError, match=f"'{arg}'"):
            K.rollout(**args)


def test_propagate_many_bad_offsets_and_X0():
    a = _good_args()
    n = len(a["h"])
    base = dict(p=a["p"], h=a["h"], warm=a["warm"], R=a["R"], dem=a["dem"], tm=a["tm"],
                dirs=a["dirs"], side=a["side"], planar=False)
    X0 = np.zeros((2, 6))
    with pytest.raises(ValueError, match="'offsets'"):
        K.propagate_many(X0, offsets=np.array([0, n], np.int64), **base)       # K + 1 != 3
    with pytest.raises(ValueError, match="'offsets'"):
        K.propagate_many(X0, offsets=np.array([0, 10, n + 1], np.int64), **base)
    with pytest.raises(ValueError, match="'offsets'"):
        K.propagate_many(X0, offsets=np.array([0, 10, 5], np.int64), **base)
    with pytest.raises(ValueError, match="'X0'"):
        K.propagate_many(np.zeros((2, 5)), offsets=np.array([0, 10, n], np.int64), **base)


def test_accel_bad_shapes():
    rng = np.random.default_rng(0)
    g = random_geometry(rng, 2, False)
    p = random_params(rng, 0.1)
    good = dict(v=np.zeros(3), R_raw=np.eye(3).reshape(9), d=np.ones(2), dd_tau=np.zeros(2),
                tm=0.0, p=p, dirs=g.dirs, side=g.side, planar=False)
    for arg, bad in (("v", np.zeros(2)), ("R_raw", np.zeros(8)), ("R_raw", np.zeros((9, 1))),
                     ("dd_tau", np.zeros(3)), ("dirs", np.zeros((3, 3))),
                     ("p", p[:-1])):
        with pytest.raises(ValueError, match=f"'{arg}'"):
            K.accel(**{**good, arg: bad})


def test_planar_accepts_numpy_bool_and_rejects_other_types():
    a = _good_args()
    x1 = K.propagate(**{**a, "planar": True})[0]
    np.testing.assert_array_equal(K.propagate(**{**a, "planar": np.bool_(True)})[0], x1)
    assert not np.array_equal(K.propagate(**a)[0], x1)
    with pytest.raises(TypeError, match="'planar'"):
        K.propagate(**{**a, "planar": "yes"})


def test_inputs_of_other_dtype_or_layout_are_converted():
    a = _good_args()
    x1, Jx, Jp = K.propagate(**a)
    b = {**a, "warm": a["warm"].astype(bool), "dem": np.asfortranarray(a["dem"]),
         "R": np.hstack([a["R"], np.zeros((len(a["h"]), 1))])[:, :9], "side": a["side"].astype(int)}
    for u, v in zip(K.propagate(**b), (x1, Jx, Jp)):
        np.testing.assert_array_equal(u, v)
