"""Imports Open3D on first use (core modules only, quiet), with a clear error naming the two supported builds."""

from __future__ import annotations

import sys
from types import ModuleType

from liver_p2p_reg.errors import LiverP2PError

# `import open3d` also imports open3d.visualization (dash, plotly) and open3d.ml (scikit-learn,
# pandas): over a second of a command's start-up, for modules this package never uses.
_UNUSED_SUBPACKAGES = ("open3d.visualization", "open3d.ml")


def o3d_module() -> ModuleType:
    """The `open3d` module (warnings silenced), or a one-line error telling how to install it.

    Open3D's core (geometry, io, pipelines, utility) is imported without its visualization
    and ML subpackages: placeholders stand in for them while `open3d/__init__` runs and are
    removed afterwards, so code that imports `open3d.visualization` later still gets the real one.
    """
    module = sys.modules.get("open3d")
    if module is not None:  # imported elsewhere first (a plain `import open3d`): quiet it all the same
        module.utility.set_verbosity_level(module.utility.VerbosityLevel.Error)
        return module
    try:
        try:
            open3d = _import_core()
        except (ImportError, AttributeError):  # an Open3D whose __init__ needs those parts: the plain import
            import open3d
    except ImportError as exc:
        raise LiverP2PError(
            f"Open3D is not usable ({exc}); install `open3d-cpu<0.20` (headless) or `open3d` "
            "(needs the system's libusb-1.0-0)"
        ) from None
    # Its C++ warnings are printed in colour on stdout, where they would corrupt JSON output and
    # interleave with tables; the readers' own problems reach the user as one-line InputErrors.
    open3d.utility.set_verbosity_level(open3d.utility.VerbosityLevel.Error)
    return open3d


def _import_core() -> ModuleType:
    """`import open3d` with empty placeholders standing in for its unused subpackages meanwhile."""
    placeholders = {name: ModuleType(name) for name in _UNUSED_SUBPACKAGES if name not in sys.modules}
    sys.modules.update(placeholders)
    try:
        import open3d
    finally:
        for name, placeholder in placeholders.items():
            if sys.modules.get(name) is placeholder:
                del sys.modules[name]
                parent, _, child = name.rpartition(".")
                if getattr(sys.modules.get(parent), child, None) is placeholder:
                    delattr(sys.modules[parent], child)
    return open3d


def quiet_open3d() -> None:
    """Silence Open3D's C++ warnings (kept for callers; `o3d_module` now always does it)."""
    o3d_module()
