"""liver_p2p_reg: automatic complete-to-partial rigid registration of liver surfaces (P2P)."""

from .config import Config
from .errors import InputError, LiverP2PError, RegistrationError, WeightsError
from .registrar import Registrar, available_methods, register
from .result import Candidate, RegistrationResult

__version__ = "0.1.0"

__all__ = [
    "Candidate",
    "Config",
    "InputError",
    "LiverP2PError",
    "RegistrationError",
    "RegistrationResult",
    "Registrar",
    "WeightsError",
    "available_methods",
    "register",
    "__version__",
]
