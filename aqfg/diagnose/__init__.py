"""Diagnosis: compare the model with the measurements, find where it fails, and rank the
candidate effects that would explain it; the loop that adds them one at a time.

The names below load on first use (PEP 562): importing one of the subpackage's modules
does not import the whole diagnosis."""
import importlib
import sys
import types

_LAZY = {"Diagnosis": "aqfg.diagnose.workflow", "diagnose": "aqfg.diagnose.workflow",
         "save_diagnosis": "aqfg.diagnose.workflow",
         "DiagnosisSequence": "aqfg.diagnose.sequence",
         "diagnose_sequence": "aqfg.diagnose.sequence", "save_sequence": "aqfg.diagnose.sequence"}

__all__ = ["Diagnosis", "DiagnosisSequence", "diagnose", "diagnose_sequence", "save_diagnosis",
           "save_sequence"]


def __getattr__(name: str):
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


class _CallablePackage(types.ModuleType):
    """``aqfg.diagnose(missions, ...)`` is :func:`aqfg.api.diagnose` (missions or their
    paths): the top-level name and this subpackage are one object."""

    def __call__(self, missions, **kw):
        from aqfg.api import diagnose as run
        return run(missions, **kw)


sys.modules[__name__].__class__ = _CallablePackage
