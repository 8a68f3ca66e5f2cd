"""The parser's vocabulary file: action names, their synonyms and the parameters each takes."""

from __future__ import annotations

import functools
import math
import re
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal

import msgspec
from msgspec import Meta

from schemas.plan import Action
from services.datafile import read_struct
from services.parser.errors import VocabularyError

Word = Annotated[str, Meta(min_length=1, max_length=64)]
StepField = Literal[
    "action", "target", "target_object", "target_location", "parameters", "description", "substeps", "on_failure"
]
# The axes of schemas.plan.Coordinates: numbers beside the action or in its parameters.
AXES = ("x", "y", "z")
STEP_FIELDS: tuple[StepField, ...] = (
    "action",
    "target",
    "target_object",
    "target_location",
    "parameters",
    "description",
    "substeps",
    "on_failure",
)


class ParamSpec(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """One parameter: its type, SI unit, bounds and the other names LLMs give it."""

    type: Literal["float", "int", "bool", "str"]
    unit: str = ""
    min: float | None = None
    max: float | None = None
    choices: list[Word] = []
    max_length: Annotated[int, Meta(ge=1, le=4000)] = 200
    aliases: list[Word] = []
    # Other names that also say the unit of a bare number: {angle_deg: deg}.
    unit_aliases: dict[Word, Word] = {}
    required: bool = False
    # A str parameter whose value sets this number's sign (turn.angle by direction).
    signed_by: Word | None = None
    # For a direction parameter: the choices that mean a negative sign.
    negative: list[Word] = []


class NameSpec(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A name an action's tool takes (target, location): what it means, for a model writing it."""

    description: str
    required: bool = False


class ActionSpec(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    synonyms: list[Word] = []
    # Synonyms that also set str parameters: {turn_right: {direction: right}}.
    variants: dict[Word, dict[Word, Word]] = {}
    params: dict[Word, ParamSpec] = {}
    # What the action does, for a model choosing among the agent's tools (services/agent/tools.py).
    summary: str = ""
    # The names its tool takes, in this order; an action without them takes parameters only.
    names: dict[Literal["target", "location"], NameSpec] = {}


class CoordinateSpec(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Where a plan may write a point (metres, map frame) and which actions carry it in Step.coordinates."""

    actions: list[Action] = []
    # Keys holding a whole point: {x, y, z?}, [x, y], [x, y, z] or "x, y".
    points: list[Word] = []
    # Points that may also hold a heading: a third number there may be z or yaw, so it is refused.
    poses: list[Word] = []
    # Headings, beside the point or inside it: ignored with `heading_reason`.
    headings: list[Word] = []
    heading_reason: str = "the resolver chooses headings"
    # Keys of a point object naming its frame, and the frame names that mean the map frame.
    frames: list[Word] = []
    map_frames: list[Word] = msgspec.field(default_factory=lambda: ["map"])


class SlotSpec(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A name an expansion takes: from the first of `fields` given, else `default`, else refused with `needs`."""

    fields: Annotated[list[Literal["target", "target_object", "target_location"]], Meta(min_length=1)]
    default: Word | None = None
    needs: str = ""


class StepTemplate(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """One step of an expansion: target and location are "{slot}" or words kept as written."""

    action: Action
    target: Word | None = None
    location: Word | None = None


class ExpansionSpec(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """An action name that stands for several steps ("bring": pick, then place by the person)."""

    synonyms: list[Word] = []
    slots: dict[Word, SlotSpec] = {}
    describe: str = ""
    steps: Annotated[list[StepTemplate], Meta(min_length=1, max_length=8)]


class GraspHints(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Grasp types given where a parameter expects something else: each type's meaning, and the reason."""

    params: list[Word] = []
    types: dict[Word, Word] = {}
    meanings: dict[Word, str] = {}
    reason: str = ""


class IgnoredHints(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    params: Annotated[list[Word], Meta(min_length=1)]
    reason: str


class MannerHints(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Manner words, what each means, and the speed each meaning sets per action when the step gives none."""

    params: list[Word] = []
    words: dict[Word, Word] = {}
    speeds: dict[Word, dict[Action, Annotated[float, Meta(gt=0.0)]]] = {}


class HintSpec(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    grasp: GraspHints = GraspHints()
    ignored: list[IgnoredHints] = []
    manner: MannerHints = MannerHints()


class Vocabulary(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    actions: dict[Action, ActionSpec]
    coordinates: CoordinateSpec = CoordinateSpec()
    position_params: list[Word] = []
    position_reason: str = "positions come from the world model"
    units: dict[Word, dict[Word, Annotated[float, Meta(gt=0.0)]]] = {}
    fields: dict[StepField, list[Word]] = {}
    ignored_fields: list[Word] = []
    plan_keys: Annotated[list[Word], Meta(min_length=1)] = msgspec.field(default_factory=lambda: ["plan"])
    # Tools whose arguments hold a whole plan (execute_plan), when a plan arrives as a tool call.
    plan_tools: list[Word] = []
    # Action names that stand for several steps (services/parser/expand.py).
    expansions: dict[Word, ExpansionSpec] = {}
    # What a plan may say that is a hint, not a command (services/parser/hints.py).
    hints: HintSpec = HintSpec()


@functools.lru_cache(maxsize=4096)
def _normalise(word: str) -> str:
    word = re.sub(r"(?<=[a-z0-9])(?=[A-Z])", "_", word.strip())
    return re.sub(r"[\s\-]+", "_", word.lower())


def normalise_word(word: str) -> str:
    """'Pick Up', 'pick-up', 'pickUp' -> 'pick_up'. Cached: the same few field names come again and again."""
    return _normalise(word) if len(word) <= 64 else _normalise.__wrapped__(word)


def default_vocabulary_path() -> Path:
    return Path(str(resources.files("services") / "parser" / "vocabulary.yaml"))


def load_vocabulary(path: Path | None = None) -> Vocabulary:
    path = path or default_vocabulary_path()
    vocabulary = read_struct(path, Vocabulary, "vocabulary", VocabularyError)
    _check(vocabulary, path)
    return vocabulary


def _check(vocabulary: Vocabulary, path: Path) -> None:
    missing = [a.value for a in Action if a not in vocabulary.actions]
    if missing:
        raise VocabularyError(f"vocabulary file {path}: no entry for actions {missing}")
    unsummed = [a.value for a, spec in vocabulary.actions.items() if not spec.summary.strip()]
    if unsummed:
        raise VocabularyError(f"vocabulary file {path}: no summary for actions {unsummed}")
    seen: dict[str, str] = {}
    for action, spec in vocabulary.actions.items():
        for name in (action.value, *spec.synonyms, *spec.variants):
            word = normalise_word(name)
            if seen.setdefault(word, action.value) != action.value:
                raise VocabularyError(f"vocabulary file {path}: {name!r} names both {seen[word]} and {action.value}")
        param_names: set[str] = set()
        for param, pspec in spec.params.items():
            where = f"vocabulary file {path}: {action.value}.{param}"
            for name in (param, *pspec.aliases, *pspec.unit_aliases):
                if normalise_word(name) in param_names:
                    raise VocabularyError(f"vocabulary file {path}: {action.value} parameter {name!r} named twice")
                param_names.add(normalise_word(name))
            if pspec.unit and pspec.unit not in vocabulary.units:
                raise VocabularyError(f"{where} has unknown unit {pspec.unit!r}")
            for alias, unit in pspec.unit_aliases.items():
                if unit not in vocabulary.units.get(pspec.unit, {}):
                    raise VocabularyError(f"{where}: unit alias {alias!r} names {unit!r}, not a unit of {pspec.unit!r}")
            for side, bound in (("min", pspec.min), ("max", pspec.max)):
                # A NaN bound compares false with every number: the parser would let any value through.
                if bound is not None and not math.isfinite(bound):
                    raise VocabularyError(f"{where}: {side} {bound} is not a finite number")
            if pspec.min is not None and pspec.max is not None and pspec.min > pspec.max:
                raise VocabularyError(f"{where} has min > max")
            if pspec.signed_by is not None:
                sign = spec.params.get(pspec.signed_by)
                if sign is None or sign.type != "str" or not sign.negative:
                    raise VocabularyError(f"{where}: signed_by {pspec.signed_by!r} is not a direction parameter")
            if not set(pspec.negative) <= set(pspec.choices):
                raise VocabularyError(f"{where}: negative values must be among its choices")
        for variant, preset in spec.variants.items():
            for param, value in preset.items():
                target = spec.params.get(param)
                if target is None or value not in target.choices:
                    raise VocabularyError(
                        f"vocabulary file {path}: variant {variant!r} sets {param}={value!r}, "
                        f"not a choice of a parameter of {action.value}"
                    )
    _check_expansions(vocabulary, path, seen)
    _check_hints(vocabulary, path)
    field_names: dict[str, str] = {}
    for field, names in vocabulary.fields.items():
        for name in names:
            if field_names.setdefault(normalise_word(name), field) != field:
                raise VocabularyError(f"vocabulary file {path}: step field {name!r} means two fields")
    _check_coordinates(vocabulary, path, field_names)


def _check_coordinates(vocabulary: Vocabulary, path: Path, field_names: dict[str, str]) -> None:
    spec = vocabulary.coordinates
    field_names = {**{name: name for name in STEP_FIELDS}, **field_names}
    kinds: dict[str, str] = {}
    groups = (
        ("coordinate axis", AXES),
        ("point", spec.points),
        ("heading", spec.headings),
        ("frame", spec.frames),
        ("position", vocabulary.position_params),
    )
    for kind, names in groups:
        for name in names:
            word = normalise_word(name)
            if kinds.setdefault(word, kind) != kind:
                raise VocabularyError(f"vocabulary file {path}: {name!r} is listed as a {kinds[word]} and a {kind} key")
            # A name field ("location": "kitchen") may also hold a point ("location": [2, 3]); nothing else may.
            if word in field_names and (kind != "point" or field_names[word] != "target_location"):
                raise VocabularyError(f"vocabulary file {path}: {kind} key {name!r} is also a step field")
    if not {normalise_word(p) for p in spec.poses} <= {normalise_word(p) for p in spec.points}:
        raise VocabularyError(f"vocabulary file {path}: coordinates.poses must be among coordinates.points")


def slot_reference(value: str | None) -> str | None:
    """'object' for "{object}"; None for words kept as written."""
    if value is not None and len(value) > 2 and value[0] == "{" and value[-1] == "}":
        return value[1:-1].strip()
    return None


def _check_expansions(vocabulary: Vocabulary, path: Path, seen: dict[str, str]) -> None:
    for name, spec in vocabulary.expansions.items():
        where = f"vocabulary file {path}: expansions.{name}"
        for word in (name, *spec.synonyms):
            key = normalise_word(word)
            if seen.setdefault(key, f"expansion {name}") != f"expansion {name}":
                raise VocabularyError(f"{where}: {word!r} also names {seen[key]}")
        for slot_name, slot_spec in spec.slots.items():
            if slot_spec.default is None and not slot_spec.needs.strip():
                raise VocabularyError(f"{where}: slot {slot_name!r} needs a `default` or a `needs` text")
        for template in spec.steps:
            for written in (template.target, template.location):
                slot = slot_reference(written)
                if slot is not None and slot not in spec.slots:
                    action = template.action.value
                    raise VocabularyError(f"{where}: step {action} names {written!r}, not one of its slots")
        try:
            spec.describe.format_map(dict.fromkeys(spec.slots, ""))
        except (KeyError, ValueError, IndexError) as exc:
            raise VocabularyError(f"{where}: describe {spec.describe!r} names what no slot gives ({exc})") from None


def _check_hints(vocabulary: Vocabulary, path: Path) -> None:
    hints = vocabulary.hints
    where = f"vocabulary file {path}: hints"
    params = {
        normalise_word(n): action.value
        for action, spec in vocabulary.actions.items()
        for name, pspec in spec.params.items()
        for n in (name, *pspec.aliases, *pspec.unit_aliases)
    }
    names = [*hints.manner.params, *(n for group in hints.ignored for n in group.params)]
    for name in names:
        if normalise_word(name) in params:
            raise VocabularyError(f"{where}: {name!r} is a parameter of {params[normalise_word(name)]}, not a hint")
    for name in hints.grasp.params:
        if not any(name in spec.params for spec in vocabulary.actions.values()):
            raise VocabularyError(f"{where}.grasp: {name!r} is no action's parameter")
    for kind in hints.grasp.types.values():
        if kind not in hints.grasp.meanings:
            raise VocabularyError(f"{where}.grasp: type {kind!r} has no meaning")
    for meaning, speeds in hints.manner.speeds.items():
        if meaning not in hints.manner.words.values():
            raise VocabularyError(f"{where}.manner: speeds for {meaning!r}, which no manner word means")
        for action, speed in speeds.items():
            spec = vocabulary.actions[action].params.get("speed")
            low = spec.min if spec is not None and spec.min is not None else 0.0
            high = spec.max if spec is not None and spec.max is not None else 0.0
            if spec is None or not low <= speed <= high:
                raise VocabularyError(f"{where}.manner: {action.value} speed {speed:g} is not one its speed allows")
