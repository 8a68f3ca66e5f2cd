"""Structured steps whose action stands for several steps ("bring", "go_home") rewritten as those steps."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from services.parser.errors import ParseError
from services.parser.vocabulary import ExpansionSpec, Vocabulary, normalise_word, slot_reference

ECHO_CHARS = 60
# The name fields a slot may take, as the parser's field map names them.
_NAME_FIELDS = ("target", "target_object", "target_location")


def _echo(text: str) -> str:
    return repr(text if len(text) <= ECHO_CHARS else text[:ECHO_CHARS] + "...")


def given_once(
    refuse: Callable[[str], ParseError], given: dict[str, Any], field: str, key: Any, first: Any, value: Any
) -> None:
    """Refuse a step field given under two of its names ('target' and 'goal_name') that differ: keeping
    either would drop the other without a word (an 'args' beside 'parameters' losing a direction).

    `given` maps each field seen to the key that gave it; `first` is what that key gave.
    """
    if field in given and value != first:
        shown = f" ({_echo(first)} and {_echo(value)})" if isinstance(value, str) else ""
        raise refuse(
            f"gives its {field} twice, as {_echo(given[field])} and {_echo(key)}, and they differ{shown}; give it once"
        )
    given[field] = key


class Expansions:
    """The vocabulary's `expansions`, looked up by any of their names (normalised)."""

    def __init__(self, vocabulary: Vocabulary, fields: dict[str, str]) -> None:
        self.by_name: dict[str, tuple[str, ExpansionSpec]] = {}
        for name, spec in vocabulary.expansions.items():
            for word in (name, *spec.synonyms):
                self.by_name[normalise_word(word)] = (name, spec)
        # Normalised key -> the step field it means (the parser's field map).
        self.fields = fields

    def rewrite(
        self,
        step: dict[Any, Any],
        label: str,
        takes: Callable[[Any, str], bool],
        refuse: Callable[[str], ParseError],
        warnings: list[str],
    ) -> dict[str, Any] | None:
        """The plain steps `step` stands for (a group of them, or the one), or None when it is no expansion.

        `takes(action, key)` says whether an action takes a parameter of that name; `refuse` makes
        the refusal that names the step.
        """
        found = self._expansion(step)
        if found is None:
            return None
        written, _, spec = found
        names: dict[str, str] = {}
        params: dict[Any, Any] = {}
        keep: dict[str, Any] = {}
        given: dict[str, Any] = {}
        for key, value in step.items():
            field = self.fields.get(normalise_word(key)) if isinstance(key, str) else None
            if field == "action" or value is None:
                continue  # null is not given: it must not blank out what a template step says
            if field in _NAME_FIELDS and isinstance(value, str):
                if value.strip():
                    given_once(refuse, given, field, key, names.get(field), value.strip())
                    names[field] = value.strip()
            elif field == "parameters" and isinstance(value, dict):
                given_once(refuse, given, field, key, step[given[field]] if field in given else None, value)
                params.update(value)
            elif field == "on_failure":
                given_once(refuse, given, field, key, keep.get(field), value)
                keep[field] = value
            elif field == "description":
                keep[field] = value
            elif field == "substeps":
                raise refuse(f"{_echo(written)} stands for steps of its own and cannot also have sub-steps")
            elif field is None:
                params[key] = value  # beside the action: the expanded steps' parameters, or warned about
            else:
                keep[field] = value  # a malformed field: the normal reading refuses it, naming it
        slots = self._slots(written, spec, names, refuse, label, warnings)
        steps: list[dict[str, Any]] = []
        for template in spec.steps:
            out: dict[str, Any] = {"action": template.action.value}
            for field, value in (("target", template.target), ("target_location", template.location)):
                slot = slot_reference(value)
                if value is not None:
                    out[field] = slots[slot] if slot is not None else value
            steps.append(out)
        for key, value in params.items():
            takers = [out for out in steps if takes(out["action"], key)]
            for out in takers or [steps[0]]:
                out.setdefault("parameters", {})[key] = value
        description = keep.pop("description", None)
        if not isinstance(description, str) or not description.strip():
            description = spec.describe.format_map(slots) if spec.describe else written
        if len(steps) == 1:
            return {**steps[0], **keep, "description": description}
        return {**keep, "description": description, "substeps": steps}

    def _expansion(self, step: dict[Any, Any]) -> tuple[str, str, ExpansionSpec] | None:
        for key, value in step.items():
            if isinstance(key, str) and self.fields.get(normalise_word(key)) == "action":
                if not isinstance(value, str):
                    return None
                found = self.by_name.get(normalise_word(value))
                return None if found is None else (value.strip(), *found)
        return None

    def _slots(
        self,
        written: str,
        spec: ExpansionSpec,
        names: dict[str, str],
        refuse: Callable[[str], ParseError],
        label: str,
        warnings: list[str],
    ) -> dict[str, str]:
        used: set[str] = set()
        slots: dict[str, str] = {}
        for slot, slot_spec in spec.slots.items():
            field = next((f for f in slot_spec.fields if f in names and f not in used), None)
            if field is not None:
                used.add(field)
                slots[slot] = names[field]
            elif slot_spec.default is not None:
                slots[slot] = slot_spec.default
            else:
                raise refuse(f"{_echo(written)} needs {' '.join(slot_spec.needs.split())}")
        for name, value in names.items():
            if name not in used:
                warnings.append(f"{label}: {name} {_echo(value)} ignored: {written} does not use it")
        return slots
