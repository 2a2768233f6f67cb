"""``aqfg simulate OUT_DIR``: simulate a mission (with optional hidden effects) and save it.

``--effect NAME[=VALUE]`` takes an effect name (``thrust_asymmetry=0.8`` sets its first
parameter; ``lever_arm=0.3,0.1,0`` sets its parameters in order; a bare name uses the
defaults of :data:`aqfg.sim.simulator.EFFECT_DEFAULTS`) or a full parameter name
(``lever_arm.x=0.4``). ``--param NAME=VALUE`` sets a true parameter (e.g. ``theta_e=0.5``).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from aqfg.commands.common import Progress, UsageError
from aqfg.data import io
from aqfg.outputs import OutputSet
from aqfg.sim.simulator import simulate

PROGRESS_MIN_DURATION = 120.0   # s of mission time above which progress is shown


def _effects(settings: list[tuple[str, str]]) -> dict:
    out: dict = {}
    for name, text in settings:
        if not name:
            raise UsageError(f"--effect needs NAME[=VALUE], got {name}={text!r}")
        if text == "":
            out[name] = None
        elif "," in text:
            out[name] = [_number(v, f"--effect {name}") for v in text.split(",")]
        else:
            out[name] = _number(text, f"--effect {name}")
    return out


def _params(settings: list[tuple[str, str]]) -> dict[str, float]:
    out = {}
    for name, text in settings:
        if not name or text == "":
            raise UsageError(f"--param needs NAME=VALUE, got {name!r}")
        out[name] = _number(text, f"--param {name}")
    return out


def _number(text: str, where: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise UsageError(f"{where}: {text!r} is not a number") from None


def _line(name: str, t: np.ndarray, detail: str = "") -> str:
    n = len(t)
    if n == 0:
        return f"  {name:<7} {0:>7} rows"
    rate = f"{(n - 1) / (t[-1] - t[0]):7.3g} Hz" if n > 1 and t[-1] > t[0] else "     n/a  "
    return f"  {name:<7} {n:>7} rows  {t[0]:8.2f} - {t[-1]:8.2f} s  {rate}" + \
        (f"  {detail}" if detail else "")


def _effects_text(tp: dict) -> str:
    parts = []
    for e in tp.get("effects", []):
        vals = ", ".join(f"{k.split('.', 1)[1]}={v:g}" for k, v in tp.items()
                         if k.startswith(e + "."))
        parts.append(f"{e} ({vals})")
    return ", ".join(parts) or "none"


def run(args: argparse.Namespace) -> int:
    effects = _effects(args.effect)
    params = _params(args.param)
    out = Path(args.out_dir)
    outs = OutputSet(out, io.MISSION_FILES, force=args.force)
    outs.check()
    from aqfg.commands.common import log
    from aqfg.data.preflight import estimate_simulation
    log.info("estimate: %s", estimate_simulation(args.duration))
    progress = Progress("simulate") if args.duration >= PROGRESS_MIN_DURATION else None
    try:                  # everything simulate() is given comes from the command line
        mission, truth = simulate(args.vehicle, seed=args.seed, duration=args.duration,
                                  params=params, effects=effects,
                                  gnss_period=args.gnss_period or None, usbl=args.usbl,
                                  progress=progress)
    except (KeyError, ValueError) as e:
        raise UsageError(e.args[0] if isinstance(e, KeyError) and e.args else e) from None
    with outs as stage:
        io.save_mission(mission, stage, truth)

    tp = truth.params
    print(f"simulated {mission.vehicle} mission '{mission.name}' ({args.duration:g} s, seed "
          f"{args.seed}) -> {out}")
    print(f"  truth: theta_e={tp['theta_e']:.4f} rad, current=({tp['s_x']:.3f}, {tp['s_y']:.3f}) "
          f"m/s, k={tp['k']:g}, k_x={tp['k_x']:g}, k_yz={tp['k_yz']:g}; hidden effects: {_effects_text(tp)}")
    print(_line("imu", mission.imu.t, "attitude + specific force + rates"))
    print(_line("motors", mission.motors.t, f"{mission.n_thrusters} thrusters, commands in "
                f"[{mission.motors.u.min():.2f}, {mission.motors.u.max():.2f}]"))
    if mission.gnss is not None:
        sig = mission.gnss.sigma
        print(_line("gnss", mission.gnss.t, f"sigma {sig[0]:g} m" if sig is not None else "sigma unknown"))
    if mission.usbl is not None:
        r = mission.usbl.range
        print(_line("usbl", mission.usbl.t,
                    f"range {r.min():.1f}-{r.max():.1f} m" if len(r) else ""))
    if mission.depth is not None:
        d = mission.depth.depth
        print(_line("depth", mission.depth.t, f"{d.min():.2f}-{d.max():.2f} m"))
    print(_line("truth", truth.t))
    return 0
