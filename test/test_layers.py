"""The package's written list of layers (docs/architecture.md) holds in the code: imports only go down, modules stay small."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "liver_p2p_reg"
MAX_MODULE_LINES = 400


def written_layers() -> list[list[str]]:
    """The layers as docs/architecture.md lists them, bottom first: each a list of top-level names."""
    text = (ROOT / "docs" / "architecture.md").read_text()
    block = text.split("<!-- LAYERS:START -->")[1].split("<!-- LAYERS:END -->")[0]
    layers = []
    for line in block.splitlines():
        m = re.match(r"^\d+\. .*?: (.+)$", line.strip())
        if m:
            layers.append([name.strip(" `") for name in m.group(1).split(",")])
    return layers


def layer_of(module: str, rank: dict[str, int]) -> int:
    """The layer of a module: its longest listed prefix (`ros.messages` before `ros`)."""
    parts = module.split(".")[1:] or ["__init__"]
    for n in range(len(parts), 0, -1):
        if ".".join(parts[:n]) in rank:
            return rank[".".join(parts[:n])]
    raise AssertionError(f"{module} is in no layer of docs/architecture.md")


def imports_of(path: Path) -> set[str]:
    """The liver_p2p_reg modules a file imports (every import statement, also inside functions)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module.startswith("liver_p2p_reg"):
                found.add(node.module)
                if node.module == "liver_p2p_reg":  # `from liver_p2p_reg import x`: a submodule, or the public API
                    found.update(f"liver_p2p_reg.{a.name}" for a in node.names if _is_submodule(a.name))
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.startswith("liver_p2p_reg"))
    return {m if m != "liver_p2p_reg" else "liver_p2p_reg.__init__" for m in found}


def _is_submodule(name: str) -> bool:
    return (PACKAGE / f"{name}.py").is_file() or (PACKAGE / name / "__init__.py").is_file()


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def test_every_top_level_module_has_one_layer() -> None:
    layers = written_layers()
    named = [n for layer in layers for n in layer]
    assert len(named) == len(set(named)), "a name stands in two layers"
    actual = {
        p.stem if p.is_file() else p.name
        for p in PACKAGE.iterdir()
        if (p.suffix == ".py" or (p / "__init__.py").is_file())
    }
    top = {n for n in named if "." not in n}
    assert actual == top, (sorted(actual - top), sorted(top - actual))
    for name in set(named) - top:  # a module listed apart from its package's layer
        assert (PACKAGE / (name.replace(".", "/") + ".py")).is_file(), name


def test_imports_only_go_down_the_layers() -> None:
    rank = {name: i for i, layer in enumerate(written_layers()) for name in layer}
    upward = []
    for path in sorted(PACKAGE.rglob("*.py")):
        here = module_name(path)
        for target in imports_of(path):
            if layer_of(target, rank) > layer_of(here, rank):
                upward.append(f"{here} -> {target}")
    assert not upward, upward


def test_no_relative_imports_and_no_importlib_for_methods() -> None:
    for path in PACKAGE.rglob("*.py"):
        tree = ast.parse(path.read_text())
        assert not any(isinstance(n, ast.ImportFrom) and n.level for n in ast.walk(tree)), path
    for path in (PACKAGE / "registration").rglob("*.py"):
        assert "importlib" not in path.read_text(), path  # the method table is explicit


def test_no_module_over_the_size_limit() -> None:
    big = {
        str(p.relative_to(ROOT)): n
        for p in PACKAGE.rglob("*.py")
        if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES
    }
    assert not big, big


def test_every_module_says_what_it_is_for() -> None:
    for path in PACKAGE.rglob("*.py"):
        text = path.read_text()
        if text.strip():
            assert ast.get_docstring(ast.parse(text)), f"{path}: no module docstring"
