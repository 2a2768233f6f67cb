"""aqfg's own simulator: ASV/AUV missions with truth and optional hidden effects."""
from aqfg.sim.simulator import simulate, true_params

__all__ = ["simulate", "true_params"]
