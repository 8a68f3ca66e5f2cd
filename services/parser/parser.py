"""Plan text -> Plan: find the plan in whatever shape it came, map LLM words onto canonical actions, validate."""

from __future__ import annotations

import functools
import math
import re
from dataclasses import dataclass, field
from typing import Any

import msgspec
from rapidfuzz import fuzz, process

from schemas.common import METRES_MAX, METRES_MIN, ErrorKind, ServiceError, Stage
from schemas.plan import (
    Action,
    Coordinates,
    ParamValue,
    ParseReply,
    Plan,
    PlanText,
    SourceFormat,
    Step,
)
from services.parser.config import ParserConfig
from services.parser.errors import ParseError, kind_of
from services.parser.expand import Expansions, given_once
from services.parser.extract import JsonFinder, RepairBudget, fenced_blocks
from services.parser.hints import Hints
from services.parser.text import TextGrammar, TextStep, load_grammar, read_text
from services.parser.toolcalls import ToolCalls, call_arguments, find_tool_calls
from services.parser.vocabulary import AXES, STEP_FIELDS, ParamSpec, Vocabulary, load_vocabulary, normalise_word
from services.parser.yamlplan import AliasBomb, load_yaml

# A point as (x, y, z) in metres, map frame.
_Point = tuple[float, float, float | None]
# What a plain step of an action is read with, by one lookup a step (see Parser._plain_steps): the
# action, the parameters its name sets, its parameters by each of their names, whether a direction
# signs one of them, its required parameters. A plain tuple: a NamedTuple unpacks slower (0.5 us a plan).
_PlainAction = tuple[Action, dict[str, str], dict[str, tuple[str, ParamSpec, str | None]], bool, list[str]]
# A decoded value that looks like a plan: (value, warnings, the line it starts on, its format).
_Candidate = tuple[Any, list[str], int, SourceFormat]

FORMATS = ("auto", "json", "yaml", "text")
MAX_NAME_CHARS = 200
# A number written as text, with its unit ("90 degrees").
MAX_NUMBER_CHARS = 100
MAX_TEXT_CHARS = 4000
# Names echoed back in messages are cut to this, so hostile input cannot bloat a reply.
ECHO_CHARS = 60
MAX_LISTED = 10
_NUMBER_WITH_UNIT = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([^\d\s.+-][^\d]*?)?\s*$")
_NAME_FIELDS = ("target", "target_object", "target_location")
# Control characters have no place in a name or a spoken sentence (newlines and tabs excepted).
_CONTROL = re.compile(r"[\x00-\x08\x0b-\x1f\x7f]")
# A list marker at the start of one English sentence of a JSON array ("1. Go to the kitchen").
_LIST_MARK = re.compile(r"^\s*(?:[-*\u2022+]|\(?\d{1,3}[.):])?\s*")
# A list item or a heading-like line: the text may be English steps. Indented within its own line
# (as _yaml_start).
_LIST_ITEM = re.compile(r"^[^\S\n]*(?:[-*\u2022+]\s|\(?\d{1,3}[.):]\s|\**step\s+\d)", re.IGNORECASE | re.MULTILINE)
_YAML_FENCES = ("yaml", "yml")
# "plan:" followed by an indented list or key: YAML, not a prose heading like "Plan:".
_YAML_BODY = re.compile(r"[^\n]*\n[ \t]+(?:-\s|[\w\"']+\s*:)")
# Two sources of one point agree when they differ by less than this (metres): rounding, not a choice.
SAME_POINT = 1e-6
# "(3.5, 2.0)", "[3.5, 2.0, 0.7]", "x=3.5, y=2": brackets around a point written as text, and axis labels.
_POINT_BRACKETS = {"(": ")", "[": "]"}
_AXIS_LABEL = re.compile(r"^\s*([xyz])\s*[:=]?\s*(?=[-+.\d])", re.IGNORECASE)
MAX_POINT_CHARS = 200
# geometry_msgs PoseStamped: {pose: {position: {x, y, z}}} is two levels below the key.
MAX_POINT_NESTING = 2
POINT_SHAPES = '{"x": 3.5, "y": 2.0}, [3.5, 2.0] or \'3.5, 2.0\' (metres, map frame)'
# A ROS PoseStamped keeps its frame in "header".
_HEADER = "header"
LONE_SURROGATE = (
    "the plan holds text that is not valid Unicode: a lone surrogate (an escape such as \\ud800 without "
    "its pair); write the character itself, or both halves of its escape"
)
NO_PLAN = (
    "no plan found: expected a JSON object with a 'plan' array, a JSON array of steps, YAML, "
    "tool calls, or numbered/bulleted steps in English"
)


def echo(value: object) -> str:
    text = value if isinstance(value, str) else repr(value)
    return repr(text if len(text) <= ECHO_CHARS else text[:ECHO_CHARS] + "...")


def _listing(names: list[str]) -> str:
    shown = ", ".join(names[:MAX_LISTED])
    return shown if len(names) <= MAX_LISTED else f"{shown} and {len(names) - MAX_LISTED} more"


@dataclass(frozen=True)
class _Where:
    """Where a step is, for messages: 'step 2.1' in structured plans, 'line 3, column 5' in text."""

    label: str
    top: int
    line: int | None = None
    column: int | None = None

    def refuse(self, message: str, **kwargs: Any) -> ParseError:
        return ParseError(message, where=self.label, step=self.top, line=self.line, column=self.column, **kwargs)

    def child(self, index: int) -> _Where:
        return _Where(f"{self.label}.{index + 1}", self.top)

    def alternative(self, index: int) -> _Where:
        return _Where(f"{self.label} on_failure {index + 1}", self.top)


@dataclass
class _Context:
    """One parse: its warnings, how many steps it has seen, and the JSON repairs it may still make."""

    config: ParserConfig
    repairs: RepairBudget
    warnings: list[str] = field(default_factory=list)
    steps: int = 0

    def count(self, where: _Where) -> None:
        self.steps += 1
        if self.steps > self.config.max_steps:
            raise where.refuse(
                f"the plan has more than {self.config.max_steps} steps (sub-steps and on_failure included); "
                "split it into smaller plans"
            )


@dataclass
class _RawStep:
    """One step's fields after mapping LLM field names onto ours."""

    action: Any = None
    names: dict[str, str] = field(default_factory=dict)
    parameters: dict[Any, Any] = field(default_factory=dict)
    description: Any = ""
    substeps: Any = None
    on_failure: Any = None
    # Fields that are none of ours: parameters of the action if it takes them, else warned about.
    extra: dict[Any, Any] = field(default_factory=dict)
    # Position-like keys (x, pose, yaw, joints...): key as given, normalised key, value, inside parameters.
    places: list[tuple[str, str, Any, bool]] = field(default_factory=list)


class Parser:
    """Turns untrusted text into a validated Plan, or raises ParseError naming what was wrong."""

    def __init__(
        self,
        vocabulary: Vocabulary,
        grammar: TextGrammar | None = None,
        *,
        config: ParserConfig | None = None,
    ) -> None:
        self.vocabulary = vocabulary
        self.grammar = grammar if grammar is not None else load_grammar()
        # Its limits: over one is refused, as early as it can be seen.
        self.config = config if config is not None else ParserConfig()
        self.finder = JsonFinder(
            max_depth=self.config.max_depth,
            lenient=self.config.lenient_json,
            max_repair_chars=self.config.max_repair_chars,
        )
        # Every name of an action, with the parameters its variant sets.
        self.actions: dict[str, tuple[Action, dict[str, str]]] = {}
        for action, spec in vocabulary.actions.items():
            for name in (action.value, *spec.synonyms):
                self.actions[normalise_word(name)] = (action, {})
            for name, preset in spec.variants.items():
                self.actions[normalise_word(name)] = (action, dict(preset))
        # Every name of a parameter, with the unit word a bare number under that name is in.
        self.params: dict[Action, dict[str, tuple[str, ParamSpec, str | None]]] = {}
        for action, spec in vocabulary.actions.items():
            names: dict[str, tuple[str, ParamSpec, str | None]] = {}
            for name, pspec in spec.params.items():
                for alias in (name, *pspec.aliases):
                    names[normalise_word(alias)] = (name, pspec, None)
                for alias, unit in pspec.unit_aliases.items():
                    names[normalise_word(alias)] = (name, pspec, unit)
            self.params[action] = names
        self.fields: dict[str, str] = {
            normalise_word(alias): name for name, aliases in vocabulary.fields.items() for alias in aliases
        }
        for name in STEP_FIELDS:
            self.fields.setdefault(name, name)
        self.expansions = Expansions(vocabulary, self.fields)
        self.hints = Hints(vocabulary)
        self.ignored_fields = {normalise_word(n) for n in vocabulary.ignored_fields}
        coordinates = vocabulary.coordinates
        self.coordinate_actions = frozenset(coordinates.actions)
        self.point_keys = {normalise_word(n) for n in coordinates.points}
        self.pose_keys = {normalise_word(n) for n in coordinates.poses}
        self.heading_keys = {normalise_word(n) for n in coordinates.headings}
        self.frame_keys = {normalise_word(n) for n in coordinates.frames}
        self.map_frames = [n.lower() for n in coordinates.map_frames]
        self.position_params = {normalise_word(n) for n in vocabulary.position_params}
        self.place_keys = {*AXES, *self.point_keys, *self.heading_keys, *self.position_params}
        self._metres_spec = ParamSpec(type="float", unit="m", min=METRES_MIN, max=METRES_MAX)
        self.plan_keys = [normalise_word(k) for k in vocabulary.plan_keys]
        self.plan_tools = {normalise_word(k) for k in vocabulary.plan_tools}
        self._known_actions = ", ".join(a.value for a in vocabulary.actions)
        # Numbers of each action signed by a direction: (number, direction, the directions meaning minus).
        self._signed = {
            action: [
                (name, pspec.signed_by, spec.params[pspec.signed_by].negative)
                for name, pspec in spec.params.items()
                if pspec.signed_by is not None
            ]
            for action, spec in vocabulary.actions.items()
        }
        # The unit of each parameter of each action that has one.
        self._unit_of = {
            action: {name: pspec.unit for name, pspec in spec.params.items() if pspec.unit}
            for action, spec in vocabulary.actions.items()
        }
        # Required parameters of each action, in the vocabulary's order.
        self._required = {
            action: [name for name, pspec in spec.params.items() if pspec.required]
            for action, spec in vocabulary.actions.items()
        }
        # The type a plain plan's steps are converted to, built once (see _plain_steps).
        self._plain_steps_type: Any = _plain_steps_type(self.fields, self.ignored_fields)
        self._plain_name_fields = [f for f in _NAME_FIELDS if self.fields.get(f) == f]
        self._plain_actions: dict[str, _PlainAction] = {
            word: (action, preset, self.params[action], bool(self._signed[action]), self._required[action])
            for word, (action, preset) in self.actions.items()
        }
        keys = sorted({*self.plan_keys, *self.fields}, key=len, reverse=True)
        # A line that starts a YAML plan: "plan:", "- action: pick", "steps:". Its indent is on that
        # line: one that ran on over newlines would be tried from every blank line to the end of a
        # run of them (seconds for a few thousand).
        self._yaml_start = re.compile(
            r"^[^\S\n]*(?:-\s+)?[\"']?(?:" + "|".join(re.escape(k) for k in keys) + r")[\"']?\s*:(?:\s|$)",
            re.IGNORECASE | re.MULTILINE,
        )

    # The whole text

    def parse(self, text: str, fmt: str = "auto") -> Plan:
        if fmt not in FORMATS:
            raise ParseError(f"unknown format {echo(fmt)}; expected one of {', '.join(FORMATS)}")
        self._check_text(text)
        ctx = _Context(self.config, self.finder.budget())
        if fmt == "text":
            return self._from_text(text, ctx)
        if fmt == "yaml":
            return self._from_candidates(self._yaml_candidates(text, strict=True), ctx)
        found = self.finder.find(text, self._looks_like_plan, ctx.repairs)
        if found.plans and found.in_prose and fmt == "auto":
            # `- {action: pick}` lines of a YAML plan are JSON objects too: YAML reads them as one plan.
            candidates = self._yaml_candidates(text, strict=False)
            if candidates:
                return self._from_candidates(candidates, ctx)
        if found.plans:
            candidates = [(c.value, c.warnings, c.line, "json") for c in found.plans]
            if fmt == "auto":  # a ```yaml block beside them must agree with them
                candidates += self._yaml_candidates(text, strict=False, fences_only=True)
            return self._from_candidates(candidates, ctx)
        if fmt == "json":
            if found.error is not None:
                raise found.error
            if found.other is not None:
                return self._from_value(found.other, "json", ctx)  # raises, naming what the JSON held
            raise ParseError(NO_PLAN)
        candidates = self._yaml_candidates(text, strict=False)
        if candidates:
            return self._from_candidates(candidates, ctx)
        if not _LIST_ITEM.search(text):
            if found.error is not None:
                raise found.error
            if found.other is not None and not (found.in_prose and _no_objects(found.other)):
                return self._from_value(found.other, "json", ctx)
        try:
            return self._from_text(text, ctx)
        except ParseError as exc:
            if _LIST_ITEM.search(text):
                raise
            raise ParseError(
                f"{NO_PLAN}; read as English: {exc}",
                line=exc.error.line,
                column=exc.error.column,
                candidates=exc.error.candidates,
            ) from None

    def _check_text(self, text: str) -> None:
        if not isinstance(text, str):
            raise ParseError(f"plan text must be a string, got {kind_of(text)}")
        if not text:
            raise ParseError("plan text is empty")
        limit = self.config.max_input_bytes
        if len(text) > limit:  # every character is at least one byte: refuse without encoding
            raise ParseError(f"plan text is over {limit} bytes; at most {limit} are accepted")
        if not text.strip():
            raise ParseError("plan text is only whitespace")
        try:
            size = len(text.encode("utf-8"))
        except UnicodeEncodeError as exc:
            raise ParseError(f"plan text is not valid UTF-8 (character {exc.start + 1} is a lone surrogate)") from None
        if size > limit:
            raise ParseError(f"plan text is {size} bytes; at most {limit} are accepted")
        if "\x00" in text:
            raise ParseError(f"plan text contains a NUL character at position {text.index(chr(0)) + 1}")

    def _looks_like_plan(self, value: Any) -> bool:
        if isinstance(value, list):
            if value and all(isinstance(v, dict) for v in value):
                return True
            if value and all(isinstance(v, str) for v in value):  # ["Go to the kitchen", "Pick up the cup"]
                return any(self.grammar.starts_step(_LIST_MARK.sub("", v, count=1), 0) for v in value[:MAX_LISTED])
        elif isinstance(value, dict):
            keys = {normalise_word(k) for k in value if isinstance(k, str)}
            if any(k in keys for k in self.plan_keys) or any(self.fields.get(k) == "action" for k in keys):
                return True
        else:
            return False
        return find_tool_calls(value) is not None

    def _yaml_candidates(self, text: str, *, strict: bool, fences_only: bool = False) -> list[_Candidate]:
        """YAML in ```yaml blocks, else the whole text; in auto mode only when it starts like a plan."""
        fences = fenced_blocks(text)
        blocks = [(at, body) for lang, at, body in fences if lang in _YAML_FENCES]
        if fences_only:
            strict = False
        elif not blocks and not strict:
            blocks = [(at, body) for lang, at, body in fences if not lang and self._yaml_start.match(body.lstrip())]
        if not blocks and not fences_only:
            if not strict and not self._yaml_start.search(text):
                return []
            # A text whose first line starts a YAML plan is YAML: its errors are YAML errors.
            head = text.lstrip()
            strict = strict or bool(self._yaml_start.match(head) and _YAML_BODY.match(head))
            blocks = [(0, text)]
        candidates: list[_Candidate] = []
        for at, body in blocks:
            line = text.count("\n", 0, at) + 1
            try:
                value = load_yaml(body, max_nodes=self.config.max_yaml_nodes, max_depth=self.config.max_depth)
            except ParseError as exc:
                # Alias bombs are refused even where other broken YAML would be skipped.
                if strict or (len(blocks) == 1 and at > 0) or isinstance(exc, AliasBomb):
                    raise ParseError(f"YAML block at line {line}: {exc}") from None
                continue
            if self._looks_like_plan(value):
                candidates.append((value, [], line, "yaml"))
            elif strict:
                self._steps_of(value, [])
        return candidates

    def _from_candidates(self, candidates: list[_Candidate], ctx: _Context) -> Plan:
        """One plan from the plan-like blocks: they must agree; a block that fails is dropped if another reads."""
        if not candidates:
            raise ParseError(NO_PLAN)
        if len(candidates) == 1:
            value, warnings, _line, fmt = candidates[0]
            ctx.warnings.extend(warnings)
            return self._from_value(value, fmt, ctx)
        plans: list[tuple[int, Plan]] = []
        failures: list[tuple[int, ParseError]] = []
        for value, warnings, line, fmt in sorted(candidates, key=lambda c: c[2]):
            one = _Context(self.config, ctx.repairs, list(warnings))
            try:
                plans.append((line, self._from_value(value, fmt, one)))
            except ParseError as exc:
                failures.append((line, exc))
        if not plans:
            raise failures[0][1]
        first_line, plan = plans[0]
        for line, other in plans[1:]:
            if other.steps != plan.steps:
                raise ParseError(
                    f"the text holds {len(plans)} conflicting plans (the plans at lines {first_line} and {line} "
                    "differ); send exactly one plan, with all its steps in one array",
                    line=line,
                )
        notes = [f"{len(plans)} identical plans found; read once"] if len(plans) > 1 else []
        notes += [f"the block at line {line} was not read as a plan: {exc}" for line, exc in failures]
        return msgspec.structs.replace(plan, warnings=[*plan.warnings, *notes][: self.config.max_steps * 4])

    def _from_value(self, value: Any, fmt: SourceFormat, ctx: _Context) -> Plan:
        plain = self._plain_steps(value)
        if plain is not None:
            steps, description = plain
            return self._plan(steps, description, fmt, ctx)
        calls = find_tool_calls(value)
        if calls is not None:
            ctx.warnings.extend(calls.warnings)
            raw_steps, description = self._steps_of_calls(calls, ctx), "\n".join(calls.text)
            fmt = calls.format
        else:
            raw_steps, description = self._steps_of(value, ctx.warnings)
        steps = [self._step(raw, _Where(f"step {i + 1}", i), 0, ctx) for i, raw in enumerate(raw_steps)]
        return self._plan(steps, description, fmt, ctx)

    def _from_text(self, text: str, ctx: _Context) -> Plan:
        text_steps, warnings = read_text(
            text, self.grammar, max_steps=self.config.max_steps, max_depth=self.config.max_nesting
        )
        ctx.warnings.extend(warnings)
        if not text_steps:
            raise ParseError(NO_PLAN)
        steps = [self._text_step(ts, i, 0, ctx) for i, ts in enumerate(text_steps)]
        return self._plan(steps, "", "text", ctx)

    def _plan(self, steps: list[Step], description: Any, fmt: SourceFormat, ctx: _Context) -> Plan:
        if not steps:
            raise ParseError("the plan has no steps")
        text = self._text(description, "the plan's description", ctx.warnings)
        warnings = [w[:MAX_TEXT_CHARS] for w in ctx.warnings[: self.config.max_steps * 4]]
        return _validated(Plan(steps=steps, description=text, warnings=warnings, source_format=fmt))

    def _steps_of(self, value: Any, warnings: list[str]) -> tuple[list[Any], Any]:
        description: Any = ""
        plan_key: str | None = None
        keys = self.plan_keys
        for _ in range(2):  # {"plan": {"steps": [...]}} is read too
            if not isinstance(value, dict):
                break
            by_key = {normalise_word(k): k for k in value if isinstance(k, str)}
            plan_key = next((by_key[k] for k in self.plan_keys if k in by_key), None)
            # Steps under two plan keys are two plans ("plan" and "steps"): reading one would drop the other.
            holders = [k for k, v in value.items() if isinstance(k, str) and v is not None]
            holders = [k for k in holders if normalise_word(k) in keys]
            if len(holders) > 1:
                raise ParseError(
                    f"the object holds steps under both {echo(holders[0])} and {echo(holders[1])}; "
                    "send exactly one plan, with all its steps in one array"
                )
            if plan_key is None:
                if any(self.fields.get(k) == "action" for k in by_key):
                    return [value], description  # a single step on its own
                keys = [echo(k) for k in value]
                raise ParseError(f"{NO_PLAN}; found an object with keys {_listing(keys)}" if keys else NO_PLAN)
            description_key = next((by_key[k] for k in ("description", "goal", "task", "summary") if k in by_key), None)
            description = value.get(description_key, "") if description_key else description
            extra = [echo(k) for k in value if k not in (plan_key, description_key)]
            if extra:
                warnings.append(f"top-level field(s) {_listing(extra)} ignored")
            value = value[plan_key]
        if plan_key is not None and not isinstance(value, list):
            raise ParseError(f"'{plan_key}' must be an array of steps, got {kind_of(value)}")
        if not isinstance(value, list):
            raise ParseError(f"{NO_PLAN}; found {kind_of(value)}")
        if not value:
            raise ParseError("the plan has no steps")
        if len(value) > self.config.max_steps:
            raise ParseError(f"the plan has {len(value)} steps; at most {self.config.max_steps} are accepted")
        return value, description

    def _steps_of_calls(self, calls: ToolCalls, ctx: _Context) -> list[Any]:
        steps: list[Any] = []
        for call in calls.calls:
            if not isinstance(call.name, str) or not call.name.strip():
                raise ParseError(f"{call.where} has no tool name")
            arguments, warnings = call_arguments(call, functools.partial(self._decode_arguments, repairs=ctx.repairs))
            ctx.warnings.extend(warnings)
            name = normalise_word(call.name)
            if name in self.plan_tools or (name not in self.actions and self._looks_like_plan(arguments)):
                inner, description = self._steps_of(arguments, ctx.warnings)
                if isinstance(description, str) and description.strip():
                    calls.text.append(description)
                steps.extend(inner)
            else:
                # Only a literal "action" collides with the tool name; "type": "wave" may be a parameter.
                action_keys = [k for k in arguments if isinstance(k, str) and normalise_word(k) == "action"]
                if action_keys:
                    ctx.warnings.append(
                        f"{call.where}: field(s) {_listing(action_keys)} ignored: the tool name is the action"
                    )
                steps.append({"action": call.name, **{k: v for k, v in arguments.items() if k not in action_keys}})
            if len(steps) > self.config.max_steps:
                raise ParseError(f"the tool calls hold more than {self.config.max_steps} steps")
        return steps

    def _decode_arguments(self, text: str, where: str, repairs: RepairBudget) -> tuple[Any, list[str]]:
        found = self.finder.find(text, lambda v: isinstance(v, dict), repairs)
        if found.plans:
            return found.plans[0].value, [f"{where}: {w}" for w in found.plans[0].warnings]
        if found.error is not None:
            raise ParseError(f"{where}: arguments are not valid JSON: {found.error}")
        raise ParseError(f"{where}: arguments must be a JSON object")

    # Plain plans

    def _plain_steps(self, value: Any) -> tuple[list[Step], Any] | None:
        """The steps and description of a plan written plainly, or None to map it field by field.

        Plainly: an array of steps, or an object holding one under a plan key (and perhaps a
        'description'), each step with its action by one of its names as the vocabulary spells it,
        the name fields, a description and parameters by their own names, and ignored fields. Those
        steps are read by one msgspec conversion into `PlainStep` structs rather than key by key.
        Everything the general mapping would refuse or warn about (a sub-step, an alias, a null, a
        blank action, a control character, a bad value) hands the whole plan over to it, so this
        path gives the same Plan as the general one for every plan it takes, and never an error or
        a warning of its own.
        """
        if self._plain_steps_type is None:
            return None
        description: Any = ""
        steps: Any = None
        if isinstance(value, dict):
            plan_key: str | None = None
            for key, item in value.items():
                if key == "description":
                    description = item
                elif plan_key is None and key in self.plan_keys:
                    plan_key, steps = key, item
                else:  # a second plan key, or a key the general mapping warns about or reads further
                    return None
        elif isinstance(value, list):
            steps = value
        if not isinstance(steps, list) or not steps or len(steps) > self.config.max_steps:
            return None
        if find_tool_calls(value) is not None:
            return None
        try:
            plain = msgspec.convert({"steps": steps}, self._plain_steps_type).steps
        except (msgspec.ValidationError, UnicodeEncodeError):  # a key with a lone surrogate: not ours
            return None
        limit = self.config.max_string_chars
        actions = self._plain_actions
        name_fields, control = self._plain_name_fields, _CONTROL.search
        out: list[Step] = []
        try:
            for raw in plain:
                named = actions.get(raw.action)
                if named is None:
                    return None
                action, preset, known, signed, required = named
                names: dict[str, str] = {}
                for name in name_fields:
                    item = getattr(raw, name)
                    if item is None or not (text := item.strip()):
                        continue
                    if control(item):
                        return None
                    names[name] = text
                text = raw.description
                if text is None:
                    text = ""
                elif len(text) > limit or control(text):
                    return None
                params: dict[str, ParamValue] = {}
                if raw.parameters:
                    for key, item in raw.parameters.items():
                        entry = known.get(key)
                        if entry is None or entry[0] in params:
                            return None
                        name, pspec, unit = entry
                        params[name] = self._value(_PLAIN, name, pspec, item, unit)
                if preset:  # most steps name their action by a word that sets no parameter
                    for name, preset_value in preset.items():
                        if params.setdefault(name, preset_value) != preset_value:
                            return None
                if signed:
                    self._apply_signs(_PLAIN, action, params)
                warnings: list[str] = []
                target, location = self._names(_PLAIN, action, names, params, warnings)
                if warnings:
                    return None
                for name in required:
                    if name not in params:
                        return None
                out.append(
                    Step(
                        action=action,
                        target=target,
                        location=location,
                        params=params,
                        units=self._units(action, params) if params else {},
                        description=text,
                    )
                )
        except ParseError:
            return None
        return out, description

    # One step

    def _step(self, value: Any, where: _Where, depth: int, ctx: _Context) -> Step:
        if isinstance(value, str):
            return self._sentence_step(value, where, depth, ctx)
        if isinstance(value, dict):
            takes = self._takes
            value = self.expansions.rewrite(value, where.label, takes, where.refuse, ctx.warnings) or value
        ctx.count(where)
        if depth > self.config.max_nesting:
            raise where.refuse(f"sub-steps are nested more than {self.config.max_nesting} levels deep")
        if not isinstance(value, dict):
            raise where.refuse(f"is {kind_of(value)}, not an object with an 'action'")
        raw = self._fields(value, where, ctx.warnings)
        substeps = self._nested(raw.substeps, "substeps", where)
        on_failure = self._nested(raw.on_failure, "on_failure", where)
        step = self._build(raw, where, bool(substeps), ctx)
        return msgspec.structs.replace(
            step,
            substeps=[self._step(v, where.child(i), depth + 1, ctx) for i, v in enumerate(substeps)],
            on_failure=[self._step(v, where.alternative(i), depth + 1, ctx) for i, v in enumerate(on_failure)],
        )

    def _takes(self, action: str, key: Any) -> bool:
        """Whether `action` takes a parameter named `key` (an expansion hands it its parameters)."""
        return isinstance(key, str) and normalise_word(key) in self.params[Action(action)]

    def _sentence_step(self, text: str, where: _Where, depth: int, ctx: _Context) -> Step:
        """A step written as an English sentence in a JSON or YAML plan; several clauses make a group."""
        try:
            text_steps, warnings = read_text(
                text, self.grammar, max_steps=self.config.max_steps, max_depth=self.config.max_nesting
            )
        except ParseError as exc:
            message = exc.error.message
            if exc.error.line == 1 and "\n" not in text.strip():  # one line: the sentence itself is quoted
                message = message.removeprefix(f"line 1, column {exc.error.column}: ")
            raise where.refuse(message, kind=exc.error.kind, candidates=exc.error.candidates) from None
        ctx.warnings.extend(f"{where.label}: {w}" for w in warnings)
        steps = [self._text_step(s, where.top, depth + (len(text_steps) > 1), ctx, where.label) for s in text_steps]
        if len(steps) == 1:
            return steps[0]
        ctx.count(where)
        description = self._text(text, f"{where.label}: description", ctx.warnings)
        return Step(action=None, description=description, substeps=steps)

    def _text_step(self, item: TextStep, top: int, depth: int, ctx: _Context, label: str | None = None) -> Step:
        if label is not None:  # a sentence of a structured plan: named by its place there
            where = _Where(label, top)
        else:
            where = _Where(f"line {item.line}, column {item.column}", top, item.line, item.column)
        ctx.count(where)
        if depth > self.config.max_nesting:
            raise where.refuse(f"sub-steps are nested more than {self.config.max_nesting} levels deep")
        raw = self._fields(item.fields, where, ctx.warnings)
        raw.description = raw.description or item.description
        step = self._build(raw, where, bool(item.substeps), ctx)
        return msgspec.structs.replace(
            step,
            substeps=[self._text_step(s, top, depth + 1, ctx, label) for s in item.substeps],
            on_failure=[self._text_step(s, top, depth + 1, ctx, label) for s in item.on_failure],
        )

    def _nested(self, value: Any, name: str, where: _Where) -> list[Any]:
        if value is None:
            return []
        if isinstance(value, dict):
            return [value]
        if not isinstance(value, list):
            raise where.refuse(f"'{name}' must be an array of steps, got {kind_of(value)}")
        return value

    def _build(self, raw: _RawStep, where: _Where, has_substeps: bool, ctx: _Context) -> Step:
        """The step itself, without its sub-steps and alternatives; a group when it has sub-steps only."""
        description = self._text(raw.description, f"{where.label}: description", ctx.warnings)
        if has_substeps:
            word = normalise_word(raw.action) if isinstance(raw.action, str) else None
            if word in self.actions:
                raise where.refuse(
                    f"has both an action ({echo(raw.action)}) and sub-steps; a step is either one action "
                    "or a group of sub-steps"
                )
            if isinstance(raw.action, str) and raw.action.strip():
                description = description or raw.action.strip()[: self.config.max_string_chars]  # its name
            elif raw.action is not None:
                ctx.warnings.append(f"{where.label}: 'action' of a group ignored: it is {kind_of(raw.action)}")
            ignored = [*raw.names, *(echo(k) for k in raw.parameters), *(echo(k) for k in raw.extra)]
            if ignored:
                ctx.warnings.append(f"{where.label}: field(s) {_listing(ignored)} of a group ignored")
            return Step(action=None, description=description)
        action, preset = self._action(where, raw.action)
        params = self._params(where, action, raw, preset, ctx.warnings)
        coordinates = self._coordinates(where, action, raw.places, ctx.warnings)
        target, location = self._names(where, action, raw.names, params, ctx.warnings, coordinates is not None)
        for name, pspec in self.vocabulary.actions[action].params.items():
            if pspec.required and name not in params:
                unit = (
                    f" (in {pspec.unit}, or with a unit such as '{_example(self.vocabulary, pspec)}')"
                    if pspec.unit
                    else ""
                )
                raise where.refuse(f"{action.value} needs parameter '{name}'{unit}")
        return Step(
            action=action,
            target=target,
            location=location,
            params=params,
            units=self._units(action, params),
            description=description,
            coordinates=coordinates,
        )

    def _units(self, action: Action, params: dict[str, ParamValue]) -> dict[str, str]:
        """The unit of each number among `params` whose parameter has one."""
        unit_of = self._unit_of[action]
        units: dict[str, str] = {}
        for name, value in params.items():  # not a comprehension: in Python 3.11 that is a function call of its own
            unit = unit_of.get(name)
            if unit is not None and not isinstance(value, _TEXT_OR_BOOL):
                units[name] = unit
        return units

    def _fields(self, value: dict[Any, Any], where: _Where, warnings: list[str]) -> _RawStep:
        raw = _RawStep()
        given: dict[str, Any] = {}  # field -> the key that gave it, for a field given under two names
        for key, item in value.items():
            word = normalise_word(key) if isinstance(key, str) else ""
            name = self.fields.get(word)
            if name is None:
                if word not in self.ignored_fields:
                    raw.extra[key] = item
            elif name == "action":
                if raw.action is None:
                    raw.action = item
                elif item != raw.action:
                    first, second = (self._canonical(v) for v in (raw.action, item))
                    if first is not None and second is not None and first is not second:
                        raise where.refuse(f"names two actions ({echo(raw.action)} and {echo(item)})")
                    raw.extra[key] = item  # {"action": "gesture", "type": "wave"}: a parameter
            elif name == "parameters":
                if item is None:
                    continue
                if not isinstance(item, dict):
                    raise where.refuse(f"'{key}' must be an object, got {kind_of(item)}")
                given_once(where.refuse, given, name, key, raw.parameters, item)
                raw.parameters = item
            elif name == "description":
                if isinstance(item, str):
                    raw.description = item
                elif item is not None:
                    warnings.append(f"{where.label}: description ignored: it is {kind_of(item)}, not text")
            elif name in ("substeps", "on_failure"):
                if item is not None:
                    given_once(where.refuse, given, name, key, getattr(raw, name), item)
                    setattr(raw, name, item)
            elif item is None or (isinstance(item, str) and not item.strip()):
                continue
            elif isinstance(item, dict | list) and word in self.point_keys:
                raw.extra[key] = item  # "location": [2.0, 3.5] is a point, not a name
            elif not isinstance(item, str):
                raise where.refuse(f"'{key}' must be a name (a string), got {kind_of(item)}")
            elif _CONTROL.search(item):
                raise where.refuse(f"'{key}' contains control characters")
            else:
                given_once(where.refuse, given, name, key, raw.names.get(name), item.strip())
                raw.names[name] = item.strip()
        return raw

    def _canonical(self, value: Any) -> Action | None:
        known = self.actions.get(normalise_word(value)) if isinstance(value, str) else None
        return known[0] if known is not None else None

    def _action(self, where: _Where, value: Any) -> tuple[Action, dict[str, str]]:
        known = self._known_actions
        if value is None or (isinstance(value, str) and not value.strip()):
            raise where.refuse(f"has no 'action'; known actions: {known}")
        if not isinstance(value, str):
            raise where.refuse(f"'action' must be a string, got {kind_of(value)}")
        word = normalise_word(value)
        if word in self.actions:
            return self.actions[word]
        matches = process.extract(word[:200], list(self.actions), scorer=fuzz.ratio, limit=3, score_cutoff=70)
        suggestions = [m[0] for m in matches]
        hint = ""
        if suggestions:
            best = suggestions[0]
            canonical = self.actions[best][0].value
            hint = f" (did you mean '{best}'?)" if best == canonical else f" (did you mean '{best}', i.e. {canonical}?)"
        raise where.refuse(
            f"unknown action {echo(value)}{hint}; known actions: {known}",
            kind=ErrorKind.UNKNOWN_ACTION,
            candidates=suggestions,
        )

    def _params(
        self, where: _Where, action: Action, raw: _RawStep, preset: dict[str, str], warnings: list[str]
    ) -> dict[str, ParamValue]:
        params: dict[str, ParamValue] = {}
        unknown: list[str] = []
        ignored: list[str] = []
        known = self.params[action]
        given = [(k, v, True) for k, v in raw.parameters.items()] + [(k, v, False) for k, v in raw.extra.items()]
        given, manner = self.hints.sift(where.label, known, given, warnings)
        for key, value, in_parameters in given:
            if value is None:  # not given: a model in strict mode sends null for each argument it leaves out
                continue
            word = normalise_word(key) if isinstance(key, str) else ""
            field_name = self.fields.get(word)
            if in_parameters and word not in known and field_name in _NAME_FIELDS and isinstance(value, str):
                name = value.strip()
                if name and raw.names.setdefault(field_name, name) != name:  # {"parameters": {"object": "cup"}}
                    raise where.refuse(
                        f"gives its {field_name} twice: {echo(raw.names[field_name])}, and {echo(name)} as "
                        f"{echo(key)} in parameters; give it once"
                    )
                continue
            if word in known:
                name, pspec, unit = known[word]
                if name in params:
                    raise where.refuse(f"parameter '{name}' is given twice (as {echo(key)})")
                params[name] = self._value(where, name, pspec, value, unit)
            elif word in self.place_keys or (word in self.frame_keys and action in self.coordinate_actions):
                raw.places.append((str(key)[:ECHO_CHARS], word, value, in_parameters))
            elif in_parameters:
                unknown.append(echo(key))
            else:
                ignored.append(echo(key))
        for name, value in preset.items():
            if params.setdefault(name, value) != value:
                raise where.refuse(f"the action says {name} {value!r} but parameter '{name}' is {echo(params[name])}")
        self.hints.slow_down(where.label, action, manner, params, warnings)
        self._apply_signs(where, action, params)
        if unknown or ignored:
            names = sorted(self.vocabulary.actions[action].params)
            takes = f"it takes {', '.join(names)}" if names else "it takes none"
            if unknown:
                warnings.append(
                    f"{where.label}: unknown parameter(s) {_listing(unknown)} for {action.value} ignored; {takes}"
                )
            if ignored:
                warnings.append(
                    f"{where.label}: field(s) {_listing(ignored)} ignored: not part of a step, "
                    f"nor a parameter of {action.value} ({takes})"
                )
        return params

    def _apply_signs(self, where: _Where, action: Action, params: dict[str, ParamValue]) -> None:
        """Fold a direction into the signed number it qualifies: turn right 90 degrees -> angle -1.5708."""
        for name, signed_by, negatives in self._signed[action]:
            if signed_by not in params:
                continue
            direction = params.pop(signed_by)
            value = params.get(name)
            if isinstance(value, _NUMBER) and not isinstance(value, bool):
                if value < 0:
                    raise where.refuse(
                        f"parameter '{name}' is negative and the direction is {direction!r}; give the "
                        f"{name} as a positive number and the direction on its own"
                    )
                params[name] = -value if direction in negatives else value

    # Coordinates

    def _coordinates(
        self, where: _Where, action: Action, places: list[tuple[str, str, Any, bool]], warnings: list[str]
    ) -> Coordinates | None:
        """The point the step wrote down, if its action takes one; headings and joints are warned about."""
        if not places:
            return None
        reason = self.vocabulary.position_reason
        if action not in self.coordinate_actions:
            self._ignored(where, [key for key, *_ in places], reason, warnings)
            return None
        self._ignored(where, [k for k, w, *_ in places if w in self.position_params], reason, warnings)
        headings = [k for k, w, *_ in places if w in self.heading_keys]
        self._ignored(where, headings, self.vocabulary.coordinates.heading_reason, warnings)
        axes: dict[str, tuple[str, float]] = {}
        sources: list[tuple[str, _Point]] = []
        for key, word, value, in_parameters in places:
            if value is None:
                continue  # "pose": null says nothing
            if word in AXES:
                number = self._metres(where, f"coordinate {echo(key)}", value)
                given = f"{echo(key)} {'in parameters' if in_parameters else 'beside the action'}"
                if word in axes and abs(axes[word][1] - number) > SAME_POINT:
                    raise where.refuse(
                        f"gives coordinate {word!r} twice: {axes[word][1]:g} ({axes[word][0]}) and {number:g} "
                        f"({given}); give the point once"
                    )
                axes[word] = (given, number)
            elif word in self.point_keys:
                sources.append((echo(key), self._point(where, key, word, value, warnings)))
        if axes:
            missing = [a for a in ("x", "y") if a not in axes]
            if missing:
                named = " and ".join(repr(a) for a in axes)
                raise where.refuse(
                    f"gives coordinate {named} without {' and '.join(repr(a) for a in missing)}: a point needs "
                    "x and y (z is optional), in metres in the map frame"
                )
            sources.insert(0, ("/".join(axes), (axes["x"][1], axes["y"][1], axes["z"][1] if "z" in axes else None)))
        frames = [(key, value) for key, word, value, _ in places if word in self.frame_keys]
        if not sources:
            self._ignored(where, [key for key, _ in frames], "the step gives no coordinates", warnings)
            return None
        for _, frame in frames:
            self._check_frame(where, "the step's point", frame)
        label, (x, y, z) = sources[0]
        for other, (ox, oy, oz) in sources[1:]:
            if (
                abs(x - ox) > SAME_POINT
                or abs(y - oy) > SAME_POINT
                or (z is not None and oz is not None and abs(z - oz) > SAME_POINT)
            ):
                raise where.refuse(
                    f"gives two different points: {label} {_point_text((x, y, z))} and {other} "
                    f"{_point_text((ox, oy, oz))}; give one point, in metres in the map frame"
                )
            z = z if z is not None else oz
        return Coordinates(x=x, y=y, z=z)

    def _ignored(self, where: _Where, keys: list[str], reason: str, warnings: list[str]) -> None:
        if keys:
            noun = "parameter" if len(keys) == 1 else "parameters"
            warnings.append(f"{where.label}: {noun} {_listing(keys)} ignored: {reason}")

    def _point(self, where: _Where, key: str, word: str, value: Any, warnings: list[str], depth: int = 0) -> _Point:
        """A point written as {x, y, z?}, [x, y], [x, y, z] or "x, y": (x, y, z) in metres, or a refusal."""
        name = echo(key)
        if isinstance(value, dict):
            return self._point_object(where, key, value, warnings, depth)
        if isinstance(value, str):
            numbers: list[Any] = self._point_in_text(where, name, value)
        elif isinstance(value, list):
            numbers = value
        else:
            raise where.refuse(f"{name} must be a point such as {POINT_SHAPES}, got {kind_of(value)}")
        if len(numbers) not in (2, 3):
            raise where.refuse(
                f"{name} must be 2 or 3 numbers (x, y and optionally z, in metres in the map frame), "
                f"got {len(numbers)} {'items' if isinstance(value, list) else 'numbers'}"
            )
        if len(numbers) == 3 and word in self.pose_keys:
            raise where.refuse(
                f"{name} has three numbers, and in a pose the third may be z or a heading; write "
                f'{{"x": ..., "y": ...}} or {{"x": ..., "y": ..., "z": ...}} '
                f"({self.vocabulary.coordinates.heading_reason})"
            )
        x, y, *z = (self._metres(where, f"{name} {axis}", n) for axis, n in zip(AXES, numbers, strict=False))
        return x, y, z[0] if z else None

    def _point_object(self, where: _Where, key: str, value: dict[Any, Any], warnings: list[str], depth: int) -> _Point:
        """{x, y, z?}, with a heading and a frame beside them, or a ROS pose ({position: {x, y, z}, orientation})."""
        name = echo(key)
        by_word = {normalise_word(k) if isinstance(k, str) else repr(k): k for k in value}
        if len(by_word) < len(value):
            raise where.refuse(f"{name} gives a coordinate twice (keys {_listing([echo(k) for k in value])})")
        axes = [a for a in AXES if a in by_word]
        inner = [w for w in by_word if w in self.point_keys and isinstance(value[by_word[w]], dict | list | str)]
        nest = not axes and len(inner) == 1 and depth < MAX_POINT_NESTING
        headings, unknown = [], []
        for word, k in by_word.items():
            if word in self.frame_keys:
                self._check_frame(where, name, value[k])
            elif word == _HEADER and isinstance(value[k], dict):
                for header_key, frame in value[k].items():
                    if isinstance(header_key, str) and normalise_word(header_key) in self.frame_keys:
                        self._check_frame(where, name, frame)
            elif word in self.heading_keys:
                headings.append(word)
            elif word not in AXES and not (nest and word == inner[0]):
                unknown.append(echo(k))
        if headings:
            reason = self.vocabulary.coordinates.heading_reason
            warnings.append(f"{where.label}: {name} {_listing(headings)} ignored: {reason}")
        if unknown:
            warnings.append(f"{where.label}: {name} field(s) {_listing(unknown)} ignored: a point has x, y and z")
        if nest:
            inner_key = by_word[inner[0]]
            return self._point(where, f"{key}.{inner_key}", inner[0], value[inner_key], warnings, depth + 1)
        if "x" not in axes or "y" not in axes:
            found = f"got {_listing([echo(k) for k in value])}" if value else "got an empty object"
            hint = "; a name goes in 'target'" if not axes else ""
            raise where.refuse(f"{name} needs x and y (z is optional), in metres in the map frame; {found}{hint}")
        x, y = (self._metres(where, f"{name} {a}", value[by_word[a]]) for a in ("x", "y"))
        z = value[by_word["z"]] if "z" in axes else None
        return x, y, None if z is None else self._metres(where, f"{name} z", z)

    def _point_in_text(self, where: _Where, name: str, value: str) -> list[str]:
        """'3.5, 2.0', '(3.5, 2.0)', 'x=3.5, y=2 m' -> the numbers as written, in x, y, z order."""
        if len(value) > MAX_POINT_CHARS:
            raise where.refuse(f"{name} is {len(value)} characters; a point is at most {MAX_POINT_CHARS}")
        text = value.strip()
        if text[:1] in _POINT_BRACKETS and text.endswith(_POINT_BRACKETS[text[0]]):
            text = text[1:-1]
        pieces = [p.strip() for p in text.split(",")]
        labels = [_AXIS_LABEL.match(p) for p in pieces]
        if any(labels):
            axes = [m.group(1).lower() if m else "" for m in labels]
            if len(set(axes)) != len(axes) or set(axes) not in ({"x", "y"}, {"x", "y", "z"}):
                raise where.refuse(f"{name} must be a point such as {POINT_SHAPES}, got {echo(value)}")
            by_axis = {a: p[m.end() :] for a, p, m in zip(axes, pieces, labels, strict=True) if m}
            pieces = [by_axis[a] for a in AXES if a in by_axis]
        if len(pieces) not in (2, 3) or not all(_NUMBER_WITH_UNIT.match(p) for p in pieces):
            hint = "; a name goes in 'target'" if not any(c.isdigit() for c in value) else ""
            raise where.refuse(f"{name} must be a point such as {POINT_SHAPES}, got {echo(value)}{hint}")
        return pieces

    def _check_frame(self, where: _Where, subject: str, frame: Any) -> None:
        if frame is None or (isinstance(frame, str) and frame.strip().lstrip("/").lower() in self.map_frames):
            return
        shown = echo(frame) if isinstance(frame, str) else kind_of(frame)
        raise where.refuse(
            f"{subject} is in frame {shown}; coordinates are read in the map frame only "
            f"({', '.join(self.map_frames)}): convert the point to the map frame, or name the place"
        )

    def _metres(self, where: _Where, what: str, value: Any) -> float:
        number, _ = self._number(where, what, self._metres_spec, value, None)
        if not math.isfinite(number):
            raise where.refuse(f"{what} must be a finite number, got {echo(value)}")
        if not METRES_MIN <= number <= METRES_MAX:
            raise where.refuse(
                f"{what} is {number:g} m; allowed {METRES_MIN:g}..{METRES_MAX:g} m (metres, in the map frame)"
            )
        return number

    def _value(self, where: _Where, name: str, spec: ParamSpec, value: Any, unit_word: str | None) -> ParamValue:
        what = f"parameter '{name}'"
        if spec.type == "str":
            if not isinstance(value, str):
                raise where.refuse(f"{what} must be text, got {kind_of(value)}")
            text = value.strip()
            if _CONTROL.search(text):
                raise where.refuse(f"{what} contains control characters")
            limit = min(spec.max_length, self.config.max_string_chars)
            if len(text) > limit:
                raise where.refuse(f"{what} is {len(text)} characters; at most {limit}")
            if spec.choices:
                if text.lower() not in spec.choices:
                    raise where.refuse(f"{what} is {echo(text)}; expected one of {', '.join(spec.choices)}")
                return text.lower()
            return text
        if spec.type == "bool":
            if isinstance(value, bool):
                return value
            if isinstance(value, str) and value.strip().lower() in ("true", "false"):
                return value.strip().lower() == "true"
            raise where.refuse(f"{what} must be true or false, got {echo(value)}")
        number, bare = self._number(where, what, spec, value, unit_word)
        if not math.isfinite(number):
            raise where.refuse(f"{what} must be a finite number, got {echo(value)}")
        unit = f" {spec.unit}" if spec.unit else ""
        if (spec.min is not None and number < spec.min) or (spec.max is not None and number > spec.max):
            low = "" if spec.min is None else f"{spec.min:g}"
            high = "" if spec.max is None else f"{spec.max:g}"
            hint = ""
            if bare and spec.unit:
                example = _example(self.vocabulary, spec, number)
                hint = f" (a number without a unit is in {spec.unit}; write the unit, e.g. '{example}')"
            raise where.refuse(f"{what} is {number:g}{unit}; allowed {low}..{high}{unit}{hint}")
        if spec.type == "int":
            if number != int(number):
                raise where.refuse(f"{what} must be a whole number, got {echo(value)}")
            return int(number)
        return float(number)

    def _number(
        self, where: _Where, what: str, spec: ParamSpec, value: Any, unit_word: str | None
    ) -> tuple[float, bool]:
        """The value in the parameter's SI unit, and whether it came without a unit."""
        factors = self.vocabulary.units.get(spec.unit, {})
        if isinstance(value, bool) or not isinstance(value, _NUMBER_OR_TEXT):
            raise where.refuse(f"{what} must be a number, got {kind_of(value)}")
        if not isinstance(value, str):
            try:
                number = float(value)
            except OverflowError:
                raise where.refuse(f"{what} is too large a number") from None
            if not math.isfinite(number):
                raise where.refuse(f"{what} must be a finite number")
            if unit_word is not None:
                return number * factors[unit_word], False
            return number, True
        if len(value) > MAX_NUMBER_CHARS:  # cut, "5 <99 spaces> mm" would lose its unit
            raise where.refuse(
                f"{what} is {len(value)} characters; a number with its unit has at most {MAX_NUMBER_CHARS}"
            )
        match = _NUMBER_WITH_UNIT.match(value)
        if match is None:
            raise where.refuse(f"{what} must be a number, got {echo(value)}")
        number = float(match.group(1))
        word = " ".join((match.group(2) or "").lower().split())
        if not word:
            if unit_word is not None:
                return number * factors[unit_word], False
            return number, True
        if word not in factors:
            expected = f"in {spec.unit} ({', '.join(list(factors)[:12])})" if factors else "without a unit"
            raise where.refuse(f"{what} has unit {echo(word)}; give it {expected}")
        return number * factors[word], False

    def _names(
        self,
        where: _Where,
        action: Action,
        names: dict[str, str],
        params: dict[str, ParamValue],
        warnings: list[str],
        has_point: bool = False,
    ) -> tuple[str | None, str | None]:
        """Target and location by action, from whichever of target / target_object / target_location was given.

        A step with coordinates needs no name: the resolver grounds the point (a name, when given, wins).
        """
        used: set[str] = set()
        target: str | None = None
        location: str | None = None
        if action in _GOES_TO:
            target = _take(names, used, "target", "target_location", "target_object")
            if target is None and not has_point:
                raise where.refuse(f"{action.value} needs a target: {_GOES_TO[action]}{self._or_point(action)}")
        elif action in _FINDS:
            target = _take(names, used, "target", "target_object")
            location = _take(names, used, "target_location")
            if target is None and not has_point:
                raise where.refuse(f"{action.value} needs a target: which object{self._or_point(action)}")
        elif action is _PLACE:
            location = _take(names, used, "target_location", "target")
            target = _take(names, used, "target_object") or (
                _take(names, used, "target") if "target_location" in names else None
            )
            if location is None and not has_point:
                need = "the furniture to put the object on"
                raise where.refuse(f"place needs a location: {need}{self._or_point(action)}")
        elif action is _GESTURE:
            target = _take(names, used, "target", "target_object")
        elif action is _SAY:
            spoken = _take(names, used, "target")
            if spoken is not None:
                spec = self.params[action]["text"][1]
                if "text" in params:
                    warnings.append(f"{where.label}: parameter 'text' ignored: the target is what is said")
                params["text"] = self._value(where, "text", spec, spoken, None)
            if not params.get("text"):
                raise where.refuse("say needs the words to speak, in 'target' or parameters.text")
        elif action is _WAIT and "duration" not in params and "target" in names:
            used.add("target")
            params["duration"] = self._value(
                where, "duration", self.params[action]["duration"][1], names["target"], None
            )
        if len(used) < len(names):  # `used` holds only names given
            for f in _NAME_FIELDS:
                if f in names and f not in used:
                    warnings.append(f"{where.label}: {f} {echo(names[f])} ignored: {action.value} does not use it")
        # Written out, not looped over (value, label) pairs: every step of a plan comes here; the loop was a
        # quarter of the time a plain step's names took.
        if target is not None and len(target) > MAX_NAME_CHARS:
            raise where.refuse(f"target is {len(target)} characters; a name has at most {MAX_NAME_CHARS}")
        if location is not None and len(location) > MAX_NAME_CHARS:
            raise where.refuse(f"location is {len(location)} characters; a name has at most {MAX_NAME_CHARS}")
        return target, location

    def _or_point(self, action: Action) -> str:
        return ", or coordinates x and y in metres" if action in self.coordinate_actions else ""

    def _text(self, value: Any, what: str, warnings: list[str]) -> str:
        if not isinstance(value, str):
            if value not in (None, ""):
                warnings.append(f"{what} ignored: it is {kind_of(value)}, not text")
            return ""
        if _CONTROL.search(value):
            warnings.append(f"{what}: control characters removed")
            value = _CONTROL.sub("", value)
        limit = self.config.max_string_chars
        if len(value) > limit:
            warnings.append(f"{what} cut to {limit} characters (was {len(value)})")
            return value[:limit]
        return value


# Actions whose target is where they go (and what each needs), those whose target is an object; the
# members looked up once, as an Enum's attribute lookups are slow.
_GOES_TO = {
    Action.NAVIGATE_TO: "where to go",
    Action.LOOK_AT: "what to look at",
    Action.MOVE_ARM: "a named arm pose such as home or ready",
}
_FINDS = frozenset((Action.PICK, Action.DETECT))
_PLACE, _GESTURE, _SAY, _WAIT = Action.PLACE, Action.GESTURE, Action.SAY, Action.WAIT


def _take(names: dict[str, str], used: set[str], *fields: str) -> str | None:
    """The first of `fields` given in `names`, noted as used."""
    for f in fields:
        if f in names:
            used.add(f)
            return names[f]
    return None


# Where a plain step is, for the checks it shares with the general mapping; their refusals are not
# shown (the general mapping reads the plan again and words them), so one place does for all.
_PLAIN = _Where("a plain step", 0)


def _plain_steps_type(fields: dict[str, str], ignored: set[str]) -> type[msgspec.Struct] | None:
    """Steps with a step's fields under their own names, and the ignored ones: what `Parser._plain_steps` reads.

    None when the vocabulary gives one of those names another meaning. The steps are held by a
    Struct rather than converted as `list[PlainStep]`: msgspec keeps a Struct's type information,
    where a list type is examined again on every call (0.8 us a plan).
    """
    own = ("action", *_NAME_FIELDS, "description", "parameters")
    if any(fields.get(name) != name for name in own):
        return None
    kinds: list[tuple[str, Any, Any]] = [("action", str, msgspec.NODEFAULT)]
    kinds += [(name, str | None, None) for name in (*_NAME_FIELDS, "description")]
    kinds.append(("parameters", dict[str, ParamValue] | None, None))
    # Ignored keys need not be identifiers: each is held by an attribute of its own, renamed.
    skipped = sorted(word for word in ignored if word not in fields)
    kinds += [(f"ignored_{i}", Any, None) for i in range(len(skipped))]
    rename = {f"ignored_{i}": word for i, word in enumerate(skipped)}
    step = msgspec.defstruct("PlainStep", kinds, kw_only=True, forbid_unknown_fields=True, rename=rename)
    return msgspec.defstruct("PlainSteps", [("steps", list[step])])  # type: ignore[valid-type]


# isinstance with a tuple: `int | float` written in a call builds the union object on every call.
_NUMBER = (int, float)
_NUMBER_OR_TEXT = (int, float, str)
_TEXT_OR_BOOL = (str, bool)


def _no_objects(value: Any) -> bool:
    """[1] in "as noted in [1]" is a citation, not a plan."""
    return isinstance(value, list) and not any(isinstance(v, dict) for v in value)


def _example(vocabulary: Vocabulary, spec: ParamSpec, number: float = 1.0) -> str:
    """'90 degrees' for an angle: the number with the first unit word that is not the SI one."""
    words = [w for w, f in vocabulary.units.get(spec.unit, {}).items() if f != 1.0 and " " not in w]
    return f"{number:g} {words[0] if words else spec.unit}"


def _point_text(point: tuple[float, float, float | None]) -> str:
    return "(" + ", ".join(f"{n:g}" for n in point if n is not None) + ")"


_ENCODER = msgspec.json.Encoder()
_PLAN_DECODER = msgspec.json.Decoder(Plan)


def _validated(plan: Plan) -> Plan:
    """Check every bound the schema declares (Struct constructors do not), naming the path on failure."""
    try:
        return _PLAN_DECODER.decode(_ENCODER.encode(plan))
    except msgspec.ValidationError as exc:
        raise ParseError(f"the plan does not fit the schema: {exc}") from None
    except UnicodeEncodeError:
        raise ParseError(LONE_SURROGATE) from None


def _encodable(error: ServiceError) -> ServiceError:
    """The refusal, its words as UTF-8 can carry them: a name it quotes from the plan may hold a lone
    surrogate (JSON's "\\ud800"), which no reply can encode; it is shown escaped."""
    texts = [error.message, *error.candidates]
    try:
        for text in texts:
            text.encode("utf-8")
    except UnicodeEncodeError:
        message, *candidates = [text.encode("utf-8", "backslashreplace").decode("utf-8") for text in texts]
        return msgspec.structs.replace(error, message=message, candidates=candidates)
    return error


@functools.cache
def default_parser() -> Parser:
    return Parser(load_vocabulary(), load_grammar())


def parse(text: str, fmt: str = "auto") -> Plan:
    """Parse plan text with the bundled vocabulary; raises ParseError naming what was wrong."""
    return default_parser().parse(text, fmt)


def answer(parser: Parser, request: PlanText) -> ParseReply:
    """What plan/parse replies: the Plan, or the refusal as a value. Never raises."""
    try:
        return parser.parse(request.text, request.format)
    except ParseError as exc:
        return _encodable(exc.error)
    except RecursionError:
        return ServiceError(kind=ErrorKind.INVALID_REQUEST, message="plan text is nested too deeply", stage=Stage.PARSE)
