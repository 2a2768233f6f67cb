"""aqfg: motion-model parameter estimation and model diagnosis for small AUVs and ASVs.

Top level: ``aqfg.load_mission``, ``aqfg.fit``, ``aqfg.diagnose``, ``aqfg.simulate``,
``aqfg.Result`` (:mod:`aqfg.api`); the rest lives in the subpackages.
"""
# Run from a source checkout with the package installed (non-editable) elsewhere, as CI
# does, the compiled aqfg._kernel lives only in the installed copy: let the package span both.
__path__ = __import__("pkgutil").extend_path(__path__, __name__)
__version__ = "0.1.0"          # the one version source (pyproject.toml reads it)

import logging as _logging

_logging.getLogger(__name__).addHandler(_logging.NullHandler())   # a library: callers decide

# The names below load on first use (PEP 562), so that `import aqfg` (and the command line
# starting up) does not pull in numpy, GTSAM and the kernel before they are needed.
# aqfg.diagnose is the subpackage, callable as aqfg.api.diagnose (aqfg/diagnose/__init__.py).
_LAZY = {"load_mission": ("aqfg.data.io", "load_mission"),
         "save_mission": ("aqfg.data.io", "save_mission"),
         "fit": ("aqfg.api", "fit"), "simulate": ("aqfg.sim.simulator", "simulate"),
         "Result": ("aqfg.result", "Result"),
         "EFFECTS": ("aqfg.model.effects", "BUILTIN"), "Effect": ("aqfg.model.effects", "Effect"),
         "UserEffect": ("aqfg.model.effects", "UserEffect"),
         "Mission": ("aqfg.data.mission", "Mission"), "Truth": ("aqfg.data.mission", "Truth"),
         "Model": ("aqfg.model.vehicle", "Model")}

__all__ = ["EFFECTS", "Effect", "Mission", "Model", "Result", "Truth", "UserEffect", "__version__",
           "diagnose", "fit", "load_mission", "save_mission", "simulate"]


def __getattr__(name: str):
    import importlib
    if name in _LAZY:
        mod, attr = _LAZY[name]
        value = getattr(importlib.import_module(mod), attr)
        globals()[name] = value
        return value
    try:
        return importlib.import_module(f"{__name__}.{name}")
    except ModuleNotFoundError:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
