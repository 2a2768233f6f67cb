"""Diagnosis: compare the model with the measurements, find where it fails, and rank the
candidate effects that would explain it; the loop that adds them one at a time."""
from aqfg.diagnose.sequence import DiagnosisSequence, diagnose_sequence, save_sequence
from aqfg.diagnose.workflow import Diagnosis, diagnose, save_diagnosis

__all__ = ["Diagnosis", "DiagnosisSequence", "diagnose", "diagnose_sequence", "save_diagnosis",
           "save_sequence"]
