"""Settings dataclasses from mappings and YAML files: each value coerced to its field's type, the ROS form flattened."""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path
from typing import Any

import yaml

from liver_p2p_reg.errors import InputError


class UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing a key given twice in one mapping (PyYAML silently keeps the last)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":  # `<<: *base`: its keys may be overridden below
                continue
            key = self.construct_object(key_node, deep=deep)
            try:
                duplicate = key in seen
            except TypeError:  # an unhashable key: the base class reports it
                break
            if duplicate:
                raise yaml.constructor.ConstructorError(None, None, f"duplicate key {key!r}", key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def load_yaml_text(path: Path, what: str) -> Any:
    """The YAML document in a file, parsed with `UniqueKeyLoader`; InputError (one line) if it cannot be."""
    try:
        return yaml.load(path.read_text(encoding="utf-8"), Loader=UniqueKeyLoader)  # a SafeLoader: no Python objects
    except OSError as exc:
        raise InputError(f"cannot read {what} {path}: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise InputError(
            f"{what} {path} is not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start})"
        ) from None
    except yaml.YAMLError as exc:
        raise InputError(f"{what} {path} is not valid YAML: {yaml_error_line(exc)}") from None


def yaml_error_line(exc: yaml.YAMLError) -> str:
    """A YAML error in one line, its problem and where ("duplicate key 'seed' (line 2)"), not PyYAML's excerpt."""
    problem = getattr(exc, "problem", None)
    mark = getattr(exc, "problem_mark", None)
    if problem is None:
        return str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    problem = " ".join(str(problem).split())
    return f"{problem} (line {mark.line + 1})" if mark is not None else problem


def read_yaml_mapping(path: str | Path, what: str = "config") -> dict[str, Any]:
    """The mapping in a YAML file: a plain one or a ROS 2 parameter file (`<node>: ros__parameters: ...`).

    `what` names the file in the one-line errors ("config", "training config").
    """
    path = Path(path)
    data = load_yaml_text(path, what) or {}
    if not isinstance(data, dict):
        raise InputError(f"{what} {path} must be a mapping of key: value lines")
    return _flatten_ros_params(data, f"{what} {path}")


def _flatten_ros_params(data: dict[str, Any], where: str) -> dict[str, Any]:
    """Accept `{node: {ros__parameters: {...}}}` as well as a plain mapping; `where` names the file in errors."""
    if not any(isinstance(value, dict) and "ros__parameters" in value for value in data.values()):
        return data
    merged: dict[str, Any] = {}
    for node, block in data.items():
        # In a ROS parameter file every top-level entry is a node's block: a plain `key: value`
        # beside them would be ignored by ROS and by this merge, so it is refused, not dropped.
        if not isinstance(block, dict) or "ros__parameters" not in block:
            raise InputError(f"{where}: {node!r} is not a node's `ros__parameters:` block (in a ROS parameter file)")
        params = block["ros__parameters"]
        if params is None:  # `ros__parameters:` with nothing under it
            continue
        if not isinstance(params, dict):
            raise InputError(f"{where}: {node}.ros__parameters must be a mapping of key: value lines, got {params!r}")
        merged.update(params)
    return merged


def _coerce(name: str, value: Any, kind: type) -> Any:
    """Coerce a YAML/CLI/ROS value to the field's type with a clear error."""
    if kind is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false"):
            return value.lower() == "true"
        raise InputError(f"{name} must be true or false, got {value!r}")
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, (int, str)):
            raise InputError(f"{name} must be an integer, got {value!r}")
        try:
            return int(value)
        except ValueError:
            raise InputError(f"{name} must be an integer, got {value!r}") from None
    if kind is float:
        if isinstance(value, bool):
            raise InputError(f"{name} must be a number, got {value!r}")
        try:
            return float(value)
        except (TypeError, ValueError):
            raise InputError(f"{name} must be a number, got {value!r}") from None
    if kind is str:
        if value is None:
            return ""
        return str(value)
    return value


def from_mapping(cls: type, values: dict[str, Any], what: str) -> Any:
    """A settings dataclass from a mapping, each value coerced to its field's type; validated."""
    defaults = cls()
    known = {f.name for f in fields(cls)}
    kwargs: dict[str, Any] = {}
    for name, value in values.items():
        if name not in known:
            raise InputError(f"unknown {what} {name!r}")
        kwargs[name] = _coerce(name, value, type(getattr(defaults, name)))
    return cls(**kwargs).validate()
