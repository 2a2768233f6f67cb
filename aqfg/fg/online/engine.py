"""The online smoother's engine interface: what the orchestration
(:class:`aqfg.fg.online.smoother.FixedLagSmoother`) asks of the window it keeps, in the
manner of GTSAM's ``FixedLagSmoother`` (one interface, an update per fix, two
implementations):

* :class:`aqfg.fg.online.numpy_engine.NumpyEngine` (default where the configuration allows
  it): knots at the fixes only, one Gauss-Newton step per update on the window's dense
  normal equations (:mod:`aqfg.fg.fastlag`);
* :class:`aqfg.fg.online.gtsam_engine.GtsamEngine`: GTSAM's ``IncrementalFixedLagSmoother``
  (ISAM2) on 1-s knots, for what the numpy engine does not model (measurement effects such
  as a lever arm or USBL distortions, a Cauchy loss, random-walk parameters, a thrust lag;
  :meth:`aqfg.fg.fastlag.LagWindow.unsupported`), and as its reference.

One update: :meth:`~WindowEngine.predict` adds the knots up to the fix (the model's
prediction), the orchestration gates the fix and adapts the process noise on that
prediction, :meth:`~WindowEngine.measure` adds the fix's measurements and
:meth:`~WindowEngine.solve` re-estimates the window.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, ClassVar

import numpy as np

if TYPE_CHECKING:
    from aqfg.fg.online.smoother import FixedLagSmoother

# per-axis 1-sigma of the broad priors on a knot ([n, e, d] m, [vn, ve, vd] m/s) with which
# an engine recovers from a failed step
BROAD_STATE_SIGMA = np.array([10.0, 10.0, 1.0, 2.0, 2.0, 0.5])


class WindowEngine(ABC):
    """A fixed-lag window over the knots of one mission and the parameter nodes.

    ``host``: the orchestration, whose mission, model, layout, settings, knots, causal
    states (``filtered``), latest smoothed fix states (``latest``), events and process
    noise (``noise``) the engine reads and extends. ``hold_placed``: the hold priors on
    the parameters are in place (the parameters are held until :meth:`release`)."""
    name: ClassVar[str]
    hold_placed: bool

    def __init__(self, host: FixedLagSmoother):
        self.host = host

    @abstractmethod
    def params(self) -> np.ndarray:
        """Current full parameter vector (inside the physical bounds)."""

    @abstractmethod
    def predict(self, t_fix: float, t_last: float, new_t: np.ndarray,
                all_t: np.ndarray) -> np.ndarray:
        """Add the knots ``new_t`` (the last at the fix ``t_fix``; ``all_t`` with the last
        processed knot first) with their dynamics, appending them to the host's knots and
        causal states; returns the model's prediction at the fix."""

    @abstractmethod
    def measure(self, t_fix: float, t_last: float, all_t: np.ndarray, drop_usbl: bool,
                usbl_scale: float) -> None:
        """Add the measurements in ``(t_last, t_fix]``; ``drop_usbl``: the USBL fix at
        ``t_fix`` left out (the gate), ``usbl_scale``: the sigma factor of one taken."""

    @abstractmethod
    def solve(self, t_fix: float) -> tuple[np.ndarray, np.ndarray]:
        """Re-estimate the window: the estimated parameters (layout order) and their
        marginal 1-sigma."""

    @abstractmethod
    def read_states(self, t_fix: float, i_fix: int) -> None:
        """Into the host: the fix knot's estimate (causal) and the latest estimates of the
        fix knots still in the window."""

    @abstractmethod
    def release(self, t_fix: float) -> None:
        """Remove the hold priors: the parameters follow the data from here."""

    @abstractmethod
    def set_lag(self, lag: float) -> None:
        """The window's length (s)."""

    @abstractmethod
    def review(self, t_fix: float) -> None:
        """After an update: USBL fixes the gate left out, seen again."""

    @abstractmethod
    def set_mission(self, mission) -> None:
        """A newer copy of the mission (live use)."""

    @abstractmethod
    def materialise(self) -> None:
        """Causal states the engine deferred, written into the host's ``filtered``."""

    @abstractmethod
    def keep_deferred_from(self, n: int) -> None:
        """Forget the deferred causal states of knots before index ``n`` (a replay keeps
        what was reported before it)."""
