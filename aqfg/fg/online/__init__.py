"""The online (fixed-lag) smoother in parts: :class:`FixedLagSmoother` (the orchestration,
:mod:`aqfg.fg.online.smoother`) over a window engine (:mod:`~aqfg.fg.online.engine`), the
USBL gate, the process-noise adaptation, the sigma report and the hold / release /
re-initialise policy."""
from aqfg.fg.online.smoother import FixedLagSmoother, UpdateInfo

__all__ = ["FixedLagSmoother", "UpdateInfo"]
