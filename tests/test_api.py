"""The top-level API: ``import aqfg; m = aqfg.load_mission(p); r = aqfg.fit(m);
d = aqfg.diagnose(m)``, and ``import aqfg`` staying cheap."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

import aqfg


def test_import_aqfg_loads_no_numerics():
    code = ("import sys, aqfg; heavy = [m for m in ('numpy', 'scipy', 'gtsam', 'aqfg._kernel') "
            "if m in sys.modules]; print(','.join(heavy))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def test_the_command_lines_parser_loads_no_numerics():
    # `aqfg --version` (the start-up of every command) builds the whole parser
    code = ("import sys; from aqfg.cli import build_parser; build_parser(); heavy = [m for m in "
            "('numpy', 'scipy', 'gtsam', 'aqfg._kernel') if m in sys.modules]; "
            "print(','.join(heavy))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


@pytest.fixture(scope="module")
def mission_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("api") / "run"
    m, tr = aqfg.simulate("asv", seed=5, duration=150.0)
    aqfg.save_mission(m, d, truth=tr)
    return d


def test_fit_by_either_method_from_a_mission_or_its_path(mission_dir):
    m = aqfg.load_mission(mission_dir)
    assert isinstance(m, aqfg.Mission)
    fg = aqfg.fit(m)
    assert isinstance(fg, aqfg.Result) and (fg.method, fg.mode) == ("fg", "batch")
    assert set(fg.estimated) >= {"theta_e", "s_x", "s_y", "k", "k_x", "k_yz"}
    ue = aqfg.fit(str(mission_dir), method="update-error")
    assert (ue.method, ue.mode) == ("update-error", "batch")
    assert np.isfinite(ue.values["theta_e"])
    online = aqfg.fit(m, mode="online", init=fg.vehicle_constants(), effects=fg.effects)
    assert online.mode == "online" and set(online.estimated) == {"theta_e", "s_x", "s_y"}
    with pytest.raises(ValueError, match="method must be one of"):
        aqfg.fit(m, method="ekf")


def test_diagnose_is_callable_before_and_after_its_subpackage_loads(mission_dir, monkeypatch):
    import aqfg.diagnose.workflow as wf
    seen = []
    monkeypatch.setattr(wf, "diagnose", lambda missions, **kw: seen.append((missions, kw)) or "d")
    assert aqfg.diagnose is sys.modules["aqfg.diagnose"]     # one object, and callable
    assert aqfg.diagnose(mission_dir, gnss_every=4.0) == "d"
    (missions, kw), = seen
    assert [m.name for m in missions] == [aqfg.load_mission(mission_dir).name]
    assert kw == {"gnss_every": 4.0}
    assert aqfg.diagnose.diagnose_sequence          # the rest of the subpackage is there


def test_every_listed_name_resolves():
    for name in aqfg.__all__:
        assert getattr(aqfg, name) is not None
    with pytest.raises(AttributeError):
        aqfg.no_such_name  # noqa: B018
