"""Why a plan text was refused."""

from __future__ import annotations

import datetime

from schemas.common import Stage
from services.refusal import Refusal


class ParseError(Refusal):
    """The text is not a plan we can run; the message names what was wrong and where."""

    stage = Stage.PARSE


class VocabularyError(Exception):
    """The vocabulary file is missing, malformed or contradicts itself; the message names the file."""


# What a value is, for a refusal: JSON's kinds, and those YAML's safe loader adds (!!timestamp,
# !!binary, !!set, the pairs of !!omap), which must not pass for numbers.
_KINDS: dict[type, str] = {
    dict: "an object",
    list: "an array",
    str: "a string",
    bool: "a boolean",
    type(None): "null",
    int: "a number",
    float: "a number",
    datetime.date: "a date",
    datetime.datetime: "a date and time",
    bytes: "binary data",
    set: "a set",
    tuple: "a pair",
}


def kind_of(value: object) -> str:
    """'an object', 'a number', 'a date'...: what `value` is, in the words of a refusal."""
    return _KINDS.get(type(value), f"a value of type {type(value).__name__}")
