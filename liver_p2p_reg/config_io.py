"""Settings dataclasses from mappings and YAML files: each value coerced to its field's type, the ROS form flattened."""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path
from typing import Any

import yaml

from liver_p2p_reg.errors import InputError


def read_yaml_mapping(path: str | Path, what: str = "config") -> dict[str, Any]:
    """The mapping in a YAML file: a plain one or a ROS 2 parameter file (`<node>: ros__parameters: ...`).

    `what` names the file in the one-line errors ("config", "training config").
    """
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except OSError as exc:
        raise InputError(f"cannot read {what} {path}: {exc.strerror or exc}") from None
    except yaml.YAMLError as exc:
        raise InputError(f"{what} {path} is not valid YAML: {str(exc).splitlines()[0]}") from None
    if not isinstance(data, dict):
        raise InputError(f"{what} {path} must be a mapping of key: value lines")
    return _flatten_ros_params(data)


def _flatten_ros_params(data: dict[str, Any]) -> dict[str, Any]:
    """Accept `{node: {ros__parameters: {...}}}` as well as a plain mapping."""
    for value in data.values():
        if isinstance(value, dict) and "ros__parameters" in value:
            merged: dict[str, Any] = {}
            for node_block in data.values():
                if isinstance(node_block, dict):
                    merged.update(node_block.get("ros__parameters", {}))
            return merged
    return data


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
