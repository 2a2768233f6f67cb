"""The one result type every estimator returns, as plain data, and the documents it is
written as (its files: :mod:`aqfg.export`; format doc, "Outputs").

Diagnosis, plots, the report and the benchmarks read a :class:`Result` and never care
which estimator produced it.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Generic, TypeVar, overload

import numpy as np

if TYPE_CHECKING:                      # the model imports nothing from here, but keep it lazy
    from aqfg.fg.dr_records import DeadReckoning
    from aqfg.fg.gnss_noise import GnssNoise
    from aqfg.fg.structure import StructuralShift
    from aqfg.identifiability import HeadingCheck
    from aqfg.model.vehicle import Model


@dataclass
class Track:
    """A trajectory: times (n,) s, position (n, 3) NED m, velocity (n, 3) NED m/s."""
    t: np.ndarray
    pos: np.ndarray
    vel: np.ndarray


@dataclass
class Residuals:
    """Per-measurement residuals of one sensor (measured - predicted).

    ``raw`` (n, d) in the sensor's units; ``normalised`` (n, d) divided by the sensor's
    1-sigma (whitened), so a consistent model gives unit-variance values.
    """
    t: np.ndarray
    raw: np.ndarray
    normalised: np.ndarray
    measured: np.ndarray | None = None
    predicted: np.ndarray | None = None


@dataclass
class ParamHistory:
    """Parameter estimates over time (online modes): t (n,), values/sigma (n, k)."""
    t: np.ndarray
    names: tuple[str, ...]
    values: np.ndarray
    sigma: np.ndarray


@dataclass
class MissionResult:
    name: str
    track: Track                       # smoothed (batch) or filtered-then-corrected (online)
    inertial: Track                    # re-traced by the model alone from the first fix
    p: np.ndarray                      # full parameter vector used for this mission's re-trace
    residuals: dict[str, Residuals] = field(default_factory=dict)
    filtered: Track | None = None      # online modes: the causal (uncorrected) track


@dataclass(frozen=True)
class Estimate:
    """One parameter's estimate and its 1-sigma (NaN when not computed)."""
    value: float
    sigma: float = float("nan")


@dataclass(frozen=True)
class Covariance:
    """A batch fit's joint covariance of the first mission's parameter nodes (model
    units): per node group (``"fixed"``, ``"variable"``, ``"sensor"``), a (k, k) matrix
    over that group's estimated parameters in the order of ``Result.estimated``."""
    blocks: dict[str, np.ndarray]

    def block(self, group: str) -> np.ndarray | None:
        """The group's matrix (None where the fit has none)."""
        return self.blocks.get(group)


@dataclass(frozen=True)
class OnlineEngine:
    """The engine that ran an online fit's window (``"numpy"`` or ``"gtsam"``) and, where
    it is GTSAM's, what the numpy engine does not take (``note``)."""
    name: str
    note: str = ""


@dataclass(frozen=True)
class HeadingEvidence:
    """The heading offset's profile over the circle of a batch fit on data too short for
    the sandwich (:mod:`aqfg.fg.profile`): theta_e at each grid point (rad, wrapped; index
    0 the fit's), the log evidence with it held there, and the sigma of theta_e (rad) the
    fit reports once widened to the profile's spread."""
    theta_e: tuple[float, ...]
    log_evidence: tuple[float, ...]
    sigma_theta_e: float


@dataclass(frozen=True)
class BlockJackknife:
    """The block jackknife of a short batch fit (:mod:`aqfg.fg.jackknife`): how many time
    blocks were left out one at a time, their length (s), the jackknife's sigma of each
    estimated parameter and the former sigma of those it widened; or why it failed
    (``failed``: the first refit's error, the sigmas left as they were)."""
    blocks: int
    block_s: float = float("nan")
    sigma: dict[str, float] = field(default_factory=dict)
    sigma_before: dict[str, float] = field(default_factory=dict)
    failed: str = ""

    def document(self) -> dict | None:
        """``parameters.json``'s ``block_jackknife`` (None where the jackknife failed)."""
        if self.failed:
            return None
        return {"blocks": int(self.blocks), "block_s": float(self.block_s),
                "sigma": {n: float(v) for n, v in self.sigma.items()},
                "sigma_before": {n: float(v) for n, v in self.sigma_before.items()}}


@dataclass(frozen=True)
class OtherMinimum:
    """Other local minima of a refit that explain the fixes as well as the one reported
    (:func:`aqfg.fg.effect_guard.widen_by_other_minimum`): their costs, the largest
    difference of each parameter from the one reported, and the sigmas before that
    difference was added."""
    cost: list[float]
    difference: dict[str, float]
    sigma_before: dict[str, float]


@dataclass(frozen=True)
class RefitCheck:
    """The structural sigma checked by the fit again with its effect
    (:func:`aqfg.fg.structural_sigma.cover_refit`): that fit's cost (None: it failed,
    ``failed`` says why), the exact move of each variable estimate (``name``, and
    ``mission:name`` for a joint fit) and the sigmas before they were widened to hold it,
    or why the refit was not used (``not_used``)."""
    effect: str
    cost: float | None = None
    move: dict[str, float] | None = None
    sigma_before: dict[str, float] | None = None
    not_used: str = ""
    failed: str = ""

    def document(self) -> dict:
        """``parameters.json``'s ``sigma_structure.refit``."""
        return {**({"failed": self.failed} if self.failed else {}),
                **({"cost": float(self.cost)} if self.cost is not None else {}),
                **({"not_used": self.not_used} if self.not_used else {}),
                **({"move": {n: float(x) for n, x in self.move.items()}}
                   if self.move is not None else {})}


@dataclass(frozen=True)
class SigmaStructure:
    """The structural part of a batch fit's sigma (``FGSettings.batch.structural_sigma``,
    :mod:`aqfg.fg.structural_sigma`): the effect the data call for most (or, not
    ``proven``, suggest), its robust score-test p, the shift of each variable parameter it
    would cause (model units), the test's ranking (as ``StructuralShift.ranked``), the
    sigmas before the shift was added, the warning, and the check by the refit with the
    effect (None: not made)."""
    effect: str
    p_value_robust: float
    shift: dict[str, float]
    proven: bool
    ranked: list[dict]
    sigma_before: dict[str, float]
    warning: str
    refit: RefitCheck | None = None


@dataclass(frozen=True)
class BaseFit:
    """The model-as-given fit kept beside a fit whose effect step added an effect: its
    effects, values and sigmas, and each mission's estimates for a joint fit (None: one
    mission), as ``info["per_mission"]``."""
    effects: list[str]
    values: dict[str, float]
    sigma: dict[str, float]
    per_mission: dict | None = None


@dataclass(frozen=True)
class FleetEffect:
    """The fleet's part of its effect step (:mod:`aqfg.fleet.effect`): the vehicles whose
    tests called for the effect, the fleet's cost without and with it, and the step's
    message (the same in every vehicle's warnings)."""
    vehicles_calling: list[str]
    cost_before: float
    cost_after: float
    message: str = ""


@dataclass(frozen=True)
class EffectStep:
    """The effect step of a batch fit (``FGSettings.batch.auto_effect``:
    :func:`aqfg.fg.fit.adopt_effect`, the fleet's :mod:`aqfg.fleet.effect`): the effect
    tried, whether it was added (else ``reason``), its robust score-test p, the costs
    without and with it, whether the model as given explained the fixes, the model-as-given
    fit (``base``), the move of the heading offset and the current the test predicted and
    the refit's (None: not known), whether the effect was ``untested`` (it did not reach
    the test's level), every try where two were made (``tried``, with the effect the test
    called for), the model-as-given solve's time (s) and the fleet's part (None: a fit's
    own step)."""
    effect: str
    adopted: bool
    p_value_robust: float
    cost_before: float
    base: BaseFit
    cost_after: float = float("nan")
    fixes_explained: bool = True
    predicted_move: dict[str, float] | None = None
    moved: dict[str, float] | None = None
    reason: str = ""
    untested: bool = False
    tried: list[dict] | None = None
    called_for: str | None = None
    seconds_base: float | None = None
    fleet: FleetEffect | None = None


T = TypeVar("T")


def _as_stored(v: object) -> object:
    return v


class InfoView(Generic[T]):
    """A typed attribute of :class:`Result` kept in its ``info`` under the attribute's
    name: read as ``kind(info[name])``, None where absent; assigning stores the value
    there."""

    def __init__(self, kind: Callable[[Any], T], doc: str) -> None:
        self.kind, self.__doc__, self.key = kind, doc, ""

    def __set_name__(self, owner: type, name: str) -> None:
        self.key = name

    @overload
    def __get__(self, obj: None, owner: type | None = None) -> InfoView[T]: ...

    @overload
    def __get__(self, obj: Result, owner: type | None = None) -> T | None: ...

    def __get__(self, obj: Result | None, owner: type | None = None) -> InfoView[T] | T | None:
        if obj is None:
            return self
        v = obj.info.get(self.key)
        return None if v is None else self.kind(v)

    def __set__(self, obj: Result, v: T | None) -> None:
        obj.info[self.key] = v


@dataclass
class Result:
    """What every estimator returns.

    Facts only some estimators have are typed attributes below (``per_mission``,
    ``histories``, ``converged``, ``iterations``, ``kernel``, ``settings``); they are kept
    in ``info`` under the same keys, so code that reads or writes ``info`` keeps working.
    The factor graph's batch leaves whether its solution is ``plausible`` (a vehicle some
    hull could be, :mod:`aqfg.fg.plausibility`; None: not checked), its parameters'
    ``covariance`` and, for a joint fit, ``observability_per_mission`` (``{mission:
    {parameter: reason}}``: what a mission's own inputs cannot determine,
    :func:`aqfg.fg.observability.mission_verdicts`), whether its data were
    ``too_short_for_sandwich`` (fewer sandwich blocks than parameters + 2,
    :mod:`aqfg.fg.graph`), each estimated parameter's ``sigma_model`` (the 1-sigma its
    noise model alone gives, model units) and ``sigma_inflation`` (the honest sigma over
    it, :func:`aqfg.fg.covariance.sigma_inflation`), the fixes it down-weighted as
    ``outliers`` (``{mission: {stream: [{"t": s, "sigmas": whitened residual}]}}``, more
    than 5 sigma from the fit, :func:`aqfg.fg.common.outliers`), each start's solve
    summarised in ``basins`` (:func:`aqfg.fg.basins.basin_summary`), those of another
    heading that fit as well as the chosen one in ``ambiguous``
    (:func:`aqfg.fg.basins.as_good_a_basin`; their spread is in the sigmas) and, on data
    too short for the sandwich, the ``heading_profile``
    (:func:`aqfg.fg.basins.widen_by_profile`; the sigmas it widened, as they were, in
    ``sigma_before_profile``) and, where the reported sigmas cover more than the chosen
    basin, each such sigma within that basin in ``sigma_unimodal``; its online smoother, the ``engine`` that
    ran its window and the ``sigma_inflation`` of its last re-initialisation. Its steps
    leave typed records: ``gnss_noise`` (the GNSS noise the fixes were weighted by,
    :mod:`aqfg.fg.gnss_noise`), ``structural_test`` (the structural test's ranking,
    :mod:`aqfg.fg.structure`), ``sigma_structure``, ``block_jackknife``, ``other_minimum``
    and ``effect_step``, and ``dead_reckoning`` (the constants and currents refined for
    dead reckoning, :mod:`aqfg.fg.dead_reckoning`); ``heading_check`` is each mission's
    fitted heading against its accelerometer's and ``identifiability_warnings`` what the
    data were found not to determine (:func:`aqfg.identifiability.settle`, where a fleet's
    worker applied it).
    """
    method: str                        # "fg" or "update-error"
    mode: str                          # "batch" or "online"
    estimated: tuple[str, ...]         # names of the estimated parameters
    values: dict[str, float]           # final estimates (all parameters of the model)
    sigma: dict[str, float]            # 1-sigma marginals of the estimated ones (nan if none)
    missions: list[MissionResult]
    timings: dict[str, list[float]] = field(default_factory=dict)  # s, per step kind
    history: ParamHistory | None = None
    info: dict = field(default_factory=dict)
    effects: tuple[str, ...] = ()
    model: Model | None = None         # the model used
    gnss_noise: GnssNoise | None = None
    block_jackknife: BlockJackknife | None = None
    other_minimum: OtherMinimum | None = None
    structural_test: StructuralShift | None = None
    sigma_structure: SigmaStructure | None = None
    effect_step: EffectStep | None = None
    heading_check: dict[str, HeadingCheck] | None = None
    identifiability_warnings: tuple[str, ...] = ()
    covariance: Covariance | None = None
    observability_per_mission: dict[str, dict[str, str]] | None = None
    too_short_for_sandwich: bool = False
    engine: OnlineEngine | None = None
    sigma_model: dict[str, float] = field(default_factory=dict)
    sigma_inflation: dict[str, float] = field(default_factory=dict)
    outliers: dict[str, dict[str, list[dict]]] | None = None
    heading_profile: HeadingEvidence | None = None
    basins: list[dict] = field(default_factory=list)
    ambiguous: list[dict] = field(default_factory=list)
    plausible: bool | None = None
    dead_reckoning: DeadReckoning | None = None
    sigma_unimodal: dict[str, float] = field(default_factory=dict)
    sigma_before_profile: dict[str, float] = field(default_factory=dict)

    def vehicle_constants(self) -> dict[str, float]:
        """The fitted vehicle's constants (the model's "fixed" group, effects' included):
        the ``init`` of an online run with this fit's model (the paper's protocol), to pass
        with ``effects=result.effects`` (what ``--params-from`` does)."""
        if self.model is None:
            return {n: float(v) for n, v in self.values.items() if n in ("k", "k_x", "k_yz")}
        return {n: float(self.values[n]) for n in self.model.active_names
                if self.model.spec(n).group == "fixed"}

    # ---- typed views of the estimator-specific facts (stored in ``info``)
    @property
    def per_mission(self) -> dict[str, dict[str, Estimate]]:
        """Estimates per mission, ``{mission name: {parameter: Estimate}}``: the
        per-mission parameters of a joint fit, or each mission's when fitted one by one."""
        raw = self.info.get("per_mission") or {}

        def num(v) -> float:           # a sigma the estimator could not give is None (null)
            return float("nan") if v is None else float(v)
        return {m: {n: e if isinstance(e, Estimate) else
                    Estimate(num(e["value"]), num(e.get("sigma")))
                    for n, e in d.items()} for m, d in raw.items()}

    @per_mission.setter
    def per_mission(self, v: dict[str, dict[str, Estimate]]) -> None:
        self.info["per_mission"] = {m: {n: {"value": float(e.value), "sigma": float(e.sigma)}
                                        for n, e in d.items()} for m, d in v.items()}

    @property
    def histories(self) -> list[ParamHistory]:
        """Parameter histories of every mission (online modes; the first is ``history``)."""
        h = self.info.get("histories")
        if h is None:
            return [] if self.history is None else [self.history]
        return list(h)

    @histories.setter
    def histories(self, v: list[ParamHistory]) -> None:
        self.info["histories"] = list(v)

    converged = InfoView(bool, "Whether the optimiser met its convergence test (None: not "
                               "reported).")
    iterations = InfoView(int, "Optimiser iterations (None: not reported).")
    kernel = InfoView(str, 'Which kernel integrated the model: "cpp" or "numpy" (None: not '
                           'reported).')
    settings = InfoView(_as_stored, "The estimator's settings object (e.g. "
                                    "``aqfg.fg.FGSettings``).")

    def parameters_json(self) -> dict:
        return {n: {"value": float(self.values[n]), "sigma": float(self.sigma.get(n, np.nan))}
                for n in self.estimated}


PARAMETERS_FORMAT = "aqfg-parameters/1"
RESULT_FILES = ("parameters.json", "trajectory.csv", "inertial.csv", "causal.csv",
                "trajectory.tum", "track.geojson")
NO_SIGMA = ("no finite 1-sigma: the data do not determine this parameter, or the estimator "
            "computed none")


# the online fit's record kept in parameters.json (format doc, "Outputs")
ONLINE_RECORD = ("events", "reinit_batches", "rejected_usbl", "process_noise_scale")


def effect_step_document(step: EffectStep) -> dict:
    """The fields of ``parameters.json``'s ``auto_effect`` that ``aqfg fit``'s and the
    fleet's share, from a result's ``effect_step``: the effect, whether it was added (and
    why not), its robust p, the costs without and with it, and how far its refit moved the
    heading offset and the current beside the move the test predicted."""
    return {"effect": step.effect, "adopted": bool(step.adopted),
            "p_value_robust": float(step.p_value_robust),
            "cost_before": float(step.cost_before),
            "cost_after": float(step.cost_after),
            **({"moved": {n: float(v) for n, v in step.moved.items()}}
               if step.moved is not None else {}),
            **({"predicted_move": {n: float(v) for n, v in step.predicted_move.items()}}
               if step.predicted_move is not None else {}),
            **({"reason": step.reason} if step.reason else {}),
            **({"untested": True} if step.untested else {})}


def without_effect_document(base: BaseFit) -> dict:
    """``auto_effect.without_effect`` of ``parameters.json`` (``aqfg fit``'s and the
    fleet's): the heading offset and current of the model as given (``base``, the effect
    step's), and each mission's under ``per_mission`` for a joint fit."""
    out: dict = {n: {"value": float(base.values[n]),
                     "sigma": float(base.sigma.get(n, float("nan")))}
                 for n in ("theta_e", "s_x", "s_y") if n in base.values}
    if base.per_mission:
        out["per_mission"] = {
            m: {n: {"value": float(e["value"]), "sigma": float(e["sigma"])}
                for n, e in d.items() if n in ("theta_e", "s_x", "s_y")}
            for m, d in base.per_mission.items()}
    return out


def parameters_document(result: Result, provenance: dict | None = None) -> dict:
    """The content of ``parameters.json`` (format doc, "Outputs"): the estimated parameters
    (value, 1-sigma, unit), the fixed parameters the model used (value, unit), per-mission
    values when several missions were fitted, and the provenance. A missing 1-sigma is
    ``null`` with a ``sigma_note``."""
    model = result.model

    def unit(n: str) -> str | None:
        try:
            return model.spec(n).unit if model is not None else None
        except (KeyError, AttributeError):
            return None

    est: dict = {}
    for n in result.estimated:
        s = float(result.sigma.get(n, np.nan))
        e = {"value": float(result.values[n]), "sigma": s if np.isfinite(s) else None,
             "unit": unit(n)}
        if not np.isfinite(s):
            e["sigma_note"] = (result.info.get("sigma_notes") or {}).get(n) or NO_SIGMA
        est[n] = e
    names = (model.active_names if model is not None and hasattr(model, "active_names")
             else tuple(result.values))
    fixed = {n: {"value": float(result.values[n]), "unit": unit(n)}
             for n in names if n not in result.estimated and n in result.values}
    doc: dict = {"format": PARAMETERS_FORMAT, "method": result.method, "mode": result.mode,
                 "parameters": est, "fixed": fixed}
    per = result.info.get("per_mission")
    if per and len(result.missions) > 1:
        doc["per_mission"] = per
    dr = result.dead_reckoning
    if dr is not None and (dr.segments or dr.current):
        doc["dead_reckoning"] = dead_reckoning_document(dr)
    if result.gnss_noise is not None:
        # the GNSS error's AR(1) sigma and correlation time the fixes were weighted by
        # (aqfg.fg.gnss_noise)
        doc["gnss_noise"] = result.gnss_noise.document()
    tq = result.info.get("track_noise_scale")
    if result.mode == "batch" and tq:
        # the process-noise factor each mission's trajectory was smoothed with
        # (FGSettings.batch.adapt_track; 1: the model explains the motion between fixes)
        doc["track"] = {"process_noise_scale": {n: float(q) for n, q in tq.items()}}
    jk = result.block_jackknife.document() if result.block_jackknife is not None else None
    if result.mode == "batch" and jk:
        # the spread of the fit without each time block's fixes, which the sigma includes
        # where larger (data too short for the sandwich; aqfg.fg.jackknife)
        doc["block_jackknife"] = jk
    st = result.sigma_structure
    if result.mode == "batch" and st is not None:
        doc["sigma_structure"] = sigma_structure_document(st)
    ae = result.effect_step
    if result.mode == "batch" and ae is not None:
        # the effect the structural test named, whether the fit added it (FGSettings.
        # auto_effect), and the heading offset and current of the model as given
        doc["auto_effect"] = {**effect_step_document(ae),
                              "without_effect": without_effect_document(ae.base)}
    if result.mode == "online" and ("events" in result.info or "reinit_batches" in result.info):
        # what the online run did besides its updates: re-initialisations, re-seeds,
        # recoveries, fixes left out (docs/independent-vehicle.md)
        doc["online"] = {k: result.info[k] for k in ONLINE_RECORD if k in result.info}
    if result.heading_check:
        # the fitted heading against the accelerometer's (aqfg.identifiability)
        doc["heading_check"] = {m: {"offset_deg": c.offset_deg, "agreement": c.agreement,
                                    "windows": c.windows}
                                for m, c in result.heading_check.items()}
    if provenance is not None:
        doc["provenance"] = provenance
    return doc


def sigma_structure_document(st: SigmaStructure) -> dict:
    """``parameters.json``'s ``sigma_structure``: the structural part of the batch's sigma."""
    # the shift of the variable parameters the missing effect the data call for most
    # would cause, included in their sigma (FGSettings.batch.structural_sigma)
    out = {"effect": st.effect, "p_value_robust": float(st.p_value_robust),
           "shift": {n: float(v) for n, v in st.shift.items()},
           "proven": bool(st.proven),
           "sigma_before": {n: float(v) for n, v in st.sigma_before.items()}}
    if st.refit is not None:
        # the fit again with the effect (aqfg.fg.fit.refit_structure)
        out["refit"] = st.refit.document()
    return out


def dead_reckoning_document(dr: DeadReckoning) -> dict:
    """The ``dead_reckoning`` entry of ``parameters.json``: whether the thrust/drag
    constants were refined by prediction error (:mod:`aqfg.fg.dead_reckoning`), the
    smoother's own values, and the prediction errors before and after (or why they were
    not tried); each mission's current for dead reckoning (:mod:`aqfg.fg.dr_current`)."""
    out: dict = {"horizon_s": dr.horizon_s, "applied": bool(dr.applied)}
    if dr.segments:                   # the constants' refinement ran
        out.update({
            "smoother": {n: {"value": v, "sigma": _finite_or_none(dr.sigma_before.get(n))}
                         for n, v in dr.before.items()},
            "prediction_error_m": {"median_before": dr.median_abs_before_m,
                                   "median_after": dr.median_abs_after_m},
            "wald": _finite_or_none(dr.wald), "wald_threshold": dr.wald_threshold})
    if not dr.applied:
        if dr.segments:
            out["refined"] = {n: {"value": v, "sigma": _finite_or_none(dr.sigma_after.get(n))}
                              for n, v in dr.after.items()}
        out["reason"] = dr.reason
    if dr.current:
        # each mission's current by prediction error (aqfg.fg.dr_current)
        out["current"] = {c.mission: c.document() for c in dr.current}
    return out


def _finite_or_none(x) -> float | None:
    return float(x) if x is not None and np.isfinite(x) else None


def read_parameter_values(doc: dict) -> dict[str, float]:
    """``{name: value}`` from a parameters.json document (estimated and fixed), in the
    current layout or the earlier flat one ``{name: {"value": v, "sigma": s}}``."""
    if "parameters" in doc and isinstance(doc["parameters"], dict):
        entries = {**doc.get("fixed", {}), **doc["parameters"]}
    else:
        entries = {k: v for k, v in doc.items() if k not in ("provenance", "null_reasons")}
    out = {}
    for name, e in entries.items():
        v = e.get("value") if isinstance(e, dict) else e
        if v is None:
            raise ValueError(f"entry {name!r} has no \"value\"")
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ValueError(f"value of {name!r} must be a number, got {v!r}")  # noqa: TRY004
        out[name] = float(v)
    return out
