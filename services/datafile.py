"""Reading a YAML, TOML or JSON data file into a Struct, with errors that name the file and the field."""

from __future__ import annotations

from pathlib import Path
from typing import TypeVar

import msgspec

T = TypeVar("T")


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
        return msgspec.yaml.decode(data, type=type_)
    except msgspec.ValidationError as exc:
        raise error(f"{what} file {path}: {exc}") from None
    except msgspec.DecodeError as exc:
        raise error(f"{what} file {path} is not valid {kind}: {exc}") from None
