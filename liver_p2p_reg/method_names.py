"""The registration methods' names and the module defining each, known without importing any of them."""

from __future__ import annotations

# The modules that define methods and the names each registers (a test checks this against the
# registry). `registrar.get_method` imports only the module a method needs (the learned ones need
# torch, the Open3D baselines do not), and the command line checks a name before importing anything.
METHOD_MODULES: dict[str, tuple[str, ...]] = {
    "liver_p2p_reg.pipelines": (
        "fpfh",
        "fpfh-p2p",
        "fpfh-p2p-icp",
        "fpfh-ransac",
        "fpfh-ransac-icp",
        "fgr",
        "icp",
        "track",
        "procrustes",
        "evaluate",
    ),
    "liver_p2p_reg.learned.pipeline": ("learned", "learned-p2p", "learned-p2p-icp"),
}


def method_names() -> list[str]:
    """Names of the methods, from the table above: nothing is imported (for early argument checks)."""
    return sorted(name for names in METHOD_MODULES.values() for name in names)
