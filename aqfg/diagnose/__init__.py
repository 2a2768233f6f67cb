"""Diagnosis: compare the model with the measurements, find where it fails, and rank the
candidate effects that would explain it; the loop that adds them one at a time."""
import sys
import types

from aqfg.diagnose.sequence import DiagnosisSequence, diagnose_sequence, save_sequence
from aqfg.diagnose.workflow import Diagnosis, diagnose, save_diagnosis

__all__ = ["Diagnosis", "DiagnosisSequence", "diagnose", "diagnose_sequence", "save_diagnosis",
           "save_sequence"]


class _CallablePackage(types.ModuleType):
    """``aqfg.diagnose(missions, ...)`` is :func:`aqfg.api.diagnose` (missions or their
    paths): the top-level name and this subpackage are one object."""

    def __call__(self, missions, **kw):
        from aqfg.api import diagnose as run
        return run(missions, **kw)


sys.modules[__name__].__class__ = _CallablePackage
