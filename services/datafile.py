"""Reading a YAML, TOML or JSON data file into a Struct, with errors that name the file and the field."""

from __future__ import annotations

from pathlib import Path
from typing import TypeVar

import msgspec

T = TypeVar("T")

# YAML's anchors and aliases let a few hundred bytes stand for billions of nodes; a data file kept in
# a recording is hostile (tether recheck loads its world and policy). A document of more nodes than
# this, every alias expanded, is refused before it is built: a world or a policy holds thousands.
MAX_YAML_NODES = 1_000_000


def read_struct(path: Path, type_: type[T], what: str, error: type[Exception]) -> T:
    """Decode `path` (JSON or TOML by suffix, else YAML) as `type_`; raise `error` naming `what` file."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise error(f"cannot read {what} file {path}: {exc.strerror}") from None
    return decode_struct(data, path, type_, what, error)


def decode_struct(data: bytes, path: Path, type_: type[T], what: str, error: type[Exception]) -> T:
    """Decode the bytes read from `path`; the same rules and errors as read_struct."""
    kind = {".json": "JSON", ".toml": "TOML"}.get(path.suffix, "YAML")
    try:
        if kind == "JSON":
            return msgspec.json.decode(data, type=type_)
        if kind == "TOML":
            return msgspec.toml.decode(data, type=type_)
        if (nodes := _yaml_nodes(data)) > MAX_YAML_NODES:
            raise error(
                f"{what} file {path}: YAML of more than {MAX_YAML_NODES} nodes once its aliases are expanded "
                f"({'an alias that holds itself' if nodes == _ENDLESS else f'{nodes} nodes'}); not read"
            )
        return msgspec.yaml.decode(data, type=type_)
    except msgspec.ValidationError as exc:
        raise error(f"{what} file {path}: {exc}") from None
    except msgspec.DecodeError as exc:
        raise error(f"{what} file {path} is not valid {kind}: {exc}") from None


_ENDLESS = MAX_YAML_NODES + 1


def _yaml_nodes(data: bytes) -> int:
    """How many nodes the YAML document holds with every alias expanded, counted on the composed graph
    without expanding it (an aliased node is counted once, then by its size); _ENDLESS for an alias
    inside its own anchor. 0 when it does not compose: decoding then says what is wrong."""
    import yaml  # as msgspec.yaml does, only for a YAML file

    try:
        root = yaml.compose(data, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
    except yaml.YAMLError:
        return 0
    sizes: dict[int, int] = {}
    stack: list[tuple[yaml.Node, bool]] = [(root, False)] if root is not None else []
    while stack:  # iterative: nesting is no limit here
        node, counted = stack.pop()
        if id(node) in sizes and not counted:
            if sizes[id(node)] < 0:
                return _ENDLESS
            continue
        children: list[yaml.Node] = []
        if isinstance(node, yaml.SequenceNode):
            children = list(node.value)
        elif isinstance(node, yaml.MappingNode):
            children = [part for pair in node.value for part in pair]
        if not counted:
            sizes[id(node)] = -1  # under way
            stack.append((node, True))
            stack.extend((child, False) for child in children)
        else:
            total = 1 + sum(sizes[id(child)] for child in children)
            sizes[id(node)] = min(total, _ENDLESS)
    return sizes.get(id(root), 0) if root is not None else 0
