"""Reading a YAML, TOML or JSON data file into a Struct, with errors that name the file and the field."""

from __future__ import annotations

import json
import os
import stat
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import msgspec

if TYPE_CHECKING:
    import yaml

T = TypeVar("T")

# YAML's anchors and aliases let a few hundred bytes stand for billions of nodes; a data file kept in
# a recording is hostile (tether recheck loads its world and policy). A document of more nodes than
# this, every alias expanded, is refused before it is built: a world or a policy holds thousands.
MAX_YAML_NODES = 1_000_000
# A world or a policy is kilobytes; a path that names a huge file (or /dev/zero) is refused, not read.
MAX_FILE_BYTES = 16 * 1024 * 1024


def read_bounded(path: Path, limit: int, what: str, error: Callable[[str], Exception]) -> tuple[int, bytes]:
    """`path`'s mode and bytes when it is a regular file of at most `limit` bytes; else `error(message)`,
    the message naming the `what` file ("config", "robot key"), its path and what is wrong. Opened
    without blocking and checked on the open file: a FIFO named in its place would hang the reader, a
    device (/dev/zero) feed it without end, and the file checked is the file read."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
        try:
            mode, data = os.fstat(fd).st_mode, b""
            if stat.S_ISREG(mode):  # only then: opening a directory's descriptor as a file raised, leaving it open
                with open(fd, "rb", closefd=False) as file:
                    # One byte more than allowed: a file over the limit is told by the length, not read to its end.
                    data = file.read(limit + 1)
        finally:
            os.close(fd)
    except OSError as exc:
        raise error(f"cannot read {what} file {path}: {exc.strerror}") from None
    if not stat.S_ISREG(mode):
        raise error(f"{what} file {path} is not a regular file")
    if len(data) > limit:
        raise error(_too_long(what, path, limit))
    return mode, data


def _too_long(what: str, path: Path, limit: int) -> str:
    return f"{what} file {path}: more than {limit} bytes; not read"


class DuplicateKey(ValueError):
    """A JSON object that gives one key twice (`key`): loaders keep the last, dropping the first."""

    def __init__(self, key: str) -> None:
        super().__init__(f"the key {key[:60]!r} appears twice in one object")
        self.key = key


def no_duplicate_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """A json object_pairs_hook that refuses {"action": "pick", "action": "place"} (DuplicateKey)
    instead of keeping the last."""
    value = dict(pairs)
    if len(value) != len(pairs):
        seen: set[str] = set()
        for key, _ in pairs:
            if key in seen:
                raise DuplicateKey(key)
            seen.add(key)
    return value


def read_struct(path: Path, type_: type[T], what: str, error: type[Exception]) -> T:
    """Decode `path` (JSON or TOML by suffix, else YAML) as `type_`; raise `error` naming `what` file."""
    return decode_struct(read_bytes(path, what, error), path, type_, what, error)


def read_bytes(path: Path, what: str, error: type[Exception]) -> bytes:
    """The bytes of `path`, a regular file of at most MAX_FILE_BYTES (read_bounded): a FIFO named as the
    world hung start-up, a device was read to the limit."""
    return read_bounded(path, MAX_FILE_BYTES, what, error)[1]


def decode_struct(data: bytes, path: Path, type_: type[T], what: str, error: type[Exception]) -> T:
    """Decode the bytes read from `path`; the same rules and errors as read_struct."""
    kind = {".json": "JSON", ".toml": "TOML"}.get(path.suffix, "YAML")
    if len(data) > MAX_FILE_BYTES:
        raise error(_too_long(what, path, MAX_FILE_BYTES))
    try:
        if kind == "JSON":
            # msgspec keeps the last of two equal keys: a second "keep_out" would drop the first's zones.
            if key := _json_duplicate_key(data):
                raise error(f"{what} file {path}: key {key!r} appears twice in one object")
            return msgspec.json.decode(_utf8(data), type=type_)
        if kind == "TOML":
            return _toml(_utf8(data), type_)  # TOML itself refuses a key given twice
        root = _yaml_compose(data)
        if (nodes := _yaml_nodes(root)) > MAX_YAML_NODES:
            raise error(
                f"{what} file {path}: YAML of more than {MAX_YAML_NODES} nodes once its aliases are expanded "
                f"({'an alias that holds itself' if nodes == _ENDLESS else f'{nodes} nodes'}); not read"
            )
        if duplicate := _yaml_duplicate_key(root):
            key, line = duplicate
            raise error(f"{what} file {path}: key {key!r} appears twice in one mapping (line {line})")
        return _yaml(data, type_)
    except msgspec.ValidationError as exc:
        raise error(f"{what} file {path}: {exc}") from None
    except msgspec.DecodeError as exc:
        raise error(f"{what} file {path} is not valid {kind}: {exc}") from None


_ENDLESS = MAX_YAML_NODES + 1


def _utf8(data: bytes) -> str:
    """The file's text; bytes that are not UTF-8 as a DecodeError (msgspec's JSON decoder raised
    UnicodeDecodeError for them, and its builds differ in what TOML's raises)."""
    try:
        return data.decode()
    except UnicodeDecodeError as exc:
        raise msgspec.DecodeError(f"not UTF-8 text (byte {exc.start})") from None


def _toml(text: str, type_: type[T]) -> T:
    """msgspec's TOML decode, its reader's other errors as DecodeErrors: arrays nested past the
    interpreter's recursion limit, an integer of thousands of digits (a recording's policy file is anyone's)."""
    try:
        return msgspec.toml.decode(text, type=type_)
    except msgspec.MsgspecError:  # what the file says against its type, named by decode_struct
        raise
    except RecursionError:
        raise msgspec.DecodeError("arrays or tables nested too deeply") from None
    except ValueError as exc:  # past Python's limit on the digits of an integer it parses
        raise msgspec.DecodeError(str(exc)) from None


def _yaml(data: bytes, type_: type[T]) -> T:
    """msgspec's YAML decode, its loader's other errors as DecodeErrors. PyYAML builds each scalar with
    Python's own int(), date() or a dict look-up, and lets what they raise out: ValueError for an integer
    of thousands of digits or a 13th month, KeyError for `!!bool x`, AttributeError for `!!timestamp x`."""
    try:
        return msgspec.yaml.decode(data, type=type_)
    except msgspec.MsgspecError:
        raise
    except Exception as exc:
        raise msgspec.DecodeError(f"a value it cannot build ({type(exc).__name__}: {exc})") from None


def _json_duplicate_key(data: bytes) -> str | None:
    """The first key given twice in one JSON object; None when there is none or it does not parse
    (decoding then says what is wrong)."""
    try:
        json.loads(data, object_pairs_hook=no_duplicate_keys)
    except DuplicateKey as exc:
        return exc.key
    except (ValueError, RecursionError):
        return None
    return None


def _yaml_compose(data: bytes) -> yaml.Node | None:
    """The YAML document as a graph of nodes, aliases not expanded; None when it does not compose
    (decoding then says what is wrong)."""
    import yaml  # as msgspec.yaml does, only for a YAML file

    try:
        return yaml.compose(data, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
    except yaml.YAMLError:
        return None


def _yaml_duplicate_key(root: yaml.Node | None) -> tuple[str, int] | None:
    """The first key given twice in one mapping, and its line; YAML loaders keep only the last."""
    import yaml

    seen: set[int] = set()
    stack = [root] if root is not None else []
    while stack:
        node = stack.pop()
        if id(node) in seen:  # an alias: its node is checked once
            continue
        seen.add(id(node))
        if isinstance(node, yaml.SequenceNode):
            stack.extend(node.value)
        elif isinstance(node, yaml.MappingNode):
            keys: set[tuple[str, str]] = set()
            for key, value in node.value:
                if isinstance(key, yaml.ScalarNode):
                    if (key.tag, key.value) in keys:
                        return key.value, key.start_mark.line + 1
                    keys.add((key.tag, key.value))
                stack.extend((key, value))
    return None


def _yaml_nodes(root: yaml.Node | None) -> int:
    """How many nodes the YAML document holds with every alias expanded, counted on the composed graph
    without expanding it (an aliased node is counted once, then by its size); _ENDLESS for an alias
    inside its own anchor. 0 when it did not compose."""
    import yaml

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
