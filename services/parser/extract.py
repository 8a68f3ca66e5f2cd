"""Find the JSON value in what an LLM wrote: bare, in a fenced code block, or inside prose."""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import json_repair

from services.parser.errors import ParseError

# A fenced block: ```lang\n body ``` (an unclosed fence runs to the end, as truncated output does).
_FENCE = re.compile(r"```[ \t]*([A-Za-z0-9_+.-]*)[^\n]*\n(.*?)(?:```|\Z)", re.DOTALL)
_STRUCTURAL = re.compile(r'[\[\]{}"\\]')
_CLOSERS = {"{": "}", "[": "]"}
# How many opening brackets in prose are tried as the start of the plan before giving up.
MAX_PROSE_STARTS = 64


@dataclass(frozen=True)
class Extracted:
    value: Any
    warnings: list[str]


@dataclass(frozen=True)
class _Span:
    """An opening bracket and where its match closes it; `end` is None when the text ends first."""

    start: int
    end: int | None
    open_brackets: int


def line_col(text: str, pos: int) -> str:
    line = text.count("\n", 0, pos) + 1
    column = pos - (text.rfind("\n", 0, pos) + 1) + 1
    return f"line {line}, column {column}"


def _scan(text: str, start: int, max_depth: int) -> _Span:
    """Match the bracket at `start`, skipping strings; refuse nesting deeper than `max_depth`."""
    stack: list[str] = []
    in_string = False
    skip_to = -1
    for match in _STRUCTURAL.finditer(text, start):
        pos = match.start()
        if pos < skip_to:
            continue
        char = match.group()
        if in_string:
            if char == "\\":
                skip_to = pos + 2
            elif char == '"':
                in_string = False
            continue
        if char == '"':
            in_string = True
        elif char in _CLOSERS:
            stack.append(char)
            if len(stack) > max_depth:
                raise ParseError(
                    f"JSON is nested more than {max_depth} levels deep at {line_col(text, pos)}; "
                    "a plan needs only a few levels"
                )
        elif char in "]}":
            if not stack or _CLOSERS[stack[-1]] != char:
                raise ParseError(f"malformed JSON at {line_col(text, pos)}: unexpected {char!r}")
            stack.pop()
            if not stack:
                return _Span(start, pos + 1, 0)
    return _Span(start, None, len(stack))


# Code blocks tried at most; a plan is in the first few, and a text of thousands is an attack.
MAX_CANDIDATES = 16


class JsonFinder:
    """Locates and decodes the plan's JSON; lenient repair only for complete, small candidates."""

    def __init__(self, *, max_depth: int, lenient: bool, max_repair_chars: int) -> None:
        self.max_depth = max_depth
        self.lenient = lenient
        self.max_repair_chars = max_repair_chars

    def find(self, text: str, looks_like_plan: Callable[[Any], bool]) -> Extracted:
        """The first candidate that looks like a plan; else the first that decodes; else the first error."""
        starts: dict[int, None] = {}  # ordered and O(1) to test, for texts full of fences
        stripped = text.lstrip()
        if stripped[:1] in _CLOSERS:
            starts[len(text) - len(stripped)] = None
        for fence in _FENCE.finditer(text):
            body = fence.group(2)
            offset = fence.start(2) + len(body) - len(body.lstrip())
            if text[offset : offset + 1] in _CLOSERS:
                starts[offset] = None
            if len(starts) >= MAX_CANDIDATES:
                break
        if not starts:
            for fence in _FENCE.finditer(text):
                if fence.group(1).lower() in ("yaml", "yml"):
                    raise ParseError(
                        "no JSON plan found, only a YAML code block; YAML plans are not supported yet: send JSON"
                    )
            return self._search_prose(text, looks_like_plan)
        first: Extracted | ParseError | None = None
        for start in starts:
            try:
                found = self._decode(text, start)
            except ParseError as exc:
                first = first or exc
                continue
            if looks_like_plan(found.value):
                return found
            first = first or found
        if isinstance(first, ParseError):
            raise first
        assert first is not None
        return first

    def _decode(self, text: str, start: int) -> Extracted:
        """The JSON value that starts at `start`; text after its closing bracket is ignored."""
        span = _scan(text, start, self.max_depth)
        if span.end is None:
            detail = self._json_error(text[start:], start, text)
            raise ParseError(
                f"malformed JSON: {detail}; the text ends with {span.open_brackets} bracket(s) still open "
                "(was the output cut off?)"
            )
        chunk = text[start : span.end]
        try:
            return Extracted(json.loads(chunk), [])
        except json.JSONDecodeError as exc:
            detail = f"{exc.msg} at {line_col(text, start + exc.pos)}"
        except (RecursionError, ValueError) as exc:
            raise ParseError(f"JSON could not be read: {exc}") from None
        if not self.lenient or len(chunk) > self.max_repair_chars:
            raise ParseError(f"malformed JSON: {detail}")
        try:
            value = json_repair.loads(chunk)
        except (RecursionError, ValueError, TypeError) as exc:
            raise ParseError(f"malformed JSON: {detail} (repair failed: {exc})") from None
        if not isinstance(value, dict | list) or not value:
            raise ParseError(f"malformed JSON: {detail}")
        return Extracted(value, [f"the JSON was malformed ({detail}) and was read leniently"])

    def _json_error(self, chunk: str, offset: int, text: str) -> str:
        try:
            json.loads(chunk)
        except json.JSONDecodeError as exc:
            return f"{exc.msg} at {line_col(text, offset + exc.pos)}"
        except (RecursionError, ValueError) as exc:
            return str(exc)
        return "unexpected end"

    def _search_prose(self, text: str, looks_like_plan: Callable[[Any], bool]) -> Extracted:
        first_error: ParseError | None = None
        resume = 0
        for tries, match in enumerate(re.finditer(r"[\[{]", text)):
            if tries >= MAX_PROSE_STARTS:
                break
            if match.start() < resume:
                continue
            try:
                found = self._decode(text, match.start())
            except ParseError as exc:
                # Brackets in prose ("[see below]") are not JSON; keep the first real-looking failure.
                if first_error is None and '"action"' in text[match.start() : match.start() + 2000]:
                    first_error = exc
                continue
            if looks_like_plan(found.value):
                return found
            span = _scan(text, match.start(), self.max_depth)
            resume = span.end or len(text)
        if first_error is not None:
            raise first_error
        raise ParseError("no plan found: expected a JSON object with a 'plan' array or a JSON array of steps")
