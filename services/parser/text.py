"""Plans written as English lists ("1. Go to the kitchen") -> step fields, or a refusal with line and column."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Annotated, Any

import msgspec
from msgspec import Meta
from rapidfuzz import fuzz, process

from schemas.common import ErrorKind
from schemas.plan import MAX_NESTING, MAX_PLAN_BYTES, MAX_STEPS, Action
from services.datafile import read_struct
from services.parser.errors import ParseError, VocabularyError

# Longer list items and clauses are refused before any pattern is tried: this bounds regex work.
MAX_ITEM_CHARS = 4000
MAX_CLAUSE_CHARS = 1100
ECHO_CHARS = 60
MAX_SUGGESTIONS = 3
SUGGEST_SCORE = 60
MAX_LISTED_LINES = 10
# How far past a separator we look for the verb that decides whether to split there.
_LOOKAHEAD = 100

Phrase = Annotated[str, Meta(min_length=1, max_length=64)]
PatternText = Annotated[str, Meta(min_length=1, max_length=1000)]
Example = Annotated[str, Meta(min_length=1, max_length=200)]
Digits = Annotated[str, Meta(pattern=r"^[0-9]+(\.[0-9]+)?$")]


# The grammar file (grammar.yaml documents the pattern syntax).


class PatternEntry(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A pattern that also stores what its words imply ("turn around": angle 180 degrees)."""

    pattern: PatternText
    set: dict[Phrase, Phrase] = {}


class RefusalEntry(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    pattern: PatternText
    reason: Annotated[str, Meta(min_length=1, max_length=1000)]


class ActionGrammar(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    examples: Annotated[list[Example], Meta(min_length=1)]
    patterns: Annotated[list[PatternText | PatternEntry], Meta(min_length=1)]


class StepTemplate(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """One step an expansion stands for. "{target}" and "{location}" are what the clause's slots read;
    any other text is kept as written ("me"); a slot the clause left out leaves the field out."""

    action: Action
    target: Phrase | None = None
    location: Phrase | None = None
    set: dict[Phrase, Phrase] = {}


class ExpansionEntry(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A clause that means several steps ("bring me the cup": pick it, put it by the person), or,
    with `reason` instead of `steps`, a clause of that kind refused with a reason of its own."""

    pattern: PatternText
    steps: Annotated[list[StepTemplate], Meta(max_length=8)] = []
    reason: Annotated[str, Meta(max_length=1000)] = ""


class ExpansionGrammar(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    examples: Annotated[list[Example], Meta(min_length=1)]
    patterns: Annotated[list[ExpansionEntry], Meta(min_length=1)]


class GrammarFile(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    actions: dict[Action, ActionGrammar]
    fillers: list[Phrase] = []
    trailing_fillers: list[Phrase] = []
    articles: list[Phrase] = []
    determiners: list[Phrase] = []
    not_in_names: list[Phrase] = []
    on_failure: list[Phrase] = []
    numbers: dict[Phrase, Digits] = {}
    quantities: dict[Phrase, list[Phrase]] = {}
    # The quantity whose unit words a number of a {point} may carry ("(3.5 m, 2 m)").
    point_quantity: Phrase | None = None
    refusals: list[RefusalEntry] = []
    # Never the first word of a noun phrase: "get to the kitchen" names no object "to the kitchen".
    not_first_in_names: list[Phrase] = []
    # Clauses that stand for several steps, tried before the actions' patterns.
    expansions: dict[Phrase, ExpansionGrammar] = {}
    # Phrases that may end a clause with a hint ("carefully", "with a pinch grasp"), read off its end
    # only when the whole clause matches no pattern.
    hints: list[PatternText | PatternEntry] = []


@dataclass(frozen=True)
class TextStep:
    """One clause read from the text: the step fields the structured parser validates, and where it was.

    A group (a list item with sub-items) has empty `fields`, the item's text as `description` and
    its sub-items as `substeps`. `on_failure` holds the clauses introduced by "if that fails".
    """

    fields: dict[str, Any]
    line: int
    column: int
    description: str
    substeps: tuple[TextStep, ...] = ()
    on_failure: tuple[TextStep, ...] = ()


# Compiling patterns

_NOUN = r"(?=[^\W_])[\w'\u2019&#/+-]+(?: [\w'\u2019&#/+-]+)*?"
_QUOTED = r"[\"\u201c'\u2018].+[\"\u201d'\u2019]"
_NUMBER = r"[-+]?(?:\d+(?:\.\d+)?|\.\d+)"
_NAME = re.compile(r"[a-z][a-z0-9_]*")
_UNNAMED = re.compile(r"\(\?P<\w+>")
_HEAD_END = r"(?=[\s,;:.!?]|$)"
_TOKEN = re.compile(r"\s+|[\[\]()|]|\{[^{}]*\}|[^\s\[\](){}|]+")
_NOUN_SLOTS = {"target": "target", "location": "target_location"}
# A {point} becomes this parameter: a list of the numbers as written, which the parser checks.
POINT_PARAM = "point"
_RESERVED_SLOTS = ("target", "location", "text", "point")
_CLOSING_QUOTES = {'"': '"\u201d', "\u201c": '"\u201d', "'": "'\u2019", "\u2018": "'\u2019"}


class _PatternProblem(Exception):
    """A pattern in the grammar file that cannot be compiled; the loader adds file and entry."""


@dataclass(frozen=True)
class _Slot:
    group: str
    kind: str  # noun, text, quantity or choice
    name: str  # field or parameter it fills
    choices: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class _Pattern:
    action: str  # canonical action name; "" for a refusal or an expansion
    regex: re.Pattern[str]
    slots: tuple[_Slot, ...]
    fixed: tuple[tuple[str, str], ...] = ()
    reason: str = ""
    steps: tuple[StepTemplate, ...] = ()  # an expansion's steps


@dataclass(frozen=True)
class _Fragment:
    regex: str  # every fragment carries its own leading space
    firsts: frozenset[str] | None  # the words it can start with; None: it cannot start a pattern
    pure: bool  # only words and choices, nothing optional: part of the verb phrase's head
    literal: bool  # only words


def _alternation(options: list[str]) -> str:
    return "(?:" + "|".join(sorted(options, key=len, reverse=True)) + ")"


def _phrase_regex(phrase: str, space: str) -> str:
    return space.join(re.escape(word) for word in phrase.lower().split())


class _PatternCompiler:
    """Recursive descent over one pattern's tokens, producing an anchored regex and its slots."""

    def __init__(self, text: str, quantities: dict[str, str], point: str) -> None:
        pieces = [m.group() for m in _TOKEN.finditer(text)]
        if "".join(pieces) != text:
            raise _PatternProblem("unbalanced '{' or '}'")
        self.tokens = [p for p in pieces if not p.isspace()]
        self.pos = 0
        self.quantities = quantities
        self.point = point
        self.slots: list[_Slot] = []

    def compile(self, *, verb: bool = True) -> tuple[str, str, frozenset[str]]:
        """(regex, head regex, first words). A hint (`verb` False) may start with anything."""
        fragments = self._sequence(in_parens=False)
        if self.pos != len(self.tokens):
            raise _PatternProblem(f"unexpected {self.tokens[self.pos]!r}")
        if not fragments:
            raise _PatternProblem("empty pattern")
        if not verb:
            return "".join(f.regex for f in fragments), "", frozenset()
        if fragments[0].firsts is None:
            raise _PatternProblem("a pattern must start with a word (its verb)")
        firsts = fragments[0].firsts
        head = ""
        for fragment in fragments:
            if not fragment.pure:
                break
            head += fragment.regex
        if not head:
            head = r"\ " + _alternation([re.escape(w) for w in firsts])
        return "".join(f.regex for f in fragments), head, firsts

    def _peek(self) -> str | None:
        return self.tokens[self.pos] if self.pos < len(self.tokens) else None

    def _take(self, expected: str | None = None) -> str:
        token = self._peek()
        if token is None or (expected is not None and token != expected):
            raise _PatternProblem(f"expected {expected!r}" if expected else "unexpected end of pattern")
        self.pos += 1
        return token

    def _sequence(self, *, in_parens: bool) -> list[_Fragment]:
        fragments: list[_Fragment] = []
        while (token := self._peek()) is not None and token not in (")", "]"):
            if token == "|":
                if in_parens:
                    break
                raise _PatternProblem("'|' must stand between two words (use parentheses for phrases)")
            fragments.append(self._item(in_parens=in_parens))
        return fragments

    def _item(self, *, in_parens: bool) -> _Fragment:
        token = self._take()
        if token == "[":
            inner = self._sequence(in_parens=False)
            self._take("]")
            if not inner:
                raise _PatternProblem("empty []")
            return _Fragment("(?:" + "".join(f.regex for f in inner) + ")?", None, False, False)
        if token == "(":
            options = [self._sequence(in_parens=True)]
            while self._peek() == "|":
                self._take()
                options.append(self._sequence(in_parens=True))
            self._take(")")
            if not all(options):
                raise _PatternProblem("empty alternative in ()")
            regexes = ["".join(f.regex for f in option) for option in options]
            literal = all(f.literal for option in options for f in option)
            firsts: frozenset[str] | None = frozenset()
            for option in options:
                if firsts is None or option[0].firsts is None:
                    firsts = None
                else:
                    firsts |= option[0].firsts
            body = _alternation(regexes) if literal else "(?:" + "|".join(regexes) + ")"
            return _Fragment(body, firsts, all(f.pure for option in options for f in option), literal)
        if token.startswith("{"):
            return self._slot(token[1:-1].strip())
        if token in (")", "]", "|"):
            raise _PatternProblem(f"unexpected {token!r}")
        words = [token.lower()]
        while not in_parens and self._peek() == "|":
            self._take()
            word = self._take()
            if word in ("(", ")", "[", "]", "|") or word.startswith("{"):
                raise _PatternProblem("'|' must stand between two words (use parentheses for phrases)")
            words.append(word.lower())
        return _Fragment(r"\ " + _alternation([re.escape(w) for w in words]), frozenset(words), True, True)

    def _named(self, name: str) -> str:
        if not _NAME.fullmatch(name):
            raise _PatternProblem(f"slot name {name!r} must be lower-case letters, digits and _")
        if any(slot.name == name for slot in self.slots):
            raise _PatternProblem(f"slot {name!r} is used twice")
        return name

    def _slot(self, body: str) -> _Fragment:
        if body == "_":
            return _Fragment(rf"\ (?:{_NOUN})", None, False, False)
        if len(body) > 2 and body[0] == body[-1] == '"':
            name = self._named(body[1:-1])
            if name != "text":
                raise _PatternProblem('only {"text"} can be quoted')
            self.slots.append(_Slot(name, "text", name))
            return _Fragment(rf"\ (?P<{name}>{_QUOTED})", None, False, False)
        if ":" in body:
            name, _, options = body.partition(":")
            name = self._named(name.strip())
            choices: dict[str, str] = {}
            for option in options.split("|"):
                written, _, stored = option.partition("=")
                written, stored = " ".join(written.split()).lower(), " ".join(stored.split()).lower()
                if not written:
                    raise _PatternProblem(f"empty choice in {{{body}}}")
                choices[written] = stored or written
            self.slots.append(_Slot(name, "choice", name, choices))
            regex = rf"\ (?P<{name}>" + _alternation([_phrase_regex(c, " ") for c in choices]) + ")"
            return _Fragment(regex, frozenset(c.split(" ")[0] for c in choices), True, False)
        name = self._named(body)
        if name in _NOUN_SLOTS:
            self.slots.append(_Slot(name, "noun", _NOUN_SLOTS[name]))
            return _Fragment(rf"\ (?P<{name}>{_NOUN})", None, False, False)
        if name == "text":
            self.slots.append(_Slot(name, "text", name))
            return _Fragment(r"\ (?P<text>.+)", None, False, False)
        if name == "point":
            self.slots.append(_Slot(name, "point", POINT_PARAM))
            return _Fragment(rf"\ (?P<point>{self.point})", None, False, False)
        if name in self.quantities:
            self.slots.append(_Slot(name, "quantity", name))
            return _Fragment(rf"\ (?P<{name}>{self.quantities[name]})", None, False, False)
        known = ", ".join([*_RESERVED_SLOTS, "_", *self.quantities])
        raise _PatternProblem(f"unknown slot {{{body}}}; slots are {known} and {{name:a|b}} choices")


class TextGrammar:
    """The grammar file compiled: patterns indexed by their verb, word lists as anchored regexes."""

    def __init__(self, spec: GrammarFile, source: str = "<grammar>") -> None:
        self.spec = spec
        self.source = source
        self.articles = frozenset(w.lower() for w in spec.articles)
        self.determiners = frozenset(w.lower() for w in spec.determiners) | self.articles
        self.not_in_names = frozenset(w.lower() for w in spec.not_in_names)
        self.not_first_in_names = frozenset(w.lower() for w in spec.not_first_in_names)
        self.trailing_fillers = tuple(" " + " ".join(w.lower().split()) for w in spec.trailing_fillers)
        numbers = ((" ".join(w.lower().split()), d) for w, d in spec.numbers.items())
        self.numbers = sorted(numbers, key=lambda pair: len(pair[0]), reverse=True)
        spaces = r"[ \t]+"
        fillers = _alternation([_phrase_regex(w, spaces) for w in spec.fillers]) if spec.fillers else "(?!)"
        markers = _alternation([_phrase_regex(w, spaces) for w in spec.on_failure]) if spec.on_failure else "(?!)"
        self.filler = re.compile(rf"[ \t]*{fillers}(?:[ \t]*[,:])?(?=[\s.!?;]|$)", re.IGNORECASE)
        self.marker = re.compile(rf"[ \t]*{markers}(?:[ \t]*[,:])?(?=[\s.!?;]|$)", re.IGNORECASE)
        number = _alternation([_NUMBER, *(_phrase_regex(w, " ") for w, _ in self.numbers)])
        quantities: dict[str, str] = {}
        for name, units in spec.quantities.items():
            if not _NAME.fullmatch(name) or name in _RESERVED_SLOTS:
                raise self._error(
                    f"quantities.{name}", f"a quantity needs a lower-case name other than {'/'.join(_RESERVED_SLOTS)}"
                )
            quantities[name] = number + _units(units)
        point_units: list[str] = []
        if spec.point_quantity is not None:
            if spec.point_quantity not in spec.quantities:
                raise self._error("point_quantity", f"{spec.point_quantity!r} is not one of the quantities")
            point_units = spec.quantities[spec.point_quantity]
        self.point, self.point_numbers = _point_regexes(_units(point_units))
        self.patterns: dict[str, list[_Pattern]] = {}
        self.refusals: dict[str, list[_Pattern]] = {}
        # The examples of each action or expansion a verb starts, shown when its clause cannot be read.
        self.examples_by_verb: dict[str, list[list[str]]] = {}
        heads: dict[str, list[str]] = {}
        for index, refusal in enumerate(spec.refusals):
            entry = f"refusals[{index}] {refusal.pattern!r}"
            pattern, head, firsts = self._compile(entry, refusal.pattern, quantities, None, {})
            pattern = _Pattern("", pattern.regex, pattern.slots, reason=" ".join(refusal.reason.split()))
            for word in firsts:
                self.refusals.setdefault(word, []).append(pattern)
                heads.setdefault(word, []).append(head)
        # Expansions first: "take the cup to the kitchen" is two steps, not a pick of "cup to the kitchen".
        for name, expansion in spec.expansions.items():
            for index, item in enumerate(expansion.patterns):
                entry = f"expansions.{name}.patterns[{index}] {item.pattern!r}"
                pattern, head, firsts = self._compile(entry, item.pattern, quantities, None, {})
                pattern = self._expansion(entry, pattern, item)
                self._index(pattern, head, firsts, heads, expansion.examples)
        for action, grammar in spec.actions.items():
            for index, action_item in enumerate(grammar.patterns):
                text, fixed = (
                    (action_item, {}) if isinstance(action_item, str) else (action_item.pattern, action_item.set)
                )
                entry = f"actions.{action.value}.patterns[{index}] {text!r}"
                pattern, head, firsts = self._compile(entry, text, quantities, action, fixed)
                self._index(pattern, head, firsts, heads, grammar.examples)
        # Verbs that start only expansions: over sub-items, such a heading names what they do.
        self.summary_verbs = frozenset(w for w, ps in self.patterns.items() if all(not p.action for p in ps))
        self.hints: list[_Pattern] = []
        for index, hint in enumerate(spec.hints):
            text, fixed = (hint, {}) if isinstance(hint, str) else (hint.pattern, hint.set)
            self.hints.append(self._hint(f"hints[{index}] {text!r}", text, quantities, fixed))
        # Heads only answer "does a step start here", so their slots need no names (which would clash).
        self.heads = {
            w: re.compile(_alternation(sorted({_UNNAMED.sub("(?:", x) for x in h})) + _HEAD_END, re.IGNORECASE)
            for w, h in heads.items()
        }
        self.verbs = sorted({w.rstrip(":") for w in self.patterns})
        general = [g.examples[0] for a, g in spec.actions.items() if a in (Action.NAVIGATE_TO, Action.PICK)]
        self.general_examples = _examples(general or [g.examples[0] for g in list(spec.actions.values())[:2]])

    def _error(self, entry: str, problem: str) -> VocabularyError:
        return VocabularyError(f"grammar file {self.source}: {entry}: {problem}")

    def _index(
        self, pattern: _Pattern, head: str, firsts: frozenset[str], heads: dict[str, list[str]], examples: list[str]
    ) -> None:
        for word in firsts:
            self.patterns.setdefault(word, []).append(pattern)
            heads.setdefault(word, []).append(head)
            groups = self.examples_by_verb.setdefault(word, [])
            if examples not in groups:
                groups.append(examples)

    def _expansion(self, entry: str, pattern: _Pattern, item: ExpansionEntry) -> _Pattern:
        if bool(item.steps) == bool(item.reason.strip()):
            raise self._error(entry, "an expansion has either `steps` or a `reason`")
        kinds = {slot.name: slot.kind for slot in pattern.slots}
        if any(kind != "noun" for kind in kinds.values()):
            raise self._error(entry, "an expansion's pattern may only have {target}, {location} and {_} slots")
        for template in item.steps:
            for value in (template.target, template.location, *template.set.values()):
                slot = _slot_reference(value)
                if slot is not None and _NOUN_SLOTS.get(slot) not in kinds:
                    raise self._error(entry, f"step {template.action.value}: {value!r} is not a slot of the pattern")
        return _Pattern("", pattern.regex, pattern.slots, reason=" ".join(item.reason.split()), steps=tuple(item.steps))

    def _hint(self, entry: str, text: str, quantities: dict[str, str], fixed: dict[str, str]) -> _Pattern:
        try:
            compiler = _PatternCompiler(text, quantities, self.point)
            regex, _, _ = compiler.compile(verb=False)
            # At the end of the clause, perhaps after a comma: "go to the kitchen, carefully".
            compiled = re.compile(f",?{regex}$", re.IGNORECASE)
        except _PatternProblem as exc:
            raise self._error(entry, str(exc)) from None
        except re.error as exc:
            raise self._error(entry, f"does not compile: {exc}") from None
        if any(slot.kind not in ("quantity", "choice") for slot in compiler.slots):
            raise self._error(entry, "a hint may only have quantity and {name:a|b} slots")
        if any(name in _NOUN_SLOTS for name in fixed):
            raise self._error(entry, "a hint sets parameters only, never a target or location")
        return _Pattern("", compiled, tuple(compiler.slots), tuple(fixed.items()))

    def _compile(
        self, entry: str, text: str, quantities: dict[str, str], action: Action | None, fixed: dict[str, str]
    ) -> tuple[_Pattern, str, frozenset[str]]:
        try:
            compiler = _PatternCompiler(text, quantities, self.point)
            regex, head, firsts = compiler.compile()
            compiled = re.compile(regex, re.IGNORECASE)
        except _PatternProblem as exc:
            raise self._error(entry, str(exc)) from None
        except re.error as exc:
            raise self._error(entry, f"does not compile: {exc}") from None
        for name in fixed:
            if not _NAME.fullmatch(name):
                raise self._error(entry, f"set: {name!r} must be lower-case letters, digits and _")
            if any(slot.name == name or slot.group == name for slot in compiler.slots):
                raise self._error(entry, f"set: {name!r} is also a slot of the pattern")
        name = action.value if action is not None else ""
        return _Pattern(name, compiled, tuple(compiler.slots), tuple(fixed.items())), head, firsts

    # Reading one list item

    def skip_fillers(self, text: str, pos: int, end: int) -> int:
        while (match := self.filler.match(text, pos, end)) is not None:
            pos = match.end()
        while pos < end and text[pos] in " \t":
            pos += 1
        return pos

    def starts_step(self, text: str, pos: int) -> bool:
        """Whether a verb phrase (or "if that fails") starts at `pos`: where " and " or "," splits clauses."""
        end = min(len(text), pos + _LOOKAHEAD)
        pos = self.skip_fillers(text, pos, end)
        if self.marker.match(text, pos, end):
            return True
        words = text[pos:end].split()
        heads = self.heads.get(words[0].rstrip(",;:.!?").lower()) if words else None
        return heads is not None and heads.match(" " + " ".join(words)) is not None

    def read_clause(self, clause: str, line: int, column: int, tail: str = "") -> list[dict[str, Any]]:
        """The step fields of one clause (whitespace collapsed, fillers removed), or a refusal.

        One clause is one step, or several when it is an expansion ("bring me the cup"). Hints at its
        end ("carefully") are read off only when the whole clause matches nothing, and go into the
        parameters of each of its steps. `tail` is the "?" or "!" trimmed off the clause, given back
        to a spoken text that ends it.
        """
        if self.hints:
            rest, hinted = self._without_hints(clause)
            # Spoken words are kept whole: "say drive carefully" is not a hint.
            if hinted and (found := self._match(rest, clause, line, column, "")) is not None and not found[0]:
                for fields in found[1]:
                    params = fields.setdefault("parameters", {})
                    for name, value in hinted.items():
                        params.setdefault(name, value)
                return found[1]
        whole = self._match(clause, clause, line, column, tail)
        if whole is not None:
            return whole[1]
        verb = clause.split(" ", 1)[0].lower()
        if verb not in self.patterns:
            near = process.extract(
                verb[:ECHO_CHARS], self.verbs, scorer=fuzz.ratio, limit=MAX_SUGGESTIONS, score_cutoff=SUGGEST_SCORE
            )
            suggestions = [choice for choice, _, _ in near]
            hint = f" (did you mean {suggestions[0]!r}?)" if suggestions else ""
            raise ParseError(
                f"cannot read {echo(clause)}: unknown verb {echo(verb)}{hint}; expected a step such as "
                f"{self.general_examples}; known verbs: {', '.join(self.verbs)}",
                kind=ErrorKind.UNKNOWN_ACTION,
                candidates=suggestions,
                **_at(line, column),
            )
        groups = self.examples_by_verb[verb]
        examples = groups[0] if len(groups) == 1 else [group[0] for group in groups]
        raise ParseError(
            f"cannot read {echo(clause)}: expected a step such as {_examples(examples[:3])}", **_at(line, column)
        )

    def _match(
        self, clause: str, written: str, line: int, column: int, tail: str
    ) -> tuple[bool, list[dict[str, Any]]] | None:
        """The steps of the first pattern `clause` matches whole, and whether that pattern reads free text;
        None if none matches. Refusals raise."""
        verb = clause.split(" ", 1)[0].lower()
        subject = " " + clause
        for refusal in self.refusals.get(verb, ()):
            if refusal.regex.fullmatch(subject):
                raise ParseError(f"cannot read {echo(written)}: {refusal.reason}", **_at(line, column))
        for pattern in self.patterns.get(verb, ()):
            match = pattern.regex.fullmatch(subject)
            if match is None or (fields := self._fields(pattern, match, tail)) is None:
                continue
            if pattern.reason:
                reason = pattern.reason.format_map(_Slots(fields))
                raise ParseError(f"cannot read {echo(written)}: {reason}", **_at(line, column))
            if pattern.steps:
                return False, [_expanded(template, fields) for template in pattern.steps]
            return any(slot.kind == "text" for slot in pattern.slots), [fields]
        return None

    def _without_hints(self, clause: str) -> tuple[str, dict[str, Any]]:
        """The clause with the hints at its end read off, and the parameters they give."""
        subject = " " + clause
        hinted: dict[str, Any] = {}
        for _ in range(len(self.hints)):
            for hint in self.hints:
                match = hint.regex.search(subject)
                if match is None or not subject[: match.start()].strip():
                    continue
                fields = self._fields(hint, match, "") or {}
                for name, value in fields.get("parameters", {}).items():
                    hinted.setdefault(name, value)
                subject = subject[: match.start()].rstrip(" ,")
                break
            else:
                break
        return subject.strip(), hinted

    def _fields(self, pattern: _Pattern, match: re.Match[str], tail: str) -> dict[str, Any] | None:
        fields: dict[str, Any] = {"action": pattern.action}
        params: dict[str, Any] = {}
        for slot in pattern.slots:
            value = match.group(slot.group)
            if value is None:
                continue
            if slot.kind == "noun":
                words = value.lower().split(" ")
                if words[0] in self.not_first_in_names:
                    return None
                if len(words) > 1 and words[0] in self.determiners:
                    words = words[1:]
                elif words[0] in self.articles:
                    return None
                if not self.not_in_names.isdisjoint(words):
                    return None
                fields[slot.name] = " ".join(words)
                continue
            if slot.kind == "text":
                unquoted = _unquoted(value)
                if unquoted == value.strip() and match.end(slot.group) == match.endpos:
                    unquoted += tail
                value = unquoted
                if not value:
                    return None
            elif slot.kind == "quantity":
                value = self._digits(value)
            elif slot.kind == "choice":
                value = slot.choices[value.lower()]
            elif slot.kind == "point":
                params[slot.name] = [m.group("number") for m in self.point_numbers.finditer(value)]
                continue
            params[slot.name] = value
        for name, value in pattern.fixed:
            if name in _NOUN_SLOTS:
                fields[_NOUN_SLOTS[name]] = value
            else:
                params[name] = value
        if params:
            fields["parameters"] = params
        return fields

    def _digits(self, quantity: str) -> str:
        """'two seconds' -> '2 seconds'; numbers written with digits are kept as written."""
        if quantity[0].isalpha():
            lowered = quantity.lower()
            for word, digits in self.numbers:
                if lowered.startswith(word) and (len(lowered) == len(word) or not lowered[len(word)].isalpha()):
                    return digits + quantity[len(word) :]
        return quantity


class _Slots(dict[str, str]):
    """What a refusal's reason may name: "{target}" is the clause's target; a missing slot stays as written."""

    def __init__(self, fields: dict[str, Any]) -> None:
        super().__init__({slot: _cut(str(fields[name])) for slot, name in _NOUN_SLOTS.items() if name in fields})

    def __missing__(self, key: str) -> str:
        return "{" + key + "}"


def _slot_reference(value: str | None) -> str | None:
    """'target' for "{target}"; None for text kept as written."""
    if value is not None and len(value) > 2 and value[0] == "{" and value[-1] == "}":
        return value[1:-1].strip()
    return None


def _expanded(template: StepTemplate, read: dict[str, Any]) -> dict[str, Any]:
    """One step of an expansion: the template's fields, with the slots the clause read filled in."""
    fields: dict[str, Any] = {"action": template.action.value}
    params: dict[str, Any] = {}
    for name, value in (("target", template.target), ("target_location", template.location), *template.set.items()):
        if value is None:
            continue
        slot = _slot_reference(value)
        if slot is not None:
            value = read.get(_NOUN_SLOTS[slot])
            if value is None:  # the clause left it out: so does the step, which the parser then checks
                continue
        if name in ("target", "target_location"):
            fields[name] = value
        else:
            params[name] = value
    if params:
        fields["parameters"] = params
    return fields


def _units(words: list[str]) -> str:
    """An optional unit word after a number ("30 cm", "30cm")."""
    return f"(?: ?{_alternation([_phrase_regex(u, ' ') for u in words])})?" if words else ""


def _point_regexes(units: str) -> tuple[str, re.Pattern[str]]:
    """A {point}: "(3.5, 2.0)", "3.5, 2.0, 0.7", "x 3.5 y 2", "[x=3.5, y=2 m]"; and the regex that finds its numbers.

    Two or three numbers, each optionally with a unit; labelled x, y, z in that order, or not at all.
    """
    number = rf"{_NUMBER}{units}"
    plain = rf"{number} ?, ?{number}(?: ?, ?{number})?"
    labelled = rf"x ?[:=]? ?{number}(?:, ?| )y ?[:=]? ?{number}(?:(?:, ?| )z ?[:=]? ?{number})?"
    inner = f"(?:{plain}|{labelled})"
    point = rf"(?:\( ?{inner} ?\)|\[ ?{inner} ?\]|{inner})"
    return point, re.compile(rf"(?P<number>{number})", re.IGNORECASE)


def _examples(examples: list[str]) -> str:
    quoted = [f"'{e}'" for e in examples]
    return quoted[0] if len(quoted) == 1 else ", ".join(quoted[:-1]) + " or " + quoted[-1]


def _unquoted(text: str) -> str:
    text = text.strip()
    if len(text) >= 2 and text[-1] in _CLOSING_QUOTES.get(text[0], ""):
        return text[1:-1].strip()
    return text


def _cut(text: str) -> str:
    return text if len(text) <= ECHO_CHARS else text[:ECHO_CHARS] + "..."


def echo(text: str) -> str:
    """Quoted, and cut so hostile input cannot bloat a refusal."""
    return repr(text if len(text) <= ECHO_CHARS else text[:ECHO_CHARS] + "...")


def _at(line: int, column: int) -> dict[str, Any]:
    return {"where": f"line {line}, column {column}", "line": line, "column": column}


def default_grammar_path() -> Path:
    return Path(str(resources.files("services") / "parser" / "grammar.yaml"))


def load_grammar(path: Path | None = None) -> TextGrammar:
    """The bundled grammar, or the one at `path`; VocabularyError names the file and the bad entry."""
    path = path or default_grammar_path()
    return TextGrammar(read_struct(path, GrammarFile, "grammar", VocabularyError), str(path))


# Reading the whole text

# A list item's marker: "1." "1)" "(1)" "Step 1:" "a." "(a)" "-" "*" "•" "+", optionally in bold.
_ITEM = re.compile(
    r"(?P<indent>[ \t]*)(?:\*\*|__)?"
    r"(?:(?P<numbered>(?:step|task)[ \t]+\d{1,4}(?:\*\*|__)?[ \t]*[:.)\-\u2013\u2014]|\d{1,4}[.)]|\(\d{1,4}\))"
    r"|(?P<lettered>[a-z][.)]|\([a-z]\))"
    r"|(?P<bullet>[-*\u2022+]))"
    r"(?:\*\*|__)?(?:[ \t]+|$)",
    re.IGNORECASE,
)
# A sub-item of the same indentation is one of a lower rank: lettered under numbered, bullets under both.
_RANK = {"numbered": 0, "lettered": 1, "bullet": 2, "sentence": 0}
_LINE_BREAK = re.compile(r"\r\n|\r|\n")
_MARKUP = re.compile(r"\*\*|__|`")
_QUOTATION = re.compile(
    r"\"[^\"\n]*\"|\u201c[^\u201d\n]*\u201d|(?<!\w)'[^'\n]*'(?!\w)|(?<!\w)\u2018[^\u2019\n]*\u2019(?!\w)"
)
# Clause separators. `then` and `soft` split only where a verb phrase follows; a conditional
# ("if that fails, ...") runs on over soft separators but ends at a hard one.
_SEPARATOR = re.compile(
    r"(?P<hard>;|,[ \t]*(?:and[ \t]+)?then(?=[ \t])|(?<![ \t])[ \t]+and[ \t]+then(?=[ \t])|[.!?](?=[ \t]))"
    r"|(?P<then>(?<![ \t])[ \t]+then(?=[ \t]))"
    r"|(?P<soft>,(?:[ \t]*and(?=[ \t]))?|(?<![ \t])[ \t]+and(?=[ \t]))",
    re.IGNORECASE,
)


@dataclass
class _Item:
    line: int
    column: int  # of the text after the marker
    indent: int
    kind: str
    text: str  # markup blanked out, so offsets still match the line
    written: str | None = None  # the text as on the line, markup included (list items only)
    children: list[_Item] = field(default_factory=list)

    @property
    def start(self) -> int:
        """Column of the first character of the text."""
        return self.column + len(self.text) - len(self.text.lstrip())

    @property
    def heading(self) -> str:
        """The text as written, without markup: a group's description."""
        return " ".join(_MARKUP.sub("", self.text if self.written is None else self.written).split())


@dataclass
class _Clause:
    steps: list[dict[str, Any]]  # one step's fields, or an expansion's steps
    line: int
    column: int
    description: str
    hard: bool  # preceded by a hard separator, or first in its item
    marker: str = ""  # the "if that fails" that makes it a fallback of the step before


@dataclass(eq=False)
class _Node:
    fields: dict[str, Any]
    line: int
    column: int
    description: str
    depth: int
    substeps: list[_Node] = field(default_factory=list)
    on_failure: list[_Node] = field(default_factory=list)

    def frozen(self) -> TextStep:
        return TextStep(
            self.fields,
            self.line,
            self.column,
            self.description,
            tuple(n.frozen() for n in self.substeps),
            tuple(n.frozen() for n in self.on_failure),
        )


def _blank_markup(text: str) -> str:
    return _MARKUP.sub(lambda m: " " * len(m.group()), text) if ("*" in text or "_" in text or "`" in text) else text


def _line_numbers(numbers: list[int]) -> str:
    shown = ", ".join(map(str, numbers[:MAX_LISTED_LINES]))
    return shown if len(numbers) <= MAX_LISTED_LINES else f"{shown} and {len(numbers) - MAX_LISTED_LINES} more"


class _Reader:
    """One read of one text: counts steps, tracks nesting, collects warnings."""

    def __init__(self, grammar: TextGrammar, max_steps: int, max_depth: int) -> None:
        self.grammar = grammar
        self.max_steps = max_steps
        self.max_depth = max_depth
        self.steps = 0
        self.warnings: list[str] = []

    def _too_many(self, line: int, column: int) -> ParseError:
        return ParseError(
            f"the plan has more than {self.max_steps} steps (sub-steps and fallbacks included); "
            f"at most {self.max_steps} are accepted, so split the task",
            **_at(line, column),
        )

    def _too_deep(self, depth: int, line: int, column: int) -> ParseError:
        return ParseError(
            f"steps are nested {depth} levels deep here; at most {self.max_depth} levels of sub-items "
            "and fallbacks are accepted",
            **_at(line, column),
        )

    # Lines -> items

    def items(self, text: str) -> list[_Item]:
        lines = _LINE_BREAK.split(text)
        roots: list[_Item] = []
        stack: list[_Item] = []
        before: list[int] = []
        after: list[int] = []
        count = 0
        for number, line in enumerate(lines, 1):
            if not line or line.isspace():
                continue
            match = _ITEM.match(line)
            if match is None:
                (after if roots else before).append(number)
                continue
            if after:
                bad = lines[after[0] - 1]
                raise ParseError(
                    f"cannot read {echo(bad.strip())} between list items: expected a list item such as "
                    "'2. pick up the red cup', or an empty line",
                    **_at(after[0], len(bad) - len(bad.lstrip()) + 1),
                )
            item_text = line[match.end() :]
            item = _Item(number, match.end() + 1, len(match.group("indent").expandtabs(4)), str(match.lastgroup), "")
            count += 1
            if count > self.max_steps:
                raise self._too_many(number, item.column)
            if len(item_text) > MAX_ITEM_CHARS:
                raise ParseError(
                    f"list item is {len(item_text)} characters; at most {MAX_ITEM_CHARS}", **_at(number, 1)
                )
            item.text, item.written = _blank_markup(item_text), item_text
            while stack and not (
                item.indent > stack[-1].indent
                or (item.indent == stack[-1].indent and _RANK[item.kind] > _RANK[stack[-1].kind])
            ):
                stack.pop()
            if len(stack) > self.max_depth:
                raise self._too_deep(len(stack), number, item.column)
            (stack[-1].children if stack else roots).append(item)
            stack.append(item)
        if not roots:
            return self._sentences(lines)
        for skipped, where in ((before, "before"), (after, "after")):
            if skipped:
                first = lines[skipped[0] - 1].strip()
                self.warnings.append(
                    f"line(s) {_line_numbers(skipped)} {where} the list skipped: not list items ({echo(first)})"
                )
        return roots

    def _sentences(self, lines: list[str]) -> list[_Item]:
        """No list at all: every line is read like a list item, so each sentence is a step."""
        items: list[_Item] = []
        for number, line in enumerate(lines, 1):
            if not line or line.isspace():
                continue
            if len(items) >= self.max_steps:
                raise self._too_many(number, len(line) - len(line.lstrip()) + 1)
            if len(line) > MAX_ITEM_CHARS:
                raise ParseError(f"line is {len(line)} characters; at most {MAX_ITEM_CHARS}", **_at(number, 1))
            items.append(_Item(number, 1, 0, "sentence", _blank_markup(line)))
        return items

    # Items -> clauses

    def clauses(self, item: _Item) -> list[_Clause]:
        grammar, text = self.grammar, item.text
        out: list[_Clause] = []
        pending: tuple[str, int] | None = None  # a bare "if that fails" waiting for its step
        for start, end, hard in self._split(text):
            pos = grammar.skip_fillers(text, start, end)
            marker = grammar.marker.match(text, pos, end)
            marker_text, marker_column = "", 0
            if marker is not None:
                marker_text = " ".join(marker.group().split()).rstrip(",:")
                marker_column = item.column + pos
                pos = grammar.skip_fillers(text, marker.end(), end)
            written = " ".join(text[pos:end].split())
            clause = self._trimmed(written)
            if not clause:
                if marker is not None:
                    pending = (marker_text, marker_column)
                continue
            if pending is not None:
                marker_text = pending[0]
                pending = None
            column = item.column + pos
            if len(clause) > MAX_CLAUSE_CHARS:
                raise ParseError(
                    f"step {echo(clause)} is {len(clause)} characters; at most {MAX_CLAUSE_CHARS}",
                    **_at(item.line, column),
                )
            tail = "".join(c for c in written[len(clause) :] if c in "?!") if len(written) > len(clause) else ""
            steps = grammar.read_clause(clause, item.line, column, tail)
            out.append(_Clause(steps, item.line, column, clause, hard, marker_text))
        if pending is not None:
            raise ParseError(
                f"{echo(pending[0])} is not followed by a step: write what to do instead, e.g. "
                f"'{pending[0]}, go back to the kitchen'",
                **_at(item.line, pending[1]),
            )
        return out

    def _trimmed(self, clause: str) -> str:
        clause = clause.rstrip(".!?,;: ")
        lowered = clause.lower()
        for filler in self.grammar.trailing_fillers:
            if lowered.endswith(filler):
                clause = clause[: -len(filler)].rstrip(".!?,;: ")
                lowered = clause.lower()
        return clause

    def _split(self, text: str) -> list[tuple[int, int, bool]]:
        """(start, end, after a hard separator) of each clause; quoted text is never split."""
        masked = text
        if '"' in text or "'" in text or "\u201c" in text or "\u2018" in text:
            masked = _QUOTATION.sub(lambda m: m.group()[0] + "x" * (len(m.group()) - 2) + m.group()[-1], text)
        pieces: list[tuple[int, int, bool]] = []
        start, hard = 0, True
        for match in _SEPARATOR.finditer(masked):
            kind = match.lastgroup
            if kind != "hard" and not self.grammar.starts_step(text, match.end()):
                continue
            pieces.append((start, match.start(), hard))
            start, hard = match.end(), kind != "soft"
        pieces.append((start, len(text), hard))
        return pieces

    # Clauses -> steps

    def node(self, fields: dict[str, Any], line: int, column: int, description: str, depth: int) -> _Node:
        if depth > self.max_depth:
            raise self._too_deep(depth, line, column)
        self.steps += 1
        if self.steps > self.max_steps:
            raise self._too_many(line, column)
        return _Node(fields, line, column, description, depth)

    def emit_items(self, items: list[_Item], out: list[_Node], depth: int, last: _Node | None) -> _Node | None:
        """Append the steps of `items` to `out`; `last` is the step a leading "if that fails" falls back from."""
        for item in items:
            if item.children:
                last = self._emit_group(item, out, depth, last)
                continue
            clauses = self.clauses(item)
            if not clauses:
                raise ParseError(
                    f"list item {echo(item.heading)} has no step: expected a step such as "
                    f"{self.grammar.general_examples}",
                    **_at(item.line, item.start),
                )
            last = self._emit_clauses(clauses, out, depth, last)
        return last

    def _emit_clauses(self, clauses: list[_Clause], out: list[_Node], depth: int, last: _Node | None) -> _Node | None:
        owner: _Node | None = None  # the step the current run of fallbacks belongs to
        for clause in clauses:
            if clause.marker:
                if last is None:
                    raise ParseError(
                        f"{echo(clause.marker)} has no step before it to fall back from: put the fallback "
                        "after the step it replaces",
                        **_at(clause.line, clause.column),
                    )
                owner = last
            elif clause.hard:
                owner = None
            if owner is not None:
                node = self._clause_node(clause, owner.depth + 1)
                owner.on_failure.append(node)
            else:
                node = self._clause_node(clause, depth)
                out.append(node)
            last = node
        return last

    def _clause_node(self, clause: _Clause, depth: int) -> _Node:
        """A clause's step; an expansion is a group named by the clause, its steps as sub-steps."""
        if len(clause.steps) == 1:
            return self.node(clause.steps[0], clause.line, clause.column, clause.description, depth)
        group = self.node({}, clause.line, clause.column, clause.description, depth)
        for fields in clause.steps:
            group.substeps.append(self.node(fields, clause.line, clause.column, "", depth + 1))
        return group

    def _emit_group(self, item: _Item, out: list[_Node], depth: int, last: _Node | None) -> _Node | None:
        heading = item.heading
        if self.grammar.marker.fullmatch(heading):
            # "If that fails:" with sub-items: they are the fallback of the step before.
            if last is None:
                raise ParseError(
                    f"{echo(heading)} has no step before it to fall back from: put the fallback after the "
                    "step it replaces",
                    **_at(item.line, item.start),
                )
            return self.emit_items(item.children, last.on_failure, last.depth + 1, None)
        group = self.node({}, item.line, item.start, heading, depth)
        out.append(group)
        # A heading that reads as steps ("Pick up the cup" over "- if that fails, ...") runs first.
        own: list[_Clause] = []
        try:
            own = self.clauses(item)
        except ParseError:
            verb = heading.split(" ", 1)[0].lower()
            # "Tidy up the table" over the steps that do it names them: nothing is lost.
            if verb in self.grammar.patterns and verb not in self.grammar.summary_verbs:
                self.warnings.append(
                    f"line {item.line}: {echo(heading)} has sub-items and cannot be read as a step; "
                    "it is kept as their heading only"
                )
        if any(len(c.steps) > 1 for c in own) and not all(self.grammar.marker.match(c.text) for c in item.children):
            # "Fetch the cup:" over the steps that fetch it: the heading names them, it is not more steps.
            own = []
        inner = self._emit_clauses(own, group.substeps, depth + 1, None) if own else None
        self.emit_items(item.children, group.substeps, depth + 1, inner)
        return group


def read_text(
    text: str, grammar: TextGrammar, *, max_steps: int = MAX_STEPS, max_depth: int = MAX_NESTING
) -> tuple[list[TextStep], list[str]]:
    """The steps of a plan written as an English list (or sentences), and warnings; raises ParseError."""
    if not isinstance(text, str):
        raise ParseError(f"plan text must be a string, got {type(text).__name__}")
    if len(text) > MAX_PLAN_BYTES:
        raise ParseError(f"plan text is {len(text)} characters; at most {MAX_PLAN_BYTES} are accepted")
    if not text.strip():
        raise ParseError("plan text is empty")
    reader = _Reader(grammar, max_steps, max_depth)
    try:
        nodes: list[_Node] = []
        reader.emit_items(reader.items(text), nodes, 0, None)
        return [node.frozen() for node in nodes], reader.warnings
    except RecursionError:
        raise ParseError(f"the plan is nested too deeply; at most {max_depth} levels are accepted") from None
