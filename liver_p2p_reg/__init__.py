"""liver_p2p_reg: automatic complete-to-partial rigid registration of liver surfaces (P2P)."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

# The public names are imported on first use (PEP 562): `liver-p2p --help`, argument errors and
# the ROS-free submodules then start without scipy, torch or Open3D.
_LAZY = {
    "Config": ".config",
    "InputError": ".errors",
    "LiverP2PError": ".errors",
    "RegistrationError": ".errors",
    "WeightsError": ".errors",
    "Registrar": ".registration.registrar",
    "available_methods": ".registration.registrar",
    "register": ".registration.registrar",
    "Candidate": ".result",
    "RegistrationResult": ".result",
}

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

if TYPE_CHECKING:
    from liver_p2p_reg.config import Config
    from liver_p2p_reg.errors import InputError, LiverP2PError, RegistrationError, WeightsError
    from liver_p2p_reg.registration.registrar import Registrar, available_methods, register
    from liver_p2p_reg.result import Candidate, RegistrationResult


def __getattr__(name: str) -> Any:
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(_LAZY[name], __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
