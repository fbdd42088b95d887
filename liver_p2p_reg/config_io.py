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

    aliases = 0  # `*name` uses composed so far

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node:
        if self.check_event(yaml.AliasEvent):
            self.aliases += 1
        return super().compose_node(parent, index)

    def compose_document(self) -> yaml.Node:
        """The document's node graph; refused when its aliases expand it past `MAX_EXPANDED_NODES` values."""
        document = super().compose_document()
        if self.aliases and document is not None and expanded_size(document) > MAX_EXPANDED_NODES:
            raise AliasBombError(
                f"its aliases (*name) expand to more than {MAX_EXPANDED_NODES} values; write the values out"
            )
        return document


# A document with aliases may stand for this many values at most: aliases repeating a node (`*a` ten times, ten
# levels deep: 10**10 values, a "billion laughs") cost nothing to parse but hang or exhaust memory in whatever walks
# the result (an error message's repr took 77 s and 6 GB). A config is tens of keys; documents without aliases
# (bag metadata of many files) are not limited: their size is their file's.
MAX_EXPANDED_NODES = 10_000
# The longest value a one-line error quotes (a YAML value may be megabytes long).
MAX_QUOTED = 80


class AliasBombError(yaml.YAMLError):
    """A YAML document whose aliases repeat its nodes too often."""


def expanded_size(root: yaml.Node) -> int:
    """The number of nodes `root` stands for with every alias written out; stops counting past the limit."""
    sizes: dict[int, int] = {}  # by id: an aliased node is one object, counted once per place it is used

    def size(node: yaml.Node) -> int:
        if id(node) not in sizes:
            sizes[id(node)] = MAX_EXPANDED_NODES + 1  # a cycle (not possible in YAML 1.1 aliases) stays bounded
            children: list[yaml.Node] = []
            if isinstance(node, yaml.SequenceNode):
                children = node.value
            elif isinstance(node, yaml.MappingNode):
                children = [item for pair in node.value for item in pair]
            total = 1
            for child in children:
                total += size(child)
                if total > MAX_EXPANDED_NODES:
                    break
            sizes[id(node)] = total
        return sizes[id(node)]

    return size(root)


def quoted(value: Any) -> str:
    """A value as a one-line error quotes it: a scalar's repr cut to `MAX_QUOTED` characters, else its kind."""
    if isinstance(value, (list, tuple)):
        return f"a list of {len(value)} items"
    if isinstance(value, dict):
        return f"a mapping of {len(value)} keys"
    if value is not None and not isinstance(value, (str, int, float)):
        return f"a {type(value).__name__}"
    return short(repr(value))


def short(text: str) -> str:
    """`text` cut to `MAX_QUOTED` characters ("..." at the end when cut)."""
    return text if len(text) <= MAX_QUOTED else text[: MAX_QUOTED - 3] + "..."


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
    except RecursionError:  # PyYAML composes nested values recursively: `[[[[...` a thousand deep
        raise InputError(f"{what} {path} nests its values too deeply") from None
    except AliasBombError as exc:
        raise InputError(f"{what} {path}: {exc}") from None
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
    """Accept `{node: {ros__parameters: {...}}}` as well as a plain mapping; `where` names the file in errors.

    The node blocks are merged into one configuration: a key two blocks give different values is refused (which
    one holds would depend on the blocks' order), the same value in several blocks is one value."""
    if not any(isinstance(value, dict) and "ros__parameters" in value for value in data.values()):
        return data
    merged: dict[str, Any] = {}
    given_by: dict[str, Any] = {}  # key -> the node block that gave it first
    for node, block in data.items():
        # In a ROS parameter file every top-level entry is a node's block: a plain `key: value`
        # beside them would be ignored by ROS and by this merge, so it is refused, not dropped.
        if not isinstance(block, dict) or "ros__parameters" not in block:
            raise InputError(
                f"{where}: {quoted(node)} is not a node's `ros__parameters:` block (in a ROS parameter file)"
            )
        params = block["ros__parameters"]
        if params is None:  # `ros__parameters:` with nothing under it
            continue
        if not isinstance(params, dict):
            raise InputError(
                f"{where}: {short(str(node))}.ros__parameters must be a mapping of key: value lines, "
                f"got {quoted(params)}"
            )
        for key, value in params.items():
            if key in merged and not _same(merged[key], value):
                raise InputError(
                    f"{where}: {quoted(key)} is {quoted(merged[key])} under {quoted(given_by[key])} but "
                    f"{quoted(value)} under {quoted(node)}; give it one value"
                )
            merged[key] = value
            given_by.setdefault(key, node)
    return merged


def _same(a: Any, b: Any) -> bool:
    """Equal values of the same type (`1` and `true`, `1` and `1.0` are two different settings as written)."""
    return type(a) is type(b) and a == b


def _coerce(name: str, value: Any, kind: type) -> Any:
    """Coerce a YAML/CLI/ROS value to the field's type with a clear error.

    Every field is a scalar: a list or mapping is refused by its kind, before it is formatted (an aliased one
    can stand for millions of values), and a quoted value is cut short (`quoted`)."""
    if isinstance(value, (list, tuple, dict)):
        raise _wrong(name, kind, value)
    if kind is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false"):
            return value.lower() == "true"
        raise _wrong(name, kind, value)
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, (int, str)):
            raise _wrong(name, kind, value)
        try:
            return int(value)
        except ValueError:
            raise _wrong(name, kind, value) from None
    if kind is float:
        if isinstance(value, bool):
            raise _wrong(name, kind, value)
        try:
            return float(value)
        except (TypeError, ValueError):
            raise _wrong(name, kind, value) from None
    if kind is str:
        if value is None:
            return ""
        return str(value)
    return value


# what a scalar field of each type wants, as the messages say it
WANTED = {bool: "true or false", int: "an integer", float: "a number", str: "a single text value"}


def _wrong(name: str, kind: Any, value: Any) -> InputError:
    """The one-line error for a value that is not what field `name` (of type `kind`) wants."""
    return InputError(f"{name} must be {WANTED.get(kind, 'a single value')}, got {quoted(value)}")


def from_mapping(cls: type, values: dict[str, Any], what: str) -> Any:
    """A settings dataclass from a mapping, each value coerced to its field's type; validated."""
    defaults = cls()
    known = {f.name for f in fields(cls)}
    kwargs: dict[str, Any] = {}
    for name, value in values.items():
        if name not in known:
            raise InputError(f"unknown {what} {quoted(name)}")
        kwargs[name] = _coerce(name, value, type(getattr(defaults, name)))
    return cls(**kwargs).validate()
