"""Every name the world knows, normalised, mapped to the things it may mean; near-misses scored."""

from __future__ import annotations

import re
import unicodedata
from dataclasses import dataclass
from typing import Literal

from rapidfuzz import fuzz, process
from rapidfuzz.distance import OSA

from schemas.world import World

Kind = Literal["room", "furniture", "place", "object", "human"]
KIND_NOUNS: dict[Kind, str] = {
    "room": "a room",
    "furniture": "furniture",
    "place": "a place",
    "object": "an object",
    "human": "a person",
}
# Words that never tell two things apart: "the red cup" is "red cup".
FILLER = frozenset({"the", "a", "an", "some", "my", "this", "that", "please"})
_PUNCTUATION = re.compile(r"[^\w\s]|_")
# Words that point instead of naming ("put it there", "give it to her", "go upstairs"): however close
# one is spelt to a name ("there" is a letter from the operator's "here"), it is never read as that name.
POINTING_WORDS = frozenset(
    {"here", "there", "where", "it", "its", "this", "that", "these", "those", "them", "they", "he", "him"}
    | {"his", "she", "her", "hers", "you", "your", "me", "us", "we", "our", "upstairs", "downstairs"}
    | {"inside", "outside", "somewhere", "anywhere", "everywhere", "nowhere", "elsewhere", "yonder"}
)
# A near-miss is read as a name only if each of its words is at most this many typos (a letter
# added, dropped or changed, or two swapped) from the name's word in the same place.
TYPOS_PER_WORD = 1
# ...but in a word this short a changed letter most often spells another word ("cap" for "cup",
# "pen" for "pan", "bed" for "red"): only a letter added, dropped or swapped is a typo there.
SHORT_WORD = 3
MAX_SUGGESTIONS = 3
# Near-misses scoring below this (0..100) are not even suggested.
SUGGESTION_CUTOFF = 60.0
# ...nor when they score this much (0..1) below the best.
SUGGESTION_SPREAD = 0.1
# Longer names are cut before fuzzy matching: no real name is this long.
MAX_MATCH_CHARS = 200


def name_words(text: str) -> list[str]:
    """'The Red-Cup.' -> ['the', 'red', 'cup']: NFKC-folded (fullwidth or ligature letters become the
    letters they show, so a name typed on a CJK keyboard is the same name), lower case, no punctuation."""
    return _PUNCTUATION.sub(" ", unicodedata.normalize("NFKC", text).lower()).split()


def normalise_name(text: str) -> str:
    """'The Red-Cup.' -> 'red cup'."""
    return " ".join(w for w in name_words(text) if w not in FILLER)


def is_misspelling(written: str, known: str) -> bool:
    """Whether the normalised name `written` may be `known` mistyped: as many words in the same order,
    each at most TYPOS_PER_WORD typos from its counterpart (`_typo`), none a pointing word. An extra
    word ("living room sofa") or another head noun ("coffee pot", not "coffee cup") is another name."""
    said, meant = written.split(), known.split()
    return (
        len(said) == len(meant)
        and POINTING_WORDS.isdisjoint(said)
        and all(_typo(a, b) for a, b in zip(said, meant, strict=True))
    )


def _typo(said: str, meant: str) -> bool:
    if OSA.distance(said, meant) > TYPOS_PER_WORD:
        return False
    changed_letter = len(said) == len(meant) and said != meant and sorted(said) != sorted(meant)
    return not (changed_letter and len(meant) <= SHORT_WORD)


@dataclass(frozen=True)
class Entity:
    kind: Kind
    id: str
    name: str


@dataclass(frozen=True)
class Scored:
    """Things a near-miss may mean, with how well it matched (0..1) and the name it matched."""

    entities: tuple[Entity, ...]
    score: float
    matched: str


class NameIndex:
    """Ids, names and synonyms of rooms, furniture, places, objects and people; objects also by
    class ("cup") and colour and class ("red cup"), furniture by its kind ("table")."""

    def __init__(self, world: World) -> None:
        self._by_name: dict[str, list[Entity]] = {}
        self.entities: list[Entity] = []
        self.colours: dict[str, str] = {o.id: normalise_name(o.color) for o in world.objects}
        for room in world.rooms:
            self._add(Entity("room", room.id, room.name), room.id, room.name, *room.synonyms)
        for item in world.furniture:
            kind = item.cls or item.name.split()[-1]
            self._add(Entity("furniture", item.id, item.name), item.id, item.name, kind, *item.synonyms)
        for place in world.places:
            self._add(Entity("place", place.id, place.name), place.id, place.name, *place.synonyms)
        for obj in world.objects:
            names = (obj.id, obj.name, obj.cls, f"{obj.color} {obj.cls}", *obj.synonyms)
            self._add(Entity("object", obj.id, obj.name), *names)
        for human in world.humans:
            self._add(Entity("human", human.id, human.name), human.id, human.name, *human.synonyms)
        self._keys = list(self._by_name)
        self.by_id = {e.id: e for e in self.entities}

    def _add(self, entity: Entity, *names: str) -> None:
        self.entities.append(entity)
        for name in names:
            key = normalise_name(name)
            if key:
                matches = self._by_name.setdefault(key, [])
                if entity not in matches:
                    matches.append(entity)

    def lookup(self, name: str) -> list[Entity]:
        return list(self._by_name.get(normalise_name(name), []))

    def of_kind(self, kind: Kind) -> list[Entity]:
        return [e for e in self.entities if e.kind == kind]

    def near_misses(self, name: str, limit: int = 8) -> list[Scored]:
        """Names `name` may be a misspelling of, best first, each with the things it names."""
        key = normalise_name(name)[:MAX_MATCH_CHARS]
        if not key:
            return []
        found = process.extract(
            key, self._keys, scorer=fuzz.token_sort_ratio, limit=limit, score_cutoff=SUGGESTION_CUTOFF
        )
        return [Scored(tuple(self._by_name[match]), score / 100.0, match) for match, score, _ in found]

    def readings(self, name: str, min_score: float) -> list[Scored]:
        """The near-misses `name` is read as, best first: those scoring at least `min_score` that it
        may be a mistyping of (`is_misspelling`). Suggestions are not held to this."""
        key = normalise_name(name)[:MAX_MATCH_CHARS]
        return [s for s in self.near_misses(name) if s.score >= min_score and is_misspelling(key, s.matched)]

    def suggestions(self, name: str) -> list[str]:
        """Display names of the things `name` most likely meant, best first."""
        names: list[str] = []
        scored_names = self.near_misses(name)
        best = scored_names[0].score if scored_names else 0.0
        for scored in scored_names:
            if scored.score < best - SUGGESTION_SPREAD:
                break
            for entity in scored.entities:
                if entity.name not in names:
                    names.append(entity.name)
        return names[:MAX_SUGGESTIONS]
