"""The diagnosis report shows the axes the vehicle has: a surface vehicle's report has no
depth or vertical-velocity panels (its model pins them), a submerged vehicle's keeps them."""
from __future__ import annotations

from types import SimpleNamespace

import pytest

import aqfg
from aqfg.diagnose.compare import sensor_series
from aqfg.diagnose.report import fig_sensors, for_vehicle


@pytest.fixture(scope="module")
def asv_fit():
    m, _ = aqfg.simulate("asv", seed=3, duration=150.0)
    return m, aqfg.fit(m)


def panel_labels(fig) -> list[str]:
    return [a.get_ylabel() for a in fig.axes if a.get_ylabel()]


def test_surface_vehicle_report_has_no_vertical_panels(asv_fit):
    m, r = asv_fit
    series = sensor_series(r.missions[0])
    assert any("vd" in s.labels for s in series)          # the fit reports them
    diag = SimpleNamespace(missions=[m], series={m.name: series})
    labels = panel_labels(fig_sensors(diag))
    assert labels and not any(w in lab for lab in labels for w in ("down", "vd", "depth"))
    assert any(lab.startswith("dynamics vn") for lab in labels)
    kept = for_vehicle(series, m)
    assert all(s.normalised.shape[1] == len(s.labels) for s in kept)
    assert sum(len(s.labels) for s in kept) == sum(len(s.labels) for s in series) - 2


def test_submerged_vehicle_keeps_every_axis(asv_fit):
    m, r = asv_fit
    series = sensor_series(r.missions[0])
    auv = SimpleNamespace(planar=False, name=m.name)
    assert for_vehicle(series, auv) == series
    labels = panel_labels(fig_sensors(SimpleNamespace(missions=[auv], series={m.name: series})))
    assert any("dynamics vd" in lab for lab in labels)
