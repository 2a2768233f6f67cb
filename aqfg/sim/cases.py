"""Hidden-effect missions for validating the diagnosis (tests and experiments/diagnosis_sweep.py).

One case per catalogue effect: a simulated mission (:func:`aqfg.sim.simulator.simulate`) where the
effect is present in the truth but absent from the model. Sizes are physically plausible
for a small ASV like the paper's (0.6 m, 2.5 kg; paper Table II) or a 2-m ASV like the
Otter, and large enough to matter for dead reckoning with GNSS fixes every 8 s:

=================== ============================ ===============================================
effect              size                         why plausible / mission
=================== ============================ ===============================================
thrust_asymmetry    ratio 0.7                    a fouled or worn brushed motor (paper §IV: wear)
reverse_thrust      ratio 0.5                    propellers are 30-50 % weaker backwards (the
                                                 otter example's truth: 0.52, found by aqfg)
thrust_lag          tau 1.0 s                    motor + propeller spin-up of a 2-m ASV
linear_drag         c_x 1.0, c_yz 0.5 1/s        the Otter's surge damping is linear, ~1.4 1/s
heading_drift       5e-4 rad/s                   MEMS yaw drift without magnetometer, 17 deg/10 min
current_drift       2e-4, -1.5e-4 m/s^2          a tidal/wind-driven current changing 0.15 m/s
wind_drag           0.04, 0.03 m/s^2             ~5 m/s wind on the hull above water
usbl_range_scale    1.02                         2 % sound-speed error (~30 m/s, a few deg C)
usbl_bearing_bias   0.05 rad                     3 deg array mounting misalignment
lever_arm           x = -0.5 m                   antenna at the stern; RTK-grade GNSS (0.1 m)
=================== ============================ ===============================================

Missions: ASV, GNSS 1 Hz (1 m) unless noted; USBL effects fly GNSS and USBL together (a
USBL's scale and bias are only observable against an independent position: with USBL
alone they are nearly a scaling/rotation of the whole track about the station, which the
heading offset and the thrust and drag constants absorb); the lever arm needs fixes more
precise than the arm (0.1 m GNSS).
"""
from __future__ import annotations

from dataclasses import dataclass, field

CASE_DURATION = 600.0     # s


@dataclass(frozen=True)
class Case:
    effect: str                                   # the hidden effect (catalogue name)
    values: dict                                  # its true parameters (full names)
    sim: dict = field(default_factory=dict)       # extra aqfg.sim.simulator.simulate arguments
    note: str = ""


CASES: dict[str, Case] = {c.effect: c for c in (
    Case("thrust_asymmetry", {"thrust_asymmetry.ratio": 0.7}),
    Case("reverse_thrust", {"reverse_thrust.ratio": 0.5}),
    Case("thrust_lag", {"thrust_lag.tau": 1.0}),
    Case("linear_drag", {"linear_drag.c_x": 1.0, "linear_drag.c_yz": 0.5}),
    Case("heading_drift", {"heading_drift.rate": 5e-4}),
    Case("current_drift", {"current_drift.ds_x": 2e-4, "current_drift.ds_y": -1.5e-4}),
    Case("wind_drag", {"wind_drag.a_n": 0.04, "wind_drag.a_e": 0.03}),
    Case("usbl_range_scale", {"usbl_range_scale.scale": 1.02}, {"usbl": True},
         "GNSS and USBL"),
    Case("usbl_bearing_bias", {"usbl_bearing_bias.bias": 0.05}, {"usbl": True},
         "GNSS and USBL"),
    Case("lever_arm", {"lever_arm.x": -0.5}, {"gnss_sigma": 0.1}, "RTK-grade GNSS"),
)}


def simulate_case(effect: str | None, seed: int, duration: float = CASE_DURATION, **kw):
    """The mission and truth of a case (``effect`` None: no hidden effect)."""
    from aqfg.sim.simulator import simulate
    if effect is None:
        return simulate("asv", seed=seed, duration=duration, **kw)
    c = CASES[effect]
    args = dict(c.sim)
    args.update(kw)
    return simulate("asv", seed=seed, duration=duration, effects=dict(c.values), **args)
