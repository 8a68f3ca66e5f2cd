"""The parser's vocabulary file: action names, their synonyms and the parameters each takes."""

from __future__ import annotations

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
StepField = Literal["action", "target", "target_object", "target_location", "parameters", "description"]


class ParamSpec(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """One parameter: its type, SI unit, bounds and the other names LLMs give it."""

    type: Literal["float", "int", "bool", "str"]
    unit: str = ""
    min: float | None = None
    max: float | None = None
    choices: list[Word] = []
    max_length: Annotated[int, Meta(ge=1, le=4000)] = 200
    aliases: list[Word] = []
    required: bool = False


class ActionSpec(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    synonyms: list[Word] = []
    params: dict[Word, ParamSpec] = {}


class Vocabulary(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    actions: dict[Action, ActionSpec]
    position_params: list[Word] = []
    position_reason: str = "positions come from the world model"
    units: dict[Word, dict[Word, Annotated[float, Meta(gt=0.0)]]] = {}
    fields: dict[StepField, list[Word]] = {}
    ignored_fields: list[Word] = []
    plan_keys: Annotated[list[Word], Meta(min_length=1)] = msgspec.field(default_factory=lambda: ["plan"])


def normalise_word(word: str) -> str:
    """'Pick Up', 'pick-up', 'pickUp' -> 'pick_up'."""
    word = re.sub(r"(?<=[a-z0-9])(?=[A-Z])", "_", word.strip())
    return re.sub(r"[\s\-]+", "_", word.lower())


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
    seen: dict[str, str] = {}
    for action, spec in vocabulary.actions.items():
        for name in (action.value, *spec.synonyms):
            word = normalise_word(name)
            if seen.setdefault(word, action.value) != action.value:
                raise VocabularyError(f"vocabulary file {path}: {name!r} names both {seen[word]} and {action.value}")
        param_names: set[str] = set()
        for param, pspec in spec.params.items():
            for name in (param, *pspec.aliases):
                if normalise_word(name) in param_names:
                    raise VocabularyError(f"vocabulary file {path}: {action.value} parameter {name!r} named twice")
                param_names.add(normalise_word(name))
            if pspec.unit and pspec.unit not in vocabulary.units:
                raise VocabularyError(f"vocabulary file {path}: {action.value}.{param} has unknown unit {pspec.unit!r}")
            if pspec.min is not None and pspec.max is not None and pspec.min > pspec.max:
                raise VocabularyError(f"vocabulary file {path}: {action.value}.{param} has min > max")
    field_names: dict[str, str] = {}
    for field, names in vocabulary.fields.items():
        for name in names:
            if field_names.setdefault(normalise_word(name), field) != field:
                raise VocabularyError(f"vocabulary file {path}: step field {name!r} means two fields")
