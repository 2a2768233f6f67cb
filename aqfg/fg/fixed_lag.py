"""Online (fixed-lag) factor-graph smoothing: ``FixedLagSmoother`` and ``UpdateInfo`` of
:mod:`aqfg.fg.online` (the smoother in parts), under their established import path."""
from aqfg.fg.online.smoother import FixedLagSmoother, UpdateInfo
from aqfg.fg.online.tracks import diverged as _diverged
from aqfg.fg.online.tracks import joined as _joined
from aqfg.fg.online.views import mission_until as _mission_until

__all__ = ["FixedLagSmoother", "UpdateInfo", "_diverged", "_joined", "_mission_until"]
