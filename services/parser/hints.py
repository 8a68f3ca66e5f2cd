"""Hints a plan gives that are not commands (grasp types, approach distances, "carefully"): warnings and mappings."""

from __future__ import annotations

from typing import Any

from schemas.plan import Action, ParamValue
from services.parser.vocabulary import Vocabulary, normalise_word

ECHO_CHARS = 60
# The parameter a manner may set, when the step gives none.
SPEED = "speed"

# A parameter as the parser collects it: key as given, value, whether it sat under `parameters`.
Given = tuple[Any, Any, bool]


def _echo(value: object) -> str:
    text = value if isinstance(value, str) else repr(value)
    return repr(text if len(text) <= ECHO_CHARS else text[:ECHO_CHARS] + "...")


class Hints:
    """The vocabulary's `hints`: which parameters are hints, what each means, and what a manner slows."""

    def __init__(self, vocabulary: Vocabulary) -> None:
        spec = vocabulary.hints
        self.grasp_params = frozenset(spec.grasp.params)
        self.grasp_types = {normalise_word(word): kind for word, kind in spec.grasp.types.items()}
        self.grasp_meanings = spec.grasp.meanings
        self.grasp_reason = spec.grasp.reason
        self.ignored = {normalise_word(name): group.reason for group in spec.ignored for name in group.params}
        self.manner_params = frozenset(normalise_word(name) for name in spec.manner.params)
        self.manner_words = {normalise_word(word): meaning for word, meaning in spec.manner.words.items()}
        self.speeds = spec.manner.speeds
        self.units = {
            action: action_spec.params[SPEED].unit
            for action, action_spec in vocabulary.actions.items()
            if SPEED in action_spec.params
        }
        self.slower = sorted({w.replace("_", " ") for w, m in spec.manner.words.items() if m in self.speeds})

    def sift(
        self, label: str, known: dict[str, tuple[str, Any, Any]], given: list[Given], warnings: list[str]
    ) -> tuple[list[Given], Any]:
        """The parameters that are not hints, and the manner given (None if none); hints are warned about."""
        kept: list[Given] = []
        manner: Any = None
        for key, value, in_parameters in given:
            word = normalise_word(key) if isinstance(key, str) else ""
            if word in known:
                kind = self._grasp_type(known[word][0], value)
                if kind is None:
                    kept.append((key, value, in_parameters))
                    continue
                warnings.append(
                    f"{label}: {_echo(key)} {_echo(value)} is a grasp type, read as a hint: "
                    f"{self.grasp_meanings[kind]}; {self.grasp_reason}"
                )
            elif word in self.ignored:
                if value is not None:
                    reason = self.ignored[word]
                    warnings.append(f"{label}: {_echo(key)} is a hint the robot does not take, ignored: {reason}")
            elif word in self.manner_params:
                if value is not None:
                    manner = value if manner is None else manner
            else:
                kept.append((key, value, in_parameters))
        return kept, manner

    def _grasp_type(self, name: str, value: Any) -> str | None:
        if name not in self.grasp_params or not isinstance(value, str) or len(value) > ECHO_CHARS:
            return None
        return self.grasp_types.get(normalise_word(value.removesuffix(" grasp").removesuffix(" grip")))

    def slow_down(
        self, label: str, action: Action, manner: Any, params: dict[str, ParamValue], warnings: list[str]
    ) -> None:
        """A manner ("carefully") as a hint: a slower speed where the vocabulary lists one and the step gives none."""
        if manner is None:
            return
        meaning = self.manner_words.get(normalise_word(manner)) if isinstance(manner, str) else None
        if meaning is None:
            slower = ", ".join(repr(w) for w in self.slower)
            warnings.append(f"{label}: manner {_echo(manner)} ignored: the manners the robot honours are {slower}")
            return
        speed = self.speeds.get(meaning, {}).get(action)
        unit = self.units.get(action, "")
        if speed is None:
            warnings.append(
                f"{label}: manner {_echo(manner)} read as a hint: {action.value} has no slower speed to choose, "
                "so it runs as usual"
            )
        elif SPEED in params:
            given = params[SPEED]
            shown = f"{given:g}" if isinstance(given, int | float) else str(given)
            warnings.append(f"{label}: manner {_echo(manner)} read as a hint: the step's speed {shown} {unit} is kept")
        else:
            params[SPEED] = speed
            warnings.append(
                f"{label}: manner {_echo(manner)} read as a hint: speed set to {speed:g} {unit}, slower than usual"
            )
