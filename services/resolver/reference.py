"""A name as a plan writes it, read into its parts: 'the big red cup on the table left of the apple'."""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Literal

from services.resolver.names import FILLER, name_words, normalise_name

RelationKind = Literal["on", "in", "at", "near", "left_of", "right_of", "nearest_to", "farthest_from"]
Superlative = Literal["nearest", "farthest", "leftmost", "rightmost", "biggest", "smallest"]

# Phrases (normalised: lower case, articles dropped) that relate the thing named before them to
# the thing named after them. Longest first, so "to left of" wins over "left of".
RELATIONS: tuple[tuple[tuple[str, ...], RelationKind], ...] = tuple(
    sorted(
        (
            (tuple(phrase.split()), kind)
            for phrase, kind in {
                "on": "on",
                "on top of": "on",
                "upon": "on",
                "in": "in",
                "inside": "in",
                "within": "in",
                "at": "at",
                "from": "at",
                "by": "near",
                "near": "near",
                "nearby": "near",
                "next to": "near",
                "beside": "near",
                "close to": "near",
                "left of": "left_of",
                "to left of": "left_of",
                "on left of": "left_of",
                "right of": "right_of",
                "to right of": "right_of",
                "on right of": "right_of",
                "nearest to": "nearest_to",
                "closest to": "nearest_to",
                "farthest from": "farthest_from",
                "furthest from": "farthest_from",
            }.items()
        ),
        key=lambda item: -len(item[0]),
    )
)
SUPERLATIVES: dict[str, Superlative] = {
    "nearest": "nearest",
    "closest": "nearest",
    "farthest": "farthest",
    "furthest": "farthest",
    "leftmost": "leftmost",
    "rightmost": "rightmost",
    "biggest": "biggest",
    "largest": "biggest",
    "smallest": "smallest",
    "left": "leftmost",
    "right": "rightmost",
}
# "the cup on the left": a side at the end of a name picks the leftmost or rightmost.
SIDES: dict[tuple[str, ...], Superlative] = {
    ("on", "left"): "leftmost",
    ("on", "right"): "rightmost",
    ("to", "left"): "leftmost",
    ("to", "right"): "rightmost",
    ("left",): "leftmost",
    ("right",): "rightmost",
}
SIZES: dict[str, Literal["big", "small"]] = {
    "big": "big",
    "large": "big",
    "huge": "big",
    "small": "small",
    "little": "small",
    "tiny": "small",
}
COLOURS = frozenset(
    {"red", "orange", "yellow", "green", "blue", "purple", "violet", "pink", "brown", "black", "white", "grey"}
    | {"gray", "silver", "gold", "beige"}
)
PRONOUNS = frozenset({"it", "that", "this", "them", "that one", "this one", "same one", "same", "same object"})
# Nouns that name no kind of thing: "the red one" is any red object.
GENERIC = frozenset({"one", "thing", "object", "item"})
ARTICLES = frozenset({"the", "a", "an"})
# Fillers that are a pronoun after a relation ("the book near that"), so kept until relations are read.
_POINTING_FILLERS = FILLER & {word for pronoun in PRONOUNS for word in pronoun.split()}
# Deep enough for any real name; a plan cannot make the reader recurse further.
MAX_RELATIONS = 4


@dataclass(frozen=True)
class Relation:
    kind: RelationKind
    other: Reference


@dataclass(frozen=True)
class Reference:
    """`noun` is what is left once colour, size, superlatives and relations are taken out ('cup');
    `key` is the whole name normalised, tried first as an exact name ('top of the stairs')."""

    text: str
    key: str
    noun: str
    colour: str | None = None
    size: Literal["big", "small"] | None = None
    superlative: Superlative | None = None
    relations: tuple[Relation, ...] = ()
    pronoun: bool = False
    # A name that starts with a relation ("next to the apple", "on the table") names where, by the
    # thing there: the rest of the Reference is that thing, `lead` the relation the name started with.
    lead: RelationKind | None = None

    @property
    def generic(self) -> bool:
        return self.noun == "" or self.noun in GENERIC


def _find_relation(words: list[str]) -> tuple[int, int, RelationKind] | None:
    """The first relation phrase with something after it: (start, end, kind)."""
    for start in range(len(words)):
        for phrase, kind in RELATIONS:
            end = start + len(phrase)
            if tuple(words[start:end]) == phrase and end < len(words):
                return start, end, kind
    return None


@lru_cache(maxsize=4096)
def parse_reference(text: str, depth: int = 0) -> Reference:
    """Read `text` into a Reference; never fails (an unreadable name becomes a noun to look up)."""
    key = normalise_name(text)
    plain = [w for w in name_words(text) if w not in ARTICLES]
    if " ".join(plain) in PRONOUNS:
        return Reference(text=text, key=" ".join(plain), noun="", pronoun=True)
    words = [w for w in plain if w not in FILLER or w in _POINTING_FILLERS]
    superlative: Superlative | None = None
    for tail, side in SIDES.items():
        if len(words) > len(tail) and tuple(words[-len(tail) :]) == tail:
            superlative, words = side, words[: -len(tail)]
            break
    relations: list[Relation] = []
    found = _find_relation(words) if depth < MAX_RELATIONS else None
    if found is not None:
        start, end, kind = found
        other = parse_reference(" ".join(words[end:]), depth + 1)
        if start == 0:
            # "next to the apple", "at the counter": where a thing is, named by what is there.
            return replace(other, text=text, lead=kind)
        relations.append(Relation(kind, other))
        words = words[:start]
    colour = size = None
    noun: list[str] = []
    for word in words:
        if word in SUPERLATIVES and superlative is None:
            superlative = SUPERLATIVES[word]
        elif word in SIZES and size is None:
            size = SIZES[word]
        elif word in COLOURS and colour is None:
            colour = word
        elif word not in FILLER:
            noun.append(word)
    return Reference(
        text=text,
        key=key,
        noun=" ".join(noun),
        colour=colour,
        size=size,
        superlative=superlative,
        relations=tuple(relations),
    )
