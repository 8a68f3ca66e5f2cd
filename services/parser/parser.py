"""Plan text -> Plan: find the JSON, map LLM words onto canonical actions, validate every value."""

from __future__ import annotations

import functools
import math
import re
from dataclasses import dataclass, field
from typing import Any

import msgspec
from rapidfuzz import fuzz, process

from schemas.common import ErrorKind, ServiceError, Stage
from schemas.plan import MAX_PLAN_BYTES, MAX_STEPS, Action, ParamValue, ParseReply, Plan, PlanText, Step
from services.parser.errors import ParseError
from services.parser.extract import JsonFinder
from services.parser.vocabulary import ParamSpec, Vocabulary, load_vocabulary, normalise_word

SUPPORTED_FORMATS = ("auto", "json")
LATER_FORMATS = ("yaml", "text")
MAX_NAME_CHARS = 200
MAX_TEXT_CHARS = 4000
# Names echoed back in messages are cut to this, so hostile input cannot bloat a reply.
ECHO_CHARS = 60
MAX_LISTED = 10
_NUMBER_WITH_UNIT = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([A-Za-z/]*)\s*$")
_STEP_FIELDS = ("target", "target_object", "target_location")
# Control characters have no place in a name or a spoken sentence (newlines and tabs excepted).
_CONTROL = re.compile(r"[\x00-\x08\x0b-\x1f\x7f]")


def echo(value: object) -> str:
    text = value if isinstance(value, str) else repr(value)
    return repr(text if len(text) <= ECHO_CHARS else text[:ECHO_CHARS] + "...")


def _listing(names: list[str]) -> str:
    shown = ", ".join(names[:MAX_LISTED])
    return shown if len(names) <= MAX_LISTED else f"{shown} and {len(names) - MAX_LISTED} more"


def _type_name(value: object) -> str:
    return {dict: "an object", list: "an array", str: "a string", bool: "a boolean", type(None): "null"}.get(
        type(value), "a number"
    )


@dataclass
class _RawStep:
    """One step's fields after mapping LLM field names onto ours; what is left over is warned about."""

    action: Any = None
    names: dict[str, str] = field(default_factory=dict)
    parameters: dict[str, Any] = field(default_factory=dict)
    description: str = ""


class Parser:
    """Turns untrusted text into a validated Plan, or raises ParseError naming what was wrong."""

    def __init__(
        self,
        vocabulary: Vocabulary,
        *,
        max_depth: int = 32,
        lenient_json: bool = True,
        max_repair_chars: int = 64 * 1024,
    ) -> None:
        self.vocabulary = vocabulary
        self.finder = JsonFinder(max_depth=max_depth, lenient=lenient_json, max_repair_chars=max_repair_chars)
        self.actions: dict[str, Action] = {}
        for action, spec in vocabulary.actions.items():
            for name in (action.value, *spec.synonyms):
                self.actions[normalise_word(name)] = action
        self.params: dict[Action, dict[str, tuple[str, ParamSpec]]] = {}
        for action, spec in vocabulary.actions.items():
            self.params[action] = {
                normalise_word(alias): (name, pspec)
                for name, pspec in spec.params.items()
                for alias in (name, *pspec.aliases)
            }
        self.fields: dict[str, str] = {
            normalise_word(alias): name for name, aliases in vocabulary.fields.items() for alias in aliases
        }
        for name in ("action", "target", "target_object", "target_location", "parameters", "description"):
            self.fields.setdefault(name, name)
        self.ignored_fields = {normalise_word(n) for n in vocabulary.ignored_fields}
        self.position_params = {normalise_word(n) for n in vocabulary.position_params}
        self.plan_keys = [normalise_word(k) for k in vocabulary.plan_keys]

    # The whole text

    def parse(self, text: str, fmt: str = "auto") -> Plan:
        if fmt in LATER_FORMATS:
            raise ParseError(f"format {fmt!r} is not supported yet; send the plan as JSON (format 'json' or 'auto')")
        if fmt not in SUPPORTED_FORMATS:
            raise ParseError(f"unknown format {echo(fmt)}; expected one of auto, json, yaml, text")
        if not isinstance(text, str):
            raise ParseError(f"plan text must be a string, got {_type_name(text)}")
        if not text:
            raise ParseError("plan text is empty")
        if not text.strip():
            raise ParseError("plan text is only whitespace")
        try:
            size = len(text.encode("utf-8"))
        except UnicodeEncodeError as exc:
            raise ParseError(f"plan text is not valid UTF-8 (character {exc.start + 1} is a lone surrogate)") from None
        if size > MAX_PLAN_BYTES:
            raise ParseError(f"plan text is {size} bytes; at most {MAX_PLAN_BYTES} are accepted")
        if "\x00" in text:
            raise ParseError(f"plan text contains a NUL character at position {text.index(chr(0)) + 1}")
        found = self.finder.find(text, self._looks_like_plan)
        warnings = list(found.warnings)
        raw_steps, description = self._steps_of(found.value, warnings)
        steps = [self._step(i, raw, warnings) for i, raw in enumerate(raw_steps)]
        plan = Plan(steps=steps, description=self._text(description, "the plan's description", warnings), warnings=[])
        plan = msgspec.structs.replace(plan, warnings=[w[:MAX_TEXT_CHARS] for w in warnings])
        return _validated(plan)

    def _looks_like_plan(self, value: Any) -> bool:
        if isinstance(value, list):
            return bool(value) and all(isinstance(v, dict) for v in value)
        if isinstance(value, dict):
            keys = {normalise_word(k) for k in value if isinstance(k, str)}
            return any(k in keys for k in self.plan_keys) or any(self.fields.get(k) == "action" for k in keys)
        return False

    def _steps_of(self, value: Any, warnings: list[str]) -> tuple[list[Any], Any]:
        no_plan = "no plan found: expected a JSON object with a 'plan' array or a JSON array of steps"
        description: Any = ""
        if isinstance(value, dict):
            by_key = {normalise_word(k): k for k in value}
            plan_key = next((by_key[k] for k in self.plan_keys if k in by_key), None)
            if plan_key is None:
                if any(self.fields.get(k) == "action" for k in by_key):
                    return [value], ""  # a single step on its own
                keys = [echo(k) for k in value]
                raise ParseError(f"{no_plan}; found an object with keys {_listing(keys)}" if keys else no_plan)
            steps = value[plan_key]
            description = value.get(by_key.get("description", ""), "")
            extra = [echo(k) for k in value if k not in (plan_key, by_key.get("description"))]
            if extra:
                warnings.append(f"top-level field(s) {_listing(extra)} ignored")
            if not isinstance(steps, list):
                raise ParseError(f"'{plan_key}' must be an array of steps, got {_type_name(steps)}")
        elif isinstance(value, list):
            steps = value
        else:
            raise ParseError(f"{no_plan}; found {_type_name(value)}")
        if not steps:
            raise ParseError("the plan has no steps")
        if len(steps) > MAX_STEPS:
            raise ParseError(f"the plan has {len(steps)} steps; at most {MAX_STEPS} are accepted")
        return steps, description

    # One step

    def _step(self, index: int, value: Any, warnings: list[str]) -> Step:
        if not isinstance(value, dict):
            raise ParseError(f"is {_type_name(value)}, not an object with an 'action'", step=index)
        raw = self._fields(index, value, warnings)
        action = self._action(index, raw.action)
        params = self._params(index, action, raw.parameters, warnings)
        target, location = self._names(index, action, raw.names, params, warnings)
        for name, pspec in self.vocabulary.actions[action].params.items():
            if pspec.required and name not in params:
                raise ParseError(f"{action.value} needs parameter '{name}'", step=index)
        description = self._text(raw.description, f"step {index + 1}: description", warnings)
        return Step(action=action, target=target, location=location, params=params, description=description)

    def _fields(self, index: int, value: dict[Any, Any], warnings: list[str]) -> _RawStep:
        raw = _RawStep()
        ignored: list[str] = []
        for key, item in value.items():
            name = self.fields.get(normalise_word(key)) if isinstance(key, str) else None
            if name is None:
                if not isinstance(key, str) or normalise_word(key) not in self.ignored_fields:
                    ignored.append(echo(key))
            elif name == "action":
                raw.action = item
            elif name == "parameters":
                if item is None:
                    continue
                if not isinstance(item, dict):
                    raise ParseError(f"'{key}' must be an object, got {_type_name(item)}", step=index)
                raw.parameters = item
            elif name == "description":
                if isinstance(item, str):
                    raw.description = item
                elif item is not None:
                    warnings.append(f"step {index + 1}: description ignored: it is {_type_name(item)}, not text")
            elif item is None or (isinstance(item, str) and not item.strip()):
                continue
            elif not isinstance(item, str):
                raise ParseError(f"'{key}' must be a name (a string), got {_type_name(item)}", step=index)
            elif _CONTROL.search(item):
                raise ParseError(f"'{key}' contains control characters", step=index)
            else:
                raw.names[name] = item.strip()
        if ignored:
            warnings.append(f"step {index + 1}: field(s) {_listing(ignored)} ignored: not part of a step")
        return raw

    def _action(self, index: int, value: Any) -> Action:
        known = ", ".join(a.value for a in self.vocabulary.actions)
        if value is None or (isinstance(value, str) and not value.strip()):
            raise ParseError(f"has no 'action'; known actions: {known}", step=index)
        if not isinstance(value, str):
            raise ParseError(f"'action' must be a string, got {_type_name(value)}", step=index)
        word = normalise_word(value)
        if word in self.actions:
            return self.actions[word]
        matches = process.extract(word[:200], list(self.actions), scorer=fuzz.ratio, limit=3, score_cutoff=70)
        suggestions = [m[0] for m in matches]
        hint = ""
        if suggestions:
            best = suggestions[0]
            canonical = self.actions[best].value
            hint = f" (did you mean '{best}'?)" if best == canonical else f" (did you mean '{best}', i.e. {canonical}?)"
        raise ParseError(
            f"unknown action {echo(value)}{hint}; known actions: {known}",
            kind=ErrorKind.UNKNOWN_ACTION,
            step=index,
            candidates=suggestions,
        )

    def _params(self, index: int, action: Action, given: dict[Any, Any], warnings: list[str]) -> dict[str, ParamValue]:
        params: dict[str, ParamValue] = {}
        positions: list[str] = []
        unknown: list[str] = []
        known = self.params[action]
        for key, value in given.items():
            word = normalise_word(key) if isinstance(key, str) else ""
            if word in known:
                name, pspec = known[word]
                if name in params:
                    raise ParseError(f"parameter '{name}' is given twice (as {echo(key)})", step=index)
                params[name] = self._value(index, name, pspec, value)
            elif word in self.position_params:
                positions.append(str(key)[:ECHO_CHARS])
            else:
                unknown.append(echo(key))
        if positions:
            noun = "parameter" if len(positions) == 1 else "parameters"
            warnings.append(
                f"step {index + 1}: {noun} {_listing(positions)} ignored: {self.vocabulary.position_reason}"
            )
        if unknown:
            names = sorted(self.vocabulary.actions[action].params)
            takes = f"it takes {', '.join(names)}" if names else "it takes none"
            warnings.append(
                f"step {index + 1}: unknown parameter(s) {_listing(unknown)} for {action.value} ignored; {takes}"
            )
        return params

    def _value(self, index: int, name: str, spec: ParamSpec, value: Any) -> ParamValue:
        where = f"parameter '{name}'"
        if spec.type == "str":
            if not isinstance(value, str):
                raise ParseError(f"{where} must be text, got {_type_name(value)}", step=index)
            text = value.strip()
            if _CONTROL.search(text):
                raise ParseError(f"{where} contains control characters", step=index)
            if len(text) > spec.max_length:
                raise ParseError(f"{where} is {len(text)} characters; at most {spec.max_length}", step=index)
            if spec.choices:
                if text.lower() not in spec.choices:
                    raise ParseError(f"{where} is {echo(text)}; expected one of {', '.join(spec.choices)}", step=index)
                return text.lower()
            return text
        if spec.type == "bool":
            if isinstance(value, bool):
                return value
            if isinstance(value, str) and value.strip().lower() in ("true", "false"):
                return value.strip().lower() == "true"
            raise ParseError(f"{where} must be true or false, got {echo(value)}", step=index)
        number = self._number(index, where, spec, value)
        if not math.isfinite(number):
            raise ParseError(f"{where} must be a finite number, got {echo(value)}", step=index)
        unit = f" {spec.unit}" if spec.unit else ""
        if (spec.min is not None and number < spec.min) or (spec.max is not None and number > spec.max):
            low = "" if spec.min is None else f"{spec.min:g}"
            high = "" if spec.max is None else f"{spec.max:g}"
            raise ParseError(f"{where} is {number:g}{unit}; allowed {low}..{high}{unit}", step=index)
        if spec.type == "int":
            if number != int(number):
                raise ParseError(f"{where} must be a whole number, got {echo(value)}", step=index)
            return int(number)
        return float(number)

    def _number(self, index: int, where: str, spec: ParamSpec, value: Any) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float | str):
            raise ParseError(f"{where} must be a number, got {_type_name(value)}", step=index)
        if not isinstance(value, str):
            try:
                number = float(value)
            except OverflowError:
                raise ParseError(f"{where} is too large a number", step=index) from None
            if not math.isfinite(number):
                raise ParseError(f"{where} must be a finite number", step=index)
            return number
        match = _NUMBER_WITH_UNIT.match(value[:100])
        if match is None:
            raise ParseError(f"{where} must be a number, got {echo(value)}", step=index)
        number, word = float(match.group(1)), match.group(2).lower()
        if not word:
            return number
        factors = self.vocabulary.units.get(spec.unit, {})
        if word not in factors:
            expected = f"in {spec.unit} ({', '.join(factors)})" if factors else "without a unit"
            raise ParseError(f"{where} has unit {echo(word)}; give it {expected}", step=index)
        return number * factors[word]

    def _names(
        self,
        index: int,
        action: Action,
        names: dict[str, str],
        params: dict[str, ParamValue],
        warnings: list[str],
    ) -> tuple[str | None, str | None]:
        """Target and location by action, from whichever of target / target_object / target_location was given."""
        target = names.get("target")
        used: set[str] = set()

        def take(*fields: str) -> str | None:
            for f in fields:
                if f in names:
                    used.add(f)
                    return names[f]
            return None

        new_target: str | None = None
        new_location: str | None = None
        if action is Action.NAVIGATE_TO:
            new_target = take("target", "target_location", "target_object")
            if new_target is None:
                raise ParseError("navigate_to needs a target: where to go", step=index)
        elif action in (Action.PICK, Action.DETECT):
            new_target = take("target", "target_object")
            new_location = take("target_location")
            if new_target is None:
                raise ParseError(f"{action.value} needs a target: which object", step=index)
        elif action is Action.PLACE:
            new_location = take("target_location", "target")
            new_target = take("target_object") or (take("target") if "target_location" in names else None)
            if new_location is None:
                raise ParseError("place needs a location: the furniture to put the object on", step=index)
        elif action is Action.SAY:
            spoken = take("target")
            if spoken is not None:
                spec = self.params[action]["text"][1]
                if "text" in params:
                    warnings.append(f"step {index + 1}: parameter 'text' ignored: the target is what is said")
                params["text"] = self._value(index, "text", spec, spoken)
            if not params.get("text"):
                raise ParseError("say needs the words to speak, in 'target' or parameters.text", step=index)
        elif action is Action.WAIT and "duration" not in params and target is not None:
            used.add("target")
            params["duration"] = self._value(index, "duration", self.params[action]["duration"][1], target)
        for f in _STEP_FIELDS:
            if f in names and f not in used:
                warnings.append(f"step {index + 1}: {f} {echo(names[f])} ignored: {action.value} does not use it")
        for value, label in ((new_target, "target"), (new_location, "location")):
            if value is not None and len(value) > MAX_NAME_CHARS:
                raise ParseError(f"{label} is {len(value)} characters; a name has at most {MAX_NAME_CHARS}", step=index)
        return new_target, new_location

    def _text(self, value: Any, what: str, warnings: list[str]) -> str:
        if not isinstance(value, str):
            if value not in (None, ""):
                warnings.append(f"{what} ignored: it is {_type_name(value)}, not text")
            return ""
        if _CONTROL.search(value):
            warnings.append(f"{what}: control characters removed")
            value = _CONTROL.sub("", value)
        if len(value) > MAX_TEXT_CHARS:
            warnings.append(f"{what} cut to {MAX_TEXT_CHARS} characters (was {len(value)})")
            return value[:MAX_TEXT_CHARS]
        return value


def _validated(plan: Plan) -> Plan:
    """Check every bound the schema declares (Struct constructors do not), naming the path on failure."""
    try:
        return msgspec.json.decode(msgspec.json.encode(plan), type=Plan)
    except msgspec.ValidationError as exc:
        raise ParseError(f"the plan does not fit the schema: {exc}") from None


@functools.cache
def default_parser() -> Parser:
    return Parser(load_vocabulary())


def parse(text: str, fmt: str = "auto") -> Plan:
    """Parse plan text with the bundled vocabulary; raises ParseError naming what was wrong."""
    return default_parser().parse(text, fmt)


def answer(parser: Parser, request: PlanText) -> ParseReply:
    """What plan/parse replies: the Plan, or the refusal as a value. Never raises."""
    try:
        return parser.parse(request.text, request.format)
    except ParseError as exc:
        return exc.error
    except RecursionError:
        return ServiceError(kind=ErrorKind.INVALID_REQUEST, message="plan text is nested too deeply", stage=Stage.PARSE)
