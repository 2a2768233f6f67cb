"""Learn the vehicle in one call: diagnose, add the missing effect, refit, and again.

``diagnose_sequence(missions) -> DiagnosisSequence``: each step is a
:func:`~aqfg.diagnose.workflow.diagnose` of the model with the effects found so far; when
it names a missing effect (:mod:`aqfg.diagnose.confirm`), the effect is added and the next
step starts from that effect's refit (no second fit: the refit *is* the next base model,
and its score tests are the ones that labelled the other candidates echo or independent).
The loop stops when nothing more is confirmed, or after ``max_steps`` added effects.

By default it does not stop merely because the held-out fixes pass the consistency test:
that test has little power against a small effect, and every effect the loop adds has
already had to be confirmed, held-out fixes included (docs/diagnosis.md, "When the loop
stops"); an effect added to a model that was already consistent is marked as small.
``stop_when_consistent=True`` stops there instead.

From a notebook::

    seq = diagnose_sequence([m])
    print(seq.summary())                 # the story in a few lines
    st = seq.staircase()                 # arrays: step, label, rmse, rmse_raw, nis_ratio, ...
    plt.step(st["step"], st["rmse"], where="post")
    seq.added, seq.final.full.values     # the effects and the final model's parameters
    seq.model_file().write("model.json")
"""
from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from aqfg.data.mission import Mission
from aqfg.diagnose.fiteval import FitEval, blas_threads
from aqfg.diagnose.rendering import json_num, json_ready
from aqfg.diagnose.wording import heldout_change
from aqfg.diagnose.workflow import Diagnosis, candidate_effects, diagnose
from aqfg.fg.common import check_missions, progress_fn
from aqfg.model.effects import resolve


@dataclass
class Step:
    """One effect the loop added: its estimate (``{name: {value, sigma}}``), the held-out
    dead-reckoning error before/after (m; ``raw``: the fixes' noise included), whether the
    held-out fixes are consistent after, the BIC change, and the step's evidence."""
    effect: str
    estimate: dict
    rmse_before: float
    rmse_after: float
    rmse_raw_before: float
    rmse_raw_after: float
    consistent_after: bool
    bic_change: float
    score_p: float
    lr_p: float
    heldout_p: float
    echoes: tuple[str, ...] = ()
    independent: tuple[str, ...] = ()
    consistent_before: bool = False
    noise_floor: float = float("nan")     # RMS distance (m) the held-out fixes' noise gives
    gain: float = float("nan")            # fall of the DR error beyond the noise (fraction)

    def beyond_text(self) -> str:
        """The dead-reckoning error beyond the noise floor, before -> after, in words."""
        if not (self.rmse_before > 0):
            return "within the noise before"
        if not (self.rmse_after > 0):
            return f"beyond the noise {self.rmse_before:.2f} m -> within it"
        return (f"beyond the noise {self.rmse_before:.2f} -> {self.rmse_after:.2f} m, "
                f"{-100 * self.gain:+.0f}%")

    def to_json(self) -> dict:
        return json_ready({"effect": self.effect, "estimate": self.estimate,
                       "consistent_before": bool(self.consistent_before),
                       "rmse_before": self.rmse_before, "rmse_after": self.rmse_after,
                       "rmse_raw_before": self.rmse_raw_before,
                       "rmse_raw_after": self.rmse_raw_after,
                       "noise_floor": self.noise_floor, "heldout_gain": self.gain,
                       "consistent_after": bool(self.consistent_after),
                       "bic_change": self.bic_change, "score_p_value": self.score_p,
                       "lr_p_value": self.lr_p, "heldout_p_value": self.heldout_p,
                       "echoes": list(self.echoes), "independent": list(self.independent)})


@dataclass
class DiagnosisSequence:
    """The diagnoses of a :func:`diagnose_sequence` run (iterate over it for them), the
    effects added (``steps``), the bare and final models' evaluations and why it stopped."""
    missions: list[Mission]
    diagnoses: list[Diagnosis]
    steps: list[Step]
    final: FitEval
    stopped: str
    timings: dict = field(default_factory=dict)

    def __iter__(self):
        return iter(self.diagnoses)

    def __len__(self) -> int:
        return len(self.diagnoses)

    def __getitem__(self, i):
        return self.diagnoses[i]

    @property
    def bare(self) -> FitEval:
        """The model before the loop added anything."""
        return self.diagnoses[0].base

    @property
    def added(self) -> tuple[str, ...]:
        return tuple(s.effect for s in self.steps)

    def evaluations(self) -> list[FitEval]:
        """The model after each step: bare, + first effect, ..., final."""
        evs = [self.bare]
        for d in self.diagnoses:
            if d.best is not None and d.best.refit is not None:
                evs.append(d.best.refit)
        return evs

    def staircase(self) -> dict:
        """Plottable arrays over the steps (0 = bare model): ``step``, ``label`` (effect
        added), ``rmse`` / ``rmse_raw`` (held-out dead-reckoning error, m), ``nis_ratio``
        (held-out NIS / expected), ``consistent``, ``bic`` (relative to the bare model)."""
        evs = self.evaluations()
        b0 = evs[0].bic
        return {"step": np.arange(len(evs)),
                "label": ["bare model"] + [f"+ {s.effect}" for s in self.steps],
                "rmse": np.array([e.rmse for e in evs]),
                "rmse_raw": np.array([e.rmse_raw for e in evs]),
                "nis_ratio": np.array([e.consistency.ratio if e.consistency else np.nan
                                       for e in evs]),
                "consistent": np.array([bool(e.consistency and e.consistency.passed)
                                        for e in evs]),
                "bic": np.array([e.bic - b0 for e in evs])}

    def model_file(self, source: dict | None = None):
        """The final model as a :class:`~aqfg.model.modelfile.ModelFile`."""
        from aqfg.model.modelfile import ModelFile
        src = {"made_by": "aqfg diagnose --auto", "missions": [m.name for m in self.missions],
               "heldout_rmse_bare": json_num(self.bare.rmse),
               "heldout_rmse": json_num(self.final.rmse)}
        src.update(source or {})
        return ModelFile.from_result(self.final.full, source=src)

    def verdict(self) -> str:
        """The story in one sentence."""
        if not self.steps:
            return "Nothing added: " + self.diagnoses[0].verdict
        b, f = self.bare, self.final
        return (f"Added {', '.join(self.added)}: {heldout_change(b, f)}; held-out fixes "
                f"{'consistent' if _passed(f) else 'NOT consistent'} with the final model. "
                f"Stopped: {self.stopped}.")

    def summary(self) -> str:
        """The console story: one line per step."""
        b = self.bare
        L = [f"{'bare model':<34} held-out RMS {b.rmse_raw:6.2f} m  "
             + f"(noise floor {b.noise_floor:.2f} m), {_cons(b)}"]
        for s, ev in zip(self.steps, self.evaluations()[1:]):
            est = ", ".join(f"{n.split('.')[-1]}={v['value']:.3g}+-{v['sigma']:.2g}"
                            for n, v in s.estimate.items())
            extra = "; small: the model was already consistent" if s.consistent_before else ""
            if s.echoes:
                extra += f"; echoes: {', '.join(s.echoes)}"
            if s.independent:
                extra += f"; still evidence for: {', '.join(s.independent)}"
            L.append(f"+ {s.effect:<32} held-out RMS {s.rmse_raw_after:6.2f} m  "
                     f"({s.beyond_text()}), {_cons(ev)}, dBIC "
                     f"{s.bic_change:.1f}  [{est}]{extra}")
        L.append(f"stopped: {self.stopped}")
        L.append(self.verdict())
        return "\n".join(L)

    def to_json(self) -> dict:
        """``diagnosis.json`` of ``aqfg diagnose --auto``: the bare model's diagnosis (so
        ``missing`` and ``ranking`` keep their meaning), plus ``sequence`` (one entry per
        added effect, in order), ``final_model`` (the model file), ``final`` (its
        evaluation), ``steps`` (every step's diagnosis) and ``stopped``."""
        out = self.diagnoses[0].to_json()
        out["missing"] = bool(self.steps) or out["missing"]
        out["verdict"] = self.verdict()
        out["sequence"] = [s.to_json() for s in self.steps]
        out["final_model"] = self.model_file().to_json()
        out["final"] = self.final.to_json()
        out["stopped"] = self.stopped
        out["steps"] = [d.to_json() for d in self.diagnoses]
        out["timings"] = self.timings
        return json_ready(out)


def _passed(ev: FitEval | None) -> bool:
    return bool(ev is not None and ev.consistency is not None and ev.consistency.passed)


def _cons(ev: FitEval) -> str:
    c = ev.consistency
    if c is None:
        return "consistency n/a"
    return f"{'consistent' if c.passed else 'NOT consistent'} (NIS/expected {c.ratio:.2f})"


def _step(d: Diagnosis) -> Step:
    c = d.best
    assert c is not None and c.refit is not None and c.gain is not None, "a confirmed effect"
    r = c.refit
    return Step(c.effect, c.estimate(), d.base.rmse, r.rmse, d.base.rmse_raw, r.rmse_raw,
                _passed(r), c.dbic, c.p_adjusted, c.lr_p, c.gain.p,
                tuple(x.effect for x in d.labelled("echo")),
                tuple(x.effect for x in d.labelled("independent")), _passed(d.base),
                d.base.noise_floor, c.gain_frac)


def diagnose_sequence(missions: Sequence[Mission] | Mission, model=None, effects: Sequence = (),
                      max_steps: int = 6, *, stop_when_consistent: bool = False,
                      progress=None, **kw) -> DiagnosisSequence:
    """Diagnose, add the missing effect, diagnose again, ... until nothing more is
    confirmed or ``max_steps`` effects have been added (``stop_when_consistent``: also
    stop as soon as the held-out fixes are consistent with the model). ``kw``: options of
    :func:`~aqfg.diagnose.workflow.diagnose` (``candidates``, ``extra_candidates``,
    ``gnss_every``, ``alpha``, ``jobs``, ...)."""
    if max_steps < 1:
        raise ValueError(f"max_steps must be at least 1, got {max_steps}")
    with blas_threads(1):
        return _sequence(missions, model, effects, max_steps, stop_when_consistent, progress,
                         **kw)


def _sequence(missions, model, effects, max_steps, stop_when_consistent, progress, **kw
              ) -> DiagnosisSequence:
    prog = progress_fn(progress)
    missions = check_missions(missions)
    effects = tuple(resolve(e) for e in effects)
    t0 = time.perf_counter()
    step_times = []
    diags: list[Diagnosis] = []
    steps: list[Step] = []
    base_eval, base_screen = None, None
    while True:
        k = len(steps)
        ts = time.perf_counter()

        def sub(frac, msg, k=k):
            prog(min(0.99, (k + frac) / (max_steps + 1)),
                 f"step {k + 1}: {msg}")
        d = diagnose(missions, model, effects, progress=sub, base_eval=base_eval,
                     base_screen=base_screen, **kw)
        diags.append(d)
        step_times.append(time.perf_counter() - ts)
        if stop_when_consistent and not steps and _passed(d.base):
            stopped = "the held-out fixes are consistent with the model"
            break
        if d.best is None:
            stopped = "nothing more is confirmed"
            break
        steps.append(_step(d))
        pool = candidate_effects(missions, effects, kw.get("extra_candidates", ()),
                                 kw.get("candidates"))
        effects = effects + (next(c for c in pool if c.name == d.best.effect),)
        base_eval, base_screen = d.best.refit, d.next_screen
        if len(steps) >= max_steps:
            stopped = (f"reached max_steps = {max_steps} "
                       "(more effects may be missing: run again with more steps)")
            break
        if stop_when_consistent and _passed(base_eval):
            stopped = "the held-out fixes are consistent with the model"
            break
    final = base_eval if base_eval is not None else diags[0].base
    prog(1.0, "done")
    return DiagnosisSequence(missions, diags, steps, final, stopped,
                             {"total": time.perf_counter() - t0, "steps": step_times})


# ---------------------------------------------------------------- output
def save_sequence(seq: DiagnosisSequence, out_dir, overwrite: bool = False,
                  plots: bool = True) -> Path:
    """Write ``diagnosis.json``, ``report.html`` and ``model.json`` into ``out_dir``."""
    from aqfg.diagnose.rendering import write_diagnosis_json
    from aqfg.diagnose.report import write_sequence_report
    out = write_diagnosis_json(seq.to_json(), Path(out_dir), ("report.html", "model.json"),
                               overwrite)
    seq.model_file().write(out / "model.json", overwrite=True)
    write_sequence_report(seq, out / "report.html", plots=plots)
    return out
