"""What the online smoother reports as its parameters' 1-sigma, and the priors it starts
(or replays) them with."""
from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np

from aqfg.fg import factors as fc
from aqfg.fg.settings import FGSettings
from aqfg.model.vehicle import Model

# parameter groups whose start prior a replay keeps as the batch had it (the user's prior,
# centred on the original start values): the heading offset, the current and the sensor
# parameters. The thrust/drag constants ("fixed") are replayed with the batch's marginals
# as priors instead (ParamPriors.replay_sigmas)
BATCH_PRIOR_GROUPS = ("variable", "sensor")


@dataclass
class SigmaReport:
    """The sigma reported for a parameter from its window marginal.

    ``inflation``: sigma reported / marginal per name, from the last re-initialisation
    batch's honest sigma of the same data; ``ambiguity``: variance added per name (the
    spread of the basins that batch found fitting as well, and the constants' doubt);
    ``raw``: the latest marginal sigma per name. ``held``: while the parameters are held,
    the sigmas they are reported with (their prior's; the hold priors' tiny marginal would
    claim a certainty no data gave), else None."""
    inflation: dict[str, float] = field(default_factory=dict)
    ambiguity: dict[str, float] = field(default_factory=dict)
    raw: dict[str, float] = field(default_factory=dict)
    held: np.ndarray | None = None

    def reported(self, names, sg: np.ndarray) -> np.ndarray:
        """The sigma reported for the parameters ``names`` from their marginal ``sg``
        (the held sigma while held): scaled to the last re-initialisation batch's honest
        sigma of the same data (the marginal assumes the model is right and the window's
        noise), and widened by the spread of the basins that batch found fitting as well
        (docs/independent-vehicle.md); ``sg`` itself where neither applies."""
        if self.held is not None:
            return self.with_ambiguity(names, self.held)
        sh = sg * np.array([self.inflation.get(n, 1.0) for n in names]) \
            if self.inflation else sg
        return self.with_ambiguity(names, sh)

    def with_ambiguity(self, names, sh: np.ndarray) -> np.ndarray:
        """``sh`` widened by ``ambiguity``, also while the parameters are held at the
        batch's values: the restart's own fix reported the hold prior's sigma alone, 19.5
        deg at a heading 159 deg off where the batch's two basins gave 81 deg
        (docs/independent-vehicle.md)."""
        if not self.ambiguity:
            return sh
        return np.hypot(sh, np.sqrt([self.ambiguity.get(n, 0.0) for n in names]))


@dataclass
class ParamPriors:
    """The parameters' start priors in a fresh smoother (as :func:`fc.param_prior`).

    ``override``: in a replay, prior sigmas by name (the batch's marginals, x2) that apply
    to the groups not in ``BATCH_PRIOR_GROUPS``; ``centre``: the values the smoother first
    started from (the original ``init``), the centre of a replay's priors of the groups in
    ``BATCH_PRIOR_GROUPS``; ``replaying``: whether this start is a replay."""
    model: Model
    layout: fc.ParamLayout
    settings: FGSettings
    override: dict[str, float] = field(default_factory=dict)
    centre: dict[str, float] | None = None
    replaying: bool = False

    def mean(self, g: str) -> np.ndarray:
        """Centre of group ``g``'s start prior: its start values; in a replay, for the
        groups of ``BATCH_PRIOR_GROUPS``, the values the smoother first started from, as
        the batch had it. The replay holds them at the batch's values and, released, the
        window solves the batch's problem (centred on the batch's values, the current's
        zero-mean prior is gone and the released estimate slides along the offset-current
        ridge; measured in docs/independent-vehicle.md)."""
        centre = self.centre if self.replaying and g in BATCH_PRIOR_GROUPS else None
        if centre is None:
            return self.layout.initial(g)
        return self.layout.project(g, self.model.nominal(centre)[self.layout.idx[g]])

    def replay_sigmas(self) -> dict[str, float]:
        """A replay's prior sigmas that are not the settings': the batch's marginals (x2)
        of the thrust/drag constants, centred on the batch's values: the window's single
        steps on constants the first minutes barely determine wander from the settings'
        flat prior (docs/independent-vehicle.md). Empty outside a replay."""
        if not self.replaying:
            return {}
        return {n: v for n, v in self.override.items()
                if self.model.spec(n).group not in BATCH_PRIOR_GROUPS}

    def sigmas_with(self, override: dict[str, float]) -> np.ndarray:
        """The settings' prior sigmas (``graph.prior_sigma``, else ``graph.prior_scale`` x the
        parameter's scale, as :func:`fc.param_prior`) with ``override``, in the layout's
        order."""
        s = self.settings
        sig = {**s.graph.prior_sigma, **override}
        return np.array([sig.get(n, s.graph.prior_scale * self.model.spec(n).scale)
                         for n in self.layout.estimated])

    def sigmas(self) -> np.ndarray:
        """Sigmas of the start priors in the layout's order."""
        return self.sigmas_with(self.replay_sigmas())

    def hold_sigmas(self) -> np.ndarray:
        """Sigmas of the removable hold priors (1e-3 x scale) in the layout's order."""
        return np.array([1e-3 * self.model.spec(n).scale for n in self.layout.estimated])

    def held_report(self) -> np.ndarray:
        """The sigmas a held parameter is reported with: its prior's, and in a replay the
        batch's (``override``)."""
        return self.sigmas_with(self.override if self.replaying else {})

    def start_factor(self, g: str, k: int) -> gtsam.PriorFactorVector:
        """The weak start prior of group ``g`` at node ``k`` (the GTSAM engine)."""
        sig = dict(self.settings.graph.prior_sigma)
        sig.update(self.replay_sigmas())
        return fc.param_prior(self.layout, g, k, self.settings.graph.prior_scale,
                              mean=self.mean(g), sigma=sig)

    def hold_factor(self, g: str, k: int) -> gtsam.PriorFactorVector:
        """The removable prior that holds group ``g`` at its start values (the GTSAM
        engine)."""
        return fc.param_prior(self.layout, g, k, 1.0, sigma={
            n: 1e-3 * self.model.spec(n).scale for n in self.layout.names[g]})
