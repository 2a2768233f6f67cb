"""Factors of the aqfg factor graph: dynamics with parameter nodes, GNSS, USBL, depth, priors.

Variables (GTSAM keys, see :func:`state_key` and :func:`node_key`):

* state knots ``x`` (Vector6): ``[north, east, down, vn, ve, vd]`` (NED, m and m/s);
* parameter nodes (Vector of the *estimated* parameters of one group, see
  :class:`ParamLayout`): ``f`` = fixed group (``k, k_x, k_yz`` + fixed effect parameters;
  one per vehicle, shared by its missions), ``v`` = variable group (``theta_e, s_x, s_y`` +
  variable effect parameters; one per mission, or one per time segment when the variable
  parameters follow a random walk), ``s`` = sensor group (USBL scale/bias, lever arm; one
  per mission). Parameters that are not estimated are held at the layout's ``base`` values.

Residual conventions (GTSAM's ``error = h(x) - z``, whitened by the noise model):

* dynamics (paper Eqs. 7-10 integrated over every input sample between the knots by the
  shared kernel, :meth:`aqfg.model.vehicle.Model.propagate`): ``r = x1 - f(x0, p)``, covariance
  :meth:`ProcessNoise.cov`;
* GNSS: ``h_gnss(x) - z`` (north, east); depth: ``down + vd * dt - z``;
* USBL: ``[h_range - z_range, wrap(h_bearing - z_bearing)]`` with constant range and
  bearing sigmas (paper Fig. 5), so the position uncertainty across the line of sight grows
  with range; a robust loss (Huber or Cauchy) downweights acoustic outliers.

Each factor is a ``gtsam.CustomFactor`` whose callback computes the residual and every
Jacobian from the kernel (C++ when built). :func:`dynamics_factor` integrates in its own
callback (used by the fixed-lag smoother); :func:`cached_dynamics_factor` reads results of one
batched ``propagate_many`` call (used by the batch smoother); both assemble the residual and
Jacobians with the same :func:`dynamics_blocks`.
"""
from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field

import gtsam
import numpy as np

from aqfg.model.effects import SensorOffsetTerm
from aqfg.model.frames import HEADING_PARAMS
from aqfg.model.params import N_PARAMS
from aqfg.model.process import white_acceleration
from aqfg.model.reference import Steps, wrap_angle
from aqfg.model.vehicle import Model

GROUPS = ("fixed", "variable", "sensor")
GROUP_CHAR = {"fixed": "f", "variable": "v", "sensor": "s"}
_I6 = np.eye(6)
MISSION_STRIDE = 1 << 32    # state / node key index = mission * MISSION_STRIDE + i


def state_key(mission: int, i: int) -> int:
    """GTSAM key of state knot ``i`` of mission ``mission``."""
    return gtsam.symbol("x", mission * MISSION_STRIDE + i)


def node_key(group: str, mission: int = 0, segment: int = 0) -> int:
    """GTSAM key of a parameter node: fixed (per vehicle), variable (per mission and time
    segment) or sensor (per mission)."""
    if group == "fixed":
        return gtsam.symbol("f", 0)
    return gtsam.symbol(GROUP_CHAR[group], mission * MISSION_STRIDE + segment)


# ---------------------------------------------------------------- noise models
# flat indices of the 6x6 [pos, vel] covariance taking b[0,0], b[0,1], b[1,0], b[1,1] x I3
_BLOCK_INDEX = np.array([6 * (3 * r + k) + 3 * c + k for r in (0, 1) for c in (0, 1)
                         for k in range(3)])


@dataclass(frozen=True)
class ProcessNoise:
    """Process noise of a dynamics factor over ``dt`` seconds.

    White-noise acceleration of spectral density ``sigma_a**2`` ((m/s^2)^2/Hz) on each
    axis gives ``Q(dt) = sigma_a^2 [[dt^3/3, dt^2/2], [dt^2/2, dt]] (x) I3``, the exact
    covariance of the model error accumulated over the interval, so the result does not
    depend on the knot spacing. A model-error floor adds ``dt * pos_rate^2`` (m^2) to the
    positions and ``dt * vel_rate^2`` ((m/s)^2) to the velocities. The same model holds on
    the vertical axis; planar vehicles (ASV) are kept on the surface by
    :func:`surface_factor` instead (a tiny vertical noise made ISAM2's Cholesky fail:
    "indeterminate system" after ~260 knots).
    """
    sigma_a: float = 0.02
    pos_rate: float = 0.01
    vel_rate: float = 0.005

    def cov(self, dt: float, planar: bool = False) -> np.ndarray:
        """6x6 covariance of ``x1 - f(x0, p)`` (NED position then velocity)."""
        dt = float(dt)
        b = white_acceleration(self.sigma_a ** 2, dt)
        b[0, 0] += dt * self.pos_rate ** 2
        b[1, 1] += dt * self.vel_rate ** 2
        Q = np.zeros(36)
        Q[_BLOCK_INDEX] = np.repeat(b.ravel(), 3)   # each entry of b times I3
        return Q.reshape(6, 6)

    def scaled(self, factor: float) -> ProcessNoise:
        """The same noise with every variance times ``factor``."""
        r = float(np.sqrt(factor))
        return ProcessNoise(self.sigma_a * r, self.pos_rate * r, self.vel_rate * r)

    def noise_model(self, dt: float, planar: bool = False, scale: float = 1.0
                    ) -> gtsam.noiseModel.Base:
        """Gaussian noise model of :meth:`cov` times ``scale`` (a variance factor)."""
        return gtsam.noiseModel.Gaussian.Covariance(scale * self.cov(dt, planar))


@dataclass(frozen=True)
class SensorNoise:
    """Measurement noise and robust loss.

    ``gnss_sigma`` (m, per horizontal axis) is used when gnss.csv has no sigma column.
    USBL (paper Fig. 5): range sigma ``sqrt(usbl_range_sigma^2 + (usbl_range_rate*range)^2)``
    (nearly constant), bearing sigma constant, so the tangential position sigma is
    ``range * usbl_bearing_sigma``. ``robust`` is ``"huber"``, ``"cauchy"`` or ``"none"``
    with threshold ``robust_k`` in sigmas (``robust_k_gnss`` for GNSS: there the loss is
    for gross errors only; at 1.5 sigma it also down-weighted the systematic misfit of a
    model that is not the vehicle and moved the fit of an Otter mission to another basin),
    applied to the streams in ``robust_on``.
    """
    gnss_sigma: float = 1.0
    usbl_range_sigma: float = 0.15
    usbl_range_rate: float = 0.0005
    usbl_bearing_sigma: float = float(np.radians(1.5))
    depth_sigma: float = 0.05
    robust: str = "huber"
    robust_k: float = 1.5
    robust_on: tuple[str, ...] = ("gnss", "usbl")
    robust_k_gnss: float = 4.0

    def __post_init__(self):
        if self.robust not in ("huber", "cauchy", "none"):
            raise ValueError(f"robust loss must be 'huber', 'cauchy' or 'none', not {self.robust!r}")

    def usbl_sigmas(self, rng: float) -> np.ndarray:
        return np.array([np.hypot(self.usbl_range_sigma, self.usbl_range_rate * rng),
                         self.usbl_bearing_sigma])

    def wrap(self, base: gtsam.noiseModel.Base, stream: str) -> gtsam.noiseModel.Base:
        """``base`` wrapped in the robust loss when ``stream`` is in ``robust_on``."""
        if self.robust == "none" or stream not in self.robust_on:
            return base
        k = self.robust_k_gnss if stream == "gnss" else self.robust_k
        est = (gtsam.noiseModel.mEstimator.Huber.Create(k) if self.robust == "huber"
               else gtsam.noiseModel.mEstimator.Cauchy.Create(k))
        return gtsam.noiseModel.Robust.Create(est, base)


# ---------------------------------------------------------------- parameter layout
@dataclass(frozen=True)
class ParamLayout:
    """Which parameters are estimated, and in which node each one lives.

    ``base`` is the full parameter vector (:meth:`Model.nominal` layout) holding the values
    of the parameters that are not estimated, and the initial values of those that are.
    """
    model: Model
    base: np.ndarray
    names: dict = field(default_factory=dict)      # group -> tuple of estimated names
    idx: dict = field(default_factory=dict)        # group -> full-vector indices
    dyn_pos: dict = field(default_factory=dict)    # group -> J_p column (-1: not in dynamics)
    dyn_direct: dict = field(default_factory=dict)  # group -> all its parameters in J_p

    @classmethod
    def build(cls, model: Model, estimate: Iterable[str], init: Mapping[str, float] | None = None
              ) -> ParamLayout:
        estimate = tuple(dict.fromkeys(estimate))
        active = set(model.active_names)
        for n in estimate:
            if n not in active:
                hint = ""
                if "." in n:
                    hint = f" (switch the effect on: --effect {n.split('.')[0]})"
                raise ValueError(f"cannot estimate {n!r}: not a parameter of this model{hint}; "
                                 f"estimable: {', '.join(model.active_names)}")
        base = model.nominal(dict(init or {}))
        dyn_cols = list(model.dyn_columns())
        names, idx, dyn_pos = {}, {}, {}
        for g in GROUPS:
            ns = tuple(n for n in estimate if model.spec(n).group == g)
            if not ns:
                continue
            ii = np.array([model.index(n) for n in ns], dtype=int)
            names[g] = ns
            idx[g] = ii
            dyn_pos[g] = np.array([dyn_cols.index(i) if i in dyn_cols else -1 for i in ii])
        direct = {g: bool(np.all(v >= 0)) for g, v in dyn_pos.items()}
        return cls(model, base, names, idx, dyn_pos, direct)

    @property
    def groups(self) -> tuple[str, ...]:
        return tuple(g for g in GROUPS if g in self.names)

    @property
    def estimated(self) -> tuple[str, ...]:
        return tuple(n for g in self.groups for n in self.names[g])

    def dim(self, group: str) -> int:
        return len(self.names.get(group, ()))

    def initial(self, group: str) -> np.ndarray:
        return self.base[self.idx[group]].copy()

    def full(self, nodes: Mapping[str, np.ndarray], base: np.ndarray | None = None) -> np.ndarray:
        """Full parameter vector with the node values ``{group: vector}`` written in."""
        p = (self.base if base is None else base).copy()
        for g, v in nodes.items():
            p[self.idx[g]] = v
        return p

    def dyn_jacobian(self, Jp: np.ndarray, group: str) -> np.ndarray:
        """Columns of the kernel's ``J_p`` (rows x len(dyn_columns)) for a node's parameters."""
        pos = self.dyn_pos[group]
        if self.dyn_direct[group]:
            return Jp[:, pos]
        out = np.zeros((Jp.shape[0], len(pos)))
        ok = pos >= 0
        out[:, ok] = Jp[:, pos[ok]]
        return out

    def meas_jacobian(self, Jp: np.ndarray, group: str) -> np.ndarray:
        """Columns of a measurement Jacobian (rows x N_PARAMS) for a node's parameters."""
        ii = self.idx[group]
        out = np.zeros((Jp.shape[0], len(ii)))
        ok = ii < N_PARAMS
        out[:, ok] = Jp[:, ii[ok]]
        return out

    def dyn_groups(self) -> tuple[str, ...]:
        """Groups with at least one parameter that enters the dynamics."""
        return tuple(g for g in self.groups if np.any(self.dyn_pos[g] >= 0))

    def bounds(self, group: str) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper physical bounds of a node's parameters (copies)."""
        lo, hi = self._bounds(group)
        return lo.copy(), hi.copy()

    def _bounds(self, group: str) -> tuple[np.ndarray, np.ndarray]:
        # cached: the dynamics factor's callback projects on every call (docs/speed.md)
        cache = self.__dict__.setdefault("_bounds_cache", {})
        if group not in cache:
            specs = [self.model.spec(n) for n in self.names[group]]
            cache[group] = (np.array([s.lower for s in specs]), np.array([s.upper for s in specs]))
        return cache[group]

    def project(self, group: str, v: np.ndarray) -> np.ndarray:
        """Projection of a node value onto the physical bounds."""
        lo, hi = self._bounds(group)
        return np.clip(v, lo, hi)

    def meas_groups(self, stream: str) -> tuple[str, ...]:
        """Groups whose parameters enter measurement ``stream`` ("gnss", "usbl", "depth").

        The sensor position is ``pos + Rz(theta) R l`` (lever arm ``l``, a sensor-offset
        term), so heading enters a fix only with such a term on; a stream also reads the
        parameters of the effects whose terms enter it (``Effect.streams``).
        """
        if stream == "depth":
            return ()
        out = []
        terms = [e for e in self.model.effects if stream in e.streams]
        offset = any(isinstance(e, SensorOffsetTerm) for e in terms)
        if offset and "variable" in self.names and any(
                n in HEADING_PARAMS for n in self.names["variable"]):
            out.append("variable")
        if "sensor" in self.names:
            rel = {n for e in terms for n in e.params}
            if any(n in rel for n in self.names["sensor"]):
                out.append("sensor")
        return tuple(out)


# ---------------------------------------------------------------- dynamics
def dynamics_blocks(x1: np.ndarray, pred: np.ndarray, Jx: np.ndarray, Jp: np.ndarray,
                    layout: ParamLayout, groups: tuple[str, ...]):
    """Residual ``x1 - f(x0, p)`` and Jacobians [d/dx0, d/dx1, d/dnode for each group]."""
    r = x1 - pred
    H = [-Jx, _I6] + [-layout.dyn_jacobian(Jp, g) for g in groups]
    return r, H


def _nodes(values: gtsam.Values, node_keys) -> dict:
    return {g: values.atVector(k) for g, k in node_keys}


def propagator(model: Model, steps: Steps) -> Callable:
    """``f(x0, p) -> (x1, J_x0, J_p)`` over ``steps``: :meth:`Model.propagate` with the
    kernel's arguments prepared once (their conversions would cost as much as the
    integration itself, see docs/architecture.md)."""
    if not model.uses_cpp:
        return lambda x0, p: model.propagate(x0, p, steps)
    from aqfg.model.params import N_DYN
    from aqfg.model.vehicle import compiled_kernel
    cpp = compiled_kernel()
    assert cpp is not None              # model.uses_cpp
    g = model.geometry
    args = (np.ascontiguousarray(steps.h, float), np.ascontiguousarray(steps.warm, np.uint8),
            np.ascontiguousarray(steps.R, float), np.ascontiguousarray(steps.dem, float),
            np.ascontiguousarray(steps.tm, float), np.ascontiguousarray(g.dirs, float),
            np.ascontiguousarray(g.side, float), bool(g.planar))
    kernel = cpp.propagate
    return lambda x0, p: kernel(x0, p[:N_DYN], *args)


def dynamics_factor(model: Model, layout: ParamLayout, steps: Steps, k0: int, k1: int,
                    node_keys: tuple, noise: gtsam.noiseModel.Base,
                    base: np.ndarray | None = None) -> gtsam.CustomFactor:
    """Dynamics factor between knots ``k0`` and ``k1`` integrating ``steps`` (all input samples
    between them) in its own callback. ``node_keys``: ``((group, key), ...)`` of the parameter
    nodes that enter the dynamics."""
    propagate = propagator(model, steps)
    p0 = (layout.base if base is None else base).copy()
    # per node: key, full-vector indices, bounds, J_p columns (all looked up once: the
    # callback runs at every relinearisation; docs/speed.md)
    nodes = []
    for g, k in node_keys:
        lo, hi = layout._bounds(g)
        pos = layout.dyn_pos[g]
        nodes.append((k, layout.idx[g], lo, hi, pos, bool(layout.dyn_direct[g]), pos >= 0))
    eye6 = _I6

    def err(this, values, H):
        x0 = values.atVector(k0)
        x1 = values.atVector(k1)
        # the model is evaluated inside the physical bounds (an incremental solver's step
        # can overshoot them before the bound factor pulls it back; a negative drag would
        # make the integration diverge); the Jacobian is the one at the bound
        p = p0.copy()
        for k, idx, lo, hi, _, _, _ in nodes:
            p[idx] = np.minimum(np.maximum(values.atVector(k), lo), hi)
        pred, Jx, Jp = propagate(x0, p)
        if H is not None:
            H[0] = -Jx
            H[1] = eye6
            for j, (_, _, _, _, pos, direct, ok) in enumerate(nodes):
                if direct:
                    H[2 + j] = -Jp[:, pos]
                else:
                    b = np.zeros((Jp.shape[0], len(pos)))
                    b[:, ok] = -Jp[:, pos[ok]]
                    H[2 + j] = b
        return x1 - pred

    return gtsam.CustomFactor(noise, [k0, k1] + [k for _, k in node_keys], err)


@dataclass
class DynamicsCache:
    """Kernel results for many dynamics factors, filled by one batched kernel call per
    (mission, parameter segment) before the graph is linearised (batch smoother)."""
    pred: np.ndarray      # (K, 6)
    Jx: np.ndarray        # (K, 6, 6)
    Jp: np.ndarray        # (K, 6, n_dyn_cols)


def cached_dynamics_factor(cache: DynamicsCache, i: int, layout: ParamLayout, k0: int, k1: int,
                           node_keys: tuple, noise: gtsam.noiseModel.Base) -> gtsam.CustomFactor:
    """The same factor as :func:`dynamics_factor`, reading ``f(x0, p)`` and its Jacobians from
    ``cache`` row ``i`` (which the caller fills at the values being evaluated)."""
    groups = tuple(g for g, _ in node_keys)

    def err(this, values, H):
        r, blocks = dynamics_blocks(values.atVector(k1), cache.pred[i], cache.Jx[i],
                                    cache.Jp[i], layout, groups)
        if H is not None:
            for j, b in enumerate(blocks):
                H[j] = b
        return r

    return gtsam.CustomFactor(noise, [k0, k1] + [k for _, k in node_keys], err)


# ---------------------------------------------------------------- measurements
def gnss_residual(model: Model, layout: ParamLayout, x: np.ndarray, nodes: dict, z: np.ndarray,
                  R_raw: np.ndarray, t: float, base: np.ndarray | None = None):
    """``h_gnss - z`` (2,), d/dx (2x6), d/dnode per group in ``nodes``."""
    p = layout.full(nodes, base)
    h, Hx, Jp = model.h_gnss(x, R_raw, t, p)      # the state: time offsets read its velocity
    return h - z, [Hx] + [layout.meas_jacobian(Jp, g) for g in nodes]


def usbl_residual(model: Model, layout: ParamLayout, x: np.ndarray, nodes: dict, z: np.ndarray,
                  R_raw: np.ndarray, t: float, station: np.ndarray, base: np.ndarray | None = None):
    """``[range - z_range, wrap(bearing - z_bearing)]`` (2,), d/dx (2x6), d/dnode per group."""
    p = layout.full(nodes, base)
    h, Hx, Jp = model.h_usbl(x, R_raw, t, p, station)
    r = h - z
    r[1] = float(wrap_angle(r[1]))
    return r, [Hx] + [layout.meas_jacobian(Jp, g) for g in nodes]


def _meas_factor(fn: Callable, kx: int, node_keys: tuple, noise) -> gtsam.CustomFactor:
    def err(this, values, H):
        r, blocks = fn(values.atVector(kx), _nodes(values, node_keys))
        if H is not None:
            for i, b in enumerate(blocks):
                H[i] = b
        return r
    return gtsam.CustomFactor(noise, [kx] + [k for _, k in node_keys], err)


def gnss_factor(model: Model, layout: ParamLayout, kx: int, node_keys: tuple, z: np.ndarray,
                R_raw: np.ndarray, t: float, noise, base: np.ndarray | None = None):
    """GNSS fix ``z`` (north, east) at knot ``kx`` (the fix time is a knot)."""
    z = np.asarray(z, float)
    return _meas_factor(lambda x, nd: gnss_residual(model, layout, x, nd, z, R_raw, t, base),
                        kx, node_keys, noise)


def usbl_factor(model: Model, layout: ParamLayout, kx: int, node_keys: tuple, z: np.ndarray,
                R_raw: np.ndarray, t: float, station: np.ndarray, noise,
                base: np.ndarray | None = None):
    """USBL range/bearing ``z`` at knot ``kx``, seen from ``station`` (NED)."""
    z = np.asarray(z, float)
    st = np.asarray(station, float)
    return _meas_factor(lambda x, nd: usbl_residual(model, layout, x, nd, z, R_raw, t, st, base),
                        kx, node_keys, noise)


def depth_residual(x: np.ndarray, z: float, dt: float):
    """``down + vd * dt - z`` for a depth reading ``dt`` s after the knot."""
    H = np.zeros((1, 6))
    H[0, 2] = 1.0
    H[0, 5] = dt
    return np.array([x[2] + x[5] * dt - z]), [H]


def depth_factor(kx: int, z: float, dt: float, noise) -> gtsam.CustomFactor:
    """Depth reading ``z`` (m, down) taken ``dt`` s after knot ``kx``."""
    return _meas_factor(lambda x, nd: depth_residual(x, z, dt), kx, (), noise)


@dataclass(frozen=True)
class LinearTerm:
    """A linear factor in numpy: whitened residual ``(sum_k J_k x_k - mean) / sigma`` over
    the variables ``keys`` (the sum formed before the whitening, as GTSAM's factors do: a
    random walk held by a sigma of 1e-8 needs the difference of the values).

    ``kind`` is its GTSAM form (:meth:`factor`): "prior" (``PriorFactorVector``, J = I),
    "between" (``BetweenFactorVector`` of ``x1 - x0``, J = (-I, I)) or "linear" (a
    ``LinearContainerFactor`` of one key's ``J``)."""
    kind: str
    keys: tuple[int, ...]
    J: tuple[np.ndarray, ...]
    mean: np.ndarray
    sigma: np.ndarray

    def factor(self) -> gtsam.NonlinearFactor:
        """The term as a factor of a GTSAM graph."""
        nm = gtsam.noiseModel.Diagonal.Sigmas(self.sigma)
        if self.kind == "prior":
            return gtsam.PriorFactorVector(self.keys[0], self.mean, nm)
        if self.kind == "between":
            return gtsam.BetweenFactorVector(self.keys[0], self.keys[1], self.mean, nm)
        jf = gtsam.JacobianFactor(self.keys[0], self.J[0], self.mean, nm)
        lp = gtsam.Values()
        lp.insert(self.keys[0], np.zeros(self.J[0].shape[1]))
        return gtsam.LinearContainerFactor(jf, lp)

    def whitened_jacobians(self) -> list[np.ndarray]:
        """``J_k / sigma`` (rows scaled by ``1 / sigma``, as GTSAM whitens)."""
        inv = 1.0 / self.sigma
        return [J * inv[:, None] for J in self.J]

    def whitened_residual(self, x: Mapping[int, np.ndarray]) -> np.ndarray:
        """The whitened residual at the variables' values ``x`` (by key)."""
        total = sum(J @ x[k] for k, J in zip(self.keys, self.J))
        return (total - self.mean) * (1.0 / self.sigma)


def prior_term(key: int, mean: np.ndarray, sigma: np.ndarray) -> LinearTerm:
    """``x ~ N(mean, diag(sigma^2))``."""
    mean = np.asarray(mean, float)
    return LinearTerm("prior", (key,), (np.eye(len(mean)),), mean, np.asarray(sigma, float))


_SURFACE_A = np.zeros((2, 6))
_SURFACE_A[0, 2] = _SURFACE_A[1, 5] = 1.0


def surface_term(kx: int, sigma_down: float = 0.01, sigma_vd: float = 0.01) -> LinearTerm:
    """A surface vehicle stays on the surface: ``down = 0``, ``vd = 0`` (m, m/s)."""
    return LinearTerm("linear", (kx,), (_SURFACE_A,), np.zeros(2),
                      np.array([sigma_down, sigma_vd]))


def surface_factor(kx: int, sigma_down: float = 0.01, sigma_vd: float = 0.01):
    """:func:`surface_term` as a factor. Linear, so it is a native ``LinearContainerFactor``
    (no Python callback)."""
    return surface_term(kx, sigma_down, sigma_vd).factor()


# ---------------------------------------------------------------- parameter priors and bounds
def param_prior_term(layout: ParamLayout, group: str, key: int, scale: float,
                     mean: np.ndarray | None = None, sigma: Mapping[str, float] | None = None
                     ) -> LinearTerm:
    """Weak prior on a node: mean = initial values, sigma = ``sigma[name]`` if given, else
    ``scale`` x ParamSpec.scale."""
    sigma = sigma or {}
    sig = np.array([sigma.get(n, scale * layout.model.spec(n).scale)
                    for n in layout.names[group]])
    return prior_term(key, layout.initial(group) if mean is None else mean, sig)


def param_prior(layout: ParamLayout, group: str, key: int, scale: float,
                mean: np.ndarray | None = None, sigma: Mapping[str, float] | None = None
                ) -> gtsam.PriorFactorVector:
    """:func:`param_prior_term` as a factor."""
    f = param_prior_term(layout, group, key, scale, mean, sigma).factor()
    assert isinstance(f, gtsam.PriorFactorVector)
    return f


def walk_term(layout: ParamLayout, k0: int, k1: int, sigma: np.ndarray, dt: float
              ) -> LinearTerm:
    """Random walk of the variable parameters between consecutive time segments:
    ``v1 - v0 ~ N(0, diag(sigma^2 dt))``, sigma in units per sqrt(s)."""
    sig = np.maximum(np.asarray(sigma, float) * np.sqrt(dt), 1e-12)
    eye = np.eye(len(sig))
    return LinearTerm("between", (k0, k1), (-eye, eye), np.zeros(len(sig)), sig)


def walk_factor(layout: ParamLayout, k0: int, k1: int, sigma: np.ndarray,
                dt: float) -> gtsam.BetweenFactorVector:
    """:func:`walk_term` as a factor."""
    f = walk_term(layout, k0, k1, sigma, dt).factor()
    assert isinstance(f, gtsam.BetweenFactorVector)
    return f


def bound_factor(layout: ParamLayout, group: str, key: int, softness: float = 1e-3
                 ) -> gtsam.CustomFactor:
    """Soft physical bounds for incremental solvers that cannot project: zero inside
    ``[lower, upper]``, ``(p - bound) / (softness * scale)`` outside (a steep hinge)."""
    lo, hi = layout.bounds(group)
    sc = np.array([softness * layout.model.spec(n).scale for n in layout.names[group]])

    def err(this, values, H):
        v = values.atVector(key)
        below, above = v < lo, v > hi
        r = np.where(below, (v - lo) / sc, np.where(above, (v - hi) / sc, 0.0))
        if H is not None:
            H[0] = np.diag(np.where(below | above, 1.0 / sc, 0.0))
        return r

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(len(lo)), [key], err)
