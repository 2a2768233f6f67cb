"""The C++ mirror of the parameter table and the EKF codes is generated, and stays so.

``cpp_factors/layout.hpp`` is written by ``cpp_factors/gen_layout.py`` from the Python
tables; this fails when the committed header is out of date (a parameter, effect, node kind
or status changed without re-running the generator), and when the compiled kernel was built
from another layout.
"""
from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

from aqfg import _kernel as K
from aqfg.ekf import window
from aqfg.ekf.history import EkfConfig
from aqfg.model import params

ROOT = Path(__file__).resolve().parents[1]


def _generator():
    spec = importlib.util.spec_from_file_location("gen_layout", ROOT / "cpp_factors" / "gen_layout.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_committed_header_matches_the_python_tables():
    gen = _generator()
    committed = (ROOT / "cpp_factors" / "layout.hpp").read_text()
    assert committed == gen.render(), "run: python cpp_factors/gen_layout.py (then rebuild)"


def test_generated_header_names_every_parameter_and_code():
    text = _generator().render()
    for i, s in enumerate(params.PARAMS[:params.N_DYN]):
        assert f"P_{_generator().cpp_name(s.name)} = {i}," in text
    for j, i in enumerate(params.MEAS_INDEX):
        assert f"M_{_generator().cpp_name(params.NAMES[i])} = {j}," in text
    assert "IMU_ACC = 4," in text and f"REJECTED = {window.REJECTED}," in text


def test_compiled_kernel_uses_this_layout():
    assert K.N_DYN == params.N_DYN
    assert K.PARAM_INDEX == {n: i for i, n in enumerate(params.NAMES[:params.N_DYN])}
    assert K.MEAS_INDEX == {params.NAMES[i]: j for j, i in enumerate(params.MEAS_INDEX)}


def test_ekf_settings_are_a_named_struct():
    cfg = EkfConfig(cov_model="full", max_rejects=5)
    s = window.kernel_settings(cfg)
    assert isinstance(s, K.EkfSettings)
    assert (s.q_h, s.sigma_bearing, s.max_rejects, s.full_cov) == \
        (cfg.q_h, cfg.sigma_bearing, 5, True)
    assert np.isinf(s.gate_gnss)
