"""The reference corpus: names as plans write them, each resolved in the household world and checked.

The format of references.yaml is described in README.md next to it. `load_raw` reads the cases,
`parse_case` checks one (a malformed case raises CorpusError naming its index), `run_case` resolves
it with a Resolver built as the service builds it and returns an Outcome, never raising.
"""

from __future__ import annotations

import re
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import msgspec
import yaml
from msgspec import UNSET, Meta, UnsetType

from schemas.common import ErrorKind, Id, Metres, Name, Pose2D, ServiceError, Vec3
from schemas.plan import Action, Coordinates, GroundedPlan, Plan, Resolution, ResolvedVia, ResolveReply, Step
from schemas.world import PerceivedHuman, PerceivedHumans, PerceivedObject, PerceivedObjects, World
from services.resolver.resolver import Resolver, answer

REFERENCES = Path(__file__).with_name("references.yaml")
ResolutionKind = Literal["room", "furniture", "place", "object", "human", "point"]


class Seen(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """An object as perception last saw it; its name, class and colour come from the world file."""

    position: Annotated[list[Metres], Meta(min_length=3, max_length=3)]
    on: Id | None = None
    room: Id | None = None
    stale: bool = False


class Expect(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    # What the name must resolve to...
    id: Id | None = None
    kind: ResolutionKind | None = None
    via: ResolvedVia | None = None
    warning: str | None = None
    # ...or how the plan must be refused.
    refused: ErrorKind | None = None
    candidates: list[str] | None = None
    message: str | None = None


class CaseSpec(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    # Empty: the step names nothing (it gives `coordinates`); its resolution is found by label alone.
    ref: Annotated[str, Meta(max_length=200)]
    action: Action = Action.PICK
    field: Literal["target", "location"] = "target"
    target: Name | None = None
    location: Name | None = None
    coordinates: Coordinates | None = None
    before: list[Step] = []
    # Absent: the world's robot.start; null: not known.
    robot: Pose2D | UnsetType | None = UNSET
    seen: dict[Id, Seen] | None = None
    humans: dict[Id, Pose2D] | None = None
    expect: Expect
    note: str = ""


class CorpusError(Exception):
    """A case in the corpus is malformed: the message names its index and what is wrong."""


@dataclass(frozen=True)
class Case:
    index: int
    spec: CaseSpec
    plan: Plan
    objects: PerceivedObjects | None
    robot: Pose2D | None
    humans: PerceivedHumans | None

    @property
    def ref(self) -> str:
        return self.spec.ref

    @property
    def label(self) -> str:
        """The label of the case's own step in the plan (after its `before` steps)."""
        return str(len(self.spec.before) + 1)

    def __str__(self) -> str:
        return f"case {self.index} ({self.spec.action} {self.spec.field} {self.ref!r})"


@dataclass(frozen=True)
class Outcome:
    case: Case
    passed: bool
    detail: str


class _Loader(yaml.SafeLoader):
    """YAML with YAML 1.2's booleans: only true and false, so the key `on` stays the word "on"."""


_Loader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers if tag != "tag:yaml.org,2002:bool"]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:bool", re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"), list("tTfF")
)


def load_raw(path: Path = REFERENCES) -> list[Any]:
    """The cases as written, unchecked: a list (each entry is checked by `parse_case`)."""
    try:
        raw = yaml.load(path.read_text(encoding="utf-8"), Loader=_Loader)
    except yaml.YAMLError as exc:
        raise CorpusError(f"{path} is not valid YAML: {exc}") from None
    if raw is None:
        return []
    if not isinstance(raw, list):
        raise CorpusError(f"{path} must hold a list of cases, not {type(raw).__name__}")
    return raw


def case_id(index: int, raw: Any) -> str:
    """A test id: the case's ref text."""
    ref = raw.get("ref") if isinstance(raw, dict) else None
    return ref if isinstance(ref, str) and ref else f"case {index}"


def parse_case(index: int, raw: Any, world: World) -> Case:
    """One case checked and turned into the resolver's inputs; CorpusError names what is wrong."""
    where = f"case {index}" + (f" ({raw['ref']!r})" if isinstance(raw, dict) and "ref" in raw else "")
    try:
        spec = msgspec.convert(raw, CaseSpec)
    except msgspec.ValidationError as exc:
        raise CorpusError(f"{where}: {exc}") from None
    problems = _problems(spec, world)
    if problems:
        raise CorpusError(f"{where}: " + "; ".join(problems))
    return Case(
        index=index,
        spec=spec,
        plan=_plan(spec),
        objects=_objects(spec, world),
        robot=world.robot.start if spec.robot is UNSET else spec.robot,
        humans=_humans(spec, world),
    )


def load_cases(world: World, path: Path = REFERENCES) -> list[Case]:
    return [parse_case(i, raw, world) for i, raw in enumerate(load_raw(path))]


def _problems(spec: CaseSpec, world: World) -> list[str]:
    problems: list[str] = []
    if getattr(spec, spec.field) is not None:
        problems.append(f"'{spec.field}' is the ref itself (field: {spec.field}); do not give it too")
    if not spec.ref and spec.coordinates is None:
        problems.append("an empty ref names nothing: give the step 'coordinates'")
    expect = spec.expect
    success = [k for k in ("id", "kind", "via", "warning") if getattr(expect, k) is not None]
    refusal = [k for k in ("candidates", "message") if getattr(expect, k) is not None]
    if expect.refused is None:
        if expect.id is None and expect.kind is None:
            problems.append("expect needs 'id' or 'kind' (what the name resolves to), or 'refused'")
        if refusal:
            problems.append(f"expect: {refusal} only go with 'refused'")
    elif success:
        problems.append(f"expect: {success} mean nothing for a refusal")
    objects = {o.id for o in world.objects}
    problems.extend(
        f"seen: {i!r} is not an object of world {world.name!r}" for i in spec.seen or {} if i not in objects
    )
    humans = {h.id for h in world.humans}
    problems.extend(
        f"humans: {i!r} is not a person of world {world.name!r}" for i in spec.humans or {} if i not in humans
    )
    return problems


def _plan(spec: CaseSpec) -> Plan:
    ref = spec.ref or None
    target = ref if spec.field == "target" else spec.target
    location = ref if spec.field == "location" else spec.location
    step = Step(action=spec.action, target=target, location=location, coordinates=spec.coordinates)
    return Plan(steps=[*spec.before, step])


def _objects(spec: CaseSpec, world: World) -> PerceivedObjects | None:
    if spec.seen is None:
        return None
    known = {o.id: o for o in world.objects}
    objects = [
        PerceivedObject(
            id=object_id,
            name=known[object_id].name,
            cls=known[object_id].cls,
            color=known[object_id].color,
            position=Vec3(x=s.position[0], y=s.position[1], z=s.position[2]),
            room=s.room,
            on=s.on,
            stamp=1.0,
            stale=s.stale,
        )
        for object_id, s in spec.seen.items()
    ]
    return PerceivedObjects(stamp=1.0, objects=objects)


def _humans(spec: CaseSpec, world: World) -> PerceivedHumans | None:
    if spec.humans is None:
        return None
    names = {h.id: h.name for h in world.humans}
    return PerceivedHumans(
        stamp=1.0, humans=[PerceivedHuman(id=i, name=names[i], pose=pose) for i, pose in spec.humans.items()]
    )


def default_resolver() -> Resolver:
    """A Resolver built as the resolver service builds it, from the default configuration."""
    # Imported here: the service module brings Zenoh in, which only this needs.
    from services.resolver.config import ResolverConfig
    from services.resolver.node import build_resolver

    return build_resolver(ResolverConfig())


def run_case(case: Case, resolver: Resolver) -> Outcome:
    """Resolve the case's plan and check the reply; a resolver that raises fails the case, with its traceback."""
    try:
        reply = answer(resolver, case.plan, case.objects, case.robot, case.humans)
    except Exception:
        return Outcome(case, False, f"{case}: the resolver raised\n{traceback.format_exc()}")
    return check(case, reply)


def check(case: Case, reply: ResolveReply) -> Outcome:
    expect = case.spec.expect
    problems = _refusal_problems(case, reply) if expect.refused is not None else _resolution_problems(case, reply)
    if problems:
        return Outcome(case, False, f"{case}: " + "; ".join(problems))
    return Outcome(case, True, f"{case}: ok")


def _resolution_problems(case: Case, reply: ResolveReply) -> list[str]:
    expect = case.spec.expect
    if isinstance(reply, ServiceError):
        return [f"expected a resolution, got a refusal ({reply.kind}): {reply.message}"]
    resolutions = [r for r in reply.resolutions if r.label == case.label and (r.text == case.ref or not case.ref)]
    if not resolutions:
        listed = ", ".join(f"{r.label}: {r.text!r} -> {r.id or r.kind}" for r in reply.resolutions) or "none"
        return [f"no resolution of {case.ref!r} at step {case.label}; resolutions: {listed}"]
    problems = min((_mismatches(expect, r) for r in resolutions), key=len)
    if expect.warning is not None and not _contains(reply, expect.warning):
        problems.append(f"no warning contains {expect.warning!r}; warnings: {reply.warnings!r}")
    return problems


def _mismatches(expect: Expect, resolution: Resolution) -> list[str]:
    return [
        f"{key}: expected {getattr(expect, key)!r}, got {getattr(resolution, key)!r}"
        for key in ("id", "kind", "via")
        if getattr(expect, key) is not None and getattr(expect, key) != getattr(resolution, key)
    ]


def _contains(reply: GroundedPlan, wanted: str) -> bool:
    return any(wanted.lower() in warning.lower() for warning in reply.warnings)


def _refusal_problems(case: Case, reply: ResolveReply) -> list[str]:
    expect = case.spec.expect
    if not isinstance(reply, ServiceError):
        got = [f"{r.text!r} -> {r.id or r.kind}" for r in reply.resolutions if r.label == case.label]
        return [f"expected a refusal ({expect.refused}), got a grounded plan; resolutions at step {case.label}: {got}"]
    problems: list[str] = []
    if reply.kind != expect.refused:
        problems.append(f"kind: expected {expect.refused}, got {reply.kind}")
    # Refused at the case's own step, not at one of its `before` steps.
    if reply.step != len(case.spec.before):
        problems.append(f"refused at step {None if reply.step is None else reply.step + 1}, not step {case.label}")
    if expect.candidates is not None and set(expect.candidates) != set(reply.candidates):
        problems.append(f"candidates: expected {sorted(expect.candidates)}, got {sorted(reply.candidates)}")
    if expect.message is not None and expect.message.lower() not in reply.message.lower():
        problems.append(f"message does not contain {expect.message!r}")
    if problems:
        problems.append(f"message: {reply.message!r}")
    return problems
