"""Imports Open3D on first use, with a clear error naming the two supported builds."""

from __future__ import annotations

from types import ModuleType

from .errors import LiverP2PError


def o3d_module() -> ModuleType:
    """The `open3d` module, or a one-line error telling how to install it."""
    try:
        import open3d
    except ImportError as exc:
        raise LiverP2PError(
            f"Open3D is not usable ({exc}); install `open3d-cpu<0.20` (headless) or `open3d` "
            "(needs the system's libusb-1.0-0)"
        ) from None
    return open3d


def quiet_open3d() -> None:
    """Silence Open3D's C++ warnings, which go to stdout and would corrupt JSON printed there."""
    o3d = o3d_module()
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
