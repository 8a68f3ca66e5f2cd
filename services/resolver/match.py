"""From a Reference to the one entity it means in a Scene, or why it cannot be told."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

from schemas.common import ErrorKind
from schemas.plan import ResolvedVia
from services.resolver.names import POINTING_WORDS, Entity, Kind, NameIndex, normalise_name
from services.resolver.reference import Reference, Relation, RelationKind
from services.resolver.scene import SIDEWAYS_MARGIN, Scene
from services.worldmodel import WorldModel

# "the big cup" picks the biggest only when it is clearly bigger than the next.
SIZE_RATIO = 1.25
# "the nearest cup" picks one only when it is clearly nearer than the next (metres).
DISTANCE_MARGIN = 0.05
ECHO_CHARS = 60
# A message names up to this many things a relation's other name may mean, else quotes the name.
MAX_LISTED = 3
# "left of X" is within this many times the near distance of X.
BESIDE = 2.0
# What each relation may point at, to break ties in what the other thing is.
RELATION_KINDS: dict[str, tuple[Kind, ...]] = {
    "on": ("furniture",),
    "in": ("room", "furniture"),
    "at": ("furniture", "place", "room"),
}
# What a step's location may name, and what a name starting with "on" or "in" may mean (a thing
# cannot be put on an apple or in a person).
LOCATION_KINDS: tuple[Kind, ...] = ("furniture", "room", "place")
# A name starting with one of these names a location by what is there ("next to the apple", "on the
# table"); one side of a thing, or far from it, is no location the resolver can ground at that thing.
LOCATING: frozenset[RelationKind] = frozenset({"on", "in", "at", "near", "nearest_to"})


def echo(name: str) -> str:
    return repr(name if len(name) <= ECHO_CHARS else name[:ECHO_CHARS] + "...")


class NoMatch(Exception):
    """The reference names nothing, or more than one thing, or needs what is not known."""

    def __init__(self, message: str, kind: ErrorKind, candidates: Iterable[str] = ()) -> None:
        super().__init__(message)
        self.message = message
        self.kind = kind
        self.candidates = list(candidates)


@dataclass(frozen=True)
class Match:
    entity: Entity
    via: ResolvedVia
    confidence: float
    # Said back as warnings: the near-miss reading ("'cofee cup' read as coffee mug"), and where the
    # thing is when the step's location says otherwise.
    reading: str | None = None
    elsewhere: str | None = None


@dataclass
class _Found:
    entities: list[Entity]
    via: ResolvedVia = "name"
    confidence: float = 1.0
    # Near-miss readings of the name and of the names in its relations.
    readings: list[str] = field(default_factory=list)

    def narrow(self, kept: list[Entity], via: ResolvedVia) -> None:
        """Keep `kept`; `via` is what told them apart, unless the name itself was a near-miss."""
        if len(kept) < len(self.entities) and self.via != "fuzzy":
            self.via = via
        self.entities = kept


def _listing(items: Sequence[str], word: str = "or") -> str:
    return items[0] if len(items) == 1 else f"{', '.join(items[:-1])} {word} {items[-1]}"


def _the(ref: Reference, entities: Sequence[Entity]) -> str:
    """How a message names the other thing of a relation: by what it is ('the operator', where the
    text may say 'me'; 'the kitchen table or the coffee table'), else by the text as written."""
    if not entities or len(entities) > MAX_LISTED:
        return echo(ref.text)
    return _listing([f"the {e.name}" for e in entities])


def _phrase(kind: str) -> str:
    return kind.replace("_", " ")


def _ambiguous(text: str, scene: Scene, entities: list[Entity]) -> NoMatch:
    described = [scene.describe(e) for e in entities]
    listed = _listing([f"the {d}" for d in described])
    return NoMatch(
        f"{echo(text)} is ambiguous: it could be {listed}; say which one", ErrorKind.AMBIGUOUS_NAME, described
    )


def _volume(model: WorldModel, entity: Entity) -> float:
    if entity.kind == "object":
        size = model.objects[entity.id].size
        return size.x * size.y * size.z
    if entity.kind == "furniture":
        size = model.furniture[entity.id].size
        return size.x * size.y * size.z
    return 0.0


class Matcher:
    """Finds what a Reference means: the name (exactly, or a near-miss above `min_confidence`),
    then colour, relations, size and superlatives, the step's location, then the robot's room."""

    def __init__(
        self,
        names: NameIndex,
        model: WorldModel,
        *,
        min_confidence: float = 0.8,
        margin: float = 0.05,
        near: float = 0.75,
    ) -> None:
        self.names = names
        self.model = model
        self.min_confidence = min_confidence
        self.margin = margin
        self.near = near

    def find(
        self,
        ref: Reference,
        scene: Scene,
        prefer: tuple[Kind, ...] = (),
        *,
        antecedent: Entity | None = None,
        hint: Reference | None = None,
    ) -> Match:
        """The one entity `ref` means. `antecedent` is what "it" means at this step, also inside a
        relation or the location `hint`. `prefer` naming objects means the step wants a thing (pick,
        detect, look_at, what a place puts down), so a name that starts with a relation is refused."""
        if ref.lead is not None:
            self._check_lead(ref, ref.lead, prefer)
        if ref.pronoun:
            it = self._antecedent(ref, antecedent)
            self._check_holder(ref, [it])
            return Match(it, "pronoun", 1.0)
        found = self._candidates(ref, scene, prefer, antecedent)
        elsewhere = None
        if hint is not None:
            elsewhere = self._locate(ref, hint, scene, found, antecedent)
        if len(found.entities) > 1 and scene.robot is not None:
            room = scene.model.room_of(scene.robot.x, scene.robot.y)
            here = [e for e in found.entities if scene.room(e) == room]
            if len(here) == 1:
                found.narrow(here, "context")
        if len(found.entities) > 1:
            raise _ambiguous(ref.text, scene, found.entities)
        entity = found.entities[0]
        self._check_holder(ref, [entity])
        reading = "; ".join(found.readings) or None
        return Match(entity, found.via, found.confidence, reading, elsewhere)

    @staticmethod
    def _check_lead(ref: Reference, lead: RelationKind, prefer: tuple[Kind, ...]) -> None:
        """Refuse a name that starts with the relation `lead` where that cannot be honoured: as a thing
        to act on ("pick next to the apple" would pick the apple; "at the apple" is the apple), or as a
        side of a thing (a location is grounded at the thing: "left of" it would be any free side)."""
        if "object" in prefer and lead != "at":
            raise NoMatch(
                f"{echo(ref.text)} says where, not what: name the thing first, as in "
                f"{echo('the cup ' + ref.text.strip())}",
                ErrorKind.UNKNOWN_NAME,
            )
        if lead not in LOCATING:
            raise NoMatch(
                f"{echo(ref.text)} cannot be honoured: a location is grounded at or next to the thing it "
                f"names (a place goes on the free spot nearest it, whichever side that is), never "
                f"{_phrase(lead)} it; say {echo('next to the ' + ref.key)} or name the surface",
                ErrorKind.INVALID_REQUEST,
            )

    @staticmethod
    def _check_holder(ref: Reference, where: Sequence[Entity]) -> None:
        """Refuse "on the apple", "in the operator": a thing can be on furniture or in a room only."""
        if ref.lead in ("on", "in") and (others := [e for e in where if e.kind not in LOCATION_KINDS]):
            name = others[0].name
            raise NoMatch(
                f"{echo(ref.text)}: nothing can be {ref.lead} the {name}, only on furniture, in a room or "
                f"at a place; name the surface, or say 'next to the {name}'",
                ErrorKind.INVALID_REQUEST,
            )

    @staticmethod
    def _antecedent(ref: Reference, antecedent: Entity | None) -> Entity:
        """What the pronoun `ref` means at this step: the object the plan last handled."""
        if antecedent is None:
            raise NoMatch(
                f"{echo(ref.text)} does not refer to anything yet: no object was handled before this "
                "step; name the object",
                ErrorKind.UNKNOWN_NAME,
            )
        return antecedent

    def _locate(
        self, ref: Reference, hint: Reference, scene: Scene, found: _Found, antecedent: Entity | None
    ) -> str | None:
        """Keep what is where the step's location `hint` says ("kitchen table", "left of the apple").
        Says back where the one thing named is when it is elsewhere; refuses when it rules out several."""
        where = self._candidates(hint, scene, LOCATION_KINDS, antecedent)
        self._check_holder(hint, where.entities)
        found.readings.extend(where.readings)
        kind = hint.lead or "at"
        kept = self._relation_test(Relation(kind, hint), scene, where.entities)(found.entities)
        if kept:
            found.narrow(kept, "relation")
            return None
        there = f"{_phrase(kind)} {_the(hint, where.entities)}"
        if len(found.entities) == 1:
            thing = found.entities[0]
            return f"{thing.name} is {scene.where(thing)}, not {there}; it is used there"
        described = [scene.describe(e) for e in found.entities]
        raise NoMatch(
            f"nothing called {echo(ref.noun or ref.key)} is {there}; "
            f"there is {_listing([f'the {d}' for d in described], 'and')}",
            ErrorKind.UNKNOWN_NAME,
            described,
        )

    # Candidates: everything the reference may mean, narrowed by what it says

    def _candidates(self, ref: Reference, scene: Scene, prefer: tuple[Kind, ...], antecedent: Entity | None) -> _Found:
        if ref.pronoun:
            return _Found([self._antecedent(ref, antecedent)], "pronoun")
        exact = self.names.lookup(ref.key)
        found = _Found(exact) if exact and not ref.relations else self._named(ref, scene)
        if len(found.entities) > 1 and prefer:
            found.entities = [e for e in found.entities if e.kind in prefer] or found.entities
        for relation in ref.relations:
            self._relate(ref, relation, scene, found, antecedent)
        if ref.size is not None:
            self._by_size(ref.size, found)
        if ref.superlative is not None:
            self._superlative(ref, scene, found)
        return found

    def _named(self, ref: Reference, scene: Scene) -> _Found:
        """The things the head of the reference names, its colour applied."""
        colour = ref.colour
        if ref.generic:
            found = _Found(self.names.of_kind("object"))
        elif colour is not None and (named := self.names.lookup(f"{colour} {ref.noun}")):
            return _Found(named)  # "red cup": the colour is part of the name
        elif named := self.names.lookup(ref.noun):
            found = _Found(named)
        else:
            found, matched = self._near_miss(ref, " ".join(w for w in (colour, ref.noun) if w))
            if colour is not None and colour in matched.split():
                return found  # "red cpu" read as "red cup"
        if colour is not None:
            coloured = [e for e in found.entities if self.names.colours.get(e.id) == colour]
            if not coloured:
                what = "object" if ref.generic else ref.noun
                others = [scene.describe(e) for e in found.entities if e.kind == "object"]
                detail = f"; there is {_listing([f'the {d}' for d in others], 'and')}" if others else ""
                raise NoMatch(f"there is no {colour} {what}{detail}", ErrorKind.UNKNOWN_NAME, others)
            found.narrow(coloured, "attribute")
        return found

    def _near_miss(self, ref: Reference, head: str) -> tuple[_Found, str]:
        """What a misspelt name most likely means, and the name it matched: only a reading that is a
        typo of a known name (`NameIndex.readings`), else refused with the closest names."""
        scored = self.names.readings(head, self.min_confidence) or self.names.readings(ref.noun, self.min_confidence)
        if not scored:
            suggestions = self.names.suggestions(head) or self.names.suggestions(ref.noun)
            listed = " or ".join(f"'{s}'" for s in suggestions)
            detail = (
                f" (did you mean {listed}?)"
                if suggestions
                else f": no room, furniture, place, object or person in world '{self.model.world.name}' has that name"
            )
            words = normalise_name(head).split()
            pointing = [w for w in dict.fromkeys(words) if w in POINTING_WORDS and not self.names.lookup(w)]
            why = f": {_listing([repr(w) for w in pointing])} points without naming" if pointing else ""
            raise NoMatch(f"unknown name {echo(ref.text)}{why}{detail}", ErrorKind.UNKNOWN_NAME, suggestions)
        best = scored[0]
        close = [s for s in scored if best.score - s.score <= self.margin]
        entities = list(dict.fromkeys(e for s in close for e in s.entities))
        names = [e.name for e in entities]
        reading = f"{echo(head)} read as {_listing(names)} (match {best.score:.2f})"
        return _Found(entities, "fuzzy", best.score, [reading]), best.matched

    def _relate(
        self, ref: Reference, relation: Relation, scene: Scene, found: _Found, antecedent: Entity | None
    ) -> None:
        other = self._candidates(relation.other, scene, RELATION_KINDS.get(relation.kind, ()), antecedent)
        found.readings.extend(other.readings)
        test = self._relation_test(relation, scene, other.entities)
        kept = test(found.entities)
        if not kept:
            described = [scene.describe(e) for e in found.entities]
            raise NoMatch(
                f"nothing called {echo(ref.noun or ref.key)} is {_phrase(relation.kind)} "
                f"{_the(relation.other, other.entities)}; "
                f"there is {_listing([f'the {d}' for d in described], 'and')}",
                ErrorKind.UNKNOWN_NAME,
                described,
            )
        found.narrow(kept, "relation")

    def _relation_test(
        self, relation: Relation, scene: Scene, others: list[Entity]
    ) -> Callable[[list[Entity]], list[Entity]]:
        kind = relation.kind
        if kind in ("on", "in", "at"):
            return lambda items: [e for e in items if any(self._at(scene, e, o) for o in others)]
        if kind == "near":
            return lambda items: [e for e in items if any(e != o and scene.distance(e, o) <= self.near for o in others)]
        if kind in ("left_of", "right_of"):
            self._need_pose(scene, _phrase(kind))
            sign = 1.0 if kind == "left_of" else -1.0

            def side(entity: Entity) -> float:
                return sign * (scene.leftward(entity) or 0.0)

            def beside(items: list[Entity]) -> list[Entity]:
                # Left of the apple means beside it, seen from the robot: not anywhere off to that side.
                return [
                    e
                    for e in items
                    if any(
                        e != o and side(e) > side(o) + SIDEWAYS_MARGIN and scene.distance(e, o) <= BESIDE * self.near
                        for o in others
                    )
                ]

            return beside
        if len(others) != 1:
            raise _ambiguous(relation.other.text, scene, others)
        target = others[0]
        sign = 1.0 if kind == "nearest_to" else -1.0
        return lambda items: self._extreme(
            [e for e in items if e != target], lambda e: sign * scene.distance(e, target)
        )

    def _at(self, scene: Scene, entity: Entity, where: Entity) -> bool:
        """Is `entity` on, in or at `where` (furniture: on its top; room: inside; otherwise: near)."""
        if where.kind == "furniture":
            return scene.is_on(entity, where)
        if where.kind == "room":
            return entity.kind != "room" and not scene.in_gripper(entity) and scene.room(entity) == where.id
        return entity != where and scene.distance(entity, where) <= self.near

    def _by_size(self, size: str, found: _Found) -> None:
        """Keep the biggest (or smallest) and whatever is about as big: within SIZE_RATIO of it."""
        if len(found.entities) < 2:
            return
        volumes = {e.id: _volume(self.model, e) for e in found.entities}
        if size == "big":
            largest = max(volumes.values())
            kept = [e for e in found.entities if volumes[e.id] * SIZE_RATIO >= largest]
        else:
            smallest = min(volumes.values())
            kept = [e for e in found.entities if volumes[e.id] <= smallest * SIZE_RATIO]
        found.narrow(kept, "attribute")

    def _superlative(self, ref: Reference, scene: Scene, found: _Found) -> None:
        which = ref.superlative
        if which in ("biggest", "smallest"):
            self._by_size("big" if which == "biggest" else "small", found)
            return
        self._need_pose(scene, f"{echo(ref.text)} (the {which})")
        if which in ("nearest", "farthest"):
            sign = 1.0 if which == "nearest" else -1.0
            found.narrow(self._extreme(found.entities, lambda e: sign * (scene.robot_distance(e) or 0.0)), "relation")
        else:
            # Left and right are as the robot sees things: those in its room, when any are.
            room = scene.model.room_of(scene.robot.x, scene.robot.y) if scene.robot else None
            here = [e for e in found.entities if scene.room(e) == room] or found.entities
            sign = -1.0 if which == "leftmost" else 1.0
            found.narrow(self._extreme(here, lambda e: sign * (scene.leftward(e) or 0.0)), "relation")

    @staticmethod
    def _extreme(items: list[Entity], cost: Callable[[Entity], float], tie: float = DISTANCE_MARGIN) -> list[Entity]:
        """The item with the lowest cost, or every item within `tie` of it (they are not told apart)."""
        if not items:
            return items
        best = min(cost(e) for e in items)
        return [e for e in items if cost(e) - best <= tie]

    @staticmethod
    def _need_pose(scene: Scene, what: str) -> None:
        if scene.robot is None:
            raise NoMatch(
                f"{what} depends on where the robot stands, and that is not known here; name the thing instead",
                ErrorKind.PRECONDITION,
            )
