"""Factor-graph smoothing on GTSAM: dynamics and sensor factors with parameter nodes, the
batch smoother of whole missions and the online fixed-lag smoother."""
from aqfg.fg.batch import BatchSmoother
from aqfg.fg.fit import fit_fg
from aqfg.fg.fixed_lag import FixedLagSmoother
from aqfg.fg.settings import BatchSettings, FGSettings, GraphSettings, OnlineSettings, SolverSettings

__all__ = ["BatchSettings", "BatchSmoother", "FGSettings", "FixedLagSmoother", "GraphSettings",
           "OnlineSettings", "SolverSettings", "fit_fg"]
