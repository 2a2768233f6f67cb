"""The one result type every estimator returns, as plain data (the documents it is written
as: :mod:`aqfg.parameters_doc`; its files: :mod:`aqfg.export`; format doc, "Outputs").

Diagnosis, plots, the report and the benchmarks read a :class:`Result` and never care
which estimator produced it.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Generic, TypeVar, overload

import numpy as np

if TYPE_CHECKING:                      # the model imports nothing from here, but keep it lazy
    from aqfg.fg.dr_records import DeadReckoning
    from aqfg.fg.gnss_noise import GnssNoise
    from aqfg.fg.online.records import OnlineEvent, ReinitBatch
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


# how an estimate's sigma that the estimator did not compute is written (EstimateNote)
SIGMA_NULL = "null"        # as null, without a null reason (the update-error batch's)
SIGMA_ABSENT = "absent"    # left out (the update-error online method reports none per mission)


@dataclass(frozen=True)
class EstimateNote:
    """What an estimator says of one mission's estimate besides its value and sigma: the
    update-error method's verdict on that mission (``verdict``) and its reason
    (``reason``, written ``note``), why the sigma is missing (``sigma_note``; the first
    reason found stands), and how a sigma the estimator did not compute is written
    (``sigma_missing``: :data:`SIGMA_NULL` or :data:`SIGMA_ABSENT`; "": it computed one,
    a NaN written null with its null reason)."""
    verdict: str = ""
    reason: str = ""
    sigma_note: str = ""
    sigma_missing: str = ""


@dataclass(frozen=True)
class Estimate:
    """One parameter's estimate and its 1-sigma (NaN when not computed); ``note``: what the
    estimator says of a mission's estimate (None: nothing)."""
    value: float
    sigma: float = float("nan")
    note: EstimateNote | None = None

    @property
    def sigma_computed(self) -> bool:
        """Whether the estimator computed the sigma (NaN included)."""
        return self.note is None or not self.note.sigma_missing

    def not_determined(self, sigma_note: str) -> Estimate:
        """This estimate with sigma NaN (computed: written null with its reason) and
        ``sigma_note`` where it has none yet."""
        n = self.note or EstimateNote()
        return dataclasses.replace(self, sigma=float("nan"), note=dataclasses.replace(
            n, sigma_missing="", sigma_note=n.sigma_note or sigma_note))

    def document(self) -> dict:
        """The entry of ``parameters.json``'s ``per_mission``: value, sigma (as the
        estimator wrote it: ``EstimateNote.sigma_missing``), verdict, note, sigma_note."""
        n = self.note or EstimateNote()
        out: dict = {"value": self.value}
        if n.sigma_missing != SIGMA_ABSENT:
            out["sigma"] = None if n.sigma_missing == SIGMA_NULL else self.sigma
        out.update({k: v for k, v in (("verdict", n.verdict), ("note", n.reason),
                                      ("sigma_note", n.sigma_note)) if v})
        return out


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
class SolveSummary:
    """How an optimiser's solve ended: whether it met its convergence test, its cost (0.5 x
    the whitened squared error at the solution; None: not reported), its iterations and
    trial steps (None: not reported), and whether it stopped at its iteration limit."""
    converged: bool
    cost: float | None = None
    iterations: int | None = None
    trials: int | None = None
    hit_iteration_limit: bool = False


@dataclass(frozen=True)
class BaseFit:
    """The model-as-given fit kept beside a fit whose effect step added an effect: its
    effects, values and sigmas, and each mission's estimates for a joint fit (None: one
    mission), as ``Result.per_mission``."""
    effects: list[str]
    values: dict[str, float]
    sigma: dict[str, float]
    per_mission: dict[str, dict[str, Estimate]] | None = None


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

    Every estimator's: ``warnings`` (what a user must be told about the fit, in words;
    logged as they arise, not written to its files), ``observability`` (each estimated
    parameter's verdict: the factor graph's ``{name: {"verdict", "reason", ...}}``,
    :func:`aqfg.fg.observability.verdicts`; the update-error method's ``{name: verdict}``
    with the reasons in ``sigma_notes``; None: not reported) and ``sigma_notes`` (why a
    parameter has no sigma, ``{name: reason}``: parameters.json's ``sigma_note``; None:
    none given). How the optimiser's solve ended is ``solve`` (:class:`SolveSummary`: the
    factor graph's batch and joint fit; the update-error batch's ``converged`` only), read
    as ``converged``, ``iterations`` and ``cost``.

    The process-noise factor a solve used is ``process_noise_scale`` (1: nominal; the
    batch's and the online smoother's); the batch's also ``process_noise_measured`` (the
    factor its evidence chose, also where the solve kept the nominal noise) and
    ``process_noise_evidence`` (the log evidence per factor tried), and the factor each
    mission's track was smoothed with, ``track_noise_scale`` (``{mission: factor}``,
    :attr:`FGSettings.batch.adapt_track`; the evidence per mission for each
    factor tried in ``track_noise_evidence``); None: not reported.

    The factor graph's batch leaves whether its solution is ``plausible`` (a vehicle some
    hull could be, :mod:`aqfg.fg.plausibility`; None: not checked) and why per mission in
    ``plausibility`` (``{mission: Plausibility.as_dict()}``), its parameters'
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
    basin, each such sigma within that basin in ``sigma_unimodal``; its online smoother,
    the ``engine`` that ran its window and the ``sigma_inflation`` of its last re-initialisation. Its steps
    leave typed records: ``gnss_noise`` (the GNSS noise the fixes were weighted by,
    :mod:`aqfg.fg.gnss_noise`), ``structural_test`` (the structural test's ranking,
    :mod:`aqfg.fg.structure`), ``sigma_structure``, ``block_jackknife``, ``other_minimum``
    and ``effect_step``, and ``dead_reckoning`` (the constants and currents refined for
    dead reckoning, :mod:`aqfg.fg.dead_reckoning`); ``heading_check`` is each mission's
    fitted heading against its accelerometer's and ``identifiability_warnings`` what the
    data were found not to determine (:func:`aqfg.identifiability.settle`, where a fleet's
    worker applied it). ``per_mission`` holds each mission's estimates (``{mission:
    {parameter: Estimate}}``, with what the estimator notes of each, :class:`EstimateNote`):
    the per-mission parameters of a joint fit, or each mission's when fitted one by one.
    The online smoother's ``events`` are what its run did besides its updates
    (:class:`aqfg.fg.online.records.OnlineEvent`), ``reinit_batches`` the batch
    re-initialisations it solved (:class:`aqfg.fg.online.records.ReinitBatch`) and
    ``rejected_usbl`` the times (s) of the USBL fixes its innovation gate left out, all in
    parameters.json's ``online`` (None: the estimator keeps no such record).

    An online fit's ``histories`` are every mission's parameter history (the first is
    ``history``; empty where the estimator keeps none per mission: a batch fit).

    ``info`` holds the rest, free-form: ``kernel`` and ``settings`` (typed views below,
    kept there under the same keys), the graph's size (``n_states``, ``n_factors``), a
    joint fit's ``rounds``, ``recovered`` and ``solver``, the held-sway fit
    (``held_sway``, ``alternative_held_sway``), the online smoother's record (``window``,
    ``n_updates``, ``warmup_end``, ``predicted_at_fix``, ``update_median_s``), the
    diagnosis's refit start (``start``, ``cost_other_start``) and the update-error
    method's optimiser record (``evaluations``, ``E``, ``status``, ``message``,
    ``preset``, ``metric``, ``optimiser``, ``bounds``, ``sigma_method``,
    ``consistency``; online, its per-parameter ``converged`` and the paper's
    ``nonconvergence``, §III-F).
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
    warnings: list[str] = field(default_factory=list)
    solve: SolveSummary | None = None
    observability: dict[str, Any] | None = None
    sigma_notes: dict[str, str] | None = None
    plausibility: dict[str, dict] = field(default_factory=dict)
    process_noise_scale: float | None = None
    process_noise_measured: float | None = None
    process_noise_evidence: dict[float, float] | None = None
    track_noise_scale: dict[str, float] | None = None
    track_noise_evidence: dict[float, list[float]] | None = None
    per_mission: dict[str, dict[str, Estimate]] = field(default_factory=dict)
    events: list[OnlineEvent] | None = None
    reinit_batches: list[ReinitBatch] | None = None
    rejected_usbl: list[float] | None = None
    histories: list[ParamHistory] = field(default_factory=list)

    def vehicle_constants(self) -> dict[str, float]:
        """The fitted vehicle's constants (the model's "fixed" group, effects' included):
        the ``init`` of an online run with this fit's model (the paper's protocol), to pass
        with ``effects=result.effects`` (what ``--params-from`` does)."""
        if self.model is None:
            return {n: float(v) for n, v in self.values.items() if n in ("k", "k_x", "k_yz")}
        return {n: float(self.values[n]) for n in self.model.active_names
                if self.model.spec(n).group == "fixed"}

    # ---- typed views of the estimator-specific facts
    @property
    def converged(self) -> bool | None:
        """Whether the optimiser met its convergence test (None: not reported)."""
        return None if self.solve is None else self.solve.converged

    @property
    def iterations(self) -> int | None:
        """Optimiser iterations (None: not reported)."""
        return None if self.solve is None else self.solve.iterations

    @property
    def cost(self) -> float:
        """The solve's cost (:attr:`SolveSummary.cost`), NaN where none was reported."""
        c = None if self.solve is None else self.solve.cost
        return float("nan") if c is None else float(c)
    kernel = InfoView(str, 'Which kernel integrated the model: "cpp" or "numpy" (None: not '
                           'reported).')
    settings = InfoView(_as_stored, "The estimator's settings object (e.g. "
                                    "``aqfg.fg.FGSettings``).")

    def parameters_json(self) -> dict:
        return {n: {"value": float(self.values[n]), "sigma": float(self.sigma.get(n, np.nan))}
                for n in self.estimated}


RESULT_FILES = ("parameters.json", "trajectory.csv", "inertial.csv", "causal.csv",
                "trajectory.tum", "track.geojson")
