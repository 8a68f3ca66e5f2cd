"""Every name the world knows, normalised, mapped to the things it may mean."""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal

from rapidfuzz import fuzz, process

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
_FILLER = frozenset({"the", "a", "an", "some", "my", "this", "that", "please"})
_PUNCTUATION = re.compile(r"[^\w\s]|_")
MAX_SUGGESTIONS = 3


def normalise_name(text: str) -> str:
    """'The Red-Cup.' -> 'red cup'."""
    words = _PUNCTUATION.sub(" ", text.lower()).split()
    return " ".join(w for w in words if w not in _FILLER)


@dataclass(frozen=True)
class Entity:
    kind: Kind
    id: str
    name: str


class NameIndex:
    """Ids, names and synonyms of rooms, furniture, places, objects and people; objects also by
    class ("cup") and colour and class ("red cup")."""

    def __init__(self, world: World) -> None:
        self._by_name: dict[str, list[Entity]] = {}
        for room in world.rooms:
            self._add(Entity("room", room.id, room.name), room.id, room.name, *room.synonyms)
        for item in world.furniture:
            self._add(Entity("furniture", item.id, item.name), item.id, item.name, *item.synonyms)
        for place in world.places:
            self._add(Entity("place", place.id, place.name), place.id, place.name, *place.synonyms)
        for obj in world.objects:
            names = (obj.id, obj.name, obj.cls, f"{obj.color} {obj.cls}", *obj.synonyms)
            self._add(Entity("object", obj.id, obj.name), *names)
        for human in world.humans:
            self._add(Entity("human", human.id, human.name), human.id, human.name, *human.synonyms)

    def _add(self, entity: Entity, *names: str) -> None:
        for name in names:
            key = normalise_name(name)
            if key:
                matches = self._by_name.setdefault(key, [])
                if entity not in matches:
                    matches.append(entity)

    def lookup(self, name: str) -> list[Entity]:
        return list(self._by_name.get(normalise_name(name), []))

    def suggestions(self, name: str) -> list[str]:
        """Display names of the things `name` most likely meant, best first."""
        key = normalise_name(name)[:200]
        if not key:
            return []
        found: list[str] = []
        for match, _score, _ in process.extract(key, list(self._by_name), scorer=fuzz.WRatio, limit=8, score_cutoff=75):
            for entity in self._by_name[match]:
                if entity.name not in found:
                    found.append(entity.name)
        return found[:MAX_SUGGESTIONS]
