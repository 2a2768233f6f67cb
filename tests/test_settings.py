"""FGSettings: groups by concern, one way to change a setting, and the grouped record that
parameters.json's provenance keeps."""
from dataclasses import fields

import pytest

from aqfg.fg import BatchSettings, FGSettings, GraphSettings, OnlineSettings, SolverSettings
from aqfg.outputs import jsonable

GROUPS = {"graph": GraphSettings, "solver": SolverSettings, "batch": BatchSettings,
          "online": OnlineSettings}


def test_with_changes_only_the_named_settings():
    base = FGSettings()
    s = base.with_(online={"init_after": 30.0}, batch={"auto_effect": False})
    assert s.online.init_after == 30.0 and s.batch.auto_effect is False
    assert s.online == OnlineSettings(init_after=30.0)           # the group's others kept
    assert s.batch == BatchSettings(auto_effect=False)
    assert (s.graph, s.solver) == (base.graph, base.solver)
    assert base == FGSettings()                                  # the original unchanged


def test_with_rejects_an_unknown_group_or_setting():
    with pytest.raises(TypeError, match="no group 'onilne'"):
        FGSettings().with_(onilne={"init_after": 30.0})
    with pytest.raises(TypeError, match="init_afterr"):
        FGSettings().with_(online={"init_afterr": 30.0})


def test_the_record_is_grouped_as_the_settings_are():
    doc = jsonable(FGSettings().with_(graph={"knot_spacing": 0.5}))
    assert set(doc) == set(GROUPS)
    for name, cls in GROUPS.items():
        assert list(doc[name]) == [f.name for f in fields(cls)], name
    assert doc["graph"]["knot_spacing"] == 0.5
