"""Find the JSON value in what an LLM wrote: bare, in a fenced code block, or inside prose."""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import json_repair

from services.datafile import no_duplicate_keys
from services.parser.errors import ParseError

# A fenced block: ```lang\n body ``` (an unclosed fence runs to the end, as truncated output does).
_FENCE = re.compile(r"```[ \t]*([A-Za-z0-9_+.-]*)[^\n]*\n(.*?)(?:```|\Z)", re.DOTALL)
_STRUCTURAL = re.compile(r'[\[\]{}"\\]')
_CLOSERS = {"{": "}", "[": "]"}
_OPENERS = re.compile(r"[\[{]")
# How many opening brackets in prose are tried as the start of the plan before giving up.
MAX_PROSE_STARTS = 64


@dataclass(frozen=True)
class _Span:
    """An opening bracket and where its match closes it; `end` is None when the text ends first.
    `deepest`: how many brackets were open at once, at most."""

    start: int
    end: int | None
    open_brackets: int
    deepest: int = 0


# Malformed JSON one parse may repair, in characters times nesting levels, per character of
# `max_repair_chars`: json-repair's time grows with both (60 KB of text 30 levels deep took 3 s on
# this 2-core machine, 8 KB 0.3 s; a 48 KB plan with trailing commas, 4 levels, 12 ms).
REPAIR_LEVELS = 4


@dataclass
class RepairBudget:
    """How much malformed JSON a parse may still have repaired (characters times levels), over all its
    candidates and tool-call arguments: a text of many small, deep candidates is bounded too."""

    left: int

    def take(self, chars: int, levels: int) -> bool:
        work = chars * max(1, levels)
        if work > self.left:
            return False
        self.left -= work
        return True


def line_col(text: str, pos: int) -> str:
    line = text.count("\n", 0, pos) + 1
    column = pos - (text.rfind("\n", 0, pos) + 1) + 1
    return f"line {line}, column {column}"


def _scan(text: str, start: int, max_depth: int) -> _Span:
    """Match the bracket at `start`, skipping strings; refuse nesting deeper than `max_depth`."""
    stack: list[str] = []
    deepest = 0
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
            deepest = max(deepest, len(stack))
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
                return _Span(start, pos + 1, 0, deepest)
    return _Span(start, None, len(stack), deepest)


# Code blocks tried at most; a plan is in the first few, and a text of thousands is an attack.
MAX_CANDIDATES = 16


@dataclass(frozen=True)
class Candidate:
    """A decoded JSON value that looks like a plan, and the line it starts on."""

    value: Any
    warnings: list[str]
    line: int
    # Where the value's closing bracket ends, when text follows it; None when it is all the text (or block).
    end: int | None = None


@dataclass
class Found:
    """Every plan-like JSON value in a text, and the first error met on the way."""

    plans: list[Candidate]
    error: ParseError | None = None
    # The first JSON value that decoded but did not look like a plan.
    other: Any = None
    # True when the values were found inside prose rather than as the text or a code block.
    in_prose: bool = False


def fenced_blocks(text: str) -> list[tuple[str, int, str]]:
    """(language, offset of the body, body) for the first MAX_CANDIDATES fenced code blocks."""
    blocks: list[tuple[str, int, str]] = []
    if "`" not in text:  # most plans have no code block: one quick look for a backquote
        return blocks
    # An opening fence's line ends in a newline, so none starts after the last one. A regex search
    # would try there anyway, the rest of the text per backquote: a minute for a line of 250 KB of them.
    last_newline = text.rfind("\n")
    at = text.find("```")
    while 0 <= at < last_newline and len(blocks) < MAX_CANDIDATES:
        fence = _FENCE.match(text, at)
        if fence is None:
            break
        blocks.append((fence.group(1).lower(), fence.start(2), fence.group(2)))
        at = text.find("```", fence.end())
    return blocks


# JSON with every key given once, built once (json.loads builds a decoder per call). Only ever
# given text that starts with a bracket, so json.loads' check for a leading byte-order mark is moot.
_STRICT = json.JSONDecoder(object_pairs_hook=no_duplicate_keys)


class TruncatedJson(ParseError):
    """JSON whose brackets are still open where the text ends: output cut off."""


# Words that make an unclosed bracket in prose the start of a plan that was cut off.
_PLAN_WORDS = re.compile(r'["\'](?:action|plan|steps|actions|tasks)["\']\s*:')


class JsonFinder:
    """Locates and decodes the plan's JSON; lenient repair only for complete, small candidates."""

    def __init__(self, *, max_depth: int, lenient: bool, max_repair_chars: int) -> None:
        self.max_depth = max_depth
        self.lenient = lenient
        self.max_repair_chars = max_repair_chars

    def budget(self) -> RepairBudget:
        """What one parse may have repaired (see REPAIR_LEVELS)."""
        return RepairBudget(self.max_repair_chars * REPAIR_LEVELS)

    def find(self, text: str, looks_like_plan: Callable[[Any], bool], repairs: RepairBudget | None = None) -> Found:
        """The plan-like values: the bare text or fenced blocks if any start with a bracket, else prose.
        Repairs are taken from `repairs` (the parse's), or from a budget of this call's own."""
        repairs = repairs if repairs is not None else self.budget()
        starts: dict[int, int] = {}  # where each value starts -> where its text or block ends; ordered
        stripped = text.lstrip()
        if stripped[:1] in _CLOSERS:
            starts[len(text) - len(stripped)] = len(text)
        for _lang, body_at, body in fenced_blocks(text):
            offset = body_at + len(body) - len(body.lstrip())
            if text[offset : offset + 1] in _CLOSERS:
                starts[offset] = body_at + len(body)
        if not starts:
            return self._search_prose(text, looks_like_plan, repairs)
        found = Found(plans=[])
        for start, stop in starts.items():
            try:
                decoded = self._decode(text, start, repairs)
            except ParseError as exc:
                found.error = found.error or exc
                continue
            if decoded.end is not None:
                # One step per line ('{"action": ...}' twice) is several values: the ones after the
                # first are plans too, which must agree with it, not text to ignore.
                fence = text.find("```", decoded.end, stop) if "`" in text else -1
                rest = self._search_prose(text, looks_like_plan, repairs, decoded.end, stop if fence < 0 else fence)
                if isinstance(rest.error, TruncatedJson):
                    found.error = found.error or rest.error
                    continue
                found.plans.extend(rest.plans)
            if looks_like_plan(decoded.value):
                found.plans.append(decoded)
            elif found.other is None:
                found.other = decoded.value
        return found

    def _decode(self, text: str, start: int, repairs: RepairBudget) -> Candidate:
        """The JSON value that starts at `start`, and where it ends when text follows (`find` reads that text)."""
        fast = self._decode_whole(text, start)
        if fast is not None:
            return fast
        span = _scan(text, start, self.max_depth)
        if span.end is None:
            detail = self._json_error(text[start:], start, text)
            raise TruncatedJson(
                f"malformed JSON: {detail}; the text ends with {span.open_brackets} bracket(s) still open "
                "(was the output cut off?)"
            )
        chunk = text[start : span.end]
        line = text.count("\n", 0, start) + 1
        try:
            return Candidate(_STRICT.decode(chunk), [], line, span.end)
        except json.JSONDecodeError as exc:
            detail = f"{exc.msg} at {line_col(text, start + exc.pos)}"
        except (RecursionError, ValueError) as exc:
            raise ParseError(f"JSON could not be read at line {line}: {exc}") from None
        if not self.lenient or len(chunk) > self.max_repair_chars:
            raise ParseError(f"malformed JSON: {detail}")
        if not repairs.take(len(chunk), span.deepest):
            raise ParseError(
                f"malformed JSON: {detail} (not repaired: the plan's malformed JSON is too large or too "
                f"deeply nested to repair; {len(chunk)} characters {span.deepest} levels deep)"
            )
        try:
            value = self._repair(chunk)
        except (RecursionError, ValueError, TypeError) as exc:
            raise ParseError(f"malformed JSON: {detail} (repair failed: {exc})") from None
        if not isinstance(value, dict | list) or not value:
            raise ParseError(f"malformed JSON: {detail}")
        return Candidate(value, [f"the JSON was malformed ({detail}) and was read leniently"], line, span.end)

    @staticmethod
    def _repair(chunk: str) -> Any:
        """json-repair, except that a key given twice is refused rather than kept once."""
        try:
            return json_repair.loads(chunk, strict=True)
        except ValueError as exc:
            if "duplicate key" in str(exc).lower():
                raise ParseError("malformed JSON: a key appears twice in one object") from None
        return json_repair.loads(chunk)

    def _decode_whole(self, text: str, start: int) -> Candidate | None:
        """The common case first: everything from `start` up to a closing fence or the end is the JSON.

        None sends the caller to the bracket scan, which finds where the value ends and words the
        error; nesting is measured here only when there are enough brackets for it to matter.
        """
        # str.find of "```" reads the text much slower than a look for one character that is not there.
        end = text.find("```", start) if "`" in text else -1
        chunk = text[start : end if end >= 0 else len(text)]
        if chunk.count("[") + chunk.count("{") > self.max_depth:
            try:
                _scan(chunk, 0, self.max_depth)
            except ParseError:
                return None
        try:
            value = _STRICT.decode(chunk)
        except (ValueError, RecursionError):
            return None
        return Candidate(value, [], text.count("\n", 0, start) + 1)

    def _json_error(self, chunk: str, offset: int, text: str) -> str:
        try:
            json.loads(chunk)
        except json.JSONDecodeError as exc:
            return f"{exc.msg} at {line_col(text, offset + exc.pos)}"
        except (RecursionError, ValueError) as exc:
            return str(exc)
        return "unexpected end"

    def _search_prose(
        self,
        text: str,
        looks_like_plan: Callable[[Any], bool],
        repairs: RepairBudget,
        start: int = 0,
        stop: int | None = None,
    ) -> Found:
        """The plan-like values in `text[start:stop]`, which may sit among words."""
        found = Found(plans=[], in_prose=True)
        resume = 0
        for tries, match in enumerate(_OPENERS.finditer(text, start, len(text) if stop is None else stop)):
            if tries >= MAX_PROSE_STARTS or len(found.plans) >= MAX_CANDIDATES:
                break
            if match.start() < resume:
                continue
            try:
                decoded = self._decode(text, match.start(), repairs)
            except TruncatedJson as exc:
                if _PLAN_WORDS.search(text, match.start(), match.start() + 2000):
                    # A plan cut off: the complete steps inside it are not a plan of their own.
                    return Found(plans=[], error=exc, in_prose=True)
                continue
            except ParseError as exc:
                # Brackets in prose ("[see below]") are not JSON; keep the first real-looking failure.
                if found.error is None and '"action"' in text[match.start() : match.start() + 2000]:
                    found.error = exc
                continue
            span = _scan(text, match.start(), self.max_depth)
            resume = span.end or len(text)
            if looks_like_plan(decoded.value):
                found.plans.append(decoded)
            elif found.other is None:
                found.other = decoded.value
        return found
