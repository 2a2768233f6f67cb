"""Array operations of the numpy batch system (:mod:`aqfg.fg.fastlm`): its measurement
blocks, the kernel's propagator per parameter segment, banded triangular solves, scattered
sums and the sandwich covariance of its parameters (:meth:`FastSystem.sandwich`)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.linalg as sla

from aqfg.model.measurements import USBL_TERMS, sensor_position
from aqfg.model.params import N_DYN
from aqfg.model.vehicle import compiled_kernel
from aqfg.threads import both

if TYPE_CHECKING:                       # the system is built on these operations
    from aqfg.fg.fastlm import FastSystem


@dataclass
class Meas:
    """Measurement factors on one knot each, of one kind."""
    kind: str             # "gnss", "usbl", "depth"
    idx: np.ndarray       # (n,) global state index
    z: np.ndarray         # (n, m)
    sigma: np.ndarray     # (n, m)
    k: float | None       # Huber threshold (None: plain Gaussian)
    extra: np.ndarray | None = None   # depth: dt after the knot; usbl: station (3,)
    # fixes through the sensor model (:mod:`aqfg.fg.fastlm_meas`); None: the knot itself
    tm: np.ndarray | None = None      # (n,) s since the mission start
    R: np.ndarray | None = None       # (n, 3, 3) raw attitude (body -> ground)
    nodes: tuple | None = None        # ((group, node key), ...) the factors read
    cols: np.ndarray | None = None    # (c,) their columns in the system's parameters
    pidx: np.ndarray | None = None    # (c,) their indices in the full parameter vector


def plain_sensors(p: np.ndarray, offsets: bool = True) -> bool:
    """True when the measurement effects at ``p`` are null (no lever arm, no USBL
    distortion; ``offsets`` False: the USBL distortions alone), so a fix measures the
    knot position itself."""
    if offsets and np.any(sensor_position(np.zeros(3), np.eye(3), 0.0, p)[0] != 0.0):
        return False
    z = np.array([10.0, 0.3])
    return all(np.array_equal(e.distort(z, p[sl]), z) for e, sl in USBL_TERMS)


def scatter_add(out: np.ndarray, idx: np.ndarray, v: np.ndarray) -> None:
    """``out[idx] += v`` with repeated indices summed (``np.add.at``, which is slow, only
    when ``idx`` repeats)."""
    if len(idx) < 2 or np.all(np.diff(idx) > 0):
        out[idx] += v
    else:
        np.add.at(out, idx, v)


def tri(cb: np.ndarray, B: np.ndarray, trans: bool = False) -> np.ndarray:
    """``L^-1 B`` (or ``L^-T B``) for the lower banded Cholesky factor ``cb``."""
    x, info = sla.lapack.dtbtrs(cb, B, uplo="L", trans="T" if trans else "N")
    if info != 0:
        raise np.linalg.LinAlgError(f"banded triangular solve failed (info {info})")
    return x


SPLIT_MIN = 200      # intervals from which a parameter segment's kernel call is split in two


def propagator(model, sl):
    """``f(X0, p) -> (X1, J_x0, J_p)`` of one parameter segment's intervals, with the
    kernel's step arguments converted once (:meth:`Model.propagate_many`)."""
    a, b, steps, offs = sl
    if not model.uses_cpp:
        return lambda X0, p: model.propagate_many(X0, p, steps, offs)
    cpp = compiled_kernel()
    assert cpp is not None                      # model.uses_cpp
    g = model.geometry
    args = (np.ascontiguousarray(steps.h, float), np.ascontiguousarray(steps.warm, np.uint8),
            np.ascontiguousarray(steps.R, float), np.ascontiguousarray(steps.dem, float),
            np.ascontiguousarray(steps.tm, float), np.ascontiguousarray(offs, np.int64),
            np.ascontiguousarray(g.dirs, float), np.ascontiguousarray(g.side, float),
            bool(g.planar))
    kernel = cpp.propagate_many
    K = len(offs) - 1
    if K < SPLIT_MIN:
        return lambda X0, p: kernel(np.ascontiguousarray(X0, float),
                                    np.ascontiguousarray(p[:N_DYN], float), *args)
    # the intervals in two halves, each one kernel call, in two threads (aqfg.threads.both;
    # the intervals are independent: the same numbers as one call)
    offs = np.asarray(offs, np.int64)
    mid, o = K // 2, int(offs[K // 2])
    halves = [tuple(np.ascontiguousarray(a[i]) for a in args[:5])
              + (np.ascontiguousarray(offs[j] - offs[j][0], np.int64),) + args[6:]
              for i, j in ((slice(0, o), slice(0, mid + 1)), (slice(o, None), slice(mid, None)))]

    def run(X0, p):
        X0 = np.ascontiguousarray(X0, float)
        q = np.ascontiguousarray(p[:N_DYN], float)
        a, b = both(lambda: kernel(X0[:mid], q, *halves[0]),
                    lambda: kernel(X0[mid:], q, *halves[1]))
        return tuple(np.concatenate([x, y]) for x, y in zip(a, b))
    return run


def sandwich(fs: FastSystem, ev: dict, fac, key_time: dict, block: float):
    """:func:`aqfg.fg.covariance.block_sandwich` from the system ``fs``: per-block score
    ``g_b`` (factors assigned to the block of their latest knot, parameter-only factors
    left out; a fix's parameter columns, a lever arm or a time offset, in its knot's
    block), ``Z = H^-1 G``. Returns ({node key: cov}, dof) or None."""
    t_state = np.empty(fs.N)
    for p, o in zip(fs.bg.parts, fs.part_off):
        t_state[o:o + len(p.keys)] = [key_time[k] for k in p.keys]
    t0 = float(t_state.min())
    blk_state = ((t_state - t0) // block).astype(np.int64)
    fs._dyn_jacobians(ev)
    d0 = fs.d0
    rows_s, rows_b, vals_s = [], [], []     # state gradient contributions
    pg_b, pg_v = [], []                     # parameter gradient contributions
    A0, Ap, rd, W = ev["A0"], ev["Ap"], ev["dyn_r"], fs.W
    bd = blk_state[d0 + 1]
    rows_s += [d0, d0 + 1]
    rows_b += [bd, bd]
    vals_s += [np.einsum("kji,kj->ki", A0, rd), np.einsum("kji,kj->ki", W, rd)]
    pg_b.append(bd)
    pg_v.append(np.einsum("kji,kj->ki", Ap, rd))
    for m, (r, J, w, Jp) in zip(fs.meas, ev["meas"]):
        rows_s.append(m.idx)
        rows_b.append(blk_state[m.idx])
        vals_s.append(w[:, None] * np.einsum("nji,nj->ni", J, r))
        if Jp is not None and m.cols is not None and len(m.cols):
            v = np.zeros((len(r), fs.P))
            v[:, m.cols] = w[:, None] * np.einsum("nki,nk->ni", Jp, r)
            pg_b.append(blk_state[m.idx])
            pg_v.append(v)
    for mm, (si, A, _) in fs.lin_s.items():
        rows_s.append(si)
        rows_b.append(blk_state[si])
        vals_s.append(np.einsum("nji,nj->ni", A, ev["lin_s"][mm]))
    allb = np.concatenate(rows_b)
    ids = np.unique(allb)
    nb = len(ids)
    n_p = fs.P
    if nb < n_p + 2:
        return None
    loc = {int(b): i for i, b in enumerate(ids)}
    lut = np.zeros(int(ids.max()) + 1, np.int64)
    for b, i in loc.items():
        lut[b] = i
    Gs = np.zeros((fs.N, 6, nb))
    for ri, rb, v in zip(rows_s, rows_b, vals_s):
        np.add.at(Gs, (ri[:, None], np.arange(6), lut[rb][:, None]), v)
    Gp = np.zeros((fs.P, nb))
    for rb, v in zip(pg_b, pg_v):
        np.add.at(Gp, (np.arange(fs.P)[:, None], lut[rb]), v.T)
    cb, Hsp2, _, S = fac
    Gs2 = Gs.reshape(6 * fs.N, nb)
    ys = sla.cho_solve_banded((cb, True), Gs2, check_finite=False)
    Zp = np.linalg.solve(S, Gp - Hsp2.T @ ys)
    scale = nb / max(nb - n_p, 1)
    out = {}
    for k, (o, d) in fs.node_off.items():
        zk = Zp[o:o + d]
        zk = zk - zk.mean(axis=1, keepdims=True)
        out[k] = scale * zk @ zk.T
    return out, nb - n_p
