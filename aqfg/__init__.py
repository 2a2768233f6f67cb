"""aqfg: motion-model parameter estimation and model diagnosis for small AUVs and ASVs."""
from .effects import BUILTIN as EFFECTS, Effect, UserEffect
from .mission import Mission, Truth
from .model import Model

__all__ = ["EFFECTS", "Effect", "UserEffect", "Mission", "Truth", "Model"]
__version__ = "0.1.0"
