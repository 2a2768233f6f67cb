"""aqfg: motion-model parameter estimation and model diagnosis for small AUVs and ASVs."""
# Run from a source checkout with the package installed (non-editable) elsewhere, as CI
# does, the compiled aqfg._kernel lives only in the installed copy: let the package span both.
__path__ = __import__("pkgutil").extend_path(__path__, __name__)
from .effects import BUILTIN as EFFECTS, Effect, UserEffect
from .mission import Mission, Truth
from .model import Model

__all__ = ["EFFECTS", "Effect", "UserEffect", "Mission", "Truth", "Model"]
__version__ = "0.1.0"
